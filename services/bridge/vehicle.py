"""Vehicle dynamics of the simulated robot: actuators, wheel-ground slip, terrain, noise.

Skid-steer: the drive controllers track commanded (v, w) through first-order lags with acceleration
limits; the ground then gives back less yaw than the wheels ask for, the more so the harder the turn
(lateral acceleration v*w), and the body slides outwards in turns. Ackermann: (v, w) becomes a
steering angle by eq. 5.27, the steering actuator is rate limited and lagged, and yaw follows from
the bicycle model with understeer. Side slopes make the robot slide and yaw downhill while moving.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.robot import RobotParams, steering_from_unicycle
from services.bridge.terrain import TerrainEffect


@dataclass
class VehicleState:
    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0
    v_act: float = 0.0          # what the drive loops achieved at the wheels
    w_act: float = 0.0
    steer: float = 0.0          # ackermann steering angle (rad)
    noise_v: float = 0.0        # Ornstein-Uhlenbeck non-repeatable disturbance states
    noise_w: float = 0.0
    # over-ground motion during the last step
    v_ground: float = 0.0
    w_ground: float = 0.0
    v_lateral: float = 0.0


def _approach(value: float, target: float, tau: float, rate_up: float, rate_down: float, h: float) -> float:
    """First-order lag towards target with separate limits for speeding up and slowing down."""
    step = (target - value) * min(1.0, h / tau)
    speeding_up = abs(target) > abs(value) and target * value >= 0.0
    limit = (rate_up if speeding_up else rate_down) * h
    return value + max(-limit, min(limit, step))


def _brake(value: float, rate: float, h: float) -> float:
    return value - math.copysign(min(abs(value), rate * h), value)


class Vehicle:
    def __init__(self, params: RobotParams):
        self.p = params
        self.s = VehicleState()

    def reset(self, x: float, y: float, theta: float) -> None:
        self.s = VehicleState(x=x, y=y, theta=theta)

    def step(self, h: float, v_cmd: float, w_cmd: float, braking: bool, terrain: TerrainEffect,
             rng: np.random.Generator) -> None:
        p, s = self.p, self.s
        v_cmd = max(-p.v_max_mps, min(p.v_max_mps, v_cmd))
        w_cmd = max(-p.w_max_radps, min(p.w_max_radps, w_cmd))

        # --- actuators ------------------------------------------------------------------
        if braking:  # watchdog: hardest braking, straight to zero
            s.v_act = _brake(s.v_act, p.decel_max_mps2, h)
            s.w_act = _brake(s.w_act, p.yaw_accel_max_radps2, h)
        else:
            s.v_act = _approach(s.v_act, v_cmd, p.tau_v_s, p.accel_max_mps2, p.decel_max_mps2, h)
        if p.drive == "ackermann":
            steer_max = math.radians(p.steer_max_deg)
            if abs(v_cmd) > 1e-3 and not braking:
                target = max(-steer_max, min(steer_max, steering_from_unicycle(v_cmd, w_cmd, p.wheelbase_m)))
            else:
                target = s.steer  # standing still: the wheels stay where they are
            rate = math.radians(p.steer_rate_max_dps)
            s.steer = _approach(s.steer, target, p.tau_steer_s, rate, rate, h)
            s.w_act = s.v_act * math.tan(s.steer) / p.wheelbase_m
        elif not braking:
            s.w_act = _approach(s.w_act, w_cmd, p.tau_w_s, p.yaw_accel_max_radps2, p.yaw_accel_max_radps2, h)

        # --- wheel-ground interaction -----------------------------------------------------
        moving = min(1.0, abs(s.v_act) / 0.3) if abs(s.v_act) > 1e-4 or abs(s.w_act) > 1e-4 else 0.0
        lat_acc = abs(s.v_act * s.w_act)
        if p.drive == "skid":
            yaw_eff = p.turn_efficiency / (1.0 + p.turn_loss_per_mps2 * lat_acc)
        else:
            yaw_eff = 1.0 / (1.0 + p.understeer_s2pm2 * s.v_act ** 2)
        v_g = s.v_act * terrain.traction_v
        w_g = s.w_act * yaw_eff * terrain.traction_w
        v_lat = -p.side_slip_s * v_g * w_g  # outward slide in turns

        # side slope: slide and yaw downhill, only while the wheels are slipping (moving)
        drift_x = drift_y = 0.0
        if terrain.slope_sin > 0.0 and moving > 0.0:
            slide = p.slope_slide_mps * terrain.slope_sin * moving
            drift_x = slide * math.cos(terrain.downhill_rad)
            drift_y = slide * math.sin(terrain.downhill_rad)
            w_g += p.slope_yaw_radps * terrain.slope_sin * moving * math.sin(terrain.downhill_rad - s.theta)
        # rough ground and ruts: a place-fixed yaw disturbance growing with speed
        w_g += terrain.yaw_field * abs(v_g)

        # non-repeatable disturbance: Ornstein-Uhlenbeck, felt only while moving
        a = h / p.noise_tau_s
        s.noise_v += -a * s.noise_v + p.noise_v_mps * math.sqrt(2 * a) * rng.standard_normal()
        s.noise_w += -a * s.noise_w + p.noise_w_radps * math.sqrt(2 * a) * rng.standard_normal()
        v_g += s.noise_v * moving
        w_g += s.noise_w * moving

        # --- integrate (midpoint heading) --------------------------------------------------
        th_mid = s.theta + 0.5 * w_g * h
        c, sn = math.cos(th_mid), math.sin(th_mid)
        s.x += (v_g * c - v_lat * sn + drift_x) * h
        s.y += (v_g * sn + v_lat * c + drift_y) * h
        s.theta = math.atan2(math.sin(s.theta + w_g * h), math.cos(s.theta + w_g * h))
        # over-ground body velocities, for truth
        s.v_ground = v_g + drift_x * c + drift_y * sn
        s.v_lateral = v_lat - drift_x * sn + drift_y * c
        s.w_ground = w_g
