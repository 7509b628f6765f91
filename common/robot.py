"""Physical description of the thesis robots, shared by the simulator (how it really moves) and the
controller (its command limits). The controller's *model* stays the nominal unicycle (eq. 5.26);
nothing below beyond the limits is known to it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from common.config import ConfigError
from common.typecheck import TypeCheckError, from_dict, to_dict


@dataclass(frozen=True, kw_only=True)
class RobotParams:
    drive: Literal["skid", "ackermann"]
    mass_kg: float
    wheelbase_m: float            # skid: length between axles; ackermann: L in eq. 5.27
    track_m: float
    # command limits (the controller knows these)
    v_max_mps: float
    w_max_radps: float
    steer_max_deg: float = 0.0    # ackermann only
    # actuators: first-order lags plus rate limits; heavier robots are slower
    tau_v_s: float
    tau_w_s: float
    accel_max_mps2: float
    decel_max_mps2: float         # hardest normal braking (used by the watchdog stop)
    yaw_accel_max_radps2: float
    steer_rate_max_dps: float = 0.0   # ackermann only
    tau_steer_s: float = 0.0          # ackermann only
    # wheel-ground interaction
    turn_efficiency: float        # share of commanded yaw rate achieved at low speed (skid-steer)
    turn_loss_per_mps2: float     # further yaw loss per unit lateral acceleration |v w|
    side_slip_s: float            # outward body slide (m/s) per unit lateral acceleration (m/s^2)
    understeer_s2pm2: float = 0.0 # ackermann: yaw rate divided by (1 + K v^2)
    slope_slide_mps: float        # downhill slide speed per sin(slope) while moving
    slope_yaw_radps: float        # yaw rate towards downhill per sin(slope)
    # non-repeatable disturbance (Ornstein-Uhlenbeck) and wheel odometry noise
    noise_v_mps: float
    noise_w_radps: float
    noise_tau_s: float = 0.5
    odom_noise: float = 0.01      # relative std of measured wheel speeds

    def __post_init__(self):
        for name in ("mass_kg", "wheelbase_m", "track_m", "v_max_mps", "w_max_radps", "tau_v_s", "tau_w_s",
                     "accel_max_mps2", "decel_max_mps2", "yaw_accel_max_radps2", "noise_tau_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0")
        if not 0.0 < self.turn_efficiency <= 1.0:
            raise ValueError("turn_efficiency must be in (0, 1]")
        if self.drive == "ackermann" and (self.steer_max_deg <= 0 or self.steer_rate_max_dps <= 0
                                          or self.tau_steer_s <= 0):
            raise ValueError("an ackermann robot needs steer_max_deg, steer_rate_max_dps and tau_steer_s > 0")

    @property
    def max_curvature(self) -> float:
        """Tightest turn the robot can command (1/m); unlimited for a skid-steer robot at rest."""
        if self.drive == "ackermann":
            return math.tan(math.radians(self.steer_max_deg)) / self.wheelbase_m
        return math.inf

    @property
    def max_curvature_rate(self) -> float:
        """How fast the steering can change the curvature, 1/(m s): d kappa / dt = d delta / dt / (L cos^2
        delta) is at least the steering rate / L at any angle; 0 (no such limit) for a skid-steer robot."""
        if self.drive == "ackermann":
            return math.radians(self.steer_rate_max_dps) / self.wheelbase_m
        return 0.0


def steering_from_unicycle(v_mps: float, w_radps: float, wheelbase_m: float) -> float:
    """Thesis eq. 5.27: delta = atan(L w / v). Reversing flips the sign of the needed angle."""
    if abs(v_mps) < 1e-6:
        return 0.0
    return math.atan(wheelbase_m * w_radps / v_mps)


PRESETS: dict[str, RobotParams] = {
    # 50 kg Clearpath Husky, skid-steer, 0.5 m wheelbase (thesis 5.4.1)
    "husky": RobotParams(
        drive="skid", mass_kg=50.0, wheelbase_m=0.5, track_m=0.55, v_max_mps=1.0, w_max_radps=2.0,
        tau_v_s=0.12, tau_w_s=0.10, accel_max_mps2=1.5, decel_max_mps2=4.0, yaw_accel_max_radps2=6.0,
        turn_efficiency=0.9, turn_loss_per_mps2=0.25, side_slip_s=0.03,
        slope_slide_mps=0.35, slope_yaw_radps=1.0, noise_v_mps=0.01, noise_w_radps=0.01),
    # 150-160 kg ROC6, six-wheel skid-steer, 1.5 m wheelbase (thesis 3.3, 5.4.1)
    "roc6": RobotParams(
        drive="skid", mass_kg=160.0, wheelbase_m=1.5, track_m=0.9, v_max_mps=1.5, w_max_radps=1.5,
        tau_v_s=0.25, tau_w_s=0.25, accel_max_mps2=1.0, decel_max_mps2=3.0, yaw_accel_max_radps2=3.0,
        turn_efficiency=0.75, turn_loss_per_mps2=0.35, side_slip_s=0.05,
        slope_slide_mps=0.3, slope_yaw_radps=0.8, noise_v_mps=0.015, noise_w_radps=0.015),
    # 900 kg Clearpath Grizzly, skid-steer (thesis ch. 7), up to 2.0 m/s
    "grizzly": RobotParams(
        drive="skid", mass_kg=900.0, wheelbase_m=1.4, track_m=1.2, v_max_mps=2.5, w_max_radps=1.2,
        tau_v_s=0.45, tau_w_s=0.40, accel_max_mps2=0.8, decel_max_mps2=2.5, yaw_accel_max_radps2=1.5,
        turn_efficiency=0.7, turn_loss_per_mps2=0.3, side_slip_s=0.06,
        slope_slide_mps=0.25, slope_yaw_radps=0.5, noise_v_mps=0.02, noise_w_radps=0.015),
    # 600 kg MATS/DMRV, Ackermann-steered (thesis 5.4.5), commands converted with eq. 5.27
    "mats": RobotParams(
        drive="ackermann", mass_kg=600.0, wheelbase_m=1.9, track_m=1.4, v_max_mps=2.5, w_max_radps=1.0,
        steer_max_deg=30.0, tau_v_s=0.5, tau_w_s=0.3, accel_max_mps2=0.7, decel_max_mps2=2.5,
        yaw_accel_max_radps2=2.0, steer_rate_max_dps=40.0, tau_steer_s=0.15,
        turn_efficiency=1.0, turn_loss_per_mps2=0.0, side_slip_s=0.03, understeer_s2pm2=0.04,
        slope_slide_mps=0.2, slope_yaw_radps=0.3, noise_v_mps=0.02, noise_w_radps=0.01),
}


def robot_from_preset(preset: str, overrides: dict | None = None, where: str = "robot") -> RobotParams:
    """A preset with optional overrides of any of its parameters (unknown names are errors)."""
    if preset not in PRESETS:
        raise ConfigError(f"{where}.preset: unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    merged = to_dict(PRESETS[preset])
    merged.update(overrides or {})
    try:
        return from_dict(RobotParams, merged, where)
    except TypeCheckError as exc:
        raise ConfigError(str(exc)) from None

