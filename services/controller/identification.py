"""The nominal model identified from the teach pass, instead of asked for.

Drive channels. Per channel (v, w) the command u_k held over period k against the wheel odometry y_k
(the drive's achieved speed at tick k, blind to ground slip) is fitted as a first-order lag with gain K,
time constant tau and dead time d periods, in discrete time:

    y_{k+1} = y_k + clip((1 - a)(K u_{k-d} - y_k), -R_down, R_up),     a = exp(-dt / tau)

with the drive's acceleration limit R_up (while speeding up) and braking limit R_down: a start from rest
is a ramp at the limit, which a plain lag would take for a slow one. The fit minimizes the output error,
the model's response to the commands alone (each stretch of data started at its first measurement)
against the measured y, for every d = 0..max_dead; a longer dead time is taken only where it lowers the
error clearly. (Predicting y_{k+1} from the measured y_k instead, the equation error, is biased by the
odometry's noise towards a drive without lag: on the heavy robots' teach passes it read a 0.45 s lag
as 0.05 s plus 0.2 s of dead time.) The NMPC's nominal model is a first-order lag (actuator.py): the
dead time is folded into its time constant, tau + d dt (e^{-theta s} ~ 1 / (1 + theta s) to first
order); the gain and the acceleration limit are reported, not modelled (slip against the ground is the
learned disturbance's business). An Ackermann robot's turn rate follows its speed (eq. 5.27), so w is
fitted only where the robot is moving.

Turn gain. The wheel odometry measures the drive's turn rate; the ground turns the robot at a share of
it (a skid-steer's tracks slip sideways, an Ackermann understeers; actuator.py). That share k is
identified against the localizer's heading: per period of the teach pass, the heading change of the
estimates dtheta against the lag model's p = wbar dt (from the commands, gain 1), dtheta = k p + d. A
plain fit of k would be biased by d, the heading the ground pushes (a side slope's yaw, ruts): the
teach driver counter-steers it, so p and d move together, and on a slope crossed straight the fit would
read the counter-steer as a robot that does not turn. The route's own turn over the period, z =
kappa(s) vbar dt (kappa across +-1 m), is the instrument: it is where the route turns, not where the
ground pushes, so k = sum(z dtheta) / sum(z p) over the route's corners, the straight stretches left out
whatever is pushed there. Where a corner lies on a slope the push changes with the heading through the
corner and still biases that corner's k (by 1-6 % on the tests' route), a slip patch or a rough
patch in a corner lowers its k (0.34 against 0.50-0.56 in a perturbed Grizzly's other three), and a
slope between two corners can split one into pieces that read 0.1 and 1.1 (the main job's): k pools
the corners within CORNER_SPREAD / 2 of the corners' median when they are at least half of them (both
of two); else the largest corner's k is kept (slip and rough ground lower a corner's k, a slope only
biases it by a few per cent, and 1, the old fallback, is further from the robot still: a perturbed
Grizzly of turn efficiency 0.58 read 0.52, 0.30, 0.46 and was planned with 1). A route without a corner keeps k = 1 too, and k is
at most 1: neither slip nor understeer turns a robot faster than its drive.

A-priori uncertainty. The identified model's one-period residuals on the teach pass, g_k (eq. 5.17,
body frame, from the teach pass's pose estimates and the commands), give its scale: the prior keeps
the shape std = base + per_mps |v| + per_radps |w| (uncertainty.PriorStd: errors grow with the distance
and the turn of a period) and each component is scaled so that the residuals have unit RMS against it,
c_i^2 = mean(g_i^2 / std_i^2), the maximum-likelihood scale of a Gaussian, or more where the residuals'
99th percentile lies beyond a Gaussian's (a side slope crossed once is a heavy tail). One teach speed
cannot separate the speed dependence from the base, so the shape stays an assumption and the level is
measured; the controller's online check (calibration.py) corrects the level further while it drives.

The localizer's own error is taken out where the localizer says how large it is. A one-period residual
holds the change of the estimate's error from one tick to the next (LocState.cov_step_T_vertex_robot),
and a sum of j residuals the change over j ticks, which grows from that one-tick value towards twice the
estimate's variance as the error decorrelates: V(j) = V_inf - (V_inf - V_1) rho^(j-1), rho = 1 - V_1 / V_inf
(exact for a Gauss-Markov wander). Left in, a localizer of 2-3 cm made a skid-steer's prior 4x the default,
its predicted spread wider than a 0.2 m corridor allows, and the robot stopped itself; twice the
variance taken out of every residual instead (independent estimates) took a slowly wandering 1 cm
localizer's error for all of the model's. The predicted spread carries the localizer's covariance apart
from the model's (horizon_covariance.py). A localizer that does not report its step covariance keeps
the whole residual in the model's share (cautious).
The subtraction only undoes an inflation: it lowers a level above the default's down to the default's
at most, and a level below the default is the residuals' as they are (the localizer's noise in them
errs on the cautious side). Free to go lower, the level followed a clean teach pass down and trial 1 of
RC-LB-NMPC drove fast into errors a slow teach had not shown (more violations on bench seed 9173); held
at the default or above, RC could not fit a 5 cm corridor (thesis 7.4.3) that the residuals' own level
fits (docs/results.md, stop 39).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from common.messages import LocState, NominalModel
from common.path import Path
from services.controller.actuator import MIN_TURN_GAIN, ActuatorLag
from services.controller.calibration import PLACE_BIN_M
from services.controller.experience import ExperienceBuilder, Observation
from services.controller.turn_share import TurnShare
from services.controller.uncertainty import PriorStd

MAX_DEAD_PERIODS = 5
MAX_HORIZON = 30          # periods of spread factors identified (the NMPC's horizon takes its first K)
# a longer dead time must explain the data this much better (a speed held constant for most of the pass
# leaves the residual at the odometry's noise whatever the dead time)
DEAD_TIME_GAIN = 0.05
MIN_SAMPLES = 20
# the default shape's level, down to which (not below) the localizer's step noise may lower the prior
DEFAULT_LEVEL = 1.0
# a channel whose command hardly changed says nothing about its dynamics
MIN_EXCITATION = {"v": 0.01, "w": 0.01}     # m/s, rad/s (std of the command)
# the turn gain is fitted in the route's corners: where its heading changes by more than
# CORNER_CURVATURE per metre across +-TURN_WINDOW_M, each corner turning CORNER_MIN_RAD at least; the
# corners' own estimates may differ by CORNER_SPREAD of the gain at most, its standard error MAX_TURN_GAIN_STD
TURN_WINDOW_M = 1.0
CORNER_CURVATURE = 0.05     # 1/m
CORNER_GAP = 10             # periods
CORNER_MIN_RAD = math.radians(20.0)
CORNER_SPREAD = 0.25
# a period whose commands are both below these is at rest: the model says the robot does not move
REST_MPS, REST_RADPS = 0.01, 0.01
MAX_TURN_GAIN_STD = 0.1


@dataclass(frozen=True)
class ChannelFit:
    tau_s: float          # first-order time constant
    dead_time_s: float    # whole periods
    gain: float
    rate_limit: float     # the acceleration limit the response met (m/s^2, rad/s^2); inf: none met
    rmse: float           # output error of the fit: its response to the commands against the measured (m/s or rad/s)
    samples: int

    @property
    def model_tau_s(self) -> float:
        """The time constant the first-order nominal model uses: lag and dead time together."""
        return self.tau_s + self.dead_time_s


def _steps(u: np.ndarray, y: np.ndarray, d: int, use: np.ndarray | None) -> np.ndarray:
    """The k whose step y_k -> y_{k+1} under u_{k-d} is fully known (and allowed by `use`)."""
    k = np.arange(d, len(y) - 1)
    ok = np.isfinite(y[k]) & np.isfinite(y[k + 1]) & np.isfinite(u[k - d])
    if use is not None:
        ok &= use[k]
    return k[ok]


def _rate_limited_fit(yk: np.ndarray, uk: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, float]:
    """(a, K, R) of dy = clip((1 - a)(K u - y), -R, R) by nonlinear least squares from the linear
    ARX solution, and the residual RMS: the equation-error fit, a start for the output-error one."""
    (a0, b0), *_ = np.linalg.lstsq(np.column_stack([yk, uk]), yk + dy, rcond=None)
    a0 = float(np.clip(a0, 0.0, 0.99))
    k0 = float(np.clip(b0 / max(1.0 - a0, 1e-3), 0.3, 3.0))
    r_max = float(np.max(np.abs(dy))) + 1e-9

    def resid(p):
        return np.clip((1.0 - p[0]) * (p[1] * uk - yk), -p[2], p[2]) - dy
    fit = least_squares(resid, [a0, k0, 0.9 * r_max], bounds=([0.0, 0.3, 1e-3 * r_max], [0.999, 3.0, 4.0 * r_max]))
    return fit.x, float(np.sqrt(np.mean(fit.fun ** 2)))


def _runs(k: np.ndarray) -> list[np.ndarray]:
    """Consecutive step indices, split where one is missing: each run is simulated from its first y."""
    return np.split(k, np.flatnonzero(np.diff(k) != 1) + 1) if len(k) else []


def _simulate(p, runs: list[np.ndarray], u: np.ndarray, y: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """The drive's response to the commands alone, each run started at its measured y: y_sim[k + 1] for
    every step k of the runs (as the simulator's drives: the acceleration limit while speeding up, the
    braking one otherwise), its derivatives by (a, K, R_up, R_down) carried along the recursion, and
    whether the acceleration limit was met."""
    a, gain, up, down = (float(x) for x in p)
    sim, jac, met = [], [], False
    for run in runs:
        ys, da, dk, dup, ddown = float(y[run[0]]), 0.0, 0.0, 0.0, 0.0
        for uk in u[run - d].tolist():
            target = gain * uk
            step = (1.0 - a) * (target - ys)
            speeding_up = abs(target) > abs(ys) and target * ys >= 0.0
            lim = up if speeding_up else down
            if -lim <= step <= lim:
                da, dk = ys - target + a * da, (1.0 - a) * uk + a * dk
                dup, ddown = a * dup, a * ddown
                ys += step
            else:
                sign = 1.0 if step > lim else -1.0
                met = met or speeding_up
                ys += sign * lim
                if speeding_up:
                    dup += sign
                else:
                    ddown += sign
            sim.append(ys)
            jac.append((da, dk, dup, ddown))
    return np.array(sim), np.array(jac).reshape(-1, 4), met


def _output_error_fit(u: np.ndarray, y: np.ndarray, k: np.ndarray, d: int,
                      start: np.ndarray | None = None) -> tuple[np.ndarray, float, bool]:
    """(a, K, R_up, R_down) of the rate-limited lag whose response to the commands alone is nearest the
    measured speeds, the RMS of that output error, and whether the acceleration limit was met; from
    `start`, else from the equation-error fit and from a 0.3 s lag, the better. The output error, not the
    one-step (equation) error: odometry noise sits on every measured y, and a fit that predicts y[k + 1]
    from the measured y[k] prefers a drive that ignores y[k] (no lag, a dead time and a slow ramp
    instead), which the heavy robots' teach passes showed (0.45 s read as 0.05 s + 0.2 s)."""
    runs = _runs(k)
    target = np.concatenate([y[r + 1] for r in runs])
    dy = y[k + 1] - y[k]
    r_max = float(np.max(np.abs(dy))) + 1e-9
    lo, hi = [0.0, 0.3, 1e-3 * r_max, 1e-3 * r_max], [0.999, 3.0, 4.0 * r_max, 4.0 * r_max]
    if start is None:
        (a0, k0, r0), _ = _rate_limited_fit(y[k], u[k - d], dy)
        starts = [[a0, k0, r0, r0], [math.exp(-1.0 / 3.0), k0, 0.9 * r_max, 0.9 * r_max]]
    else:
        starts = [start]
    memo: dict[bytes, tuple[np.ndarray, np.ndarray, bool]] = {}

    def run(p):
        key = np.asarray(p, dtype=float).tobytes()
        if key not in memo:
            memo.clear()
            memo[key] = _simulate(p, runs, u, y, d)
        return memo[key]
    best = None
    for x0 in starts:
        fit = least_squares(lambda p: run(p)[0] - target, np.clip(x0, lo, hi), jac=lambda p: run(p)[1],
                            bounds=(lo, hi), x_scale=[0.1, 0.1, r_max, r_max])
        if best is None or fit.cost < best.cost:
            best = fit
    return best.x, float(np.sqrt(np.mean(best.fun ** 2))), run(best.x)[2]


def fit_channel(u: np.ndarray, y: np.ndarray, dt: float, use: np.ndarray | None = None,
                max_dead: int = MAX_DEAD_PERIODS) -> ChannelFit | None:
    """First-order lag with dead time and rate limits for one channel; u[k] held over period k, y[k]
    measured at tick k (NaN: missing); `use[k]`: whether the step k -> k+1 may enter the fit. The dead
    time is the shortest whose output error no longer one is clearly below. None when the data cannot
    identify it."""
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    best, previous = None, None
    for d in range(max_dead + 1):
        k = _steps(u, y, d, use)
        if len(k) < MIN_SAMPLES:
            continue
        # each longer dead time starts from the last one's fit
        p, rmse, met = _output_error_fit(u, y, k, d, None if previous is None else previous)
        previous = p
        if best is None or rmse < best[0] * (1.0 - DEAD_TIME_GAIN):
            best = (rmse, d, p[0], p[1], p[2], met, k)
    if best is None or best[2] >= 0.999:
        return None            # no stable first-order response in these data
    rmse, d, a, gain, up, met, k = best
    tau = 0.0 if a <= 0.0 else -dt / math.log(a)
    return ChannelFit(tau_s=tau, dead_time_s=d * dt, gain=float(gain), rate_limit=up / dt if met else math.inf,
                      rmse=rmse, samples=len(k))


class TeachRecorder:
    """Collects, per tick of the teach pass: the command held from the tick on, the wheel odometry at
    the tick, and the pose estimate relative to the newest vertex when the localizer gives one. A
    repeat's commands and odometry are collected the same way for its turn drive's limit (turn_accel.py)."""

    def __init__(self, dt: float):
        self.dt = dt
        self.u: dict[int, tuple[float, float]] = {}
        self.y: dict[int, tuple[float, float]] = {}
        self.estimates: dict[int, LocState] = {}

    def add_applied(self, tick: int, v_mps: float, w_radps: float) -> None:
        """The bridge's status at `tick` reports the command held over the period that ends there."""
        if tick > 0:
            self.u[tick - 1] = (v_mps, w_radps)

    def add_odometry(self, tick: int, v_mps: float, w_radps: float) -> None:
        self.y[tick] = (v_mps, w_radps)

    def add_estimate(self, loc: LocState) -> None:
        if loc.T_vertex_robot is not None:
            self.estimates[loc.capture_tick] = loc

    def arrays(self, until_tick: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(u, y), each (n, 2) over the ticks seen (up to `until_tick`), NaN where missing."""
        ticks = sorted(t for t in set(self.u) | set(self.y) if until_tick is None or t <= until_tick)
        if not ticks:
            return np.zeros((0, 2)), np.zeros((0, 2))
        t0, n = ticks[0], ticks[-1] - ticks[0] + 1
        u, y = np.full((n, 2), np.nan), np.full((n, 2), np.nan)
        for t, val in self.u.items():
            if t0 <= t < t0 + n:
                u[t - t0] = val
        for t, val in self.y.items():
            if t0 <= t < t0 + n:
                y[t - t0] = val
        return u, y


@dataclass(frozen=True)
class DriveFit:
    v: ChannelFit | None
    w: ChannelFit | None
    notes: tuple[str, ...]

    def lag(self, dt: float, curvature_rate_max_per_ms: float = 0.0) -> ActuatorLag:
        return ActuatorLag(self.v.model_tau_s if self.v else 0.0, self.w.model_tau_s if self.w else 0.0, dt,
                           curvature_rate_max_per_ms)


def identify_drive(u: np.ndarray, y: np.ndarray, dt: float) -> DriveFit:
    """Both channels; a channel that cannot be identified keeps no lag, and the notes say why."""
    notes = []
    moving = np.abs(y[:, 0]) > 0.1 * max(float(np.nanmax(np.abs(y[:, 0]), initial=0.0)), 1e-6)
    fits = {}
    for i, name in enumerate(("v", "w")):
        excitation = float(np.nanstd(u[:, i])) if np.isfinite(u[:, i]).any() else 0.0
        fit = None
        if excitation < MIN_EXCITATION[name]:
            notes.append(f"{name}: the command hardly changed during teach (std {excitation:.3f}): no lag identified")
        else:
            fit = fit_channel(u[:, i], y[:, i], dt, use=None if name == "v" else moving)
            if fit is None:
                notes.append(f"{name}: no stable first-order response in the teach data: no lag identified")
        fits[name] = fit
    return DriveFit(fits["v"], fits["w"], tuple(notes))


@dataclass(frozen=True)
class TeachResiduals:
    """The nominal model's one-period residuals on the teach pass (body frame: along, across, heading),
    the commands they were driven with, and per residual the variances the localizer's error adds: over
    one period (`step_var`) and once decorrelated (`decorrelated_var`, its two estimates' variances);
    zero where the localizer does not say."""
    g: np.ndarray                   # (m, 3)
    u: np.ndarray                   # (m, 2)
    step_var: np.ndarray            # (m, 3)
    decorrelated_var: np.ndarray    # (m, 3)
    turn_model: np.ndarray          # (m,) the heading change the model predicted over the period (rad)
    turn_route: np.ndarray          # (m,) the route's turn over the period at the model's speed (rad)
    route_curvature: np.ndarray     # (m,) the route's heading change per metre there (1/m)
    along_m: np.ndarray | None = None   # (m,) where along the route each period began (None: not known)

    def __len__(self) -> int:
        return len(self.g)

    def noise_over(self, j: int) -> np.ndarray:
        """Per window of j consecutive residuals (m - j + 1, 3), the variance of the localizer's error
        change across it: the sum telescopes to the error of its last estimate less its first."""
        kernel = np.ones(j) / j
        v1 = np.column_stack([np.convolve(self.step_var[:, i], kernel, "valid") for i in range(3)])
        vinf = np.column_stack([np.convolve(self.decorrelated_var[:, i], kernel, "valid") for i in range(3)])
        vinf = np.maximum(vinf, v1)
        rho = np.divide(vinf - v1, vinf, out=np.zeros_like(vinf), where=vinf > 0.0)
        return vinf - (vinf - v1) * rho ** (j - 1)


def teach_observations(rec: TeachRecorder, path: Path, lag: ActuatorLag) -> Iterator[tuple[LocState, Observation]]:
    """The teach pass's disturbance observations under `lag` (experience.py, eq. 5.17), in capture order,
    each with the estimate that completed it: the commands were the teach driver's, the estimates are
    relative to the route they built."""
    builder = ExperienceBuilder(path, rec.dt, lag=lag)
    for tick in sorted(rec.estimates):
        loc = rec.estimates[tick]
        if loc.vertex >= len(path):
            continue
        for t in range(tick - lag.history_periods - 2, tick + 1):
            if t in rec.u and builder.command_at(t) is None:
                builder.add_command(t, *rec.u[t])
        obs = builder.add_estimate(tick, loc.capture_stamp_s, loc.vertex, loc.T_vertex_robot)
        if obs is not None:
            yield loc, obs


def teach_residuals(rec: TeachRecorder, path: Path, lag: ActuatorLag) -> TeachResiduals:
    """The nominal model's one-period residuals on the teach pass from the teach estimates (made
    relative to the taught route), with the localizer's share of them."""
    G, U, step, decorrelated, turn_model, speed, along = [], [], [], [], [], [], []
    for loc, obs in teach_observations(rec, path, lag):
        tick = loc.capture_tick
        G.append(obs.g)
        U.append(obs.a[5:7])
        vb, wb = lag.step(lag.state_before(tick - 1, rec.u.get), obs.a[5:7])[0]
        turn_model.append(wb * rec.dt)
        speed.append(vb)
        along.append(obs.a[0])
        before = rec.estimates.get(tick - 1)
        known = loc.cov_step_T_vertex_robot is not None and before is not None
        step.append(_body_variance(loc, loc.cov_step_T_vertex_robot) if known else np.zeros(3))
        decorrelated.append(_body_variance(loc, loc.cov_T_vertex_robot) + _body_variance(before, before.cov_T_vertex_robot)
                            if known else np.zeros(3))
    as_array = lambda rows, n: np.array(rows, dtype=float).reshape(-1, n)   # noqa: E731
    curvature = _route_turn(path, np.array(along, dtype=float))
    return TeachResiduals(as_array(G, 3), as_array(U, 2), as_array(step, 3), as_array(decorrelated, 3),
                          np.array(turn_model, dtype=float), curvature * np.array(speed) * rec.dt, curvature,
                          np.array(along, dtype=float))


def _route_turn(path: Path, s: np.ndarray) -> np.ndarray:
    """The route's heading change per metre across +-TURN_WINDOW_M of each s (1/m)."""
    lo, hi = np.maximum(s - TURN_WINDOW_M, path.s[0]), np.minimum(s + TURN_WINDOW_M, path.s[-1])
    th = np.unwrap(path.poses[:, 2])
    span = hi - lo
    return np.divide(np.interp(hi, path.s, th) - np.interp(lo, path.s, th), span,
                     out=np.zeros_like(span), where=span > 0)


@dataclass(frozen=True)
class TurnGain:
    gain: float
    std: float                          # standard error (0: not identified)
    corners: tuple[float, ...] = ()     # each corner's own estimate
    note: str = ""


def _corners(res: TeachResiduals) -> list[np.ndarray]:
    """The residuals' corners: runs where the route turns faster than CORNER_CURVATURE, joined across
    gaps of up to CORNER_GAP periods, each turning CORNER_MIN_RAD at least."""
    idx = np.flatnonzero(np.abs(res.route_curvature) > CORNER_CURVATURE)
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > CORNER_GAP) + 1) if len(idx) else []
    return [r for r in runs if abs(float(np.sum(res.turn_route[r]))) >= CORNER_MIN_RAD]


def fit_turn_gain(res: TeachResiduals) -> TurnGain:
    """The robot's turn rate over the drive's from residuals of a gain-1 model (module docstring): per
    corner k_c = sum(z dtheta) / sum(z p), z the route's turn as the instrument; pooled over the corners
    within CORNER_SPREAD / 2 of their median when they are at least half of them (both of two), else the
    largest corner's; at most 1 (neither slip nor understeer turns a robot faster than its drive)."""
    corners = _corners(res)
    if not corners:
        return TurnGain(1.0, 0.0, (), f"turn gain: no corner of {math.degrees(CORNER_MIN_RAD):.0f} deg in the "
                                      "teach pass to identify it on: 1 kept")
    z, p = res.turn_route, res.turn_model
    dtheta = p + res.g[:, 2]
    zp = np.array([float(np.dot(z[c], p[c])) for c in corners])
    zd = np.array([float(np.dot(z[c], dtheta[c])) for c in corners])
    if not np.all(zp > 0.0):
        return TurnGain(1.0, 0.0, (), "turn gain: the commands did not turn with the route: 1 kept")
    each = tuple(float(x) for x in zd / zp)
    median = float(np.median(each))
    agree = [i for i, x in enumerate(each) if abs(x - median) <= 0.5 * CORNER_SPREAD * median]
    note = ""
    if len(agree) < (len(each) + 1) // 2:      # of two, both (they lie either side of their median)
        listed = ", ".join(f"{x:.2f}" for x in each)
        agree = [int(np.argmax(each))]
        note = (f"turn gain: the corners disagree ({listed}): the ground pushes the robot in some of them; "
                f"slip and rough ground lower a corner's turn, so the largest ({max(each):.2f}, at most 1) kept")
    zp, zd, corners = zp[agree], zd[agree], [corners[i] for i in agree]
    k = float(zd.sum() / zp.sum())
    every = np.concatenate(corners)
    std = math.sqrt(float(np.mean((dtheta[every] - k * p[every]) ** 2)) * float(np.dot(z[every], z[every]))) / float(zp.sum())
    if not (MIN_TURN_GAIN <= k and std <= MAX_TURN_GAIN_STD):
        return TurnGain(1.0, 0.0, each, f"turn gain {k:.2f} +- {std:.2f} not believed: 1 kept")
    return TurnGain(min(k, 1.0), std, each, note)


def _body_variance(loc: LocState, cov: tuple[float, ...] | None) -> np.ndarray:
    """A vertex-frame covariance as variances along and across the estimate's heading, and in heading."""
    if cov is None:
        return np.zeros(3)
    c = np.asarray(cov, dtype=float).reshape(3, 3)
    th = float(loc.T_vertex_robot[2])
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    pos = R.T @ c[:2, :2] @ R
    return np.array([pos[0, 0], pos[1, 1], c[2, 2]])


def _needed_scale(err: np.ndarray, model_var: np.ndarray, noise_var: np.ndarray, z: float = 2.576) -> np.ndarray:
    """Per error, the factor c on the model's standard deviation that puts it at z sqrt(c^2 model_var +
    noise_var), by default a Gaussian's 99th percentile (0 where the noise explains it)."""
    need = np.maximum(np.square(err) / z ** 2 - noise_var, 0.0) / np.maximum(model_var, 1e-18)
    return np.sqrt(need)


def _level(g: np.ndarray, var: np.ndarray, noise_var: np.ndarray) -> np.ndarray:
    """Per component, the scale on the shape's std that fits the residuals less `noise_var`: their RMS,
    or wider where they have heavy tails (a side slope crossed once): 99 % of them within 2.576 sigma,
    as a Gaussian's."""
    rms = np.sqrt(np.maximum(np.mean((np.square(g) - noise_var) / var, axis=0), 0.0))
    return np.maximum(rms, np.quantile(_needed_scale(g, var, noise_var), 0.99, axis=0))


def scaled_prior(res: TeachResiduals, shape: PriorStd = PriorStd()) -> tuple[PriorStd, np.ndarray]:
    """The prior of `shape` scaled per component to the residuals' spread, and the scales. The
    localizer's step noise is taken out of a level above the default's only, down to the default's at
    most: below it, the residuals as they are decide (see the module's docstring)."""
    var = shape.std(res.u) ** 2
    raw = _level(res.g, var, np.zeros_like(res.g))
    scale = np.maximum(_level(res.g, var, res.step_var), np.minimum(raw, DEFAULT_LEVEL))
    c = tuple(float(x) for x in scale)
    prior = PriorStd(base=tuple(b * s for b, s in zip(shape.base, c)),
                     per_mps=tuple(p * s for p, s in zip(shape.per_mps, c)),
                     per_radps=tuple(p * s for p, s in zip(shape.per_radps, c)))
    return prior, scale


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _window_needs(res: TeachResiduals, var: np.ndarray, j: int, z: float) -> np.ndarray:
    """Per window of j consecutive residuals (m - j + 1,), the factor on the prior's spread that puts the
    window's summed lateral and heading residuals (the larger) at z sigma, the localizer's share aside."""
    kernel = np.ones(j)
    noise = res.noise_over(j)
    need = [_needed_scale(np.convolve(res.g[:, i], kernel, "valid"), np.convolve(var[:, i], kernel, "valid"),
                          noise[:, i], z) for i in (1, 2)]
    return np.maximum(*need)


def horizon_factors(res: TeachResiduals, prior: PriorStd, steps: int = MAX_HORIZON) -> np.ndarray:
    """Per horizon step j, the factor on the prior's spread that held the teach pass's own errors: its
    residuals summed over j consecutive periods against the spread the prior gives them (independent per
    period, as the sigma-point transform propagates it). A disturbance tied to a place (a slope's push)
    repeats period after period, and the sum grows like j where the prior's spread grows like sqrt(j):
    the online check (calibration.py) starts from these factors. Lateral and heading alike; the factor
    holds 99 % of them where a Gaussian's 2.576 sigma would, the localizer's share of each sum aside."""
    var = prior.std(res.u) ** 2
    out = np.ones(steps)
    for j in range(1, min(steps, len(res)) + 1):
        out[j - 1] = max(1.0, float(np.quantile(_window_needs(res, var, j, 2.576), 0.99)))
    return out


def place_factors(res: TeachResiduals, prior: PriorStd, steps: int = MAX_HORIZON) -> tuple[np.ndarray, np.ndarray]:
    """(bins, steps): per PLACE_BIN_M of the route from its start, per horizon step j, the factor on the
    prior's spread that held at 3 sigma every window of j residuals begun there (at least 1); and (bins,)
    the fastest speed commanded there. The teach pass is the route's first pass: the online check
    remembers the errors of a place from one pass to the next (calibration.py), and these seed that
    memory for trial 1. The global factors above forget a rough patch once the check has seen WINDOW calm
    predictions; the place's do not.

    Windows spent wholly at rest are left out: there the model's spread is its base alone, far below the
    localizer's step noise, so one estimate a little beyond 3 sigma of that noise reads as a need of
    several times the model's spread, which the place would then put on every plan at speed (bench seed
    1583's Grizzly s359857086: 2.9 from the teach pass's stop at the route's end, which stopped trials
    3-5 six metres before it)."""
    if res.along_m is None or not len(res):
        return np.ones((0, steps)), np.zeros(0)
    var = prior.std(res.u) ** 2
    bins = np.floor(np.maximum(res.along_m, 0.0) / PLACE_BIN_M).astype(int)
    out = np.ones((int(bins.max()) + 1, steps))
    moving = ((np.abs(res.u[:, 0]) >= REST_MPS) | (np.abs(res.u[:, 1]) >= REST_RADPS)).astype(float)
    for j in range(1, min(steps, len(res)) + 1):
        need = _window_needs(res, var, j, 3.0) * (np.convolve(moving, np.ones(j), "valid") > 0)
        np.maximum.at(out[:, j - 1], bins[:len(need)], need)
    speed = np.zeros(len(out))
    np.maximum.at(speed, bins, np.abs(res.u[:, 0]))
    return out, speed


def place_turn_shares(res: TeachResiduals, path: Path, w_limit: Callable[[float], float], turn_gain: float,
                      dt: float, bins: int) -> np.ndarray:
    """(bins,) per PLACE_BIN_M of the route, the largest share of the steering margin the teach driver's
    commands took there (turn_share.py, the route's own turn at the pass's speed left out). The teach
    pass is trial 1's only pass over a place: a patch whose yaw took the teach driver's whole margin at
    0.8 m/s is not entered at twice that by a trial that has seen it only through the prior's spread."""
    out = np.zeros(bins)
    if res.along_m is None or not len(res):
        return out
    share = TurnShare(dt, w_limit)
    kappa = np.interp(res.along_m, path.s, path.curvature)
    for (v, w), k, s in zip(res.u.tolist(), kappa.tolist(), res.along_m.tolist()):
        x = share.add(v, w, k * v / turn_gain)
        b = min(max(math.floor(s / PLACE_BIN_M), 0), bins - 1)
        if not math.isnan(x) and x > out[b]:
            out[b] = x
    return out


def identify(rec: TeachRecorder, path: Path, robot: str, stamp_s: float, shape: PriorStd = PriorStd(),
             curvature_rate_max_per_ms: float = 0.0,
             w_limit: Callable[[float], float] | None = None) -> NominalModel:
    """The nominal model of the robot that drove this teach pass, as the controller will use it. An
    Ackermann robot's steering-rate limit comes with it (the robot's limits, as its steering-angle limit
    does): a teach pass driven smoothly never shows it, and it is what bounds a fast repeat's turns.
    `w_limit`: the robot's turn-rate limit at a speed, for the share of it the teach pass took (None: none
    recorded)."""
    u, y = rec.arrays()
    drive = identify_drive(u, y, rec.dt)
    lag = drive.lag(rec.dt, curvature_rate_max_per_ms)
    res = teach_residuals(rec, path, lag)
    notes = list(drive.notes)
    turn = TurnGain(1.0, 0.0)
    if len(res) >= MIN_SAMPLES:
        turn = fit_turn_gain(res)
        notes += [turn.note] if turn.note else []
        if turn.gain != 1.0:
            lag = replace(lag, turn_gain=turn.gain)
            res = teach_residuals(rec, path, lag)
    if len(res) >= MIN_SAMPLES:
        prior, scale = scaled_prior(res, shape)
        factors, (places, place_speeds) = horizon_factors(res, prior), place_factors(res, prior)
        if not res.step_var.any():
            notes.append("the localizer does not report its step covariance: its noise counts as the model's")
    else:
        prior, scale, factors = shape, np.ones(3), np.ones(MAX_HORIZON)
        places, place_speeds = np.ones((0, MAX_HORIZON)), np.zeros(0)
        notes.append(f"only {len(res)} teach residuals (no teach pose estimates?): the default prior is kept")
    shares = place_turn_shares(res, path, w_limit, lag.turn_gain, rec.dt, len(place_speeds)) \
        if w_limit is not None else np.zeros(len(place_speeds))
    fit = lambda c, attr, default: getattr(c, attr) if c is not None else default   # noqa: E731
    return NominalModel(
        stamp_s=stamp_s, robot=robot, path_id=path.path_id, dt_s=rec.dt, model_tag=lag.model_tag,
        tau_v_s=fit(drive.v, "tau_s", 0.0), tau_w_s=fit(drive.w, "tau_s", 0.0),
        dead_time_v_s=fit(drive.v, "dead_time_s", 0.0), dead_time_w_s=fit(drive.w, "dead_time_s", 0.0),
        gain_v=fit(drive.v, "gain", 1.0), gain_w=fit(drive.w, "gain", 1.0),
        rate_limit_v_mps2=_finite(fit(drive.v, "rate_limit", math.inf)),
        rate_limit_w_radps2=_finite(fit(drive.w, "rate_limit", math.inf)),
        fit_rmse_v_mps=fit(drive.v, "rmse", 0.0), fit_rmse_w_radps=fit(drive.w, "rmse", 0.0),
        samples_v=fit(drive.v, "samples", 0), samples_w=fit(drive.w, "samples", 0),
        actuator_tau_s=(lag.tau_v_s, lag.tau_w_s), curvature_rate_max_per_ms=lag.curvature_rate_max_per_ms,
        turn_gain=lag.turn_gain, turn_gain_std=turn.std,
        prior_std_base=prior.base, prior_std_per_mps=prior.per_mps,
        prior_std_per_radps=prior.per_radps, prior_scale=tuple(float(s) for s in scale),
        spread_factors=[float(f) for f in factors], place_bin_m=PLACE_BIN_M,
        place_spread_factors=[[round(float(f), 4) for f in row] for row in places],
        place_speed_mps=[round(float(v), 4) for v in place_speeds],
        place_turn_share=[round(float(x), 4) for x in shares],
        residual_samples=len(res), notes=notes)
