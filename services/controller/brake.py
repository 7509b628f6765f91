"""Where a safety stop steers while the robot rolls out: the corridor's two limits weighed against each other.

A stop from speed rolls on for a while (a Grizzly from 1.9 m/s: 1.2 m, its drive lagging 0.5 s). Over
that distance d a curvature offset D from the route's own turns the heading error by D d and moves the
lateral error by D d^2 / 2 (small angles), on top of what the heading error already carries it:

    e_L(x) = e_L + sin(e_H) x + D x^2 / 2,      e_H(x) = e_H + D x,      0 < x <= d

Steering back towards the route as feedback linearization does (its lateral term grows like 1 / v^2
as the robot slows) turned a Grizzly 10-18 deg while it corrected a few centimetres (`lbc bench
stops`); not steering at all lets a robot that is already drifting out keep drifting. The offset here
minimizes the largest share of its limit that either error takes at the points still to come (the
lateral error measured from the corridor's middle against its half-width, the heading against its
limit: 1 on an edge), so a tight heading limit buys little lateral correction and a tight lateral one
more. Pure: inputs in, the offset out.
"""
from __future__ import annotations

import math

import numpy as np

from services.controller.actuator import ActuatorLag

OFFSETS = 101            # candidate offsets over [-bound, +bound]
POINTS = 8               # points of the roll-out the shares are taken at
MAX_PERIODS = 200        # a roll-out longer than 20 s at 10 Hz is cut there


def roll_out_m(lag: ActuatorLag, drive: tuple[float, float], v_cmd: float, decel_mps2: float,
               period_s: float, rest_mps: float) -> float:
    """How far the robot still rolls: the lag model's drive from `drive` under speed commands that fall
    from `v_cmd` at `decel_mps2` per second, until both are below `rest_mps`."""
    d, xi, v = 0.0, drive, v_cmd
    for _ in range(MAX_PERIODS):
        (v_avg, _), xi = lag.step(xi, (v, 0.0))
        d += max(0.0, v_avg) * period_s
        if xi[0] <= rest_mps and v <= rest_mps:
            break
        v = max(0.0, v - decel_mps2 * period_s)
    return d


def balanced_offset(lateral_m: float, heading_rad: float, d_m: float, right_m: float, left_m: float,
                    heading_limit_rad: float, bound_per_m: float) -> float:
    """The curvature offset (1/m, within +-bound_per_m; > 0 turns left) that minimizes the largest
    share of the lateral and heading errors' limits over the next `d_m` metres (module docstring).
    `right_m` < `left_m`: the corridor's edges."""
    if d_m <= 0.0:
        return 0.0
    D = np.linspace(-bound_per_m, bound_per_m, OFFSETS)[:, None]
    x = np.linspace(d_m / POINTS, d_m, POINTS)[None, :]
    lat = lateral_m + math.sin(heading_rad) * x + 0.5 * D * x * x
    head = heading_rad + D * x
    lat_share = np.abs(lat - 0.5 * (left_m + right_m)) / (0.5 * (left_m - right_m))
    worst = np.maximum(lat_share, np.abs(head) / heading_limit_rad).max(axis=1)
    best = np.flatnonzero(worst <= worst.min() + 1e-9)
    return float(D[best[np.argmin(np.abs(D[best, 0]))], 0])   # of equals, the least steering
