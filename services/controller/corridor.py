"""The safety corridor around a taught route (thesis eq. 7.3-7.4): per vertex, how far the robot may be
left (+) and right (-) of the route and how far its heading may turn from the taught one.

It comes from the scenario's `[constraints]` (one width for the whole route) and can be narrowed or
widened per stretch at run time (a guidance module or an operator, over Zenoh: `CorridorUpdate`).
"""
from __future__ import annotations

import math

import numpy as np


class Corridor:
    def __init__(self, s: np.ndarray, lateral_m: float, heading_rad: float):
        if lateral_m <= 0 or heading_rad <= 0:
            raise ValueError("corridor limits must be > 0")
        self.s = np.asarray(s, dtype=float)
        n = len(self.s)
        self.left = np.full(n, float(lateral_m))
        self.right = np.full(n, -float(lateral_m))
        self.heading = np.full(n, float(heading_rad))
        self.version = 0

    def update(self, from_m: float, to_m: float, left_m: float, right_m: float, heading_rad: float) -> int:
        """Set the limits over [from_m, to_m] of the route; returns how many vertices changed."""
        if not (left_m > right_m and heading_rad > 0 and to_m >= from_m):
            raise ValueError("need left_m > right_m, heading_rad > 0 and to_m >= from_m")
        sel = (self.s >= from_m) & (self.s <= to_m)
        self.left[sel], self.right[sel], self.heading[sel] = left_m, right_m, heading_rad
        self.version += 1
        return int(np.count_nonzero(sel))

    def at(self, s_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(right, left, heading) limits at distances along the route (the nearest vertex's)."""
        i = np.clip(np.searchsorted(self.s, np.asarray(s_m, dtype=float)), 0, len(self.s) - 1)
        return self.right[i], self.left[i], self.heading[i]

    def share(self, s_m: float, lateral_m: float, heading_rad: float) -> float:
        """How much of the corridor at s_m (lateral, from the route towards the edge on its side, or
        heading) the errors take: 1 on its edge; inf on a side whose edge is not beyond the route."""
        lo, hi, h = (float(x) for x in self.at(s_m))
        return max(_towards(lateral_m, hi if lateral_m >= 0.0 else lo), abs(heading_rad) / h)

    def contains(self, s_m: float, lateral_m: float, heading_rad: float,
                 tolerance: tuple[float, float] = (0.0, 0.0)) -> str:
        """'' when (lateral, heading) is inside the corridor at s_m, or outside it by no more than
        `tolerance` (m, rad), else why not."""
        lo, hi, h = (float(x) for x in self.at(s_m))
        tol_lat, tol_head = tolerance
        beyond = "" if tol_lat <= 0 and tol_head <= 0 else \
            f" by more than the estimate's 1 sigma ({tol_lat:.3f} m, {np.degrees(tol_head):.1f} deg)"
        if not lo - tol_lat <= lateral_m <= hi + tol_lat:
            return f"lateral error {lateral_m:+.3f} m outside the corridor [{lo:+.2f}, {hi:+.2f}] m{beyond}"
        if abs(heading_rad) > h + tol_head:
            return (f"heading error {np.degrees(heading_rad):+.1f} deg outside the corridor "
                    f"(+-{np.degrees(h):.1f} deg){beyond}")
        return ""


def _towards(lateral_m: float, edge_m: float) -> float:
    """The share of the way from the route to `edge_m` that `lateral_m` lies (inf beyond an edge that
    is not beyond the route)."""
    if lateral_m == 0.0:
        return 0.0 if edge_m != 0.0 else 1.0
    return lateral_m / edge_m if lateral_m * edge_m > 0.0 else math.inf
