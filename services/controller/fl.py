"""Feedback-linearized path tracking (thesis eq. 3.1-3.5, after Samson and Ait-Abderrahim 1991).

Convention used throughout this project: e_L = y of the robot in the vertex frame (left of the route
positive) and e_H = robot heading minus route heading. Then, along a route of curvature kappa,

    de_L/dt = v sin e_H,        de_H/dt = w - v kappa cos e_H / (1 - kappa e_L).

With p = (e_L, v sin e_H) and dp2/dt = v cos e_H (w - w_ref) = eta, choosing eta = -g1 p1 - g2 p2 gives
the stable linear error dynamics of eq. 3.4 and

    w = w_ref + (-g1 e_L - g2 v sin e_H) / (v cos e_H),                     (eq. 3.5 plus w_ref)

where w_ref = v kappa cos e_H / (1 - kappa e_L) is the route's own turn rate. The thesis leaves w_ref
to the feedforward term (ILC learns it); we include it by default (`curvature_feedforward`) because a
tracker without it settles at e_L = -v^2 kappa / g1 on every arc. Note the thesis writes e_L = y_d - y
and e_H = theta_d - theta; the signs above are that law rederived in our convention.

A robot that turns at a share k of its drive's turn rate (a skid-steer's ground slip, actuator.py
turn_gain) is asked for w_ref / k, so it turns at the route's rate. The feedback is not divided by k: the
gains then act at k times their value, and restoring them made a 47 %-turning Grizzly with a 0.3 s drive
lag and a 0.16 s old estimate cycle +-60 deg at 1.2 m/s (docs/results.md, stop 44): eq. 3.4's poles
placed without the lag and the delay leave the loop too little phase margin once its gain is whole.
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class FLGains:
    gamma1: float = 1.0   # 1/s^2, lateral
    gamma2: float = 1.8   # 1/s, heading (damping ratio gamma2 / (2 sqrt(gamma1)))
    curvature_feedforward: bool = True

    def __post_init__(self):
        if not (self.gamma1 > 0 and self.gamma2 > 0):
            raise ValueError("gamma1 and gamma2 must be > 0")


def route_turn_rate(v: float, e_L: float, e_H: float, kappa: float) -> float:
    denom = 1.0 - kappa * e_L
    if denom < 0.1:  # robot near/beyond the centre of curvature: cap the term
        denom = 0.1
    return v * kappa * math.cos(e_H) / denom


def fl_angular_rate(v: float, e_L: float, e_H: float, kappa: float, gains: FLGains, v_min: float = 0.05,
                    turn_gain: float = 1.0) -> float:
    """Commanded angular rate (rad/s) from lateral/heading errors; eq. 3.5 in our sign convention. A robot
    that turns at `turn_gain` times its drive's rate (actuator.py) is asked for the route's own rate over
    it; the feedback stays as tuned (module docstring)."""
    v_eff = math.copysign(max(abs(v), v_min), v if v != 0 else 1.0)
    cos_h = math.cos(e_H)
    cos_h = math.copysign(max(abs(cos_h), 0.2), cos_h if cos_h != 0 else 1.0)  # singular at 90 deg
    w = (-gains.gamma1 * e_L - gains.gamma2 * v_eff * math.sin(e_H)) / (v_eff * cos_h)
    if gains.curvature_feedforward:
        w += route_turn_rate(v, e_L, e_H, kappa) / turn_gain
    return w
