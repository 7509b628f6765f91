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
channel, over the last LONG_WINDOW predictions, across trials:
- what it missed beyond the model's own share (the larger of 0 and the variance its error asked for
  less that share): MARGIN times the most of it is added to every later share, the robot's own noise
  on top of whatever the model claims;
- the variance its error asked for, whatever the model claimed: every later share is at least MARGIN
  times its QUANTILE (split conformal prediction), so a model surer than the errors of the last
  150 s have been (the first fit after a trial 1 on the wide prior) is held to them from its first step.
Per channel, so a heading that wanders does not widen the lateral tube the speed depends on; in
addition to the ratio factors, never instead of them. Pure: inputs in, floors out.
"""
from __future__ import annotations

import bisect
import math
from collections import deque
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


class SlidingMax:
    """The maximum of the last `size` values pushed, in amortized O(1) per push (a monotone deque of
    (index, value), values decreasing)."""

    def __init__(self, size: int):
        self.size = size
        self._q: deque[tuple[int, float]] = deque()
        self._n = 0

    def copy(self) -> "SlidingMax":
        out = SlidingMax(self.size)
        out._q, out._n = deque(self._q), self._n
        return out

    def push(self, value: float) -> None:
        while self._q and self._q[-1][1] <= value:
            self._q.pop()
        self._q.append((self._n, float(value)))
        self._n += 1
        while self._q[0][0] <= self._n - 1 - self.size:
            self._q.popleft()

    @property
    def value(self) -> float:
        return self._q[0][1] if self._q else 0.0


class SlidingQuantile:
    """The q-quantile (the ceil((1 - q) n)-th largest) of the last `size` values pushed: a sorted copy
    beside the arrival order, O(size) memmove per push."""

    def __init__(self, size: int, q: float):
        self.size, self.q = size, q
        self._order: deque[float] = deque()
        self._sorted: list[float] = []

    def copy(self) -> "SlidingQuantile":
        out = SlidingQuantile(self.size, self.q)
        out._order, out._sorted = deque(self._order), list(self._sorted)
        return out

    def push(self, value: float) -> None:
        value = float(value)
        self._order.append(value)
        bisect.insort(self._sorted, value)
        if len(self._order) > self.size:
            old = self._order.popleft()
            del self._sorted[bisect.bisect_left(self._sorted, old)]

    @property
    def value(self) -> float:
        n = len(self._sorted)
        if not n:
            return 0.0
        return self._sorted[n - max(1, math.ceil((1.0 - self.q) * n - 1e-9))]


class MissedVariance:
    """Per horizon step and channel, the last LONG_WINDOW realized predictions' missed and asked-for
    variances (at least 0)."""

    def __init__(self, horizon: int, size: int = LONG_WINDOW):
        self._missed = [[SlidingMax(size) for _ in range(CHANNELS)] for _ in range(horizon)]
        self._asked = [[SlidingQuantile(size, QUANTILE) for _ in range(CHANNELS)] for _ in range(horizon)]

    def copy(self) -> "MissedVariance":
        """The same memory, for the next trial on the route: what a pass missed holds for the next
        model too (it is not a ratio to this one)."""
        out = MissedVariance(0)
        out._missed = [[m.copy() for m in row] for row in self._missed]
        out._asked = [[m.copy() for m in row] for row in self._asked]
        return out

    @property
    def horizon(self) -> int:
        return len(self._missed)

    def add(self, step: int, asked: tuple[float, float], share: tuple[float, float]) -> None:
        """A realized prediction of horizon step `step` (1..K): per channel, the model variance its error
        asked for (the 3-sigma boundary through it, the estimate's and the localizer's variance taken
        off) and the model's share it was predicted with."""
        if not 1 <= step <= self.horizon:
            return
        for c in range(CHANNELS):
            a = max(asked[c], 0.0)
            self._asked[step - 1][c].push(a)
            self._missed[step - 1][c].push(max(a - share[c], 0.0))

    def floors(self) -> SpreadFloors:
        """MARGIN times the most missed (added to the share) and the asked-for QUANTILE (the least share)."""
        added = np.array([[m.value for m in row] for row in self._missed]).reshape(self.horizon, CHANNELS)
        least = np.array([[m.value for m in row] for row in self._asked]).reshape(self.horizon, CHANNELS)
        return SpreadFloors(MARGIN * added, MARGIN * least)
