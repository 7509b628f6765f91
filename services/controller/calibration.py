"""The predicted spread checked online against what happens, and widened where it is too narrow.

The uncertainty-aware laws (MM-, C-, RC-LB-NMPC) predict, at tick k, the robot's poses x_1..x_K with
their lateral and heading standard deviations along the route. The corridor bounds the errors against
the route, so those are what is checked: when the estimate of tick k + j arrives, its lateral and
heading errors against the route (each at its own place) are compared with those the prediction made
for it had at its place, normalized by the spread the law expected plus the estimate's own:

    z_j = (e_estimate - e_predicted)_lateral, heading / sqrt(sigma_pred,j^2 + sigma_estimate^2)

(Poses are not compared directly: a later solve that drives slower than the plan leaves the robot
behind the predicted pose along the route, which in a corner is a pose difference across it and in
heading that no corridor cares about.)

A calibrated 3-sigma region holds all but ~0.3 % of them. The learned model can be over-confident (the
GP's posterior variance measures how well it knows its own data, not how well the world repeats), and
the a-priori one is a guess, so each horizon step j has a factor kappa_j >= 1 on its predicted
variance. Per step, because the errors of a wrong model are correlated in time: a bias grows linearly
over the horizon where independent disturbances grow with its square root, and one factor on the
per-period disturbance would widen the first steps (whose spread decides a stop) for the errors of
the last. Each realized prediction says which factor would just have held it,

    need = max(1, (err^2 / 9 - sigma_estimate^2 - sigma_loc^2) / (sigma_model^2 - sigma_loc^2))
                                                                     (lateral and heading, the larger)

with sigma_model the spread before widening and sigma_loc the share of it that is the localizer's own
covariance carried along the plan: only what the motion model adds is widened (horizon_covariance.py),
so a factor learned at speed does not multiply the estimate's noise at standstill. kappa_j is MARGIN
times the largest need (where above 1) of the last WINDOW predictions of step j (conformal
prediction's recent-maximum rule): a new
exceedance widens at once, and the widening is forgotten WINDOW ticks after the errors that asked
for it, so a corner's surprise does not slow the straight that follows for the rest of the trial.
With exchangeable errors about 1 / (WINDOW + 1) of the predictions leave their widened 3-sigma
region. A new route starts from the teach pass's factors (identification.horizon_factors), kept as a
floor until a step has seen WINDOW predictions; a later trial starts from the last one's window.

The errors of a place repeat (a rough patch, a slope: the premise of learning from experience), and a
recent window forgets them by the time the robot is back: a trial that ended on a calm stretch would
enter the next trial's rough patch, at a speed the calm window allows, with its spread unwidened. So
each need is also kept by the place the prediction was made at (PLACE_BIN_M bins of the route's
distance); near a place, kappa_j is at least MARGIN times the largest need of the latest pass over it
(the neighbouring bins included). The latest pass replaces an earlier one's needs, so a model that has
learned the place narrows the spread there one trial later. The teach pass is a route's first pass: its
needs by place (identification.place_factors) start trial 1's memory, so that a rough patch the teach
pass crossed is not entered unwidened after a calm stretch has emptied the window of the teach factors.
A plan counts the places ahead of it as far as the robot needs to slow down (v^2 / 2a, with the drive's
acceleration limit identified on the teach pass): the ladder changes speed at once, the drive does not.

Rare errors and a model that changes between trials are what the recent window and the ratios do not
hold: each realized prediction also tells, in m^2 and rad^2, the variance its error asked for and what
it missed beyond the model's own share, which missed_variance.py remembers per step and channel, with
the speed it was made at, over a longer window, across trials, as floors under every later prediction's
model share at that speed or faster (`floors`), whatever the ratio factors say. In heading the variance
asked for there is the truth's (`_Channel.asked_followed`): the next plans steer the estimate onto the
plan, so the robot's true heading wanders with the estimate's error, and the estimate's 1 s errors vary
less than the truth's where the check's independent form assumed more (docs/results.md, stop 70).

What a pass met at a place holds near the speed it drove there: a calm pass at 1.4 m/s says nothing of
2.3 m/s, where the learned model has no experience (its variance the prior's) and the errors of a rough
patch outgrow a lagging turn. So each place also keeps the fastest speed the latest pass over it (the
teach pass, before trial 1) commanded there, the pass whose needs the place holds, and a plan faster than
GROWTH times it is widened by the larger of those needs and the teach pass's (`beyond_at`): speed at a
place the teach pass found rough grows by at most GROWTH per trial over what was last driven there
(thesis 4: speed raised with experience). Not over the fastest pass ever: that pass's needs were
replaced, and a calm crawl through a place the teach pass found rough vouched by the teach pass's speed.

Wherever the latest pass came near the corridor's edge, speed also grows by no more than its errors
there allow (`speed_cap_at`, the scheduler's guard for a law that chooses its own speed): the largest
share of the corridor the estimates took near a place (`observe`), grown in proportion to speed,
reaches GUARD_SHARE at GUARD_SHARE / share times the pass's speed there; a plan is held below that, but
never below that pass's own speed (slowing down is the spread's to decide, and a slide that acts per
second grows as the robot slows). A MATS whose trial 1 crossed rough ground at 1 m/s within 0.225 of a
0.245 m corridor entered it at 1.2-1.5 m/s in the next trials, where its yaw, growing with speed,
outran the steering before the model's spread said so (bench seed 4409, s1021326272). The share of the
steering margin (the turn left beyond the route's own) the pass's commands took there counts the same way
(turn_share.py): the issue's MATS (docs/scenarios/issue18-mats-rc.toml) crossed rough ground in trial 1
at 1.0-1.3 m/s, its curvature at the steering's limit for 1.1 s, calm in the corridor (24 %); trial 2
entered at 1.5 m/s, the steering saturated against the yaw for 1.5 s and the robot left the corridor.
Pure: inputs in, factors out.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from services.controller.missed_variance import MARGIN, FloorsBySpeed, MissedVariance, SpreadFloors

WINDOW = 150             # predictions per horizon step remembered (15 s at 10 Hz)
# MARGIN (missed_variance.py) on the largest need: the next error is rarely exactly the worst seen
MAX_SCALE = 400.0        # 20x the modelled standard deviation
PLACE_BIN_M = 2.0        # route distance per place whose needs are remembered across trials
GROWTH = 1.25            # a place's latest pass vouches for plans up to this times its speed there
GUARD_SHARE = 0.8        # of the corridor, that a place's errors grown in proportion to speed may reach
TEACH_STEERING = "steering margin (teach pass)"


@dataclass(frozen=True)
class Prediction:
    """One predicted pose's errors against the route (at its own place) with their spread."""
    step: int                 # j, 1..K: how many periods ahead it was predicted
    lateral_m: float
    heading_rad: float
    sigma_lat_m: float
    sigma_head_rad: float
    scale: float              # the factor of step j the spread was predicted with
    loc_sigma_lat_m: float = 0.0      # the localizer's share of the spread (not widened)
    loc_sigma_head_rad: float = 0.0
    s_m: float = math.nan             # where along the route it was made (NaN: remembered by no place)
    v_mps: float = 0.0                # the speed commanded when it was made
    model_sigma_lat_m: float = math.nan   # the spread as the model gave it, before any widening (NaN:
    model_sigma_head_rad: float = math.nan   # the one `scale` alone widened)
    from_tick: int = -1               # capture tick of the estimate the plan started from (-1: unknown)


@dataclass(frozen=True)
class Beyond:
    """What a plan faster than a place's passes vouch for is widened by: from `speed_mps` on, `factors`
    (kappa_j) instead of factors_at's."""
    speed_mps: float = math.inf
    factors: np.ndarray | None = None


@dataclass(frozen=True)
class PlaceCap:
    """The speed the latest pass near a place allows (inf: no limit), the share of `what` (the corridor,
    or the steering margin: turn_share.py) it took and where (route distance of the place's start)."""
    speed_mps: float = math.inf
    share: float = 0.0
    at_m: float = math.nan
    what: str = "corridor"


class SpreadCalibration:
    def __init__(self, horizon: int, scales: np.ndarray | None = None,
                 recent: list[deque] | None = None, places: dict[int, np.ndarray] | None = None,
                 speeds: dict[int, float] | None = None, first: dict[int, np.ndarray] | None = None,
                 brake_mps2: float = math.inf, missed: MissedVariance | None = None,
                 shares: dict[int, tuple[float, str]] | None = None):
        """`brake_mps2`: the deceleration the drive is held to (identified on the teach pass; inf: none
        seen): how far ahead a place must already be allowed for (_near). `missed`: the variance earlier
        trials' predictions missed (copied). `shares`: place bin -> the largest share of the corridor the
        latest pass's errors, or of the steering margin its commands, took there, and which of the two."""
        start = np.ones(horizon) if scales is None else np.asarray(scales, dtype=float)[:horizon]
        self.floor = np.maximum(np.pad(start, (0, horizon - len(start)), constant_values=1.0), 1.0)
        self.recent = [deque(r, maxlen=WINDOW) for r in recent] if recent is not None else \
            [deque(maxlen=WINDOW) for _ in range(horizon)]
        self.scales = np.array([self._scale(j) for j in range(horizon)])
        self.checked = np.zeros(horizon, dtype=int)
        self.outside = np.zeros(horizon, dtype=int)
        self._pending: dict[int, list[Prediction]] = {}
        self.places_before = dict(places or {})      # place bin -> needs per step, of the latest pass
        self.places_now: dict[int, np.ndarray] = {}  # the same, of this trial
        self.first = dict(first if first is not None else self.places_before)   # the teach pass's needs
        self.speeds_before = dict(speeds or {})      # place bin -> the fastest speed its latest pass commanded
        self.speeds_now: dict[int, float] = {}
        self.shares_before = dict(shares or {})
        self.shares_now: dict[int, tuple[float, str]] = {}
        self.brake_mps2 = brake_mps2
        self.missed = missed.copy() if missed is not None and missed.horizon == horizon else MissedVariance(horizon)

    def continued(self) -> "SpreadCalibration":
        """A calibration for the next trial on the same route and model: this one's recent needs, and by
        place its needs and speeds (the earlier passes' where it did not pass), no predictions pending,
        counts from zero."""
        return SpreadCalibration(len(self.recent), self.scales, self.recent,
                                 {**self.places_before, **self.places_now}, {**self.speeds_before, **self.speeds_now},
                                 self.first, self.brake_mps2, self.missed, {**self.shares_before, **self.shares_now})

    def _near(self, s_m: float, v_mps: float) -> range:
        """The place bins a plan made at `s_m` at speed `v_mps` must already allow for: the neighbouring
        ones, and those within the distance the robot needs to slow down (v^2 / 2a) beyond: a place the
        ladder first saw one bin ahead would be met at the speed of the bins before it."""
        reach = v_mps * v_mps / (2.0 * self.brake_mps2) if self.brake_mps2 > 0.0 else 0.0
        return range(math.floor(s_m / PLACE_BIN_M) - 1, math.floor((s_m + reach) / PLACE_BIN_M) + 2)

    def factors_at(self, s_m: float | None, v_mps: float = 0.0) -> np.ndarray:
        """kappa_j for a prediction made at route distance `s_m` at speed `v_mps` (None: the recent
        window's alone), the places near it (_near) included."""
        if s_m is None or not math.isfinite(s_m) or not self.places_before:
            return self.scales.copy()
        near = [self.places_before[i] for i in self._near(s_m, v_mps) if i in self.places_before]
        if not near:
            return self.scales.copy()
        return _widened(self.scales, np.max(near, axis=0))

    def floors(self, v_mps: float | None = None, s_m: float | None = None) -> SpreadFloors:
        """Per step and channel, what is added to the model's share of the predicted variance and the
        least that share may be, for a plan at `v_mps` (missed_variance.py; None: at any speed) made at
        route distance `s_m` (None: anywhere, every place's misses held)."""
        return self.missed.floors(v_mps, self._near_or_none(s_m, v_mps or 0.0))

    def floors_by_speed(self, s_m: float | None = None, v_mps: float = 0.0) -> FloorsBySpeed:
        """The same as a function of the plan's speed, for this control step, made at route distance `s_m`
        while commanding `v_mps`."""
        return self.missed.by_speed(self._near_or_none(s_m, v_mps))

    def _near_or_none(self, s_m: float | None, v_mps: float) -> range | None:
        return self._near(s_m, v_mps) if s_m is not None and math.isfinite(s_m) else None

    def beyond_at(self, s_m: float | None, v_mps: float = 0.0) -> Beyond:
        """For a plan made at route distance `s_m` at speed `v_mps`: from which speed it outruns what the
        latest passes over the places near (_near) vouch for (GROWTH times the slowest of their speeds),
        and the factors then (the teach pass's needs there over factors_at's). Nothing where the teach
        pass needed no widening."""
        if s_m is None or not math.isfinite(s_m) or not self.first:
            return Beyond()
        near = self._near(s_m, v_mps)
        first = [self.first[i] for i in near if i in self.first]
        if not first:
            return Beyond()
        seen = [self.speeds_before[i] for i in near if i in self.speeds_before]
        kappa = _widened(self.factors_at(s_m, v_mps), np.max(first, axis=0))
        return Beyond(GROWTH * min(seen) if seen else math.inf, kappa)

    def observe(self, s_m: float, share: float, what: str = "corridor") -> None:
        """The estimate at route distance `s_m` took `share` of the corridor there (Corridor.share; inf:
        beyond an edge the route lies on), or the commands there that of the steering margin (`what`)."""
        if math.isfinite(s_m) and not math.isnan(share):
            b = math.floor(s_m / PLACE_BIN_M)
            if share > self.shares_now.get(b, (0.0, what))[0]:
                self.shares_now[b] = (share, what)

    def speed_cap_at(self, s_m: float | None, v_mps: float = 0.0) -> PlaceCap:
        """The fastest plan the latest passes' errors over the places near (_near) allow (module
        docstring): the lowest over those places of their pass's speed times max(1, GUARD_SHARE / share)."""
        if s_m is None or not math.isfinite(s_m):
            return PlaceCap()
        out = PlaceCap()
        for b in self._near(s_m, v_mps):
            (share, what), v = self.shares_before.get(b, (0.0, "")), self.speeds_before.get(b, 0.0)
            if share <= 0.0 or v <= 0.0:
                continue
            cap = v * max(1.0, GUARD_SHARE / share)
            if cap < out.speed_mps:
                out = PlaceCap(cap, share, b * PLACE_BIN_M, what)
        return out

    def predict(self, tick: int, predictions: list[Prediction]) -> None:
        """The law's predictions of step k made at `tick`: prediction j is for the estimate of tick + j."""
        for p in predictions:
            self._pending.setdefault(tick + p.step, []).append(p)
        for old in [t for t in self._pending if t < tick - 200]:
            del self._pending[old]

    def realize(self, tick: int, lateral_m: float, heading_rad: float, var_lat_m2: float,
                var_head_rad2: float, jumped: Callable[[int], float] | None = None) -> list[float]:
        """The route errors of the estimate captured at `tick` and its variances across the route and in
        heading: |z| of every prediction made for it. `jumped(c0)`: how far the estimate stepped sideways
        without the robot since capture tick c0 (estimate_jumps.py), taken off the lateral error."""
        out = []
        for p in self._pending.pop(tick, []):
            d = lateral_m - p.lateral_m - (jumped(p.from_tick) if jumped is not None and p.from_tick >= 0 else 0.0)
            h = math.remainder(heading_rad - p.heading_rad, 2 * math.pi)
            z_lat = d / math.sqrt(p.sigma_lat_m ** 2 + var_lat_m2 + 1e-12)
            z_head = h / math.sqrt(p.sigma_head_rad ** 2 + var_head_rad2 + 1e-12)
            lat = _Channel(d, var_lat_m2, p.loc_sigma_lat_m, p.sigma_lat_m, p.scale, p.model_sigma_lat_m)
            head = _Channel(h, var_head_rad2, p.loc_sigma_head_rad, p.sigma_head_rad, p.scale, p.model_sigma_head_rad)
            need = max(lat.need, head.need)
            out.append(self._update(p.step - 1, max(abs(z_lat), abs(z_head)), need))
            self.missed.add(p.step, (lat.asked, head.asked_followed), (lat.share, head.share), p.v_mps,
                            math.floor(p.s_m / PLACE_BIN_M) if math.isfinite(p.s_m) else -1,
                            (d * d / 9.0, h * h / 9.0))
            self._remember(p, need)
        return out

    def _remember(self, p: Prediction, need: float) -> None:
        j = p.step - 1
        if not math.isfinite(p.s_m) or j >= len(self.scales):
            return
        b = math.floor(p.s_m / PLACE_BIN_M)
        needs = self.places_now.setdefault(b, np.ones(len(self.scales)))
        needs[j] = max(needs[j], need)
        self.speeds_now[b] = max(self.speeds_now.get(b, 0.0), abs(p.v_mps))

    def _update(self, j: int, z: float, need: float) -> float:
        if j >= len(self.scales):
            return z
        self.checked[j] += 1
        self.outside[j] += z > 3.0
        self.recent[j].append(need)
        self.scales[j] = self._scale(j)
        return z

    def _scale(self, j: int) -> float:
        window = self.recent[j]
        worst = max(window) if window else 1.0
        seen = MARGIN * worst if worst > 1.0 else 1.0
        floor = self.floor[j] if len(window) < WINDOW else 1.0
        return float(min(MAX_SCALE, max(1.0, floor, seen)))

    def spread_factors(self, s_m: float | None = None) -> tuple[float, ...]:
        """sqrt(kappa_j): what each step's predicted standard deviations are multiplied by, at route
        distance `s_m`."""
        return tuple(float(x) for x in np.sqrt(self.factors_at(s_m)))


def teach_places(bin_m: float, rows: list[list[float]], horizon: int) -> dict[int, np.ndarray]:
    """The memory of places a route's first trial starts with: the teach pass's factors on the spread
    needed per place (identification.place_factors, one row per `bin_m` of route) as needs on the
    variance per PLACE_BIN_M, the places that needed none left out."""
    out: dict[int, np.ndarray] = {}
    for b, row in enumerate(rows):
        f = np.asarray(row[:horizon], dtype=float)
        if not len(f) or f.max() <= 1.0:
            continue
        need = np.square(np.pad(f, (0, horizon - len(f)), mode="edge"))
        key = math.floor((b + 0.5) * bin_m / PLACE_BIN_M)
        out[key] = np.maximum(out[key], need) if key in out else need
    return out


def teach_speeds(bin_m: float, speeds: list[float]) -> dict[int, float]:
    """The teach pass's fastest commanded speed per PLACE_BIN_M (identification.place_factors' rows)."""
    out: dict[int, float] = {}
    for b, v in enumerate(speeds):
        key = math.floor((b + 0.5) * bin_m / PLACE_BIN_M)
        out[key] = max(out.get(key, 0.0), float(v))
    return out


def teach_shares(bin_m: float, shares: list[float]) -> dict[int, tuple[float, str]]:
    """The teach pass's largest share of the steering margin per PLACE_BIN_M (identification.place_turn_shares)
    as the place cap's memory for trial 1; the places where it took none left out."""
    out: dict[int, tuple[float, str]] = {}
    for b, x in enumerate(shares):
        key = math.floor((b + 0.5) * bin_m / PLACE_BIN_M)
        if x > 0.0 and x > out.get(key, (0.0, ""))[0]:
            out[key] = (float(x), TEACH_STEERING)
    return out


def _widened(kappa: np.ndarray, worst: np.ndarray) -> np.ndarray:
    """`kappa` widened to MARGIN times a place's largest needs `worst` where they are above 1."""
    return np.minimum(MAX_SCALE, np.maximum(kappa, np.where(worst > 1.0, MARGIN * worst, 1.0)))


@dataclass(frozen=True)
class _Channel:
    """One channel (lateral or heading) of a realized prediction: its error `err`, the estimate's variance,
    the predicted sigma with its localizer's share, widened (`scale`, the floors) from `sigma_model`."""
    err: float
    var_estimate: float
    sigma_loc: float
    sigma: float
    scale: float
    sigma_model: float = math.nan

    @property
    def _loc2(self) -> float:
        return min(self.sigma_loc ** 2, self.sigma ** 2)

    @property
    def share(self) -> float:
        """The model's share of the predicted variance before it was widened."""
        if math.isfinite(self.sigma_model):
            return max(self.sigma_model ** 2 - min(self.sigma_loc ** 2, self.sigma_model ** 2), 0.0)
        return (self.sigma ** 2 - self._loc2) / max(self.scale, 1e-9)

    @property
    def asked(self) -> float:
        """The model variance that puts `err` on the 3-sigma boundary, the estimate's and the localizer's
        variance taken off (may be negative: an error inside the localizer's own spread)."""
        return self.err * self.err / 9.0 - self.var_estimate - self._loc2

    @property
    def asked_followed(self) -> float:
        """`asked` where the closed loop steers its estimate onto the plan (heading): `err` is then the
        model's own error and the robot's true one is it less the end estimate's error, independent of it,
        so the truth's variance is err's plus the estimate's; on the 3-sigma boundary of the model's and
        the localizer's share. Absolute, for the floors only: as a ratio to a crawl's tiny model share it
        would hold every faster plan to the crawl's estimate noise."""
        return self.err * self.err / 9.0 + self.var_estimate - self._loc2

    @property
    def need(self) -> float:
        """The factor on the model's share that puts `err` on the 3-sigma boundary (at least 1)."""
        return max(1.0, self.asked / max(self.share, 1e-18))
