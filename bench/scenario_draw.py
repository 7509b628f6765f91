"""The scenario distribution of `lbc bench scenarios`: one pure, seeded draw per scenario index.

`draw(rng, index)` returns a scenario table that `common.scenario.parse_scenario` accepts. The runner
seeds one `numpy.random.Generator` per scenario, `default_rng([seed, index])`, so scenario `index`
of a seed is the same whatever N is. The ranges below are the defaults of `Bounds` (the benchmark;
only smoke tests shorten the routes).

Assignment (no randomness): algorithm family `FAMILIES[index % 4]`, in turn lb-nmpc (fixed speed,
5 trials), lb-nmpc-scheduled (LB-NMPC with the speed scheduler, 8 trials), rc-lb-nmpc (high requested
speed, 5 trials), ilc (6 trials); robot preset `PRESETS_IN_TURN[(index + index // 4) % 4]` of husky,
roc6, grizzly, mats, so every 16 consecutive scenarios hold each (family, preset) pair once.

Drawn, in this order, uniformly unless said otherwise:
- `seed` of the simulator: an integer in [0, 2^31).
- route: a loop with probability 1/3, else an open route; then its length L in [30, 120] m,
  measured along the smoothed route the teach driver drives (`smooth_waypoints`), and one corner
  radius R per route in [R_min, 8] m, where R_min is the largest of 2 m, 1.5x the preset's tightest
  turn (Ackermann steering limit) and 1.2 v_max / w_max.
  - open route: k corners, k in 1..min(5, 1 + floor(L / 20)), starting at the origin along +x; each
    corner turns by 20-110 deg, left or right with probability 1/2.
  - loop: a star-shaped polygon of k in 3..6 corners at polar angles 2 pi (i + u_i) / k, u_i in
    [-0.3, 0.3], and radii in [0.6, 1] (scaled), either direction with probability 1/2; it starts in
    the middle of its longest leg.
  - legs: every leg is at least 1 m longer than the two tangent lengths R tan(turn / 2) of its corners
    (so every corner is the full-radius arc) and the first and last legs of an open route at least
    5 m; the legs share the remaining length in Dirichlet(1, ..., 1) proportions (open routes) or keep
    the polygon's proportions (loops). Legs that are not neighbours stay at least 3 m apart. A draw
    that breaks a rule, or whose length leaves [30, 120] m after rounding to 1 cm, is redrawn (all
    but the loop choice), so accepted loops lean long and their radii small: a short loop with wide
    corners cannot close.
- teach speed: min(1 m/s, [0.3, 0.5] x v_max).
- terrain: 1, 2 or 3 patches (probability 1/3 each: alone or combined), kind side_slope | slip |
  rough | rut with probability 1/4 each, radius 3-8 m. The first patch is centred on the route at a
  distance [0.15, 0.85] L from its start; every later one at the previous patch's place with
  probability 1/2 (overlapping effects) or at a new such place; each centre then moves sideways off
  the route by [-0.5, 0.5] of the patch radius (the route crosses its full-effect core).
  side_slope: slope 3-15 deg, downhill direction [-180, 180) deg; slip: traction 0.5-0.9;
  rough: amplitude 0.05-0.2 rad/s at 1 m/s; rut: starts flat, deepens 4-10 mm per pass up to 40-80 mm.
- localization: the `pose` source, noise 0.005-0.03 m, delay 0-0.2 s (other errors at their defaults).
- corridor: lateral half-width 0.15-0.5 m, heading limit 8-20 deg.
- speed (v_max: the preset's limit): lb-nmpc and ilc a fixed [0.3, 0.8] v_max; rc-lb-nmpc a fixed
  [0.7, 1.0] v_max; lb-nmpc-scheduled the scheduler's ceiling `v_max` in [0.6, 1.0] v_max (its other
  settings at their defaults, so trial 1 runs at the default v_init).
- robot body (only with `robots = "perturbed"`, `--robots perturbed`: a user's own robot rather than a
  thesis robot; drawn from its own stream `default_rng([seed, index, 1])`, so everything above stays
  the same draw): each physical parameter the controller is not told, as overrides of the preset:
  drive lags `tau_v_s`, `tau_w_s` (and `tau_steer_s`) x [0.5, 2]; `accel_max_mps2`,
  `yaw_accel_max_radps2` (and `steer_rate_max_dps`) x [0.6, 1.5]; `turn_efficiency` x [0.8, 1.1]
  (at most 1), `turn_loss_per_mps2`, `side_slip_s`, `slope_slide_mps`, `slope_yaw_radps` (and
  `understeer_s2pm2`) x [0.5, 2]; the non-repeatable noise `noise_v_mps`, `noise_w_radps` x [0.5, 2];
  log-uniform factors. The command limits (speed, turn rate, steering angle) stay the preset's, so the
  requested speeds mean the same.
Every controller, scheduler and store setting not named here keeps its default (no per-scenario
tuning: actuator lags and prior model uncertainties included). Lengths are rounded to 1 cm, speeds
to 1 cm/s, everything else to 4 decimals.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.robot import PRESETS, RobotParams
from services.bridge.teach_driver import smooth_waypoints


@dataclass(frozen=True, kw_only=True)
class Family:
    """One algorithm family of the benchmark: how its scenarios are controlled and how long they run."""
    name: str                          # the key in the benchmark's JSON
    algorithm: str                     # [controller] algorithm
    trials: int
    scheduled: bool                    # the speed scheduler sets the speeds (else one fixed speed)
    speed_frac: tuple[float, float]    # fixed speed, or the scheduler's ceiling, as a share of v_max


FAMILIES: tuple[Family, ...] = (
    Family(name="lb-nmpc", algorithm="lb-nmpc", trials=5, scheduled=False, speed_frac=(0.3, 0.8)),
    Family(name="lb-nmpc-scheduled", algorithm="lb-nmpc", trials=8, scheduled=True, speed_frac=(0.6, 1.0)),
    Family(name="rc-lb-nmpc", algorithm="rc-lb-nmpc", trials=5, scheduled=False, speed_frac=(0.7, 1.0)),
    Family(name="ilc", algorithm="ilc", trials=6, scheduled=False, speed_frac=(0.3, 0.8)),
)
PRESETS_IN_TURN: tuple[str, ...] = ("husky", "roc6", "grizzly", "mats")
TERRAIN_KINDS: tuple[str, ...] = ("side_slope", "slip", "rough", "rut")


@dataclass(frozen=True, kw_only=True)
class Bounds:
    """The distribution's ranges (module docstring); (lo, hi) pairs are uniform ranges."""
    route_m: tuple[float, float] = (30.0, 120.0)
    loop_prob: float = 1.0 / 3.0
    corner_radius_max_m: float = 8.0
    corner_radius_floor_m: float = 2.0
    turn_deg: tuple[float, float] = (20.0, 110.0)
    max_corners: int = 5
    m_per_extra_corner: float = 20.0
    loop_corners: tuple[int, int] = (3, 6)
    end_leg_m: float = 5.0
    straight_m: float = 1.0
    clearance_m: float = 3.0
    teach_frac: tuple[float, float] = (0.3, 0.5)
    teach_max_mps: float = 1.0
    patches: tuple[int, int] = (1, 3)
    patch_radius_m: tuple[float, float] = (3.0, 8.0)
    patch_at: tuple[float, float] = (0.15, 0.85)
    patch_offset: float = 0.5
    slope_deg: tuple[float, float] = (3.0, 15.0)
    traction: tuple[float, float] = (0.5, 0.9)
    rough_amplitude: tuple[float, float] = (0.05, 0.2)
    rut_growth_m: tuple[float, float] = (0.004, 0.01)
    rut_max_depth_m: tuple[float, float] = (0.04, 0.08)
    noise_m: tuple[float, float] = (0.005, 0.03)
    delay_s: tuple[float, float] = (0.0, 0.2)
    lateral_m: tuple[float, float] = (0.15, 0.5)
    heading_deg: tuple[float, float] = (8.0, 20.0)

    def __post_init__(self):
        if not 0 < self.route_m[0] <= self.route_m[1]:
            raise ValueError("route_m: 0 < min <= max required")


BOUNDS = Bounds()
MAX_ATTEMPTS = 10_000   # a route draw that fails this often means the bounds admit no route


# a user's own robot (module docstring): the preset's hidden physics scaled by log-uniform factors
BODY_FACTORS: dict[str, tuple[float, float]] = {
    "tau_v_s": (0.5, 2.0), "tau_w_s": (0.5, 2.0), "tau_steer_s": (0.5, 2.0),
    "accel_max_mps2": (0.6, 1.5), "yaw_accel_max_radps2": (0.6, 1.5), "steer_rate_max_dps": (0.6, 1.5),
    "turn_efficiency": (0.8, 1.1), "turn_loss_per_mps2": (0.5, 2.0), "side_slip_s": (0.5, 2.0),
    "slope_slide_mps": (0.5, 2.0), "slope_yaw_radps": (0.5, 2.0), "understeer_s2pm2": (0.5, 2.0),
    "noise_v_mps": (0.5, 2.0), "noise_w_radps": (0.5, 2.0),
}
ROBOTS = ("presets", "perturbed")


def family_of(index: int) -> Family:
    return FAMILIES[index % len(FAMILIES)]


def preset_of(index: int) -> str:
    return PRESETS_IN_TURN[(index + index // len(FAMILIES)) % len(PRESETS_IN_TURN)]


def min_corner_radius(robot: RobotParams, bounds: Bounds = BOUNDS) -> float:
    """R_min: tight enough to be a real turn, wide enough for the steering and for w_max at full speed."""
    steer = 1.5 / robot.max_curvature if math.isfinite(robot.max_curvature) else 0.0
    return max(bounds.corner_radius_floor_m, steer, 1.2 * robot.v_max_mps / robot.w_max_radps)


def route_length(waypoints, corner_radius_m: float, loop: bool) -> float:
    """Length of the route the teach driver drives through `waypoints`."""
    ref = smooth_waypoints(waypoints, corner_radius_m, loop)
    return float(np.sum(np.hypot(*np.diff(ref[:, :2], axis=0).T)))


def draw(rng: np.random.Generator, index: int, bounds: Bounds = BOUNDS,
         body_rng: np.random.Generator | None = None) -> dict:
    """Scenario `index` of the benchmark (a table for `parse_scenario`), drawn from `rng`; with
    `body_rng`, the robot's physics are perturbed from its preset's (`perturbed_body`)."""
    family, preset = family_of(index), preset_of(index)
    robot = PRESETS[preset]
    seed = int(rng.integers(0, 2**31))
    waypoints, loop, radius = draw_route(rng, robot, bounds)
    teach = min(bounds.teach_max_mps, rng.uniform(*bounds.teach_frac) * robot.v_max_mps)
    ref = smooth_waypoints(waypoints, radius, loop)
    scenario = {
        "name": f"s{seed}-{index:04d}-{family.name}-{preset}",
        "seed": seed,
        "robot": {"preset": preset, **(perturbed_body(body_rng, robot) if body_rng is not None else {})},
        "path": {"waypoints": waypoints, "loop": loop, "teach_speed_mps": round(teach, 2),
                 "corner_radius_m": radius},
        "terrain": draw_terrain(rng, ref, bounds),
        "localization": {"source": "pose", "noise_m": _r4(rng.uniform(*bounds.noise_m)),
                         "delay_s": _r4(rng.uniform(*bounds.delay_s))},
        "controller": {"algorithm": family.algorithm},
        "constraints": {"lateral_m": _r4(rng.uniform(*bounds.lateral_m)),
                        "heading_deg": _r4(rng.uniform(*bounds.heading_deg))},
    }
    speed = round(rng.uniform(*family.speed_frac) * robot.v_max_mps, 2)
    if family.scheduled:
        scenario["scheduler"] = {"enabled": True, "v_max": speed}
        scenario["trials"] = {"count": family.trials}
    else:
        scenario["trials"] = {"count": family.trials, "speed": speed}
    return scenario


def perturbed_body(rng: np.random.Generator, robot: RobotParams) -> dict:
    """Overrides of `robot`'s hidden physics (BODY_FACTORS); parameters the preset leaves at 0 (a
    skid-steer robot's steering) stay 0."""
    out = {}
    for name, (lo, hi) in BODY_FACTORS.items():
        factor = math.exp(rng.uniform(math.log(lo), math.log(hi)))
        value = getattr(robot, name)
        if value > 0:
            out[name] = _r4(min(1.0, value * factor) if name == "turn_efficiency" else value * factor)
    return out


def _r4(x: float) -> float:
    return round(float(x), 3)


# --- routes ---------------------------------------------------------------------------------------
def draw_route(rng: np.random.Generator, robot: RobotParams,
               bounds: Bounds = BOUNDS) -> tuple[list[list[float]], bool, float]:
    """(waypoints rounded to 1 cm, loop, corner radius) of a drivable route; redrawn until one is."""
    r_min = min_corner_radius(robot, bounds)
    loop = bool(rng.random() < bounds.loop_prob)    # kept: only the route's geometry is redrawn
    for _ in range(MAX_ATTEMPTS):
        length = rng.uniform(*bounds.route_m)
        radius = round(rng.uniform(r_min, max(r_min, bounds.corner_radius_max_m)), 2)
        pts = (_loop_polygon if loop else _open_polyline)(rng, length, radius, bounds)
        if pts is None:
            continue
        waypoints = np.round(pts, 2)
        if not _clear(waypoints, loop, bounds.clearance_m):
            continue
        if bounds.route_m[0] <= route_length(waypoints, radius, loop) <= bounds.route_m[1]:
            return waypoints.tolist(), loop, radius
    raise RuntimeError(f"no drivable route in {MAX_ATTEMPTS} draws within {bounds}")


def _tangents(turns: np.ndarray, radius: float) -> np.ndarray:
    return radius * np.tan(np.abs(turns) / 2.0)


def _arc_saving(turns: np.ndarray, radius: float) -> float:
    """How much shorter the rounded route is than its polyline (2 tangents minus the arc, per corner)."""
    return float(np.sum(2.0 * _tangents(turns, radius) - radius * np.abs(turns)))


def _open_polyline(rng, length: float, radius: float, bounds: Bounds) -> np.ndarray | None:
    k = int(rng.integers(1, min(bounds.max_corners, 1 + int(length // bounds.m_per_extra_corner)) + 1))
    turns = np.radians(rng.uniform(*bounds.turn_deg, size=k)) * rng.choice([-1.0, 1.0], size=k)
    t = np.concatenate([[0.0], _tangents(turns, radius), [0.0]])
    min_legs = 2.0 * np.maximum(t[:-1], t[1:]) + bounds.straight_m
    min_legs[[0, -1]] = np.maximum(min_legs[[0, -1]], bounds.end_leg_m)
    spare = length + _arc_saving(turns, radius) - float(np.sum(min_legs))
    if spare < 0:
        return None
    legs = min_legs + spare * rng.dirichlet(np.ones(k + 1))
    headings = np.concatenate([[0.0], np.cumsum(turns)])
    steps = legs[:, None] * np.column_stack([np.cos(headings), np.sin(headings)])
    return np.vstack([[0.0, 0.0], np.cumsum(steps, axis=0)])


def _loop_polygon(rng, length: float, radius: float, bounds: Bounds) -> np.ndarray | None:
    k = int(rng.integers(bounds.loop_corners[0], bounds.loop_corners[1] + 1))
    angles = 2.0 * np.pi * (np.arange(k) + rng.uniform(-0.3, 0.3, size=k)) / k
    pts = rng.uniform(0.6, 1.0, size=k)[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
    if rng.random() < 0.5:
        pts = pts[::-1]
    legs = np.hypot(*(np.roll(pts, -1, axis=0) - pts).T)          # leg i: corner i -> i + 1
    pts = np.roll(pts, -int(np.argmax(legs)), axis=0)               # the loop starts on its longest leg
    d_in = pts - np.roll(pts, 1, axis=0)
    d_out = np.roll(pts, -1, axis=0) - pts
    turns = np.arctan2(d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0], np.sum(d_in * d_out, axis=1))
    scale = (length + _arc_saving(turns, radius)) / float(np.sum(np.hypot(*d_out.T)))
    pts, legs = pts * scale, np.hypot(*d_out.T) * scale
    t = _tangents(turns, radius)
    if np.any(legs < 2.0 * np.maximum(t, np.roll(t, -1)) + bounds.straight_m):
        return None
    return pts - pts[0]


def _clear(pts: np.ndarray, loop: bool, clearance_m: float) -> bool:
    """Legs that are not neighbours keep `clearance_m` apart (the route never crosses or grazes itself)."""
    n = len(pts)
    legs = [(pts[i], pts[(i + 1) % n]) for i in range(n if loop else n - 1)]
    m = len(legs)
    for i in range(m):
        for j in range(i + 2, m):
            if loop and i == 0 and j == m - 1:
                continue
            if _segment_gap(*legs[i], *legs[j]) < clearance_m:
                return False
    return True


def _segment_gap(a, b, c, d) -> float:
    def cross(o, p, q):
        return (p[0] - o[0]) * (q[1] - o[1]) - (p[1] - o[1]) * (q[0] - o[0])
    if cross(a, b, c) * cross(a, b, d) < 0 and cross(c, d, a) * cross(c, d, b) < 0:
        return 0.0
    return min(_point_gap(a, c, d), _point_gap(b, c, d), _point_gap(c, a, b), _point_gap(d, a, b))


def _point_gap(p, a, b) -> float:
    ab = b - a
    u = float(np.clip(np.dot(p - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
    return float(np.hypot(*(p - a - u * ab)))


# --- terrain --------------------------------------------------------------------------------------
def draw_terrain(rng: np.random.Generator, ref: np.ndarray, bounds: Bounds = BOUNDS) -> list[dict]:
    """Patches on the route `ref` (dense (M, 3) poses, as `smooth_waypoints` gives)."""
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref[:, :2], axis=0).T))])
    count = int(rng.integers(bounds.patches[0], bounds.patches[1] + 1))
    patches, at = [], None
    for i in range(count):
        if i == 0 or rng.random() >= 0.5:
            at = int(np.searchsorted(s, rng.uniform(*bounds.patch_at) * s[-1]))
        at = min(at, len(ref) - 1)
        kind = TERRAIN_KINDS[int(rng.integers(len(TERRAIN_KINDS)))]
        radius = rng.uniform(*bounds.patch_radius_m)
        side = rng.uniform(-bounds.patch_offset, bounds.patch_offset) * radius
        x, y, th = ref[at]
        center = [round(float(x - side * math.sin(th)), 2), round(float(y + side * math.cos(th)), 2)]
        patches.append({"kind": kind, "center": center, "radius_m": _r4(radius), **_terrain_params(rng, kind, bounds)})
    return patches


def _terrain_params(rng: np.random.Generator, kind: str, bounds: Bounds) -> dict:
    if kind == "side_slope":
        return {"slope_deg": _r4(rng.uniform(*bounds.slope_deg)), "downhill_deg": _r4(rng.uniform(-180.0, 180.0))}
    if kind == "slip":
        return {"traction": _r4(rng.uniform(*bounds.traction))}
    if kind == "rough":
        return {"amplitude": _r4(rng.uniform(*bounds.rough_amplitude))}
    return {"depth_m": 0.0, "growth_m_per_pass": _r4(rng.uniform(*bounds.rut_growth_m)),
            "max_depth_m": _r4(rng.uniform(*bounds.rut_max_depth_m))}
