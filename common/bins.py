"""How experiences are binned and windowed (thesis 5.3.2, defaults of 5.4.2): shared by the store that
keeps them, the controller that asks for local windows, and the scenario file."""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, kw_only=True)
class BinPolicy:
    """Up to (2 c_vertex + 1) (2 c_velocity + 1) c_bin experiences per local window (132..180 by default)."""
    v_bin_mps: float = 0.25   # width of a commanded-speed bin
    c_bin: int = 4            # experiences kept per (vertex, speed bin); the oldest beyond are evicted
    c_vertex: int = 5         # vertices on either side of the window's centre
    c_velocity: int = 1       # speed bins on either side of the window's own

    def __post_init__(self):
        if not self.v_bin_mps > 0 or self.c_bin < 1 or self.c_vertex < 0 or self.c_velocity < 0:
            raise ValueError("v_bin_mps > 0, c_bin >= 1, c_vertex >= 0 and c_velocity >= 0 required")

    def speed_bin(self, v_cmd_mps: float) -> int:
        return int(math.floor(v_cmd_mps / self.v_bin_mps))
