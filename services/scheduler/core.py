"""The experience-based speed scheduler (thesis chapter 4), as pure functions.

After trial j the scheduler knows, at every route vertex i, what the robot experienced passing it:
lateral and heading error, commanded angular rate and matched features (4.2.2). The next schedule is
(4.2.3-4.2.4):

1. suggest (eq. 4.2): v_sched,i + gamma1 where every criterion is comfortably met, v_sched,i - gamma2
   where any is violated beyond the deadband lambda_db, unchanged in between;
2. prune isolated increases: a run of increases shorter than `prune_min_m` metres is not increased
   (a smooth profile; a lone faster vertex only creates accelerations);
3. a-priori speed limits (eq. 4.3): the robot's v_max, slower start and end segments;
4. acceleration and deceleration limits (eq. 4.4, vertex distances of eq. 4.5), applied as a forward
   and a backward sweep so that every pair of neighbours satisfies them (one pass of eq. 4.4 with the
   suggested neighbours, as printed, would not guarantee that along a chain of changes).

Beyond the thesis (its 4.4 discussion): with `use_all_trials`, a vertex is never raised to a speed at
which an earlier trial violated a criterion there; past experience caps the increases.
A criterion without data (no matched features from a `pose` localizer) is skipped, and said so.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

INCREASE, KEEP, DECREASE = 1, 0, -1


@dataclass(frozen=True, kw_only=True)
class SchedulerParams:
    """Thesis names (table 5.1, 4.3.2); lambda_H in degrees, lambda_L in metres, lambda_omega rad/s."""
    v_init: float = 0.5
    v_max: float = 2.0
    gamma1: float = 0.2          # increase per trial (m/s)
    gamma2: float = 0.24         # decrease per trial (m/s)
    lambda_L: float = 0.15
    lambda_H: float = 10.0
    lambda_omega: float = 1.0
    lambda_feat: float = 30.0
    lambda_db: float = 1.1
    a_max: float = 0.2           # m/s^2
    a_min: float = -0.05         # m/s^2 (< 0)
    v_start: float = 0.4         # speed limit over the first start_m metres
    start_m: float = 5.0
    v_end: float = 0.4           # ... and the last end_m metres
    end_m: float = 5.0
    prune_min_m: float = 2.0
    use_all_trials: bool = False

    def __post_init__(self):
        if self.gamma1 <= 0 or self.gamma2 <= 0:
            raise ValueError("gamma1 and gamma2 must be > 0")
        if self.lambda_L < 0 or self.lambda_H < 0 or self.lambda_omega <= 0 or self.lambda_feat < 3:
            raise ValueError("lambda_L, lambda_H >= 0, lambda_omega > 0 and lambda_feat >= 3 (thesis 4.2.3)")
        if self.lambda_db <= 1:
            raise ValueError("lambda_db must be > 1 (it makes the deadband)")
        if self.a_max <= 0 or self.a_min >= 0:
            raise ValueError("a_max must be > 0 and a_min < 0")
        if not 0 < self.v_init <= self.v_max or self.v_start <= 0 or self.v_end <= 0:
            raise ValueError("speeds must be > 0 and v_init <= v_max")
        if self.start_m < 0 or self.end_m < 0 or self.prune_min_m < 0:
            raise ValueError("start_m, end_m and prune_min_m must be >= 0")


@dataclass
class VertexPasses:
    """What one trial experienced at each vertex (4.2.2). NaN where there is no data."""
    e_lat_m: np.ndarray
    e_head_rad: np.ndarray
    w_cmd_radps: np.ndarray
    features: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "VertexPasses":
        nan = np.full(n, np.nan)
        return cls(nan.copy(), nan.copy(), nan.copy(), nan.copy())

    @property
    def seen(self) -> np.ndarray:
        return np.isfinite(self.e_lat_m)


class PassCollector:
    """Accumulates a trial's passes from the controller's per-step status: per vertex the worst (largest)
    |error| and |w| and the smallest feature count seen while that vertex was the nearest one."""

    def __init__(self, n_vertices: int):
        self.passes = VertexPasses.empty(n_vertices)

    def add(self, vertex: int, e_lat: float, e_head: float, w_cmd: float, features: float | None = None) -> None:
        p = self.passes
        if not 0 <= vertex < len(p.e_lat_m):
            return
        p.e_lat_m[vertex] = np.fmax(p.e_lat_m[vertex], abs(e_lat))
        p.e_head_rad[vertex] = np.fmax(p.e_head_rad[vertex], abs(e_head))
        p.w_cmd_radps[vertex] = np.fmax(p.w_cmd_radps[vertex], abs(w_cmd))
        if features is not None:
            self.add_features(vertex, features)

    def add_features(self, vertex: int, features: float) -> None:
        if 0 <= vertex < len(self.passes.features):
            self.passes.features[vertex] = np.fmin(self.passes.features[vertex], features)


@dataclass
class Proposal:
    schedule: np.ndarray
    suggested: np.ndarray           # after eq. 4.2 and pruning, before the limits
    decisions: np.ndarray           # INCREASE / KEEP / DECREASE per vertex
    limits: np.ndarray              # eq. 4.3 limits
    notes: list[str] = field(default_factory=list)


def decide(passes: VertexPasses, p: SchedulerParams) -> tuple[np.ndarray, list[str]]:
    """Eq. 4.2 per vertex: +1 increase, -1 decrease, 0 keep (deadband or not seen)."""
    notes = []
    lam_h = math.radians(p.lambda_H)
    e_l, e_h, w = np.abs(passes.e_lat_m), np.abs(passes.e_head_rad), np.abs(passes.w_cmd_radps)
    good = (e_l < p.lambda_L) & (e_h < lam_h) & (w < p.lambda_omega)
    bad = (e_l > p.lambda_L * p.lambda_db) | (e_h > lam_h * p.lambda_db) | (w > p.lambda_omega * p.lambda_db)
    feat = passes.features
    if np.any(np.isfinite(feat)):
        has = np.isfinite(feat)
        good &= ~has | (feat > p.lambda_feat)
        bad |= has & (feat < p.lambda_feat / p.lambda_db)
    else:
        notes.append("no matched-feature counts (pose localization): the feature criterion is skipped")
    seen = passes.seen
    out = np.where(bad & seen, DECREASE, np.where(good & seen, INCREASE, KEEP))
    if not np.all(seen):
        notes.append(f"{int(np.sum(~seen))} vertices not passed: their speeds are kept")
    return out.astype(int), notes


def prune_isolated(decisions: np.ndarray, s: np.ndarray, min_run_m: float) -> np.ndarray:
    """Runs of INCREASE shorter than `min_run_m` (arc length from their first to last vertex plus one
    vertex spacing) become KEEP."""
    out = decisions.copy()
    n = len(out)
    i = 0
    while i < n:
        if out[i] != INCREASE:
            i += 1
            continue
        j = i
        while j + 1 < n and out[j + 1] == INCREASE:
            j += 1
        spacing = (s[min(j + 1, n - 1)] - s[j]) if j + 1 < n else (s[j] - s[max(j - 1, 0)])
        if s[j] - s[i] + spacing < min_run_m:
            out[i:j + 1] = KEEP
        i = j + 1
    return out


def a_priori_limits(s: np.ndarray, p: SchedulerParams) -> np.ndarray:
    """Eq. 4.3's V_max: the robot's speed limit, with slower start and end segments."""
    lim = np.full(len(s), p.v_max)
    lim[s <= s[0] + p.start_m] = min(p.v_max, p.v_start)
    lim[s >= s[-1] - p.end_m] = np.minimum(lim[s >= s[-1] - p.end_m], p.v_end)
    return lim


def acceleration_limits(v: np.ndarray, d: np.ndarray, a_max: float, a_min: float) -> np.ndarray:
    """Eq. 4.4 with the distances d[i] = d_{i,i+1} of eq. 4.5: speeding up from vertex i-1 to i by at
    most a_max, slowing down from i to i+1 by at most |a_min|, as a forward and a backward sweep."""
    out = np.asarray(v, dtype=float).copy()
    for i in range(1, len(out)):                    # acceleration, from the start onwards
        out[i] = min(out[i], math.sqrt(out[i - 1] ** 2 + 2.0 * d[i - 1] * a_max))
    for i in range(len(out) - 2, -1, -1):           # deceleration, from the end backwards
        out[i] = min(out[i], math.sqrt(out[i + 1] ** 2 - 2.0 * d[i] * a_min))
    return out


def vertex_distances(xy: np.ndarray) -> np.ndarray:
    """Eq. 4.5 between consecutive vertices."""
    return np.hypot(*np.diff(np.asarray(xy, dtype=float), axis=0).T)


def limit(v: np.ndarray, s: np.ndarray, xy: np.ndarray, p: SchedulerParams) -> tuple[np.ndarray, np.ndarray]:
    lim = a_priori_limits(s, p)
    return acceleration_limits(np.minimum(v, lim), vertex_distances(xy), p.a_max, p.a_min), lim


def initial_schedule(s: np.ndarray, xy: np.ndarray, p: SchedulerParams) -> Proposal:
    """Trial 1: v_init everywhere, within the a-priori limits."""
    v = np.full(len(s), p.v_init)
    sched, lim = limit(v, s, xy, p)
    return Proposal(sched, v, np.zeros(len(s), dtype=int), lim, [f"trial 1 at v_init = {p.v_init} m/s"])


def next_schedule(prev: np.ndarray, passes: VertexPasses, s: np.ndarray, xy: np.ndarray, p: SchedulerParams,
                  failed_at: np.ndarray | None = None) -> Proposal:
    """The schedule for trial j+1 from trial j's schedule and experience. `failed_at[i]`: the lowest
    scheduled speed at which any earlier trial decreased vertex i (inf if never), for use_all_trials."""
    decisions, notes = decide(passes, p)
    decisions = prune_isolated(decisions, s, p.prune_min_m)
    sugg = np.where(decisions == INCREASE, prev + p.gamma1, np.where(decisions == DECREASE, prev - p.gamma2, prev))
    if p.use_all_trials and failed_at is not None:
        capped = (decisions == INCREASE) & (sugg >= failed_at)
        sugg = np.where(capped, np.maximum(prev, failed_at - p.gamma2), sugg)
        if np.any(capped):
            notes.append(f"{int(np.sum(capped))} increases capped below speeds that failed in earlier trials")
    sugg = np.maximum(sugg, 0.05)   # never schedule a standstill: the robot must finish the route
    sched, lim = limit(sugg, s, xy, p)
    return Proposal(sched, sugg, decisions, lim, notes)


def failure_speeds(history: list[tuple[np.ndarray, VertexPasses]], p: SchedulerParams) -> np.ndarray:
    """Per vertex, the lowest scheduled speed of any trial in `history` whose experience there called
    for a decrease (eq. 4.2's second case); inf where none did."""
    if not history:
        return np.array([])
    out = np.full(len(history[0][0]), np.inf)
    for sched, passes in history:
        dec, _ = decide(passes, p)
        out = np.where(dec == DECREASE, np.minimum(out, sched), out)
    return out
