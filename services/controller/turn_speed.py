"""The fastest speed at which the robot can still turn along its route, per vertex.

A law at a fixed speed (FL, ILC, LB-NMPC, MM-LB-NMPC, and the scheduler's speeds they follow) has no
say over its speed; C-/RC-LB-NMPC choose theirs under their speed ladder, which this leaves alone.
Where the route turns faster than the robot can at the asked speed, such a law holds its turn limit and
leaves the route: a perturbed Grizzly asked for 1.85 m/s round 2.77 m corners, needing 0.67 rad/s of a
robot that makes about 0.5 at its limit there, left it by 4-7 m in every trial, learning or not (bench
seed 6841). The tracker therefore caps its speed where the route's turn would take more than TURN_SHARE
of the turn the robot makes at its limit,

    v |kappa(s)| <= TURN_SHARE * k * w_limit(v) / (1 + c v w_limit(v)),

k the turn gain identified on the teach pass, c a skid-steer's turn lost to skidding per m/s^2 of its
drive's load (TurnLoss, learned as it drives: a teach pass at walking speed hardly shows it), kappa
averaged over the distance the turn drive settles in (a wiggle shorter than that is not followed at any
speed). It brakes into each such place at the tracker's gentle deceleration, a speed lag early, so that
it is at the cap when it gets there. The share left over is for the law's corrections.

On an Ackermann, w_limit(v) = min(w_max, v kappa_max): a curvature beyond TURN_SHARE k kappa_max is no
easier slower, and caps nothing; its understeer, which does grow with speed, is not learned (c = 0).
Pure: the route, the limits and the turns measured in, speeds out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.path import Path

TURN_SHARE = 0.8        # of the robot's turn at its limit that the route's own turn may take
LOAD_MIN_MPS2 = 0.3     # the route's own turn load |v^2 kappa| below which a period says little of the loss
SPEED_MIN_MPS = 0.3
SAMPLES_MIN = 10        # loaded periods before the loss is believed (a second of corners)


@dataclass
class TurnLoss:
    """A skid-steer's turn lost to skidding, learned while it drives: the ground turns it at

        w = k w_drive / (1 + c v |w_drive|),

    k the turn gain identified on the teach pass, c (per m/s^2) what a teach pass at walking speed does
    not show. Least squares of c over the loaded periods (k w_d - w) = c (w v |w_d|), signs taken along
    w_d. Only corners count, where the drive turns the way the route does, which loads it: a drive held
    against a side slope's yaw on a straight turns hard while the ground turns the robot back, which is
    the slope, not skidding (a Husky on a 10 deg slope read 24 per m/s^2 from such periods). Kept from
    trial to trial by the controller's node, as the robot's own."""
    turn_gain: float
    sxx: float = 0.0
    sxy: float = 0.0
    samples: int = 0

    def add(self, v_mps: float, w_drive_radps: float, w_radps: float, w_route_radps: float) -> None:
        """One period: the speed, the drive's turn rate (before the turn gain), the ground's, and the
        route's own (its curvature times the speed)."""
        if abs(v_mps) < SPEED_MIN_MPS or abs(v_mps * w_route_radps) < LOAD_MIN_MPS2 \
                or w_route_radps * w_drive_radps <= 0.0:
            return
        d, m = abs(w_drive_radps), (w_radps if w_drive_radps >= 0.0 else -w_radps)
        x = m * abs(v_mps) * d
        self.sxx += x * x
        self.sxy += x * (self.turn_gain * d - m)
        self.samples += 1

    @property
    def per_mps2(self) -> float:
        """c, at least 0 (0 until SAMPLES_MIN loaded periods)."""
        if self.samples < SAMPLES_MIN or self.sxx <= 0.0:
            return 0.0
        return max(0.0, self.sxy / self.sxx)


def turn_cap(kappa_abs: float, usable_gain: float, w_max_radps: float, max_curvature: float,
             loss_per_mps2: float = 0.0) -> float:
    """The fastest speed at which a route turning at `kappa_abs` (1/m) takes at most `usable_gain` (the
    share times the turn gain k) of the robot's turn at its limit, k w_max / (1 + c v w_max) with the
    loss c (inf: any speed)."""
    if kappa_abs <= 0.0 or kappa_abs > usable_gain * max_curvature:
        return math.inf
    if loss_per_mps2 <= 0.0:
        return usable_gain * w_max_radps / kappa_abs
    a, b, c = loss_per_mps2 * w_max_radps * kappa_abs, kappa_abs, -usable_gain * w_max_radps
    return (-b + math.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)


def turn_speed_caps(path: Path, usable_gain: float, w_max_radps: float, max_curvature: float, *,
                    settle_m: float, decel_mps2: float, lead_m: float, loss_per_mps2: float = 0.0) -> np.ndarray:
    """(N,) per vertex the fastest speed commanded there: every vertex's turn_cap over the route's
    curvature averaged over `settle_m`, held from `lead_m` before it and braked into at `decel_mps2`."""
    kappa = np.abs(path.curvature_over(settle_m))
    cap = np.array([turn_cap(k, usable_gain, w_max_radps, max_curvature, loss_per_mps2) for k in kappa.tolist()])
    ahead = np.searchsorted(path.s, path.s + lead_m, side="right")
    held = np.array([cap[i:j].min() for i, j in enumerate(ahead.tolist())])
    return _braked(held, path.s, decel_mps2)


def _braked(cap: np.ndarray, s: np.ndarray, decel_mps2: float) -> np.ndarray:
    """Each vertex's cap lowered to what braking at `decel_mps2` from it reaches at every later cap."""
    out = cap.copy()
    if not decel_mps2 > 0.0 or not math.isfinite(decel_mps2):
        return out
    for i in range(len(out) - 2, -1, -1):
        if math.isfinite(out[i + 1]):
            out[i] = min(out[i], math.sqrt(out[i + 1] ** 2 + 2.0 * decel_mps2 * (s[i + 1] - s[i])))
    return out
