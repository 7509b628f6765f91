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
(and meanwhile by the recent window's factors). Pure: inputs in, floors out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LONG_WINDOW = 1500       # predictions per horizon step remembered (150 s of tracking at 10 Hz)
QUANTILE = 0.995         # of the variance the errors asked for, that no model share may go below
MARGIN = 1.1             # on both floors, as on the calibration's factors
CHANNELS = 2             # lateral (m^2), heading (rad^2)


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
        self._speed = np.zeros((horizon, size), dtype=np.float32)
        self._count = np.zeros(horizon, dtype=int)     # values pushed per step, ever

    def copy(self) -> "MissedVariance":
        """The same memory, for the next trial on the route: what a pass missed holds for the next
        model too (it is not a ratio to this one)."""
        out = MissedVariance(0, self.size)
        out._asked, out._missed = self._asked.copy(), self._missed.copy()
        out._speed, out._count = self._speed.copy(), self._count.copy()
        return out

    @property
    def horizon(self) -> int:
        return len(self._count)

    def add(self, step: int, asked: tuple[float, float], share: tuple[float, float], v_mps: float = 0.0) -> None:
        """A realized prediction of horizon step `step` (1..K), made while commanding `v_mps`: per
        channel, the model variance its error asked for (the 3-sigma boundary through it, the estimate's
        and the localizer's variance taken off) and the model's share it was predicted with."""
        if not 1 <= step <= self.horizon:
            return
        j = step - 1
        i = self._count[j] % self.size
        a = np.maximum(np.asarray(asked, dtype=float), 0.0)
        self._asked[j, :, i] = a
        self._missed[j, :, i] = np.maximum(a - np.asarray(share, dtype=float), 0.0)
        self._speed[j, i] = abs(v_mps) if math.isfinite(v_mps) else 0.0
        self._count[j] += 1

    def floors(self, v_mps: float | None = None) -> SpreadFloors:
        """MARGIN times the most missed (added to the share) and the asked-for QUANTILE (the least share),
        for a plan at `v_mps` (module docstring; None: every prediction in full, whatever its speed)."""
        asked, missed = self._asked, self._missed
        if v_mps is not None:
            w = speed_weights(self._speed, v_mps)[:, None, :]
            asked, missed = asked * w, missed * w
        # the slots not filled yet hold 0, below every value, so the r-th largest of a whole ring is that of
        # its values wherever r <= their count
        kth = self.size - np.array([_rank(min(int(c), self.size)) for c in self._count], dtype=int)
        ranked = np.partition(asked, np.unique(kth), axis=2) if self.horizon else asked
        least = ranked[np.arange(self.horizon), :, kth]
        return SpreadFloors(MARGIN * missed.max(axis=2).astype(float), MARGIN * least.astype(float))

    def any(self) -> bool:
        return bool(self._asked.any())     # what was missed is at most what was asked for

    def by_speed(self) -> "FloorsBySpeed":
        """This memory's floors as a function of the plan's speed, for one control step (a view: valid
        until the next `add`)."""
        return FloorsBySpeed(self)


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

    def __init__(self, memory: MissedVariance):
        self._memory = memory
        self._at: dict[float, SpreadFloors] = {}

    def any(self) -> bool:
        return self._memory.any()

    def at(self, v_mps: float) -> SpreadFloors:
        v = float(v_mps)
        if v not in self._at:
            self._at[v] = self._memory.floors(v)
        return self._at[v]
