"""Learning-based NMPC (thesis 5.2, 5.3.1): the nominal unicycle plus a learned disturbance.

Each step: the desired states are where the speed profile (schedule, end of route) takes the robot
(`build_problem`); a delayed estimate is first carried forward to now through the commands applied
since its capture (the mean of eq. 7.12); the linear speed of every step is fixed by the profile and the
angular rates w_0..w_{K-1} are optimized by Gauss-Newton (eq. 5.5-5.10, gauss_newton.py) on the
horizon's cost (horizon.py, eq. 5.16) with the actuator (and Ackermann steering) limits as bounds,
warm-started from the previous solution shifted by one step (on a rate-limited steering, from the
cheapest of it and either turn limit held: best_start).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np

from services.controller.actuator import ActuatorLag
from services.controller.gauss_newton import gauss_newton
from services.controller.held_turn import held_note, hold_turn_where_cancelled
from services.controller.horizon import (DelayedPeriod, DisturbanceModel, HorizonProblem, HorizonStart,
                                         reference_at)
from services.controller.laws import LawResult, SolveReport, StepContext
from services.controller.settings import NMPCSettings


@dataclass(frozen=True)
class Plan:
    """What one solve produced, for status and for the next step's warm start."""
    w: np.ndarray
    poses: np.ndarray           # (K+1, 3) predicted, x_0 first
    desired: np.ndarray         # (K+1, 3)
    cost: float
    iterations: int
    converged: bool


def _measured_velocity(ctx: StepContext, dt: float) -> tuple[float, float]:
    """v_{k-1} of thesis 5.3.1 from the two latest estimates; without an earlier one, as commanded."""
    if ctx.prev_pose is None:
        return ctx.cmd_before_capture or ctx.prev_cmd
    pp, x0 = ctx.prev_pose, ctx.pose
    c, s = math.cos(pp[2]), math.sin(pp[2])
    return ((c * (x0[0] - pp[0]) + s * (x0[1] - pp[1])) / dt, math.remainder(x0[2] - pp[2], 2 * math.pi) / dt)


def _carry_through_delay(ctx: StepContext, dt: float, model: DisturbanceModel | None,
                         v_prev: tuple[float, float], lag: ActuatorLag):
    """Eq. 7.12 (its mean): carry the estimate, captured D periods ago, forward through the D commands
    applied since, with the same model the horizon uses, so that the problem starts from now and its
    first a-vector pairs the right pose, velocities and commands (as experiences were built).
    Returns (pose, arc length, v_prev, u_prev, the periods passed)."""
    x = np.array(ctx.pose, dtype=float)
    u_before = ctx.cmd_before_capture if ctx.cmd_before_capture is not None else ctx.delayed_cmds[0]
    hint = ctx.vertex
    xi = ctx.xi_capture
    periods = []
    for v_i, w_i in ctx.delayed_cmds:
        g = np.zeros(3)
        pr = ctx.path.project(x, hint)
        hint = pr.vertex
        a = np.array([pr.distance_m, pr.lateral_m, pr.heading_rad, *v_prev, v_i, w_i, *u_before])
        (vb, wb), xi = lag.step(xi, (v_i, w_i))
        periods.append(DelayedPeriod(x.copy(), a, vb, wb))
        if model is not None:
            g = model.mean_and_grad(a)[0]
        c, s = math.cos(x[2]), math.sin(x[2])
        x_next = np.array([x[0] + vb * dt * c + c * g[0] - s * g[1], x[1] + vb * dt * s + s * g[0] + c * g[1],
                           x[2] + wb * dt + g[2]])
        v_prev = ((c * (x_next[0] - x[0]) + s * (x_next[1] - x[1])) / dt, (x_next[2] - x[2]) / dt)
        u_before = (v_i, w_i)
        x = x_next
    return x, ctx.path.project(x, hint).distance_m, v_prev, u_before, tuple(periods)


def crab_offsets(model: DisturbanceModel, s_d: np.ndarray, taught: np.ndarray, tangent: np.ndarray, v: np.ndarray,
                 w_ref: np.ndarray, dt: float, turn_gain: float = 1.0, passes: int = 3, min_speed_mps: float = 0.2,
                 max_offset_rad: float = 0.2) -> np.ndarray:
    """(K,) the heading, relative to the taught heading, at which the learned model has x_1..x_K move
    along the route. Where the robot slides sideways (a side slope), holding the route takes a crab
    angle -atan2(g_lat, v dt + g_along) that shrinks as the speed grows; the taught heading holds the
    crab of the teach speed. Weighed against it, a robot repeating faster is pulled uphill of the route
    (and the terminal lookahead, extrapolating along a heading that is not its course, adds to it): a
    steady offset that appeared exactly when the model became accurate. Per desired pose the model is
    asked at the route pose (lateral error 0) driving the route's turn rate (commanded `w_ref`, turned at
    `turn_gain` times it, actuator.py) with its heading disturbance compensated; crab, command and speed are settled by a few fixed-point passes (all
    poses in one batch each). Below `min_speed_mps` (stopping) there is no course to hold: 0."""
    K = len(v)
    idx = np.minimum(np.arange(1, K + 1), K - 1)     # the inputs leaving x_j (the last repeats)
    vj, wr = np.asarray(v, dtype=float)[idx], np.asarray(w_ref, dtype=float)[idx]
    A = np.zeros((K, 9))
    A[:, 0] = s_d[1:]
    A[:, 3], A[:, 4], A[:, 5], A[:, 6], A[:, 7], A[:, 8] = vj, turn_gain * wr, vj, wr, vj, wr
    e_h = np.zeros(K)
    for _ in range(passes):
        g = model.mean(A)
        crab = -np.arctan2(g[:, 1], np.maximum(vj * dt + g[:, 0], 0.5 * vj * dt))
        e_h = np.remainder(tangent[1:] + crab - taught[1:, 2] + math.pi, 2 * math.pi) - math.pi
        A[:, 2] = e_h
        A[:, 6] = A[:, 8] = wr - g[:, 2] / (dt * turn_gain)   # the command that cancels the heading disturbance
        A[:, 3] = vj + g[:, 0] / dt
    e_h = np.clip(e_h, -max_offset_rad, max_offset_rad)
    e_h[vj < min_speed_mps] = 0.0
    return e_h


def _profile(ctx: StepContext, s0: float, K: int, dt: float, lag: ActuatorLag) -> tuple[np.ndarray, np.ndarray]:
    """The profile's speeds (K,) and the arc lengths (K+1,) they take the robot to, its lag included."""
    s_d, v = np.empty(K + 1), np.empty(K)
    s_d[0] = s0
    xi = ctx.xi_now
    for j in range(K):
        v[j] = ctx.v_mps if j == 0 else ctx.speed_at(s_d[j])
        (vb, _), xi = lag.step(xi, (v[j], 0.0))
        s_d[j + 1] = s_d[j] + vb * dt
    return v, s_d


def shifted(w: np.ndarray) -> np.ndarray:
    """A plan's turn rates one period on: the next step's warm start."""
    return np.concatenate([w[1:], w[-1:]])


def build_problem(ctx: StepContext, settings: NMPCSettings, dt: float, model: DisturbanceModel | None,
                  probes: Sequence[np.ndarray] = ()) -> tuple[HorizonProblem, np.ndarray]:
    """This step's problem: start (carried through the delay), reference where the speed profile takes
    the robot, the route's turn rates; returns (problem, |w| bound per step). The model's turn is
    checked at the reference's rollout and the `probes`' (held_turn.py)."""
    v_prev = _measured_velocity(ctx, dt)
    x0, s0, u_prev, delay = np.array(ctx.pose, dtype=float), ctx.s_m, ctx.prev_cmd, ()
    lag = settings.lag(dt)
    if ctx.delayed_cmds and settings.delay_compensation:
        x0, s0, v_prev, u_prev, delay = _carry_through_delay(ctx, dt, model, v_prev, lag)
    v, s_d = _profile(ctx, s0, settings.horizon, dt, lag)
    ref = reference_at(ctx.path, s_d)
    x0[2] = ref.poses[0, 2] + math.remainder(x0[2] - ref.poses[0, 2], 2 * math.pi)
    w_ref = lag.command_for(v * ref.kappa)
    if model is not None and settings.crab_reference:
        ref = replace(ref, head_offset=crab_offsets(model, s_d, ref.poses, ref.direction_rad, v, w_ref, dt,
                                                    lag.turn_gain))
    start = HorizonStart(x0=x0, v_prev_act=v_prev, u_prev=u_prev, xi0=ctx.xi_now, delay=delay)
    problem = HorizonProblem(start, ref, v, w_ref, dt, settings, model, ctx.path, lag)
    held = hold_turn_where_cancelled(problem, settings.min_turn_share, (w_ref, *probes))
    if held is not model:
        problem = problem.with_model(held)
    return problem, np.array([ctx.w_limit_at(vj) for vj in v])


def best_start(problem: HorizonProblem, starts: Sequence[np.ndarray]) -> np.ndarray:
    """The start of lowest cost (the first of equal ones; the first is evaluated last). A rate-limited
    steering (actuator.py) moves its curvature at its limit whatever the command beyond it, so where the
    plan's commands lie far from the curvature reached the nominal cost is flat in them (the soft limit's
    slope vanishes) and only their side matters; Gauss-Newton there stays where it started, or follows
    the only slope left, a learned heading model's answer to the command, to a limit on the wrong side.
    Measured: bench seed 5903, scheduled LB-NMPC on a MATS in ruts, trial 7: -0.305 rad/s held,
    "converged" in one iteration, at cost 14.7 against 7.5 at +0.305, into a -17 deg heading error,
    1.96 m off the route."""
    first, *others = (np.asarray(w, dtype=float) for w in starts)
    costs = [problem.cost(w) for w in others]
    r, _ = problem.residual(first)     # last and with its Jacobian: the solver's first rollout, memoized
    costs = [0.5 * float(r @ r), *costs]
    costs = [c if math.isfinite(c) else math.inf for c in costs]
    return np.array(starts[int(np.argmin(costs))], dtype=float)


@dataclass(frozen=True)
class LBNMPCStep:
    """One LB-NMPC step's problem and answer, for re-solving it elsewhere (bench: CasADi/IPOPT)."""
    problem: HorizonProblem
    w0: np.ndarray           # where the solve started (LBNMPCLaw.start)
    w_limit: np.ndarray      # (K,) |w| bounds
    w: np.ndarray            # the solution


class LBNMPCLaw:
    """The LB-NMPC steering law. `model_for(ctx)` gives the disturbance model of the local window (None:
    the nominal model, as before any experience exists or when learning is off)."""
    name = "lb-nmpc"

    def __init__(self, settings: NMPCSettings, dt: float,
                 model_for: Callable[[StepContext], DisturbanceModel | None] = lambda ctx: None):
        self.settings = settings
        self.dt = dt
        self.model_for = model_for
        self.last_plan: Plan | None = None
        self.last_step: LBNMPCStep | None = None

    def warm_start(self, problem: HorizonProblem) -> np.ndarray:
        """The previous solution shifted by one period, or the route's own turn rates."""
        return problem.w_ref.copy() if self.last_plan is None else shifted(self.last_plan.w)

    def start(self, problem: HorizonProblem, w_limit: np.ndarray) -> np.ndarray:
        """Where Gauss-Newton starts: the warm start or, on a rate-limited steering, the lowest-cost of it
        and either turn limit held over the horizon (best_start)."""
        warm = self.warm_start(problem)
        if not problem.curvature_steered:
            return warm
        return best_start(problem, (warm, w_limit, -w_limit))

    def _solve(self, problem: HorizonProblem, w0: np.ndarray, w_limit: np.ndarray):
        s = self.settings
        return gauss_newton(problem.residual, w0, -w_limit, w_limit, max_iter=s.max_iter, tol=s.tol,
                            max_evals=s.max_evals)

    def angular(self, ctx: StepContext) -> LawResult:
        s = self.settings
        model = self.model_for(ctx)
        probes = () if self.last_plan is None else (shifted(self.last_plan.w),)
        problem, w_limit = build_problem(ctx, s, self.dt, model, probes)
        w0 = self.start(problem, w_limit)
        res = self._solve(problem, w0, w_limit)
        held = hold_turn_where_cancelled(problem, s.min_turn_share, (res.u,))
        if held is not problem.model:      # the solution went where the model cancels the turn: plan held
            problem = problem.with_model(held)
            w0 = self.start(problem, w_limit)
            res = self._solve(problem, w0, w_limit)
        X, _ = problem.rollout(res.u, with_jac=False)
        self.last_plan = Plan(res.u, X, problem.ref.poses, res.cost, res.iterations, res.converged)
        self.last_step = LBNMPCStep(problem, w0, w_limit, res.u)
        return LawResult(float(res.u[0]), predicted=X[1:],
                         solve=SolveReport(res.cost, res.iterations, res.evaluations, res.status, model is not None),
                         note=held_note(problem.model))
