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

A plan that turns towards the route (to take out a lateral error) and is carried on that way crosses it
with its heading still growing, and the arc goes on to the far edge: at a crawl such a plan of bench seed
5683's MATS s1297402567, 0.05-0.07 m off on a straight, turning its heading to -4.5 deg towards the route,
read as reaching -0.35 m of a 0.20 m corridor, and the robot stopped. Its turn towards the route is the
plan's choice, made for the error it sees; a path follower does not go on turning once it heads back, and
turns back once it is across. So a plan heading towards the route is carried on with its last heading held
(its change per metre kept only where the plan closes it, or where its steering is at the curvature limit
against it: the ground's turn, which goes on), and once across the route (e = 0, heading h_c) the heading
closes at the share TURN_BACK_SHARE of the curvature the robot has to turn back with, kappa_max + sign(h_c)
kappa_route, overshooting by about h_c^2 / (2 rate).
Pure: the plan's errors in, the lateral errors it reaches out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

SHORTEST_M = 1e-3      # a plan that moves less says nothing of its heading's change per metre
TURN_BACK_SHARE = 0.5  # of the curvature left to turn back with: the rest for the steering's lag and the ground
HELD_SHARE = 0.9       # of the curvature limit at which a command is held there


def lateral_reach(E: np.ndarray, X: np.ndarray, lookahead_m: float, turn_back: TurnBack | None = None
                  ) -> tuple[float, float]:
    """The lowest and highest lateral error (m) of the plan's last step carried on `lookahead_m` (module
    docstring). `E` (K, 3): the plan's errors in the corridor's frame (along, lateral, heading); `X`
    (K + 1, 3): its poses, X[0] the start; `turn_back`: what the robot can turn back with once across the
    route (None: the arc is carried on as it is)."""
    e, h, m = float(E[-1, 1]), float(E[-1, 2]), len(E) // 2
    path = float(np.sum(np.hypot(*np.diff(X[m:, :2], axis=0).T)))        # E[i] is X[i + 1]'s
    rho = (h - float(E[m - 1, 2])) / path if path >= SHORTEST_M and m >= 1 else 0.0
    if turn_back is None or e * h >= 0.0:
        end = _arc_end(e, h, rho, lookahead_m)
        return min(e, end), max(e, end)
    if rho * h > 0.0 and not turn_back.held_against(rho):
        rho = 0.0                                       # the plan's own turn towards the route: not grown
    x_c = _crossing(e, h, rho, lookahead_m)
    if x_c is None:
        end = _arc_end(e, h, rho, lookahead_m)
    else:
        h_c = h + rho * x_c
        back = max(turn_back.rate(h_c), -rho if rho * h_c < 0.0 else 0.0, 0.0)   # the plan's closing: at least
        end = _arc_end(0.0, h_c, -math.copysign(back, h_c), lookahead_m - x_c)
    return min(e, end), max(e, end)


@dataclass(frozen=True)
class TurnBack:
    """What a curvature-limited robot turns its heading error with beyond the plan: its curvature limit
    (1/m), the route's own turn there (rad/m) and the plan's last commanded curvature."""
    kappa_max: float
    kappa_route: float
    kappa_cmd: float

    def rate(self, h: float) -> float:
        """The heading error's change per metre credited for closing a heading error h."""
        return TURN_BACK_SHARE * (self.kappa_max + self.kappa_route * math.copysign(1.0, h))

    def held_against(self, rho: float) -> bool:
        """The plan steers at its curvature limit against a heading change of rho per metre: the ground's."""
        return abs(self.kappa_cmd) >= HELD_SHARE * self.kappa_max and (self.kappa_cmd - self.kappa_route) * rho < 0.0


def _arc_end(e: float, h: float, rho: float, x_max: float) -> float:
    """The lateral error where the arc from (e, h), its heading changing by rho per metre, ends: at x_max,
    or where its heading has closed."""
    x = x_max
    if rho * h < 0.0:                                   # closing: carried on only until it has closed
        x = min(x, -h / rho)
    return e + math.sin(h) * x + 0.5 * rho * x * x


def _crossing(e: float, h: float, rho: float, x_max: float) -> float | None:
    """Where the arc from (e, h), heading towards the route (e h < 0), first crosses it within its length
    (None: it does not)."""
    if e * h >= 0.0:
        return None
    x_end = x_max if rho * h >= 0.0 else min(x_max, -h / rho)
    a, b = 0.5 * rho, math.sin(h)                       # e + b x + a x^2 = 0, b of the other sign than e
    if abs(a) < 1e-12:
        x = -e / b
    else:
        disc = b * b - 4.0 * a * e
        if disc < 0.0:
            return None
        q = -0.5 * (b + math.copysign(math.sqrt(disc), b))   # the roots q / a and e / q, without cancellation
        x = min((r for r in (q / a, e / q) if r > 0.0), default=-1.0)
    return x if 0.0 < x <= x_end else None
