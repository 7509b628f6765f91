"""Where a curvature-limited robot at a crawl is carried out of its corridor beyond the horizon.

An Ackermann robot turns by the metre, not by the second: slowing down relieves its steering's rate, not
its curvature, and ground that yaws it by the metre (rough ground, ruts) does so at any speed. At a
crawl (the speed ladder's slowest rung or slower, whoever chose it) the one-second horizon covers a few
centimetres, so a plan whose heading error points out of the corridor and closes too slowly (or opens)
fits every one of its steps while the robot creeps out over the next metre (bench seed 3847, MATS
s1840372140: in a rough corner at 0.05 m/s with the curvature at its limit, the heading error stayed at
+2.5-3 deg and the truth crept from 0.10 to 0.18 m of a 0.172 m corridor in 10 s). So the plan's last
step is carried on for the lookahead distance L, its heading error changing per metre as it did over the
plan's second half, where the steering has got to the curvature the plan asks for (a curvature offset
held):

    e(x) = e_K + sin(h_K) x + rho x^2 / 2,    rho = (h_K - h_m) / (path from x_m to x_K),    0 <= x <= L

with m = K / 2, until the heading error has closed (x = -h_K / rho, where a path follower stops turning
back): e moves monotonically from e_K to its value there or at L.
Pure: the plan's errors in, the lateral errors it reaches out.
"""
from __future__ import annotations

import math

import numpy as np

SHORTEST_M = 1e-3      # a plan that moves less says nothing of its heading's change per metre


def lateral_reach(E: np.ndarray, X: np.ndarray, lookahead_m: float) -> tuple[float, float]:
    """The lowest and highest lateral error (m) of the plan's last step carried on `lookahead_m` (module
    docstring). `E` (K, 3): the plan's errors in the corridor's frame (along, lateral, heading); `X`
    (K + 1, 3): its poses, X[0] the start."""
    e, h, m = float(E[-1, 1]), float(E[-1, 2]), len(E) // 2
    path = float(np.sum(np.hypot(*np.diff(X[m:, :2], axis=0).T)))        # E[i] is X[i + 1]'s
    rho = (h - float(E[m - 1, 2])) / path if path >= SHORTEST_M and m >= 1 else 0.0
    x = lookahead_m
    if rho * h < 0.0:                                   # closing: carried on only until it has closed
        x = min(x, -h / rho)
    end = e + math.sin(h) * x + 0.5 * rho * x * x
    return min(e, end), max(e, end)
