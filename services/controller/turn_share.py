"""How much of its steering margin the robot's commands take at a place: the turn rate commanded beyond
the route's own turn there, over what the turn limit leaves beyond that turn,

    share = |mean(w - w_route)| / (w_limit(mean v) - |mean w_route|),    w_route = kappa v / turn_gain

over the last AVERAGE_S of tracking commands (1: all of it, or a route tighter than the limit).

A pass that needed nearly all of its margin near a place (rough ground, ruts: a yaw the learned model
did not foresee at that speed) cannot hold the place faster: a skid-steer's corrections grow with speed
against a fixed limit, and an Ackermann's curvature per metre does not grow at all while its steering
lag and understeer take more of it. The calibration's place cap (calibration.speed_cap_at) treats this
share as it treats the share of the corridor. The route's own turn is left out, since the plan already
holds it against the limit at every speed it tries. Averaged, so that one step of an alternating plan
is not taken for the place's need; and only at speed, since a crawl's turn rate costs its plan nothing
and says nothing of the place. Pure: commands in, shares out.
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
        self.recent: deque[tuple[float, float, float]] = deque(maxlen=max(1, round(AVERAGE_S / period_s)))

    def add(self, v_mps: float, w_radps: float, w_route_radps: float = 0.0) -> float:
        """The share after this tracking command, `w_route_radps` the command that turns along the route
        at its speed (NaN: too slow, or too few commands yet)."""
        self.recent.append((v_mps, w_radps, w_route_radps))
        if len(self.recent) < self.recent.maxlen:
            return math.nan
        n = len(self.recent)
        v, w, w_route = (sum(c[i] for c in self.recent) / n for i in range(3))
        if v < MIN_SPEED_MPS:
            return math.nan
        margin = self.w_limit(v) - abs(w_route)
        correction = abs(w - w_route)
        return 1.0 if margin <= correction else correction / margin

    def reset(self) -> None:
        """Not tracking: the next share starts from new commands."""
        self.recent.clear()
