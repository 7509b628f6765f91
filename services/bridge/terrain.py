"""Terrain patches the nominal unicycle model knows nothing about.

Each patch has a smooth footprint (full effect inside 70% of its radius, fading to zero at the rim)
so that disturbances are continuous in space, as real terrain is, and learnable from neighbours.
Rough and rut patterns are fixed per scenario seed (repeatable trial to trial); ruts deepen with
every trial that crosses them, so the disturbance slowly changes with repetition.

Besides disturbing the 2-D motion (`effect`), the terrain sets the body's attitude (`attitude`), which
tilts and lowers the simulated stereo camera (render.py). Robot frame x forward, y left, z up; the
body's orientation in the level frame that has the heading theta is R = Ry(pitch) Rx(roll) (ZYX Euler
angles as in REP 103: positive roll lifts the left side, positive pitch lowers the nose).

* side slope: the body lies on the slope plane. Its tilt sigma, sin(sigma) = footprint * sin(slope_deg)
  (the patch `effect` picks, so the camera tilts where the robot slides), falls towards downhill_deg;
  with a = downhill - theta (where downhill lies, seen from the robot) the plane's normal in the
  heading frame is (sin(sigma) cos(a), sin(sigma) sin(a), cos(sigma)) = R e_z, so
      sin(roll) = -sin(sigma) sin(a),   tan(pitch) = tan(sigma) cos(a)
  (downhill on the left: the left side down, roll = -sigma; downhill ahead: nose down, pitch = +sigma).
  The slope is not drawn (the rendered ground stays the plane z = 0), so it does not lift the body.
* rut: each track sinks by footprint * depth * (1 + RUT_UNEVENNESS * pattern) under its wheels, with
  the rut's current depth (deeper every pass) and its seeded pattern; the body sits at the tracks'
  mean sink (z_m < 0) and rolls by atan((sink_right - sink_left) / track) (the deeper side down).
Overlapping patches add their rolls and sinks (small angles).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.scenario import TerrainPatch

RUT_UNEVENNESS = 0.3      # a rut's floor is this share of its depth deeper or shallower along its pattern
DEFAULT_TRACK_M = 0.55    # wheel track when the terrain is built without a robot (the Husky's)


@dataclass(frozen=True, kw_only=True)
class Attitude:
    """The robot body on the terrain: roll and pitch (rad, R_level_body = Ry(pitch) Rx(roll) about the
    ground contact point, see the module docstring) and the height of the ground contact point above
    the flat ground z = 0 (m; negative when sunk into a rut)."""
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    z_m: float = 0.0

    @property
    def is_level(self) -> bool:
        return self.roll_rad == 0.0 and self.pitch_rad == 0.0 and self.z_m == 0.0

    def R_level_body(self) -> np.ndarray:
        """3x3 rotation from body coordinates into the level frame with the robot's heading."""
        cr, sr = math.cos(self.roll_rad), math.sin(self.roll_rad)
        cp, sp = math.cos(self.pitch_rad), math.sin(self.pitch_rad)
        return np.array([[cp, sp * sr, sp * cr], [0.0, cr, -sr], [-sp, cp * sr, cp * cr]])


LEVEL = Attitude()


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
    def __init__(self, patches: list[TerrainPatch], seed: int, track_m: float = DEFAULT_TRACK_M):
        if track_m <= 0:
            raise ValueError("track_m must be > 0")
        self.patches = list(patches)
        self.track_m = float(track_m)
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

    def _slope(self, x: float, y: float) -> tuple[float, float]:
        """(sin of the footprint-weighted tilt, downhill direction) of the strongest side slope here."""
        best, downhill = 0.0, 0.0
        for p in self.patches:
            if p.kind != "side_slope":
                continue
            s = footprint(p, x, y) * math.sin(math.radians(p.slope_deg))
            if s > best:
                best, downhill = s, math.radians(p.downhill_deg)
        return best, downhill

    def effect(self, x: float, y: float) -> TerrainEffect:
        out = TerrainEffect()
        out.slope_sin, out.downhill_rad = self._slope(x, y)
        for i, p in enumerate(self.patches):
            w = footprint(p, x, y)
            if w <= 0.0:
                continue
            self._crossed[i] = True
            if p.kind == "slip":
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

    def attitude(self, x: float, y: float, theta: float) -> Attitude:
        """The body's roll, pitch and sink at (x, y) heading theta (module docstring); a pure function of
        the pose, the seed and how often each rut has been driven (it marks nothing as crossed)."""
        roll = pitch = z = 0.0
        slope_sin, downhill = self._slope(x, y)
        if slope_sin > 0.0:
            a = downhill - theta
            roll = -math.asin(slope_sin * math.sin(a))
            pitch = math.atan(slope_sin / math.sqrt(1.0 - slope_sin ** 2) * math.cos(a))
        half = 0.5 * self.track_m
        left = (x - half * math.sin(theta), y + half * math.cos(theta))
        right = (x + half * math.sin(theta), y - half * math.cos(theta))
        for i, p in enumerate(self.patches):
            if p.kind != "rut":
                continue
            depth = self.rut_depth(i)
            sink_l, sink_r = (footprint(p, *q) * depth * (1.0 + RUT_UNEVENNESS * self.patterns[i](*q))
                              for q in (left, right))
            z -= 0.5 * (sink_l + sink_r)
            roll += math.atan((sink_r - sink_l) / self.track_m)
        return Attitude(roll_rad=roll, pitch_rad=pitch, z_m=z)
