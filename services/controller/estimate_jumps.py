"""Steps in the estimate that the robot did not make, kept out of the online check of the predicted spread.

A localizer can shift its estimate sideways in one frame although the robot did not move: a 'teach pass
failure' (thesis 5.4.5: a ~25 cm step-change of the lateral error in a single time step, where the
learning then turned in anticipation of a disturbance that was not there). Every prediction made before
such a step and checked after it misses by the step, however good the model. Taken for a model error,
one step asks for a widening of up to 20x (calibration.MAX_SCALE) at its place and over the whole route,
so RC-LB-NMPC stops itself there in the next trials (the main job with a 0.08 m jump at 24 m: trials 2 and
3 stopped, "3 sigma: 0.337 m lateral, 48 deg heading").

A ground robot's lateral error moves smoothly: between two consecutive estimates by the distance driven
times the tangent of the heading error, plus what slip adds in one period. What the estimates show
beyond that is their innovation,

    i_k = (e_lat,k - e_lat,k-1) - (s_k - s_k-1) tan(e_head) (1 - kappa e_lat)    (both at the midpoint),

whose spread (a robust one: the median absolute deviation of the recent ones) is the localizer's frame
to frame noise. An estimate whose innovation is far outside it (GATE_SIGMAS spreads and MIN_JUMP_M at
least) is a candidate; it is a jump when the next innovation is back within the spread (ISOLATED_SIGMAS,
or a quarter of the step): the estimate stays where it jumped to. A slide that starts keeps moving the
estimate, so its innovations stay large and it is not a jump. Confirmed jumps add up to an offset per
capture tick; a prediction started from the estimate of tick c0 and checked at c1 is compared with the
estimate minus the jumps between them. Pure: estimates in, jumps out.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

GATE_SIGMAS = 8.0        # a candidate's innovation, in robust spreads of the recent innovations
ISOLATED_SIGMAS = 4.0    # the next innovation within this many: the estimate stays where it jumped to
MIN_JUMP_M = 0.02        # below this a step is within what one period of slip can do at speed
WINDOW = 50              # recent innovations the spread is taken from (5 s at 10 Hz)
MIN_SEEN = 10            # no verdict before this many
MAX_HEADING_RAD = 0.5    # beyond this heading error the robot is far off its route, and where it projects
                         # onto the route (its s and lateral error) can step at a corner: no verdict


@dataclass(frozen=True)
class Jump:
    capture_tick: int
    lateral_m: float     # the step the estimate made that the robot did not


@dataclass
class _Candidate:
    capture_tick: int
    step_m: float
    sigma_m: float


class EstimateJumps:
    def __init__(self):
        self.jumps: list[Jump] = []
        self._recent: deque[float] = deque(maxlen=WINDOW)
        self._last: tuple[int, float, float, float] | None = None     # (capture tick, s, e_lat, e_head)
        self._candidate: _Candidate | None = None

    def add(self, capture_tick: int, s_m: float, lateral_m: float, heading_rad: float,
            kappa_per_m: float = 0.0) -> bool:
        """The newest estimate's route errors and the route's curvature there; True while it is a
        candidate (its verdict comes with the next estimate: `jumps` then holds it if it was one)."""
        last, self._last = self._last, (capture_tick, s_m, lateral_m, heading_rad)
        if last is None or capture_tick != last[0] + 1:
            self._candidate = None       # a gap: no innovation, and a pending candidate has no verdict
            return False
        mid_lat, mid_head = 0.5 * (lateral_m + last[2]), 0.5 * (heading_rad + last[3])
        if abs(mid_head) > MAX_HEADING_RAD:
            self._candidate = None
            return False
        driven = (s_m - last[1]) * math.tan(mid_head) * (1.0 - kappa_per_m * mid_lat)
        innovation = (lateral_m - last[2]) - driven
        centre, sigma = self._spread()
        if self._candidate is not None:
            c, self._candidate = self._candidate, None
            if abs(innovation - centre) < max(ISOLATED_SIGMAS * c.sigma_m, 0.25 * abs(c.step_m)):
                self.jumps.append(Jump(c.capture_tick, c.step_m))
            else:
                self._recent.append(c.step_m + centre)
        if sigma is not None and abs(innovation - centre) > max(GATE_SIGMAS * sigma, MIN_JUMP_M):
            self._candidate = _Candidate(capture_tick, innovation - centre, sigma)
            return True
        self._recent.append(innovation)
        return False

    def _spread(self) -> tuple[float, float | None]:
        if len(self._recent) < MIN_SEEN:
            return 0.0, None
        x = np.asarray(self._recent)
        centre = float(np.median(x))
        return centre, 1.4826 * float(np.median(np.abs(x - centre)))

    def offset_between(self, from_tick: int, to_tick: int) -> float:
        """What the confirmed jumps after capture tick `from_tick` up to `to_tick` moved the estimate."""
        return sum(j.lateral_m for j in self.jumps if from_tick < j.capture_tick <= to_tick)
