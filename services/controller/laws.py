"""Steering laws: what turns one localization estimate into an angular-rate command.

The tracker (tracker.py) owns safety, the speed profile and limits; a law only chooses w for the speed
the tracker set. Every law sees the same StepContext, so FL, ILC and the NMPC family plug in alike.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from common.path import Path
from services.controller.corridor import Corridor
from services.controller.actuator import ActuatorLag
from services.controller.fl import MAX_LEAD_S, FLGains, fl_angular_rate, led_errors, route_turn_rate
from services.controller.calibration import PlaceCap
from services.controller.missed_variance import FloorsBySpeed


@dataclass(frozen=True)
class StepContext:
    now_s: float
    path: Path
    vertex: int
    pose: np.ndarray            # estimated robot pose in the route's frame (x, y, theta)
    s_m: float                  # route coordinates of the estimate
    e_lat_m: float
    e_head_rad: float
    v_mps: float                # linear speed the tracker commands this step
    speed_at: Callable[[float], float]   # commanded speed at a distance along the route (schedule + end)
    prev_cmd: tuple[float, float]        # u_{k-1}, the command applied during the last period
    prev_pose: np.ndarray | None         # estimate one period before `pose` (for v_{k-1}, thesis 5.3.1)
    w_limit: float              # |w| the tracker will allow at v_mps
    w_limit_at: Callable[[float], float]  # the same bound for another speed
    # localization delay (eq. 7.12): `pose` was captured D periods ago; these are the D commands applied
    # since (oldest first) and the one applied just before the capture, when known
    delayed_cmds: tuple[tuple[float, float], ...] = ()
    cmd_before_capture: tuple[float, float] | None = None
    # the (v, w) the drive has reached (actuator.py's lag model, from the commands sent) at the start of
    # the capture's period and of this one
    xi_capture: tuple[float, float] = (0.0, 0.0)
    xi_now: tuple[float, float] = (0.0, 0.0)
    pose_cov: np.ndarray | None = None   # 3x3 covariance of `pose` (route frame), from the localizer
    corridor: Corridor | None = None   # per-vertex limits (thesis 7.3), for the constrained laws
    v_max_mps: float = float("inf")      # the robot's speed limit (the constrained laws choose v)
    # per horizon step, the factor on the predicted standard deviations from the online check of the
    # predicted spread (calibration.py); empty: none
    spread_factors: tuple[float, ...] = ()
    # ... and those for a plan faster than the passes over this place vouch for, from which speed
    # (calibration.Beyond; empty: the same)
    spread_factors_beyond: tuple[float, ...] = ()
    spread_beyond_mps: float = float("inf")
    # the calibration's floors on each horizon step's model share of the predicted variance, lateral and
    # heading, by the plan's speed (calibration.floors_by_speed); None: none
    spread_floors: FloorsBySpeed | None = None
    # the speed the latest pass's errors near here allow (calibration.speed_cap_at): C-/RC-LB-NMPC plan no
    # faster; None: no limit
    place_cap: PlaceCap | None = None
    loc_age_s: float = 0.0               # how old `pose` is (now - its capture): what the feedback lags by


@dataclass(frozen=True)
class SolveReport:
    """What an optimizing law's solve did this step."""
    cost: float
    iterations: int
    evaluations: int     # residual evaluations (the budget that bounds the step's time)
    status: str          # converged | budget | stalled | qp-failed | non-finite
    learned: bool        # the local window's GP was in the model

    @property
    def converged(self) -> bool:
        return self.status == "converged"


@dataclass(frozen=True)
class UncertaintyReport:
    """The predicted spread along the horizon (MM-, C-, RC-LB-NMPC)."""
    sigma_lat_max_m: float
    sigma_head_max_rad: float
    speed_scale: float = 1.0    # RC: the share of the scheduled speeds the speed ladder allowed
    violation: float = 0.0      # C/RC: the largest tightened-corridor violation the plan needed
    worst_case: int = -1        # MM: index into minmax.SIGNS of the worst boundary sequence
    # route-frame 1-sigma of the predicted x_1..x_K (what the online calibration checks)
    horizon_sigma_lat_m: tuple[float, ...] = ()
    horizon_sigma_head_rad: tuple[float, ...] = ()
    # the localizer's share of them (its covariance carried along the plan; the calibration leaves it)
    horizon_loc_sigma_lat_m: tuple[float, ...] = ()
    horizon_loc_sigma_head_rad: tuple[float, ...] = ()
    # the calibration's factors on the variance the spreads were widened by, where not the step's
    # spread_factors (RC: a rung faster than the place's passes vouch for; empty: those)
    spread_kappa: tuple[float, ...] = ()
    # the spreads as the model gave them, before the calibration widened them (empty: not reported)
    horizon_model_sigma_lat_m: tuple[float, ...] = ()
    horizon_model_sigma_head_rad: tuple[float, ...] = ()


@dataclass(frozen=True)
class LawResult:
    w_radps: float
    v_mps: float | None = None            # a law that optimizes the speed too (C-/RC-LB-NMPC) sets it
    predicted: np.ndarray | None = None   # (K, 3) predicted poses in the route frame, if the law predicts
    stop_reason: str = ""                 # the law cannot go on safely: stop the robot and say why
    solve: SolveReport | None = None
    uncertainty: UncertaintyReport | None = None
    feedforward_radps: float = 0.0        # ILC: the learned part of w_radps
    note: str = ""                        # what the law did unlike its usual step (the status's reason)
    held_by: str = ""                     # where v_mps is below the asked speed: why (messages.SpeedCause)


class SteeringLaw(Protocol):
    name: str

    def angular(self, ctx: StepContext) -> LawResult: ...


class FLLaw:
    """Feedback linearization, eq. 3.5 (see fl.py for the sign convention, w_ref and the lead)."""
    name = "fl"

    def __init__(self, gains: FLGains, lag: ActuatorLag | None = None):
        self.gains = gains
        self.lag = lag or ActuatorLag()     # the drive the command goes through (actuator.py; fl.py)

    def angular(self, ctx: StepContext) -> LawResult:
        return LawResult(fl_command(ctx, self.gains, self.lag))


def fl_command(ctx: StepContext, gains: FLGains, lag: ActuatorLag) -> float:
    """Eq. 3.5 at this step; with `gains.lead`, at the errors the robot's turn leads to over the
    estimate's age and the drive's settling time, and with the route's turn where that takes it (fl.py)."""
    kappa = float(ctx.path.curvature[ctx.vertex])
    e_L, e_H = ctx.e_lat_m, ctx.e_head_rad
    if gains.lead:
        v_now = ctx.xi_now[0]
        delta = turn_now(ctx, lag) - route_turn_rate(v_now, e_L, e_H, kappa)
        lead_s = min(max(ctx.loc_age_s + lag.turn_settling_s(delta, v_now), 0.0), MAX_LEAD_S)
        e_L, e_H = led_errors(v_now, e_L, e_H, delta, lead_s)
        kappa = ctx.path.curvature_at(ctx.s_m + abs(v_now) * lead_s)
    return fl_angular_rate(ctx.v_mps, e_L, e_H, kappa, gains, turn_gain=lag.turn_gain)


def turn_now(ctx: StepContext, lag: ActuatorLag) -> float:
    """The robot's turn rate now: the estimates' over the period before the capture, plus the change
    the drive's lag model makes of it since (the ground's yaw, which the drive model does not know,
    is in the first); the model's alone without an estimate one period earlier."""
    if ctx.prev_pose is None:
        return lag.turn_rate(ctx.xi_now)
    measured = math.remainder(float(ctx.pose[2] - ctx.prev_pose[2]), 2.0 * math.pi) / lag.dt
    return measured + lag.turn_rate(ctx.xi_now) - lag.turn_rate(ctx.xi_capture)
