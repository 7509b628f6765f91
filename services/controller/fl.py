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

Eq. 3.5 reads the errors as they are, as if the turn it commands came at once. It comes late: the
estimate is already `age` old, the drive follows within its lag tau_w, and a rate-limited steering (an
Ackermann's) needs |delta| / r more to swing back from a turn rate delta beyond the route's, r = v R_kappa.
A MATS at 1.6 m/s takes about a second to bring its steering back from a full lock; meanwhile its
heading turns on by 15-20 deg, which the law, seeing it only then, answers with the opposite lock: the
saturated swing of +-35 deg and +-2 m that a single yaw kick set off (docs/results.md, stop 65). With
`lead` (default), the law is evaluated at the errors the robot will have once that turn has played
out (`led_errors`: the robot keeps turning at delta relative to the route for the lead time), which in
the small is a lead compensator on the drive's lag, and in the large starts the counter-steer early
enough for the steering's rate. delta is the turn the estimates show (laws.turn_now), so the ground's
yaw, which the drive model does not know, counts too. The route's own turn w_ref is then the one at
the place the lead takes the robot to (s + v T on the route, T the lead time): a corner is asked for as
early as the drive needs to turn on arrival, and its end straightens as early. At the corner's own
curvature, a Grizzly with a 0.45 s turn lag went wide into every corner and overshot at its end
(tests/test_fl_lead.py). `lead = false` gives eq. 3.5 as the thesis writes it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class FLGains:
    gamma1: float = 1.0   # 1/s^2, lateral
    gamma2: float = 1.8   # 1/s, heading (damping ratio gamma2 / (2 sqrt(gamma1)))
    curvature_feedforward: bool = True
    lead: bool = True     # evaluate the law at the errors the drive's lag and the estimate's age lead to

    def __post_init__(self):
        if not (self.gamma1 > 0 and self.gamma2 > 0):
            raise ValueError("gamma1 and gamma2 must be > 0")


MAX_LEAD_S = 2.0          # errors further ahead than this are not extrapolated from one turn rate


def led_errors(v: float, e_L: float, e_H: float, delta_radps: float, lead_s: float) -> tuple[float, float]:
    """(e_L, e_H) after `lead_s` (capped at MAX_LEAD_S) of driving at v and turning at `delta_radps`
    relative to the route: the arc's exact offset along a straight route."""
    t = min(max(lead_s, 0.0), MAX_LEAD_S)
    e_H1 = e_H + delta_radps * t
    if abs(delta_radps * t) < 1e-6:
        return e_L + v * t * math.sin(e_H), e_H1
    return e_L + v * (math.cos(e_H) - math.cos(e_H1)) / delta_radps, e_H1


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
