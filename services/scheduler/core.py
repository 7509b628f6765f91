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
   The thesis's DMRV used a_max = 0.2 and a_min = -0.05 m/s^2 (4.3.2) with the single pass, which holds
   back only the vertex just before a slower one. Swept, -0.05 makes a robot at 2 m/s start slowing 38 m
   ahead of every slower section and of the end segment: most of a 30-120 m route. The default deceleration
   is therefore as gentle as the acceleration, -0.2 m/s^2 (2 -> 0.4 m/s in 9.6 m); set a_min = -0.05 for
   the thesis's experiments (examples/sched-mats.toml does).

Beyond the thesis (its 4.4 discussion): with `use_all_trials` (or the guard, G7), a vertex is never raised
to a speed at which an earlier trial violated a criterion there; past experience caps the increases.
A criterion without data (no matched features from a `pose` localizer) is skipped, and said so.

The guard (`guard`, on by default; off, the schedule is eq. 4.2-4.5 exactly). Eq. 4.2 raises a vertex
by gamma1 when its criteria were met at the *old* speed; it does not ask whether they will be met at
the new one: a turn that took 0.86 rad/s at 0.7 m/s is scheduled at 0.9 m/s, where it takes ~1.1 rad/s
against a 1.2 rad/s limit, and the corrections on top of that saturate the controller. The guard asks of
a prediction at the new speed what eq. 4.2 asks of the last pass, with a margin, and caps the increase
there (it never lowers a speed for a prediction at a new speed; G5 holds back decreases that did not
help, G6 lowers where the errors grow at one speed, G8 holds an Ackermann's turn against a slope). For
each criterion c (|e_L|, |e_H| of eq. 4.1 and |omega_cmd| of 4.2.2) and vertex i, over the latest
`guard_trials` trials t:

  (G1) of the passes of trial t within guard_radius_m of vertex i (a peak moves a little with speed),
       the one with the largest c / v: E_t,i its value, V_t,i its commanded speed (the scheduled one
       where none was recorded);
  (G2) proportional growth from the latest pass, c(v) = E_last v / V_last: the turn rate follows the
       route's curvature, omega = v kappa, and the controller's corrections grow with speed with it;
       and the least-squares line c(v) = a + b v through the trials' (V, E) when their speeds spread
       over at least gamma1 / 2 (a closer fit is noise) and b > 0: growth faster than proportional,
       as a drive lag makes near a robot's limits;
  (G3) the cap v_cap,i = the lowest speed at which either (G2) reaches its bound: guard_share * lambda_L,
       guard_share * lambda_H, and for the turn rate min(lambda_omega, guard_share * w_max): eq. 4.2's
       own turn-rate threshold, and headroom under the robot's limit for the corrections on top of the
       predicted peak (eq. 4.2 alone never sees a saturated turn rate exceed a lambda_omega set at or
       above w_max); then v_sugg,i <- max(v_sched,i, min(v_sugg,i, v_cap,i)) for the increased
       vertices, before eq. 4.3-4.4.
  (G4) no cap lies below v_init, the speed trial 1 ran at, and for the two tracking errors no growth is
       modelled below it (their pass speeds count as at least v_init in G1-G2). Errors from disturbances
       that act per second (slip down a side slope) grow as the robot slows, so proportional growth
       extrapolated from a pass at a crawl (a vertex eq. 4.2 lowered to 0.05 m/s) would hold it at that
       crawl, and at its larger errors, for good; below v_init the speeds are eq. 4.2's alone. The turn
       rate keeps its real pass speeds: omega = v kappa is proportional at any speed.

  (G5) a decrease is withheld where slowing has not helped: where an earlier trial passed a vertex
       faster than the latest (by at least gamma2 / 2) and the latest pass's worst tracking error within
       guard_radius_m, as a share of its limit (max |e_L| / lambda_L, |e_H| / lambda_H), fell by less
       than `guard_help` of the proportional fall, e_slow > e_fast (1 - guard_help (1 - v_slow / v_fast)).
       A side slope slides the robot per second, not per metre: slowing there leaves the error as it was
       or makes it larger, spends longer in the slide, and puts the robot in a speed bin its learned model
       has no experience of; eq. 4.2 alone lowers such a vertex trial after trial to the 0.05 m/s floor
       (a perturbed Grizzly on an 8.5 deg slope: 0.34 m at 0.5 m/s, 0.32 m at 0.26 m/s, then 200 s a
       trial crawling at 0.05 m/s with errors of 0.26-0.64 m). Held at its speed, the vertex is driven at
       one speed trial after trial, which the learned model can learn. A vertex whose turn rate broke its
       criterion is lowered as eq. 4.2 says: omega = v kappa falls with the speed.

  (G5b) a vertex goes back to an earlier trial's speed where slowing made it worse: where the latest pass
       took a tracking limit or more (its worst share of the limits nearby, as G5 reads it, >= 1) and an
       earlier trial passed faster (by at least gamma2 / 2) with a smaller worst share, it is scheduled
       at that trial's speed (the one with the smallest share). G5 only stops the slowing; the vertex
       stays at the speed that did worse, trial after trial (bench seed 3607's Grizzly s584978763, a
       12.5 deg side slope and a slip patch in a 0.248 m corridor: 0.245 m at 0.5 m/s in trial 1, then
       0.35-0.41 m at 0.26 m/s and below in trials 2-8, every one beyond the corridor). Not where the
       latest turn rate broke its criterion (slowing is what cuts that).

  (G6) a vertex is lowered where its errors grow from trial to trial towards the limit at a speed that
       does not explain it: a rut that deepens with every pass, a patch that wears. With the worst share
       of the limits nearby as in G5, S_t (latest) and S_t-1, and the pass speeds V (counted as at least
       v_init, G4), the growth the speed leaves unexplained is d = S_t - S_t-1 V_t / V_t-1. Where the
       latest pass took at least guard_share of a limit and S_t + d > 1 (the next pass, at the same speed,
       beyond its limit), the vertex is lowered by gamma2 as eq. 4.2 would lower it one trial later, after
       the violation (bench seed 4127's MATS s277878960, a corner over a rut deepening 9 mm a pass:
       heading errors of 6.1, 8.0 and 9.3 deg in trials 5-7 against a 10.5 deg corridor, then 13.0 deg).
       G5 holds it back like any decrease. Not below v_init: G6 lowers no vertex further than v_init, and
       one at or below it (eq. 4.2 slowed it, or eq. 4.3's segments) is only kept from rising. As in G4
       and G7, below trial 1's speed growth says little about speed: it is as often a side slope's slide,
       which a crawl makes longer, as a rut's (bench seed 5261's Grizzly s2052584713, a 14 deg slope over
       a rut: G6 took the end of its loop from 0.26-0.43 m/s to 0.05-0.19 m/s, and the errors grew at the
       crawl).

  (G7) a vertex is never raised again to within gamma2 (eq. 4.2's step down) of a speed at which any
       earlier trial went beyond eq. 4.2's deadband within guard_radius_m of it (`use_all_trials`, on with
       the guard, over G1's neighbourhood: a swing that peaks beyond the limit began before its peak). A
       failure at trial 1's speed counts only where a slower pass met the criteria there, and one below it
       (eq. 4.3's start and end segments, eq. 4.2's decreases) never: as in G4, such a pass alone says
       nothing about speed, and remembered, it would keep a side slope's vertex at eq. 4.2's crawl for
       good, or an end segment below its a-priori speed for a spike of the estimate's noise (bench seed
       1931's Grizzly s187421464: 0.21 m at 0.4 m/s, the truth within 0.12 m). Once slowing has kept the
       errors within the deadband, a failure at v_init does say something about speed (bench seed
       2029's Husky s1330754404, 11.5 deg side slope, 8.1 deg corridor: 8.8 deg at v_init 0.5 m/s, 6.5
       deg at 0.34 m/s, then raised by eq. 4.2 and G2 to 0.48 m/s, 9.1 deg; at 0.51 m/s in trial 8, 9.6
       deg). Within gamma2 of it, not only at it: a raise that stops just short of the failed speed (0.48
       against 0.50 m/s) meets about the same errors. G2 looks at the latest guard_trials only, and
       some errors do not grow smoothly with speed: bench seed 1931's MATS s93349841 (Ackermann, a rough
       rutted patch at its curvature limit) swung 2-5 deg at 0.5-0.86 m/s in every trial and 11.3 deg at
       0.9 m/s in trial 3; lowered there, then raised by eq. 4.2 with G2 fitting trials 4-6 at 0.66-0.86
       m/s, it swung 10.8 deg at 1.0 m/s in trial 7.

  (G8) on a curvature-limited robot (an Ackermann, kappa_max), a vertex is not lowered below v_init where a
       pass within guard_radius_m turned at its curvature limit (|omega_cmd| >= AUTHORITY_SHARE kappa_max v)
       on a stretch of route straighter than kappa_max / 2. Its heading can change by at most v kappa_max
       per second, and what held it there was not the route but a disturbance that acts per second (a side
       slope's yaw and slide): slower, it has less of the turn it needs. Bench seed 9973's MATS s1638813658
       (14.6 deg side slope): 0.25 m at 0.5 m/s turning at the limit, 0.15 rad/s; eq. 4.2 lowered it to
       0.26 m/s, where the limit is 0.08 rad/s against the slope's 0.064 rad/s, and it slid 0.51 m. Above
       v_init the decreases are eq. 4.2's (slowing cuts a lag's overshoot, G7 remembers where it failed).

The learned model's variance at the new speed bin (thesis 5.3.2, 7.2) would be a third prediction, but
it lives in the store and describes the disturbance, not the errors and turn rates the controller will
produce with it; the passes predict those directly, without a query on the bus, so the guard uses them
only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

INCREASE, KEEP, DECREASE = 1, 0, -1
AUTHORITY_SHARE = 0.9   # a pass turning at this share of v kappa_max or more is at its curvature limit (G8)


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
    a_min: float = -0.2          # m/s^2 (< 0); the thesis's -0.05 was for eq. 4.4 applied once (module doc)
    v_start: float = 0.4         # speed limit over the first start_m metres
    start_m: float = 5.0
    v_end: float = 0.4           # ... and the last end_m metres
    end_m: float = 5.0
    prune_min_m: float = 2.0
    use_all_trials: bool = False # never raise a vertex to where an earlier trial failed (on with the guard, G7)
    guard: bool = True           # cap increases at the speed the next trial can be expected to hold (module doc)
    w_max: float | None = None   # the robot's turn-rate limit (rad/s), set by the deployment; None: unknown,
                                 # the guard then holds predicted turn rates under lambda_omega alone
    guard_share: float = 0.8     # predictions at the new speed may reach this share of lambda_L, lambda_H
                                 # and w_max (G3)
    guard_radius_m: float = 3.0  # passes this close to a vertex count as its own (G1)
    guard_trials: int = 3        # the latest trials the growth with speed is fitted over (G2)
    guard_help: float = 0.5      # slowing must have cut the error by this share of its proportional fall (G5)
    kappa_max: float | None = None  # the robot's curvature limit (1/m), set by the deployment for an Ackermann;
                                    # None: not curvature-limited (G8 off)

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
        if self.w_max is not None and not self.w_max > 0:
            raise ValueError("w_max must be > 0 (or left out: unknown)")
        if not 0 < self.guard_share <= 1 or self.guard_radius_m < 0 or self.guard_trials < 1:
            raise ValueError("guard_share must be in (0, 1], guard_radius_m >= 0 and guard_trials >= 1")
        if not 0 < self.guard_help <= 1:
            raise ValueError("guard_help must be in (0, 1]")
        if self.kappa_max is not None and not self.kappa_max > 0:
            raise ValueError("kappa_max must be > 0 (or left out: not curvature-limited)")


@dataclass
class VertexPasses:
    """What one trial experienced at each vertex (4.2.2), and the commanded speed it passed at (for the
    guard's G1). NaN where there is no data; v_mps left out: not recorded (all NaN)."""
    e_lat_m: np.ndarray
    e_head_rad: np.ndarray
    w_cmd_radps: np.ndarray
    features: np.ndarray
    v_mps: np.ndarray | None = None

    def __post_init__(self):
        if self.v_mps is None:
            self.v_mps = np.full(len(self.e_lat_m), np.nan)

    @classmethod
    def empty(cls, n: int) -> "VertexPasses":
        nan = np.full(n, np.nan)
        return cls(nan.copy(), nan.copy(), nan.copy(), nan.copy(), nan.copy())

    @property
    def seen(self) -> np.ndarray:
        return np.isfinite(self.e_lat_m)


class PassCollector:
    """Accumulates a trial's passes from the controller's per-step status: per vertex the worst (largest)
    |error|, |w| and commanded speed, and the smallest feature count seen while that vertex was the
    nearest one."""

    def __init__(self, n_vertices: int):
        self.passes = VertexPasses.empty(n_vertices)

    def add(self, vertex: int, e_lat: float, e_head: float, w_cmd: float, features: float | None = None,
            v_cmd: float | None = None) -> None:
        p = self.passes
        if not 0 <= vertex < len(p.e_lat_m):
            return
        p.e_lat_m[vertex] = np.fmax(p.e_lat_m[vertex], abs(e_lat))
        p.e_head_rad[vertex] = np.fmax(p.e_head_rad[vertex], abs(e_head))
        p.w_cmd_radps[vertex] = np.fmax(p.w_cmd_radps[vertex], abs(w_cmd))
        if v_cmd is not None:
            p.v_mps[vertex] = np.fmax(p.v_mps[vertex], abs(v_cmd))
        if features is not None:
            self.add_features(vertex, features)

    def add_features(self, vertex: int, features: float) -> None:
        if 0 <= vertex < len(self.passes.features):
            self.passes.features[vertex] = np.fmin(self.passes.features[vertex], features)


@dataclass
class Proposal:
    schedule: np.ndarray
    suggested: np.ndarray           # after eq. 4.2, pruning and the guard, before the limits
    decisions: np.ndarray           # INCREASE / KEEP / DECREASE per vertex (eq. 4.2's, before the guard)
    limits: np.ndarray              # eq. 4.3 limits
    notes: list[str] = field(default_factory=list)
    caps: GuardCaps | None = None   # the guard's ceilings (None: guard off)


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
                  failed_at: np.ndarray | None = None, caps: GuardCaps | None = None,
                  withhold: np.ndarray | None = None, worsening: np.ndarray | None = None,
                  turn_limited: np.ndarray | None = None, restore: np.ndarray | None = None) -> Proposal:
    """The schedule for trial j+1 from trial j's schedule and experience. `failed_at[i]`: the lowest
    scheduled speed at which any earlier trial decreased vertex i (inf if never), for use_all_trials and G7;
    `caps`: the guard's ceilings (guard_caps), `withhold`: the decreases it holds back (unhelpful_decreases),
    `worsening`: the vertices it lowers, no further than v_init, or keeps from rising below it
    (growing_errors), `turn_limited`: the vertices not lowered below v_init (curvature_limited); all None
    for the thesis rule alone."""
    decisions, notes = decide(passes, p)
    decisions = prune_isolated(decisions, s, p.prune_min_m)
    sugg, lower, more = suggest(decisions, prev, p, withhold, worsening)
    notes += more
    if turn_limited is not None:
        kept = lower & turn_limited & (sugg < np.minimum(prev, p.v_init))
        sugg = np.where(kept, np.minimum(prev, p.v_init), sugg)
        if np.any(kept):
            notes.append(f"guard: {int(np.sum(kept))} vertices not lowered below v_init where the robot turned at "
                         f"its curvature limit against a disturbance")
    raised = np.where(lower, DECREASE, decisions)     # the increases left once G6 has lowered some
    if failed_at is not None:
        held = np.maximum(prev, failed_at - p.gamma2)
        # the thesis's use_all_trials caps a raise that reaches a failed speed; the guard (G7) one that comes
        # within eq. 4.2's step down of it, which is about as fast
        reach = failed_at - (p.gamma2 if p.guard else 0.0)
        # the 1e-9: 0.7 + 0.2 is 0.8999999999999999
        capped = (raised == INCREASE) & (sugg >= reach - 1e-9) & (sugg > held + 1e-9)
        sugg = np.where(capped, held, sugg)
        if np.any(capped):
            notes.append(f"{int(np.sum(capped))} increases capped below speeds that failed in earlier trials")
    if caps is not None:
        sugg, note = apply_guard(sugg, prev, raised, caps)
        notes += [note] if note else []
    if restore is not None and np.any(restore > sugg + 1e-9):
        back = restore > sugg + 1e-9
        sugg = np.where(back, restore, sugg)
        notes.append(f"guard: {int(np.sum(back))} vertices back at an earlier pass's speed where slowing down made "
                     f"the tracking error larger")
    sugg = np.maximum(sugg, 0.05)   # never schedule a standstill: the robot must finish the route
    sched, lim = limit(sugg, s, xy, p)
    return Proposal(sched, sugg, decisions, lim, notes, caps)


def suggest(decisions: np.ndarray, prev: np.ndarray, p: SchedulerParams, withhold: np.ndarray | None = None,
            worsening: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Eq. 4.2's suggestion from `decisions` and the speeds `prev`, with G5 (`withhold`: decreases kept at
    their speed) and G6 (`worsening`: lowered by gamma2 but no further than v_init; at or below v_init kept
    from rising). Returns the suggestion, the vertices lowered and the guard's notes."""
    notes: list[str] = []
    lower = decisions == DECREASE
    grown = np.zeros(len(lower), dtype=bool) if worsening is None else worsening & ~lower
    slow = grown & (prev <= p.v_init + 1e-9)   # G6 acts above v_init only: below it the speeds are eq. 4.2's
    grown &= ~slow
    lower |= grown
    if withhold is not None and np.any(lower & withhold):
        notes.append(f"guard: {int(np.sum(lower & withhold))} decreases withheld where slowing down did not "
                     f"cut the tracking error")
        lower &= ~withhold
    if np.any(grown & lower):     # said after G5, which may hold some of them back
        notes.append(f"guard: {int(np.sum(grown & lower))} vertices lowered where the errors grew towards the "
                     f"limit from trial to trial")
    floored = slow | (grown & lower & (prev - p.gamma2 < p.v_init))
    if np.any(floored):
        notes.append(f"guard: {int(np.sum(floored))} vertices whose errors grew kept at v_init, or at their speed "
                     f"below it")
    sugg = np.where(lower, prev - p.gamma2, np.where(decisions == INCREASE, prev + p.gamma1, prev))
    sugg = np.where(grown & lower, np.maximum(sugg, p.v_init), np.where(slow, np.minimum(sugg, prev), sugg))
    return sugg, lower, notes


def plan(prev: np.ndarray, passes: VertexPasses, history: list[tuple[np.ndarray, VertexPasses]], s: np.ndarray,
         xy: np.ndarray, p: SchedulerParams, route_kappa: np.ndarray | None = None) -> Proposal:
    """The next schedule as the service makes it: from the latest trial's `passes` (eq. 4.2-4.5), capped by
    the earlier trials of `history` (each trial's schedule and passes, oldest first, this one included)
    where use_all_trials and the guard ask for them. `route_kappa`: the route's curvature per vertex (1/m),
    for G8 (None: G8 off)."""
    failed = failure_speeds(history, p) if (p.use_all_trials or p.guard) and history else None
    if failed is not None and p.guard:          # G7: above v_init, or at it and met slower; over G1's neighbourhood
        at_v_init = (np.abs(failed - p.v_init) < 1e-9) & (met_speeds(history, p) < failed - 1e-9)
        counted = (failed > p.v_init + 1e-9) | at_v_init
        failed = nearby_min(np.where(counted, failed, np.inf), *neighbourhoods(s, p.guard_radius_m))
    caps = guard_caps(history, s, p) if p.guard and history else None
    withhold = unhelpful_decreases(history, s, p) if p.guard else None
    worsening = growing_errors(history, s, p) if p.guard else None
    limited = (curvature_limited(prev, passes, s, route_kappa, p)
               if p.guard and p.kappa_max is not None and route_kappa is not None else None)
    restore = faster_and_better(history, s, p) if p.guard else None
    return next_schedule(prev, passes, s, xy, p, failed, caps, withhold, worsening, limited, restore)


# --- the guard (module doc, G1-G8) ----------------------------------------------------------------------
CRITERIA = ("lateral error", "heading error", "turn rate")


@dataclass(frozen=True)
class GuardCaps:
    """Per vertex, the highest speed the guard lets an increase reach (inf where nothing caps it) and
    the criterion that set it (an index into CRITERIA; -1 where none)."""
    v_cap: np.ndarray
    by: np.ndarray


def guard_limits(p: SchedulerParams) -> np.ndarray:
    """G3's bounds on the predicted |e_L| (m), |e_H| (rad) and |omega_cmd| (rad/s)."""
    w_lim = p.lambda_omega if p.w_max is None else min(p.lambda_omega, p.guard_share * p.w_max)
    return np.array([p.guard_share * p.lambda_L, p.guard_share * math.radians(p.lambda_H), w_lim])


def neighbourhoods(s: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex i, the index range [lo_i, hi_i) of the vertices within radius_m of arc length."""
    s = np.asarray(s, dtype=float)
    return np.searchsorted(s, s - radius_m, side="left"), np.searchsorted(s, s + radius_m, side="right")


def pass_speeds(sched: np.ndarray, passes: VertexPasses) -> np.ndarray:
    """The speed each vertex was passed at: the commanded one where recorded, else the scheduled one."""
    v = passes.v_mps
    return np.where(np.isfinite(v) & (v > 0), v, np.asarray(sched, dtype=float))


def worst_nearby(values: np.ndarray, v: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """G1: per vertex, of the passes within its neighbourhood the one with the largest |value| / speed
    (the steepest proportional growth): its |value| and speed (both NaN where there is no pass)."""
    ok = np.isfinite(values) & np.isfinite(v) & (v > 0)
    ratio = np.where(ok, np.abs(values) / np.where(ok, v, 1.0), -np.inf)
    worst, at_v = np.full(len(ratio), np.nan), np.full(len(ratio), np.nan)
    for i in range(len(ratio)):
        j = lo[i] + int(np.argmax(ratio[lo[i]:hi[i]]))
        if np.isfinite(ratio[j]):
            worst[i], at_v[i] = abs(values[j]), v[j]
    return worst, at_v


def growth_cap(V: np.ndarray, E: np.ndarray, allowed: float, min_spread: float) -> np.ndarray:
    """G2-G3 per vertex (columns) from passes over trials (rows, oldest first; NaN: no pass): the
    lowest speed at which proportional growth from the latest pass, or the rising least-squares line
    through all of them, reaches `allowed`; inf where neither does."""
    V, E = np.atleast_2d(V), np.atleast_2d(E)
    have = np.isfinite(V) & np.isfinite(E)
    e_last, v_last = np.full(V.shape[1], np.nan), np.full(V.shape[1], np.nan)
    for t in range(V.shape[0]):                     # the latest pass of each vertex
        e_last, v_last = np.where(have[t], E[t], e_last), np.where(have[t], V[t], v_last)
    with np.errstate(divide="ignore", invalid="ignore"):
        prop = np.where(e_last > 0, allowed * v_last / e_last, np.inf)
        k = have.sum(axis=0)
        v0, e0 = np.where(have, V, 0.0), np.where(have, E, 0.0)
        v_mean, e_mean = v0.sum(axis=0) / k, e0.sum(axis=0) / k
        dv, de = np.where(have, V - v_mean, 0.0), np.where(have, E - e_mean, 0.0)
        slope = (dv * de).sum(axis=0) / (dv * dv).sum(axis=0)
        spread = np.where(have, V, -np.inf).max(axis=0) - np.where(have, V, np.inf).min(axis=0)
        fits = (k >= 2) & (spread >= min_spread) & (slope > 0)
        line = np.where(fits, v_mean + (allowed - e_mean) / slope, np.inf)
    return np.fmin(prop, line)


def guard_caps(history: list[tuple[np.ndarray, VertexPasses]], s: np.ndarray, p: SchedulerParams) -> GuardCaps:
    """G1-G4 over the latest guard_trials trials of `history` (each trial's schedule and passes, oldest
    first)."""
    recent = history[-p.guard_trials:]
    lo, hi = neighbourhoods(s, p.guard_radius_m)
    allowed = guard_limits(p)
    caps = np.full((len(CRITERIA), len(s)), np.inf)
    for c in range(len(CRITERIA)):
        floor = p.v_init if CRITERIA[c] != "turn rate" else 0.0      # G4
        worst = [worst_nearby((pa.e_lat_m, pa.e_head_rad, pa.w_cmd_radps)[c],
                              np.maximum(pass_speeds(sched, pa), floor), lo, hi) for sched, pa in recent]
        E, V = np.array([w[0] for w in worst]), np.array([w[1] for w in worst])
        caps[c] = growth_cap(V, E, float(allowed[c]), p.gamma1 / 2)
    v_cap = caps.min(axis=0)
    return GuardCaps(np.maximum(v_cap, p.v_init), np.where(np.isfinite(v_cap), np.argmin(caps, axis=0), -1))


def unhelpful_decreases(history: list[tuple[np.ndarray, VertexPasses]], s: np.ndarray,
                        p: SchedulerParams) -> np.ndarray:
    """G5 per vertex: an earlier trial of `history` passed it faster than the latest one, whose worst
    tracking error nearby fell by less than guard_help of the proportional fall, and whose turn rate kept
    to its criterion. All False with fewer than two trials."""
    n = len(s)
    if len(history) < 2:
        return np.zeros(n, dtype=bool)
    lo, hi = neighbourhoods(s, p.guard_radius_m)
    sched1, latest = history[-1]
    v1, e1 = pass_speeds(sched1, latest), _worst_share(latest, lo, hi, p)
    out = np.zeros(n, dtype=bool)
    for sched0, before in history[:-1]:
        v0, e0 = pass_speeds(sched0, before), _worst_share(before, lo, hi, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            expected = e0 * (1.0 - p.guard_help * (1.0 - v1 / v0))
            out |= (v1 <= v0 - p.gamma2 / 2) & (e1 > expected) & np.isfinite(e0) & np.isfinite(e1)
    return out & ~(np.abs(latest.w_cmd_radps) > p.lambda_omega * p.lambda_db)


def faster_and_better(history: list[tuple[np.ndarray, VertexPasses]], s: np.ndarray,
                      p: SchedulerParams) -> np.ndarray:
    """G5b per vertex: where the latest pass took a tracking limit or more (eq. 4.2 would not raise it) and
    an earlier trial passed faster (by at least gamma2 / 2) with a smaller worst share of the limits nearby,
    the scheduled speed of the earlier trial with the smallest; -inf elsewhere (and with fewer than two
    trials, or where the latest turn rate broke its criterion: there slowing is eq. 4.2's remedy)."""
    n = len(s)
    out = np.full(n, -np.inf)
    if len(history) < 2:
        return out
    lo, hi = neighbourhoods(s, p.guard_radius_m)
    sched1, latest = history[-1]
    v1, e1 = pass_speeds(sched1, latest), _worst_share(latest, lo, hi, p)
    best = np.where(np.isfinite(e1), e1, np.inf)
    for sched0, before in history[:-1]:
        v0, e0 = pass_speeds(sched0, before), _worst_share(before, lo, hi, p)
        with np.errstate(invalid="ignore"):
            better = (v0 >= v1 + p.gamma2 / 2) & (e0 < best) & np.isfinite(e0)
        out = np.where(better, np.asarray(sched0, dtype=float), out)
        best = np.where(better, e0, best)
    with np.errstate(invalid="ignore"):
        keep = (e1 >= 1.0) & ~(np.abs(latest.w_cmd_radps) > p.lambda_omega * p.lambda_db)
    return np.where(keep, out, -np.inf)


def growing_errors(history: list[tuple[np.ndarray, VertexPasses]], s: np.ndarray,
                   p: SchedulerParams) -> np.ndarray:
    """G6 per vertex: the latest pass took at least guard_share of a tracking limit, and its growth over
    the trial before, beyond what the speeds explain, would carry the next pass beyond the limit. All
    False with fewer than two trials."""
    n = len(s)
    if len(history) < 2:
        return np.zeros(n, dtype=bool)
    lo, hi = neighbourhoods(s, p.guard_radius_m)
    (sched0, before), (sched1, latest) = history[-2], history[-1]
    v0 = np.maximum(pass_speeds(sched0, before), p.v_init)
    v1 = np.maximum(pass_speeds(sched1, latest), p.v_init)
    e0, e1 = _worst_share(before, lo, hi, p), _worst_share(latest, lo, hi, p)
    with np.errstate(invalid="ignore"):
        grown = e1 - e0 * v1 / v0
        out = (e1 >= p.guard_share) & (e1 + grown > 1.0)
    return out & np.isfinite(e0) & np.isfinite(e1)


def curvature_limited(sched: np.ndarray, passes: VertexPasses, s: np.ndarray, route_kappa: np.ndarray,
                      p: SchedulerParams) -> np.ndarray:
    """G8 per vertex: within guard_radius_m of it the latest pass turned at the robot's curvature limit where
    the route is straighter than kappa_max / 2 (the limit was taken by a disturbance, not by the route)."""
    v = pass_speeds(sched, passes)
    with np.errstate(invalid="ignore"):
        at_limit = ((np.abs(passes.w_cmd_radps) >= AUTHORITY_SHARE * p.kappa_max * v) & (v > 0)
                    & (np.abs(np.asarray(route_kappa, dtype=float)) <= 0.5 * p.kappa_max))
    lo, hi = neighbourhoods(s, p.guard_radius_m)
    return np.array([bool(np.any(at_limit[a:b])) for a, b in zip(lo, hi)], dtype=bool)


def _worst_share(pa: VertexPasses, lo: np.ndarray, hi: np.ndarray, p: SchedulerParams) -> np.ndarray:
    """Per vertex, the largest of |e_L| / lambda_L and |e_H| / lambda_H within [lo, hi) (NaN: no pass)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.fmax(np.abs(pa.e_lat_m) / max(p.lambda_L, 1e-9),
                        np.abs(pa.e_head_rad) / max(math.radians(p.lambda_H), 1e-9))
    out = np.full(len(share), np.nan)
    for i in range(len(share)):
        window = share[lo[i]:hi[i]]
        if np.any(np.isfinite(window)):
            out[i] = np.nanmax(window)
    return out


def apply_guard(sugg: np.ndarray, prev: np.ndarray, decisions: np.ndarray,
                caps: GuardCaps) -> tuple[np.ndarray, str]:
    """G3's last step: increases no higher than the caps, and never below the previous speed (lowering
    is eq. 4.2's decision, not the guard's). Returns the suggestion and a note ("" if nothing capped)."""
    capped = (decisions == INCREASE) & (sugg > caps.v_cap)
    out = np.where(capped, np.maximum(prev, np.minimum(sugg, caps.v_cap)), sugg)
    if not np.any(capped):
        return out, ""
    held = int(np.sum(capped & (out <= prev)))
    by = ", ".join(f"{name} {int(np.sum(capped & (caps.by == c)))}" for c, name in enumerate(CRITERIA)
                   if np.any(capped & (caps.by == c)))
    return out, f"guard: {int(np.sum(capped))} increases capped ({by}), {held} of them kept at their speed"


def nearby_min(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per vertex i, the least of values[lo_i:hi_i] (neighbourhoods)."""
    return np.array([values[a:b].min() if b > a else values[i] for i, (a, b) in enumerate(zip(lo, hi))])


def met_speeds(history: list[tuple[np.ndarray, VertexPasses]], p: SchedulerParams) -> np.ndarray:
    """Per vertex, the lowest scheduled speed of any trial in `history` that passed it without calling
    for a decrease (within eq. 4.2's deadband or better); inf where none did."""
    return _lowest_speeds(history, p, failed=False)


def failure_speeds(history: list[tuple[np.ndarray, VertexPasses]], p: SchedulerParams) -> np.ndarray:
    """Per vertex, the lowest scheduled speed of any trial in `history` whose experience there called
    for a decrease (eq. 4.2's second case); inf where none did."""
    return _lowest_speeds(history, p, failed=True)


def _lowest_speeds(history: list[tuple[np.ndarray, VertexPasses]], p: SchedulerParams, failed: bool) -> np.ndarray:
    if not history:
        return np.array([])
    out = np.full(len(history[0][0]), np.inf)
    for sched, passes in history:
        dec, _ = decide(passes, p)
        hit = (dec == DECREASE) if failed else passes.seen & (dec != DECREASE)
        out = np.where(hit, np.minimum(out, sched), out)
    return out
