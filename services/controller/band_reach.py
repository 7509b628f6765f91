"""How much of the corridor RC-LB-NMPC's tightening may take where the mean cannot get away from an edge.

The band left to the mean (eq. 7.4: the corridor tightened by alpha * sigma, capped) is a demand on the
plan. Near an edge at a crawl, no plan reaches a band narrower than the robot's offset within the
horizon: a lateral error closes at v sin(heading), and the heading itself has to stay in its band. The
slack's L1 price then makes the SQP spend every input on millimetres of band: it turns at the drive's
limit, and the turn widens the next step's spread. So, beyond the first step (whose spread the law
checks as it is), the tightening is capped again: the mean must be able to reach the band by a moderate
correction: turning back along a curvature of at most `REACH_CURVATURE` (and `REACH_SHARE` of the drive's
turn-rate limit) to at most `REACH_SHARE` of the heading band, as a path follower would. Where the mean
can reach the band so, nothing changes; where it cannot, the band starts where that correction takes it.

Only while the first step's own alpha-sigma region fits: a robot already that close to an edge (a slope
pushing it out, say) is in trouble, and everything that shrinks the exposure (slowing to a crawl,
correcting at any cost) is what the slack price should buy.
"""
from __future__ import annotations

import math

import numpy as np

REACH_SHARE = 0.5       # of the drive's turn-rate limit and of the tightened heading band, for a correction
REACH_CURVATURE = 1.0   # 1/m: the correction's turn rate is at most this times the speed


def start_errors(problem) -> tuple[float, float]:
    """(lateral m, heading rad) of the start in the corridor's frame at the first desired pose."""
    ref, x0 = problem.ref, problem.x0
    d = x0[:2] - ref.poses[0, :2]
    lat = -ref.sin_dir[0] * d[0] + ref.cos_dir[0] * d[1]
    head = math.remainder(float(x0[2] - ref.poses[0, 2]), 2 * math.pi)
    return float(lat), head


def reach_capped(cap: np.ndarray, start: tuple[float, float], v_eff: np.ndarray, w_lim: np.ndarray, dt: float,
                 lo_lat: np.ndarray, hi_lat: np.ndarray, head_lim: np.ndarray, t: np.ndarray) -> np.ndarray:
    """`cap` (K, 3) lowered at x_2..x_K so that the correction from `start` (lateral, heading) reaches
    the band: v_eff (K,) the speeds moved at, w_lim (K,) the drive's |w| bounds at them, t (K, 3) the
    tightening alpha * sigma the plan would get. Unchanged where the first step's region does not fit."""
    e0, h0 = start
    e1 = e0 + dt * v_eff[0] * math.sin(h0)
    if not (lo_lat[0] + t[0, 1] <= e1 <= hi_lat[0] - t[0, 1] and abs(h0) + t[0, 2] <= head_lim[0]):
        return cap
    rate = np.minimum(REACH_SHARE * w_lim, REACH_CURVATURE * v_eff)
    turned = dt * np.concatenate([[0.0], np.cumsum(rate[:-1])])   # by the start of each period
    out = cap.copy()
    # heading: the least |error| reachable by x_j, turning back since period 0
    least_head = np.maximum(abs(h0) - dt * np.cumsum(rate), 0.0)
    out[1:, 2] = np.minimum(cap[1:, 2], np.maximum(head_lim[1:] - least_head[1:], 0.0))
    # lateral: headings of each period turned towards either side, inside a share of the heading band
    band = REACH_SHARE * np.maximum(head_lim - np.minimum(t[:, 2], out[:, 2]), 0.0)
    band = np.concatenate([[abs(h0)], band[:-1]])     # period i starts at x_i's heading (x_0: the robot's)
    down = np.maximum(h0 - turned, np.minimum(h0, -band))
    up = np.minimum(h0 + turned, np.maximum(h0, band))
    lowest = e0 + dt * np.cumsum(v_eff * np.sin(down))
    highest = e0 + dt * np.cumsum(v_eff * np.sin(up))
    room = np.maximum(np.minimum(hi_lat - lowest, highest - lo_lat), 0.0)
    out[1:, 1] = np.minimum(cap[1:, 1], room[1:])
    return out
