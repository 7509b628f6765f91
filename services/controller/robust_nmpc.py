"""The uncertainty-aware LB-NMPC laws: Min-Max (thesis ch. 6) and (Robust) Constrained (ch. 7).

Both start like LB-NMPC (nmpc.py: desired states from the schedule, the delayed estimate carried to now,
the GP mean of the local window in the model) and add the horizon's covariance from the sigma-point
transform (uncertainty.py), started from the localizer's covariance carried through the delay (7.12).

MM-LB-NMPC (eq. 6.2-6.9): the cost is that of the worst of the 2^3 boundary sequences
xbar_j + Gamma_l 3 sigma_j (eq. 6.5; errors along, lateral and heading in the route frame), with the
mean's Jacobian for all of them (eq. 6.7-6.8). It is minimized as a min-max (minmax.py): each iteration
linearizes all eight sequences and solves a small epigraph QP, then takes the damped step beta of eq. 6.9
that lowers the true worst-case cost; it stops when the step is below tol (the thesis's alpha). The
thesis's iteration on the single worst sequence stalls where several are worst at once. The covariance
is computed once per step at the warm start (it moves little within a solve).

C-/RC-LB-NMPC (eq. 7.2-7.6): linear and angular speeds are both optimized inside the corridor tightened
by alpha * sigma (corridor_sqp.py; alpha = 0 is C-LB-NMPC). RC first caps the speeds with the fastest
of a ladder of slowed-down profiles whose 3-sigma region fits the corridor (speed_ladder.py).
Violating a tightened limit is possible only through a slack with a heavy L1 price, so the QP is always
feasible and the law says when it had to use it; beyond the first step the band is no narrower than a
path follower's correction can reach (band_reach.py), so that price does not buy a spin at a crawl.
When even the first predicted step's 3-sigma region does not fit inside the corridor, or the robot is
already outside it, the law stops the robot and says why. At the ladder's slowest rung it also stops
where the plan's first predicted step, its lateral 3-sigma region around it, reaches beyond the corridor: no
slower speed is left to try, and a crawl on a side slope drifts out while it corrects (bench seed 6607,
ROC6 s2103228252: at 0.05-0.13 m/s in a corner on a 14.5 deg slope, from 0.01 to 0.19 m of a 0.172 m
corridor). A robot that turns by the metre (an Ackermann) also stops at a crawl, whether the ladder or the SQP chose
it, where the plan carried on for the lookahead distance reaches beyond it (steered_out.py): its horizon
covers centimetres there.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from services.controller.band_reach import reach_capped, start_errors
from services.controller.corridor import Corridor
from services.controller.corridor_sqp import CorridorNLP, CorridorResult, Iterate, solve_corridor
from services.controller.held_turn import held_note
from services.controller.horizon import HorizonProblem
from services.controller.horizon_covariance import HorizonCovariance, variance_model
from services.controller.laws import LawResult, SolveReport, StepContext, UncertaintyReport
from services.controller.minmax import MinMaxQP, boundary_costs, solve_minmax
from services.controller.missed_variance import SpreadFloors
from services.controller.nmpc import Plan, build_problem, crab_offsets, shifted
from services.controller.settings import NMPCSettings
from services.controller.speed_ladder import SPEED_LADDER, AskedModel, Rung, fastest_fitting_rung
from services.controller.sqp_qp import CorridorQP
from services.controller.turn_accel import TurnLead
from services.controller.steered_out import lateral_reach
from services.controller.uncertainty import lateral_sigma_speed_jacobian, variance_speed_derivatives

SLOWEST_REACHED = 1.25   # the drive's speed at most this times the slowest rung's for the robot to be at it


def _horizon_sigmas(sig: np.ndarray, loc: np.ndarray, raw: np.ndarray) -> dict:
    """UncertaintyReport's per-step spreads from route-frame sigmas (K, 3) as widened, their localizer's
    share and as the model gave them."""
    return {"horizon_sigma_lat_m": tuple(float(x) for x in sig[:, 1]),
            "horizon_sigma_head_rad": tuple(float(x) for x in sig[:, 2]),
            "horizon_model_sigma_lat_m": tuple(float(x) for x in raw[:, 1]),
            "horizon_model_sigma_head_rad": tuple(float(x) for x in raw[:, 2]),
            "horizon_loc_sigma_lat_m": tuple(float(x) for x in loc[:, 1]),
            "horizon_loc_sigma_head_rad": tuple(float(x) for x in loc[:, 2])}


def _kappa(cov: HorizonCovariance) -> tuple[float, ...]:
    """The calibration's factors on the variance `cov` widens by (empty: none)."""
    return () if cov.factors is None else tuple(float(f * f) for f in cov.factors)


def _floors_at(ctx: StepContext, v: np.ndarray) -> SpreadFloors | None:
    """The calibration's floors for a plan at speeds `v` (its fastest decides)."""
    return None if ctx.spread_floors is None else ctx.spread_floors.at(float(np.max(v)))


def _capped(ctx: StepContext) -> tuple[StepContext, str, str]:
    """The step's context with its speeds held to the place's cap (calibration.speed_cap_at), what the
    status says of it and its SpeedCause ("" where it does not bind)."""
    cap = ctx.place_cap
    if cap is None or not math.isfinite(cap.speed_mps):
        return ctx, "", ""
    c, f = cap.speed_mps, ctx.speed_at
    note, cause = "", ""
    if c < ctx.v_mps:
        note = f"held to {c:.2f} m/s: the last pass here took {cap.share:.0%} of the {cap.what} at {cap.at_m:.0f} m"
        cause = "place-corridor" if cap.what == "corridor" else "place-steering"
    return dataclasses.replace(ctx, v_mps=min(ctx.v_mps, c), speed_at=lambda s: min(f(s), c)), note, cause


def _beyond(ctx: StepContext, cov: HorizonCovariance) -> tuple[float, HorizonCovariance] | None:
    """From which speed a rung is widened by the teach pass's needs at the place, and `cov` so widened
    (calibration.beyond_at; None: nowhere)."""
    if not ctx.spread_factors_beyond or not math.isfinite(ctx.spread_beyond_mps):
        return None
    return ctx.spread_beyond_mps, dataclasses.replace(cov, factors=np.asarray(ctx.spread_factors_beyond))


def _slowed(rung: Rung | None) -> str:
    """What the status says of a speed ladder held below the asked speed ("" where it was not)."""
    return f"slowed to {rung.scale:.2f} x the asked speed: {rung.held_by}" if rung is not None and rung.held_by else ""


def _at_the_slowest(rung: Rung) -> bool:
    """The ladder chose its slowest rung and the drive is already near its speed: a robot still fast was
    put there by one descent, and braking from speed in a corner is no safer than the plan (a Grizzly
    stopped from 1.5 m/s turned 25 deg off the route: bench seed 6607, s1583139655)."""
    return rung.scale <= SPEED_LADDER[-1] and rung.problem.start.xi0[0] <= SLOWEST_REACHED * float(np.max(rung.v))


def _crawling(rung: Rung, base: HorizonProblem, it: Iterate) -> bool:
    """The plan's command (whether the ladder or the SQP chose it) is no faster than the ladder's slowest
    rung, and the drive already near that speed. Its later steps may speed up: the next step's plan is
    made again from the crawl."""
    top = SPEED_LADDER[-1] * float(np.max(base.v))
    return float(it.v[0]) <= top and rung.problem.start.xi0[0] <= SLOWEST_REACHED * top


def _estimate_sigmas(ctx: StepContext) -> tuple[float, float]:
    """The estimate's 1-sigma across the route and in heading. An estimate outside the corridor by less
    cannot tell a robot at the edge from one just inside: the law then steers it back (its plan pays the
    slack price) instead of stopping where it is, which would leave it there."""
    if ctx.pose_cov is None:
        return 0.0, 0.0
    cov = np.asarray(ctx.pose_cov, dtype=float)
    th = float(ctx.path.tangent_at(ctx.s_m))
    n = np.array([-math.sin(th), math.cos(th)])
    return math.sqrt(max(float(n @ cov[:2, :2] @ n), 0.0)), math.sqrt(max(float(cov[2, 2]), 0.0))


@dataclass(frozen=True)
class MinMaxStep:
    """One MM-LB-NMPC step's problem and answer, for re-solving it elsewhere (bench: CasADi/IPOPT)."""
    problem: HorizonProblem
    bound: np.ndarray        # (K, 3) mm_sigmas * sigma of the boundary sequences (eq. 6.5)
    w0: np.ndarray           # the warm start
    w_limit: np.ndarray      # (K,) |w| bounds
    w: np.ndarray            # the solution


class MMLBNMPCLaw:
    """Min-Max LB-NMPC (thesis ch. 6). `model_for(ctx)`: the GP of the local window or None."""
    name = "mm-lb-nmpc"

    def __init__(self, settings: NMPCSettings, dt: float, model_for: Callable[[StepContext], object] = lambda c: None):
        self.settings = settings
        self.dt = dt
        self.model_for = model_for
        self.last_plan: Plan | None = None
        self.last_step: MinMaxStep | None = None
        self._qp: MinMaxQP | None = None

    def angular(self, ctx: StepContext) -> LawResult:
        s = self.settings
        gp = self.model_for(ctx)
        probes = () if self.last_plan is None else (shifted(self.last_plan.w),)
        problem, w_limit = build_problem(ctx, s, self.dt, gp, probes)
        u0 = self._warm_start(problem, w_limit)
        sig, loc, raw = self._sigmas(ctx, problem, gp, u0)
        bound = s.mm_sigmas * sig                                   # (K, 3)
        if self._qp is None or self._qp.K != problem.K:
            self._qp = MinMaxQP(problem.K)
        res = solve_minmax(problem, bound, u0, -w_limit, w_limit, self._qp, s.max_iter, s.tol, s.max_evals)
        worst_case = int(np.argmax(boundary_costs(problem, bound, res.u, False)))
        X, _ = problem.rollout(res.u, with_jac=False)
        self.last_plan = Plan(res.u, X, problem.ref.poses, res.cost, res.iterations, res.converged)
        self.last_step = MinMaxStep(problem, bound, u0, w_limit, res.u)
        return LawResult(float(res.u[0]), predicted=X[1:],
                         solve=SolveReport(res.cost, res.iterations, res.evaluations, res.status, gp is not None),
                         uncertainty=UncertaintyReport(float(sig[:, 1].max()), float(sig[:, 2].max()),
                                                       worst_case=worst_case, **_horizon_sigmas(sig, loc, raw)),
                         note=held_note(problem.model))

    def _warm_start(self, problem: HorizonProblem, w_limit: np.ndarray) -> np.ndarray:
        if self.last_plan is None:
            return np.clip(problem.w_ref, -w_limit, w_limit)
        return np.clip(shifted(self.last_plan.w), -w_limit, w_limit)

    def _sigmas(self, ctx: StepContext, problem: HorizonProblem, gp,
                u0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Route-frame sigmas (K, 3) along the warm start's plan, widened, their localizer's share and as
        the model gave them: computed once per step (the covariance moves little within a solve)."""
        s = self.settings
        A = np.empty((problem.K, 9))
        X0, _ = problem.rollout(u0, with_jac=True, a_out=A)     # the solver's first linearization reuses it
        cov = HorizonCovariance.at_start(ctx.pose_cov, problem.start, variance_model(gp, s), self.dt, s.sp_gamma,
                                         ctx.spread_factors, _floors_at(ctx, problem.v))
        loc = cov.localizer_part(X0, problem.ref.direction_rad[1:])
        raw = cov.along(problem, X0, A, problem.v, u0)[1]
        return cov.widened(raw, loc), loc, raw


@dataclass(frozen=True)
class CorridorStep:
    """One C-/RC-LB-NMPC step's problem, starting plan and answer (bench: re-solved by CasADi/IPOPT)."""
    nlp: CorridorNLP
    start: Iterate
    result: CorridorResult


class RCLBNMPCLaw:
    """(Robust) Constrained LB-NMPC (thesis ch. 7); alpha = 0 gives C-LB-NMPC. `model_for(ctx)`: the GP of
    the local window at ctx.v_mps; `model_at(ctx, v)`: the one drawn at speed v, for the speed ladder's
    top rung while the law drives slower (speed_ladder.py)."""

    def __init__(self, settings: NMPCSettings, dt: float, model_for: Callable[[StepContext], object] = lambda c: None,
                 alpha: float | None = None, model_at: Callable[[StepContext, float], object] = lambda c, v: None):
        self.settings = settings
        self.dt = dt
        self.model_for = model_for
        self.model_at = model_at
        self.alpha = settings.alpha if alpha is None else alpha
        self.name = "rc-lb-nmpc" if self.alpha > 0 else "c-lb-nmpc"
        tau_w = settings.actuator_tau_s[1] if settings.actuator_tau_s else 0.0
        self.turn_lead = TurnLead.of(settings.turn_accel_max_radps2, tau_w, dt)
        self._qp: CorridorQP | None = None
        self._rung = 0                       # the speed ladder's rung of the last step
        self.last_plan: Plan | None = None
        self.last_step: CorridorStep | None = None

    def angular(self, ctx: StepContext) -> LawResult:
        s, dt, corridor = self.settings, self.dt, self._corridor_of(ctx)
        why = corridor.contains(ctx.s_m, ctx.e_lat_m, ctx.e_head_rad, _estimate_sigmas(ctx))
        if why:
            return LawResult(0.0, v_mps=0.0, stop_reason=f"{why}: stopped")
        ctx, capped, capped_by = _capped(ctx)
        gp = self.model_for(dataclasses.replace(ctx, v_mps=self._window_speed(ctx)))
        probes = () if self.last_plan is None else (shifted(self.last_step.result.iterate.w),)
        base, _ = build_problem(ctx, s, dt, gp, probes)
        cov = HorizonCovariance.at_start(ctx.pose_cov, base.start, variance_model(gp, s), dt, s.sp_gamma,
                                         ctx.spread_factors, _floors_at(ctx, base.v))
        v, w, v_max = self._warm_start(ctx, base)
        problem = base.following(v)
        lo_lat, hi_lat, head_lim = corridor.at(problem.ref.s_m[1:])
        cap = self._band_cap(lo_lat, hi_lat, head_lim)
        A = np.empty((base.K, 9))
        # the asked speed's model costs a GP and a problem, and most steps never ask for it
        asked = functools.cache(lambda: self._asked_model(ctx, gp, probes, v))
        rung = self._speed_cap(ctx, problem, v, w, cov, cap, A, asked) if self.alpha > 0 else None
        if rung is not None:
            problem, v, w, cov = rung.problem, rung.v, rung.w, rung.cov
            gp = asked().model if rung.asked_model else gp
            v_max = np.maximum(np.minimum(v_max, rung.scale * base.v), s.v_min_mps)
        if gp is not None and s.crab_reference:    # the learned crab at the speeds this step starts from
            ref = problem.ref
            problem = problem.with_head_offset(crab_offsets(gp, ref.s_m, ref.poses, ref.direction_rad, v,
                                                            v * ref.kappa / problem.turn_gain, dt,
                                                            problem.turn_gain))
        sig = rung.sig if rung is not None else np.zeros((base.K, 3))
        nlp = CorridorNLP(problem, lo_lat, hi_lat, head_lim, cap, self.alpha, sig, np.zeros((base.K, base.K)), v,
                          v_max, ctx.w_limit_at, turn_lead=self.turn_lead)
        if rung is not None:
            nlp = dataclasses.replace(nlp, cap=reach_capped(cap, start_errors(problem), problem.effective(v)[0],
                                                            nlp.w_limits(v), dt, lo_lat, hi_lat, head_lim,
                                                            self.alpha * sig))
        start = self._start(nlp, v, w, A)
        if rung is not None and (reason := self._uncertainty_too_wide(nlp)):
            return LawResult(0.0, v_mps=0.0, predicted=start.X[1:], stop_reason=reason,
                             uncertainty=UncertaintyReport(float(sig[0, 1]), float(sig[0, 2])))
        if rung is not None:
            nlp = dataclasses.replace(nlp, dsig_v=self._sigma_speed_jacobian(problem, start, rung, cov, A),
                                      sig_floor=np.minimum(rung.cov.least(rung.sig_loc)[:, 1], sig[:, 1]))
        result = solve_corridor(nlp, start, self._qp_for(base.K))
        if rung is not None and (reason := self._crawl_stop(nlp, result.iterate, rung, base)):
            return LawResult(0.0, v_mps=0.0, predicted=result.iterate.X[1:], stop_reason=reason,
                             uncertainty=UncertaintyReport(float(sig[0, 1]), float(sig[0, 2])))
        return self._report(nlp, start, result, gp is not None, rung, cov, capped, capped_by)

    @staticmethod
    def _start(nlp: CorridorNLP, v: np.ndarray, w: np.ndarray, A: np.ndarray) -> Iterate:
        """Where the SQP starts: the warm start or, on a rate-limited steering, the one of least merit of it
        and either curvature limit held over the horizon at its speeds (nmpc.best_start: far from the
        curvature the steering has reached the cost is flat in the commands, and the SQP stalls where it
        started; bench seed 4409, MATS s1021326272 at 1.22 m/s through rough ground: turn rates of
        -0.03 to -0.14 rad/s against a -0.37 rad/s limit while the heading error grew from 1 to 13 deg).
        `A` receives the chosen start's GP inputs. A skid-steer whose drive's acceleration limit is known
        starts from the warm start brought within it (turn_accel.TurnLead)."""
        if not nlp.problem.curvature_steered:
            if nlp.turn_lead is not None:
                w = nlp.turn_lead.followable(w, nlp.problem.start.xi0[1])
            return nlp.evaluate(v, w, A)
        warm = nlp.evaluate(v, w, A)
        limit, best, best_a = nlp.w_limits(v), warm, A.copy()
        for held in (limit, -limit):
            a = np.empty_like(A)
            cand = nlp.evaluate(v, held, a)
            if cand.merit < best.merit:
                best, best_a = cand, a
        A[:] = best_a
        return best

    def _corridor_of(self, ctx: StepContext) -> Corridor:
        if ctx.corridor is None:
            raise ValueError(f"{self.name} needs a corridor ([constraints])")
        return ctx.corridor

    def _window_speed(self, ctx: StepContext) -> float:
        """The local window is drawn around the speed the law commands (thesis 5.3.2: l from v_cmd), not
        the schedule's: this law may drive well below the schedule, and experience there is what it needs."""
        if self.last_plan is None:
            return ctx.v_mps
        v = self.last_step.result.iterate.v
        return float(v[min(1, len(v) - 1)])

    def _warm_start(self, ctx: StepContext, base: HorizonProblem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(v, w) of the previous plan shifted by one period (or the schedule's), and the speed bound:
        never above the desired speeds."""
        s = self.settings
        v_max = np.minimum(np.full(base.K, ctx.v_max_mps), np.maximum(base.v, s.v_min_mps))
        if self.last_plan is None:
            return base.v.copy(), base.w_ref.copy(), v_max
        it = self.last_step.result.iterate
        return np.clip(shifted(it.v), s.v_min_mps, v_max), shifted(it.w), v_max

    def _band_cap(self, lo_lat: np.ndarray, hi_lat: np.ndarray, head_lim: np.ndarray) -> np.ndarray:
        """The most alpha * sigma may tighten each limit: beyond the first step the band keeps
        min_band_fraction of the corridor (the open-loop covariance ignores the localization updates
        still to come; without a floor the far end of the horizon is infeasible whenever uncertainty
        is high and the slack drives the solution)."""
        f = 1.0 - self.settings.min_band_fraction
        cap = np.column_stack([np.full(len(lo_lat), np.inf), f * 0.5 * (hi_lat - lo_lat), f * head_lim])
        cap[0] = np.inf
        return cap

    def _speed_cap(self, ctx: StepContext, problem: HorizonProblem, v: np.ndarray, w: np.ndarray,
                   cov: HorizonCovariance, cap: np.ndarray, A: np.ndarray,
                   asked: Callable[[], AskedModel | None] | None = None) -> Rung:
        last = self._rung if self.last_plan is not None else None
        # the drive's turn-rate limit at any speed (its curvature limit, if any, left out: speed_ladder.py)
        rung = fastest_fitting_rung(problem, v, w, cov, cap, self.alpha, ctx.w_limit_at(math.inf), last, A,
                                    _beyond(ctx, cov), ctx.spread_floors, asked)
        self._rung = rung.index
        return rung

    def _asked_model(self, ctx: StepContext, gp, probes: tuple, v: np.ndarray) -> AskedModel | None:
        """The step's problem and covariance on the window drawn at the asked speed (None: no such window,
        or it is the one the law drives with)."""
        model = self.model_at(ctx, ctx.v_mps)
        if model is None or model is gp:
            return None
        s = self.settings
        base, _ = build_problem(ctx, s, self.dt, model, probes)
        cov = HorizonCovariance.at_start(ctx.pose_cov, base.start, variance_model(model, s), self.dt, s.sp_gamma,
                                         ctx.spread_factors, _floors_at(ctx, base.v))
        return AskedModel(model, base.following(v), cov, _beyond(ctx, cov))

    def _uncertainty_too_wide(self, nlp: CorridorNLP) -> str:
        """Why the robot must stop: the first predicted step's alpha-sigma region does not fit ("" if it does)."""
        a, sig0 = self.alpha, nlp.sig_start[0]
        if min(nlp.hi_lat[0] - nlp.lo_lat[0] - 2 * a * sig0[1], nlp.head_lim[0] - a * sig0[2]) > 0:
            return ""
        return (f"predicted uncertainty no longer fits the corridor ({a:g} sigma: {a * sig0[1]:.3f} m lateral, "
                f"{math.degrees(a * sig0[2]):.1f} deg heading): stopped")

    def _crawl_stop(self, nlp: CorridorNLP, it: Iterate, rung: Rung, base: HorizonProblem) -> str:
        """Why the robot must stop at a crawl ("" if it need not): at the ladder's slowest rung, the next
        step's region (_leaving); at any crawl of a robot that turns by the metre, the plan carried on
        (_steered_out)."""
        if _at_the_slowest(rung) and (reason := self._leaving(nlp, it)):
            return reason
        return self._steered_out(nlp, it) if _crawling(rung, base, it) else ""

    def _leaving(self, nlp: CorridorNLP, it: Iterate) -> str:
        """Why the robot must stop at the slowest speed: the plan's first predicted step, with its lateral
        alpha-sigma region, reaches beyond the corridor ("" if it does not). The heading is left out: at a
        crawl the plan's own turn on the spot moves it, and the first step's spread already must fit."""
        a, e_lat, s_lat = self.alpha, float(it.E[0, 1]), float(it.sig[0, 1])
        lo, hi = float(nlp.lo_lat[0]), float(nlp.hi_lat[0])
        if lo <= e_lat - a * s_lat and e_lat + a * s_lat <= hi:
            return ""
        return (f"at the slowest speed the plan's next lateral error {e_lat:+.3f} m +- {a * s_lat:.3f} m "
                f"({a:g} sigma) reaches beyond the corridor [{lo:+.2f}, {hi:+.2f}] m: stopped")

    def _steered_out(self, nlp: CorridorNLP, it: Iterate) -> str:
        """Why a robot that turns by the metre must stop at a crawl: its plan's last step carried on for the
        lookahead distance (steered_out.py) reaches beyond the corridor with the first step's lateral
        alpha-sigma region ("" if it does not, or the robot turns by the second). The first step's: beyond it
        the band may be narrower than the spread (min_band_fraction), and the plan's own last step is
        accepted so; what this adds is where the mean goes."""
        if not nlp.problem.curvature_steered:
            return ""
        a, L = self.alpha, self.settings.lookahead_m
        low, high = lateral_reach(it.E, it.X, L)
        s_lat, lo, hi = float(it.sig[0, 1]), float(nlp.lo_lat[-1]), float(nlp.hi_lat[-1])
        if lo <= low - a * s_lat and high + a * s_lat <= hi:
            return ""
        e_out = high if high + a * s_lat > hi else low
        return (f"at a crawl the steering turns the heading error ({math.degrees(it.E[-1, 2]):+.1f} deg) back too "
                f"slowly: the lateral error reaches {e_out:+.3f} m +- {a * s_lat:.3f} m ({a:g} sigma) within "
                f"{L:g} m, beyond the corridor [{lo:+.2f}, {hi:+.2f}] m: stopped")

    def _sigma_speed_jacobian(self, problem: HorizonProblem, start: Iterate, rung: Rung, cov: HorizonCovariance,
                              A: np.ndarray) -> np.ndarray:
        """d sigma_lat / d v around the starting plan (uncertainty.py), for the SQP's tightening."""
        dvar_dv, dvar_dvprev = variance_speed_derivatives(cov.var, A)
        raw = lateral_sigma_speed_jacobian(start.X, rung.Sigma, problem.effective(start.v)[0],
                                           problem.ref.direction_rad[1:], rung.sig_model[:, 1], self.dt, dvar_dv,
                                           dvar_dvprev, None if problem.lag is None else problem.lag.Lv)
        return cov.widened_derivative(raw, rung.sig_model, rung.sig_loc)

    def _qp_for(self, K: int) -> CorridorQP:
        if self._qp is None or self._qp.K != K:
            self._qp = CorridorQP(K, self.settings.slack_weight)
        return self._qp

    @staticmethod
    def _plan_spread(nlp: CorridorNLP, it: Iterate,
                     cov: HorizonCovariance) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(widened sigmas, the localizer's share, the model's) of the plan as commanded, along its own poses
        and speeds. The SQP's sigma is a first-order line in the speeds floored at the localizer's share:
        reported as the prediction, the model's share would read 0 at the floor, and the calibration would
        take any error beyond the localizer's 3 sigma for an infinite need."""
        q = nlp.problem.following(it.v)
        A = np.empty((q.K, 9))
        X = q.rollout(it.w, False, v=it.v, a_out=A)[0]
        loc = cov.localizer_part(X, q.ref.direction_rad[1:])
        raw = cov.along(q, X, A, it.v, it.w)[1]
        return cov.widened(raw, loc), loc, raw

    def _report(self, nlp: CorridorNLP, start: Iterate, result: CorridorResult, learned: bool,
                rung: Rung | None, cov: HorizonCovariance, capped: str = "", capped_by: str = "") -> LawResult:
        it = result.iterate
        sig, loc, raw = (np.zeros_like(it.sig),) * 3 if rung is None else self._plan_spread(nlp, it, cov)
        cost = 0.5 * float(it.r @ it.r)
        self.last_step = CorridorStep(nlp, start, result)
        self.last_plan = Plan(it.w, it.X, it.reference.poses, cost, result.iterations, result.status == "converged")
        return LawResult(float(it.w[0]), v_mps=float(it.v[0]), predicted=it.X[1:],
                         solve=SolveReport(cost, result.iterations, result.evaluations, result.status, learned),
                         uncertainty=UncertaintyReport(float(sig[:, 1].max()), float(sig[:, 2].max()),
                                                       speed_scale=1.0 if rung is None else rung.scale,
                                                       violation=it.violation, **_horizon_sigmas(sig, loc, raw),
                                                       spread_kappa=_kappa(cov)),
                         note="; ".join(n for n in (held_note(nlp.problem.model), capped, _slowed(rung)) if n),
                         held_by=f"ladder-{rung.cause}" if rung is not None and rung.cause else capped_by)
