"""How much of its turn authority the robot's commands take at a place: |mean w| / w_limit(mean v) over
the last AVERAGE_S of tracking commands.

A pass that needed nearly all of its turn rate (or, steered by curvature, all of its steering) near a
place cannot hold it faster: a skid-steer's turn rate for the same path grows with speed against a fixed
limit, and an Ackermann's curvature per metre does not grow at all while its steering lag and understeer
take more of it. The calibration's place cap (calibration.speed_cap_at) treats this share as it treats the
share of the corridor. Averaged, so that one step of an alternating plan is not taken for the place's
need; and only at speed, since a crawl's turn rate costs its plan nothing and says nothing of the place.
Pure: commands in, shares out.
"""
from __future__ import annotations

import math
from collections import deque
from typing import Callable

AVERAGE_S = 0.3          # commands averaged: about a drive's turn lag
MIN_SPEED_MPS = 0.3      # slower commands say nothing of what the place needs


class TurnShare:
    def __init__(self, period_s: float, w_limit: Callable[[float], float]):
        self.w_limit = w_limit
        self.recent: deque[tuple[float, float]] = deque(maxlen=max(1, round(AVERAGE_S / period_s)))

    def add(self, v_mps: float, w_radps: float) -> float:
        """The share after this tracking command (NaN: too slow, or too few commands yet)."""
        self.recent.append((v_mps, w_radps))
        if len(self.recent) < self.recent.maxlen:
            return math.nan
        v = sum(c[0] for c in self.recent) / len(self.recent)
        w = sum(c[1] for c in self.recent) / len(self.recent)
        limit = self.w_limit(v)
        if v < MIN_SPEED_MPS or limit <= 0.0:
            return math.nan
        return abs(w) / limit

    def reset(self) -> None:
        """Not tracking: the next share starts from new commands."""
        self.recent.clear()
