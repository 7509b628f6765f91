"""What the predictions missed, remembered long enough to estimate a rare error's size.

The calibration's recent window (calibration.py, 15 s) reacts within a second to a model that has become
over-confident, but its maximum is taken over 15 s of errors whose predictions overlap for a second:
some 15 independent samples, too few for the size of a one-in-a-hundred error. And its needs are
ratios to the model's own share, which a new model (the next trial's fit) changes: the errors a wide
prior held in trial 1 say nothing, as a ratio, of the narrow GP of trial 2.

Part of what the predictions miss does not depend on the model: the robot's own non-repeatable
disturbances (the drive's jitter, a heading that wanders with the wheels' slip), which no experience
predicts and which the GP's variance, small next to its data, leaves out. So each realized prediction
is also remembered in absolute terms (m^2 across the route, rad^2 in heading), per horizon step and
channel, with the speed it was made at, over the last LONG_WINDOW predictions, across trials:
- what it missed beyond the model's own share (the larger of 0 and the variance its error asked for
  less that share): MARGIN times the most of it is added to every later share, the robot's own noise
  on top of whatever the model claims;
- the variance its error asked for, whatever the model claimed: every later share is at least MARGIN
  times its QUANTILE (split conformal prediction), so a model surer than the errors of the last
  150 s have been (the first fit after a trial 1 on the wide prior) is held to them from its first step.
Per channel, so a heading that wanders does not widen the lateral tube the speed depends on; in
addition to the ratio factors, never instead of them.

Per speed: a plan is held in full to what was missed at its own speed or slower, and to what was missed
faster in proportion to its speed (v / v_then). Ground that kicks the heading per metre driven, and a
drive whose jitter grows with its speed, miss more the faster the robot goes; held in full at any
speed, one surprise at 2.3 m/s put 3.6 deg of heading sigma on every plan of the next 150 s, a crawl's
included, so that slowing down could never make a plan fit (bench seed 1709, Grizzly s968909746). A
robot whose jitter does not fade with speed is held to it again by its slower predictions' own misses
(and meanwhile by the recent window's factors).

Per place: what the predictions made over a few places missed is those places' (a rough corner, a slip
patch), not the robot's. Each prediction keeps the place it was made at (calibration.PLACE_BIN_M of
route); a place whose largest miss is more than PLACE_RATIO times the median place's largest error
(as a variance) is held to it only near it (the places a plan must already allow for:
calibration._near), the rest of the route to the others'. Held everywhere, one surprise in a rough
corner at 1.2 m/s put 2.3 deg of heading sigma on every plan of the next 150 s, so a Grizzly drove its
calm straights at 1.1 of its 1.75 m/s for the whole next trial (bench seed 1583, s155658429: trial 5
took 67.0 s where trial 3 took 48.0). A noise the robot shows everywhere is the median place's too, and
is held everywhere as before. Pure: inputs in, floors out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LONG_WINDOW = 1500       # predictions per horizon step remembered (150 s of tracking at 10 Hz)
QUANTILE = 0.995         # of the variance the errors asked for, that no model share may go below
MARGIN = 1.1             # on both floors, as on the calibration's factors
CHANNELS = 2             # lateral (m^2), heading (rad^2)
PLACE_RATIO = 4.0        # a place's largest miss beyond this times the median place's is held only near it
                         # (variances: twice the standard deviation)


@dataclass(frozen=True)
class SpreadFloors:
    """Per horizon step (rows) and channel (lateral m^2, heading rad^2): what is added to the model's share
    of the predicted variance, and the least that share may be."""
    added: np.ndarray        # (K, 2)
    least: np.ndarray        # (K, 2)

    def any(self) -> bool:
        return bool(self.added.any() or self.least.any())


class MissedVariance:
    """Per horizon step, the last LONG_WINDOW realized predictions' asked-for and missed variances (at
    least 0, per channel) and the speeds they were made at: a ring per step."""

    def __init__(self, horizon: int, size: int = LONG_WINDOW):
        # float32, channels before the ring: the floors partition each ring in place of a sort, every step
        self.size = size
        self._asked = np.zeros((horizon, CHANNELS, size), dtype=np.float32)
        self._missed = np.zeros((horizon, CHANNELS, size), dtype=np.float32)
        self._total = np.zeros((horizon, CHANNELS, size), dtype=np.float32)   # err^2 / 9, nothing taken off
        self._speed = np.zeros((horizon, size), dtype=np.float32)
        self._place = np.full((horizon, size), -1, dtype=np.int32)   # -1: made at no known place
        self._count = np.zeros(horizon, dtype=int)     # values pushed per step, ever

    def copy(self) -> "MissedVariance":
        """The same memory, for the next trial on the route: what a pass missed holds for the next
        model too (it is not a ratio to this one)."""
        out = MissedVariance(0, self.size)
        out._asked, out._missed = self._asked.copy(), self._missed.copy()
        out._speed, out._count = self._speed.copy(), self._count.copy()
        out._place, out._total = self._place.copy(), self._total.copy()
        return out

    @property
    def horizon(self) -> int:
        return len(self._count)

    def add(self, step: int, asked: tuple[float, float], share: tuple[float, float], v_mps: float = 0.0,
            place: int = -1, total: tuple[float, float] | None = None) -> None:
        """A realized prediction of horizon step `step` (1..K), made while commanding `v_mps` at place bin
        `place` (-1: none): per channel, the model variance its error asked for (the 3-sigma boundary
        through it, the estimate's and the localizer's variance taken off), the model's share it was
        predicted with, and the variance on whose 3-sigma boundary the error lies, nothing taken off
        (`total`; None: `asked`)."""
        if not 1 <= step <= self.horizon:
            return
        j = step - 1
        i = self._count[j] % self.size
        a = np.maximum(np.asarray(asked, dtype=float), 0.0)
        self._asked[j, :, i] = a
        self._missed[j, :, i] = np.maximum(a - np.asarray(share, dtype=float), 0.0)
        self._speed[j, i] = abs(v_mps) if math.isfinite(v_mps) else 0.0
        self._place[j, i] = max(int(place), -1)
        self._total[j, :, i] = np.maximum(np.asarray(asked if total is None else total, dtype=float), 0.0)
        self._count[j] += 1

    def floors(self, v_mps: float | None = None, near: range | None = None,
               held: np.ndarray | None = None) -> SpreadFloors:
        """MARGIN times the most missed (added to the share) and the asked-for QUANTILE (the least share),
        for a plan at `v_mps` (module docstring; None: every prediction in full, whatever its speed) made
        where it must allow for the place bins `near` (None: wherever; every place's misses held).
        `held`: held_near(near), if already at hand."""
        asked, missed = self._asked, self._missed
        if v_mps is not None:
            w = speed_weights(self._speed, v_mps)[:, None, :]
            asked, missed = asked * w, missed * w
        # the slots not filled yet hold 0, below every value, so the r-th largest of a whole ring is that of
        # its values wherever r <= their count
        kth = self.size - np.array([_rank(min(int(c), self.size)) for c in self._count], dtype=int)
        ranked = np.partition(asked, np.unique(kth), axis=2) if self.horizon else asked
        least = ranked[np.arange(self.horizon), :, kth]
        if near is not None:
            missed = np.where(self.held_near(near) if held is None else held, missed, 0.0)
        return SpreadFloors(MARGIN * missed.max(axis=2).astype(float), MARGIN * least.astype(float))

    def held_near(self, near: range) -> np.ndarray:
        """(K, 2, size): the predictions whose misses hold a plan that must allow for the place bins `near`:
        those made at ordinary places, at no known place, or at `near`. A place is not ordinary where its
        most missed exceeds PLACE_RATIO times the median place's largest error variance, nothing taken off
        (module docstring): the median of the most missed (or asked for) is 0 wherever the model's share
        (or the localizer's) held at most places, and every tail of the robot's own noise would then count
        as its place's. Judged on the misses in full, whatever their speed: once per control step."""
        n_bins = int(self._place.max(initial=-1)) + 2          # the last column: no known place
        col = np.where(self._place >= 0, self._place, n_bins - 1)
        per_missed, per_total = _most_per_place(self._missed, col, n_bins), _most_per_place(self._total, col, n_bins)
        seen = np.zeros((self.horizon, n_bins), dtype=bool)
        np.put_along_axis(seen, col, True, axis=1)
        median = _median_seen(per_total[:, :, :-1], seen[:, :-1])
        ordinary = per_missed <= PLACE_RATIO * median[:, :, None]        # (K, 2, n_bins)
        ordinary[:, :, -1] = True
        here = [b for b in near if 0 <= b < n_bins - 1]
        ordinary[:, :, here] = True
        return np.take_along_axis(ordinary, np.broadcast_to(col[:, None, :], self._missed.shape), axis=2)

    def any(self) -> bool:
        return bool(self._asked.any())     # what was missed is at most what was asked for

    def by_speed(self, near: range | None = None) -> "FloorsBySpeed":
        """This memory's floors as a function of the plan's speed, for one control step made where it must
        allow for the place bins `near` (a view: valid until the next `add`)."""
        return FloorsBySpeed(self, near)


def _most_per_place(values: np.ndarray, col: np.ndarray, n_bins: int) -> np.ndarray:
    """(K, 2, n_bins): the largest of `values` (K, 2, size) per place column `col` (K, size)."""
    K, C, _ = values.shape
    out = np.zeros((K, C, n_bins), dtype=np.float32)
    idx = (np.arange(K)[:, None, None] * C + np.arange(C)[None, :, None]) * n_bins + col[:, None, :]
    np.maximum.at(out.reshape(-1), idx.reshape(-1), values.reshape(-1))
    return out


def _median_seen(per: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(K, 2): the median over the seen places (K, P) of `per` (K, 2, P); 0 where none was seen."""
    n = seen.sum(axis=1)
    if per.shape[2] == 0:
        return np.zeros(per.shape[:2])
    ranked = np.sort(np.where(seen[:, None, :], per, np.inf), axis=2)
    lo, hi = np.maximum((n - 1) // 2, 0), np.maximum(n // 2, 0)
    rows = np.arange(len(n))[:, None]
    chans = np.arange(per.shape[1])[None, :]
    mid = 0.5 * (ranked[rows, chans, lo[:, None]] + ranked[rows, chans, hi[:, None]])
    return np.where(n[:, None] > 0, mid, 0.0)


def speed_weights(v_then: np.ndarray, v_mps: float) -> np.ndarray:
    """What a prediction made at `v_then` counts for a plan at `v_mps`: in full at or below its speed,
    in proportion (v / v_then) above."""
    return np.minimum(np.float32(1.0), np.float32(max(v_mps, 0.0)) / np.maximum(v_then, np.float32(1e-9)))


def _rank(n: int) -> int:
    """The QUANTILE of n values is the _rank(n)-th largest (ceil((1 - q) n), at least the largest)."""
    return max(1, math.ceil((1.0 - QUANTILE) * n - 1e-9))


class FloorsBySpeed:
    """One control step's floors as a function of the plan's speed (MissedVariance.floors), memoized:
    the speed ladder asks for each rung it tries."""

    def __init__(self, memory: MissedVariance, near: range | None = None):
        self._memory = memory
        self._near = near
        self._held: np.ndarray | None = None
        self._at: dict[float, SpreadFloors] = {}

    def any(self) -> bool:
        return self._memory.any()

    def at(self, v_mps: float) -> SpreadFloors:
        v = float(v_mps)
        if v not in self._at:
            if self._near is not None and self._held is None:
                self._held = self._memory.held_near(self._near)
            self._at[v] = self._memory.floors(v, self._near, self._held)
        return self._at[v]
