"""Terrain patches the nominal unicycle model knows nothing about.

Each patch has a smooth footprint (full effect inside 70% of its radius, fading to zero at the rim)
so that disturbances are continuous in space, as real terrain is, and learnable from neighbours.
Rough and rut patterns are fixed per scenario seed (repeatable trial to trial); ruts deepen with
every trial that crosses them, so the disturbance slowly changes with repetition.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.scenario import TerrainPatch


@dataclass
class TerrainEffect:
    traction_v: float = 1.0      # multiplies achieved linear speed
    traction_w: float = 1.0      # multiplies achieved yaw rate
    slope_sin: float = 0.0       # sin(slope) weighted by footprint
    downhill_rad: float = 0.0    # world direction of the (strongest) slope
    yaw_field: float = 0.0       # yaw-rate disturbance per m/s of speed (rad/m)


class _Pattern:
    """A smooth, seeded 2-D field in [-1, 1]: a sum of a few plane waves of 1.5-5 m wavelength."""

    def __init__(self, rng: np.random.Generator, waves: int = 4):
        ang = rng.uniform(0, 2 * np.pi, waves)
        wavelength = rng.uniform(1.5, 5.0, waves)
        self.k = np.column_stack([np.cos(ang), np.sin(ang)]) * (2 * np.pi / wavelength)[:, None]
        self.phase = rng.uniform(0, 2 * np.pi, waves)
        self.norm = 1.0 / math.sqrt(waves / 2.0)

    def __call__(self, x: float, y: float) -> float:
        return float(np.clip(self.norm * np.sum(np.sin(self.k[:, 0] * x + self.k[:, 1] * y + self.phase)), -1, 1))


def footprint(patch: TerrainPatch, x: float, y: float) -> float:
    r = math.hypot(x - patch.center[0], y - patch.center[1])
    inner = 0.7 * patch.radius_m
    if r <= inner:
        return 1.0
    if r >= patch.radius_m:
        return 0.0
    return 0.5 * (1.0 + math.cos(math.pi * (r - inner) / (patch.radius_m - inner)))


class Terrain:
    def __init__(self, patches: list[TerrainPatch], seed: int):
        self.patches = list(patches)
        rng = np.random.default_rng([seed, 7919])  # terrain is part of the world: fixed per seed
        self.patterns = [_Pattern(rng) for _ in self.patches]
        self.rut_passes = [0] * len(self.patches)
        self._crossed = [False] * len(self.patches)

    def rut_depth(self, i: int) -> float:
        p = self.patches[i]
        return min(p.max_depth_m, p.depth_m + p.growth_m_per_pass * self.rut_passes[i])

    def begin_trial(self) -> None:
        self._crossed = [False] * len(self.patches)

    def end_trial(self) -> None:
        """Every rut the robot drove through during the trial gets one pass deeper."""
        for i, crossed in enumerate(self._crossed):
            if crossed and self.patches[i].kind == "rut":
                self.rut_passes[i] += 1
        self._crossed = [False] * len(self.patches)

    def effect(self, x: float, y: float) -> TerrainEffect:
        out = TerrainEffect()
        best_slope = 0.0
        for i, p in enumerate(self.patches):
            w = footprint(p, x, y)
            if w <= 0.0:
                continue
            self._crossed[i] = True
            if p.kind == "side_slope":
                s = w * math.sin(math.radians(p.slope_deg))
                if s > best_slope:
                    best_slope = s
                    out.slope_sin = s
                    out.downhill_rad = math.radians(p.downhill_deg)
            elif p.kind == "slip":
                # sand/gravel: yaw suffers more than forward motion for a skid-steer robot
                out.traction_w *= 1.0 - w * (1.0 - p.traction)
                out.traction_v *= 1.0 - 0.5 * w * (1.0 - p.traction)
            elif p.kind == "rough":
                out.yaw_field += w * p.amplitude * self.patterns[i](x, y)
                out.traction_v *= 1.0 - 0.1 * w * min(1.0, p.amplitude)
            elif p.kind == "rut":
                depth = self.rut_depth(i)
                # deeper ruts steer the wheels harder and cost more rolling resistance
                out.yaw_field += w * (depth / 0.05) * 0.15 * self.patterns[i](x, y)
                out.traction_v *= 1.0 - w * min(0.5, 2.0 * depth)
        return out
