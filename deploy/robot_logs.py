"""A robot's own driving logs as the learning pipeline sees them: poses, commands and measured drive
speeds on the controller's grid, and from them the one-period residuals of a nominal model (eq. 5.17)
with their inputs (eq. 5.15), which the GP learns (thesis 5.2).

Formats:
- `f1tenth-csv`: a folder of the F1/10 FrictionMaps logs (commandData.csv: V, delta; pfPoseData.csv:
  particle-filter pose; odomData.csv: wheel odometry twist). An Ackermann command (V, delta) becomes a
  unicycle turn rate by the inverse of eq. 5.27, w = V tan(delta) / L (L: the wheelbase, 0.325 m for
  the F1/10 by default; the logs do not state it).
- `ros2-mcap`: a ROS 2 bag in MCAP: poses and measured speeds from a nav_msgs/Odometry topic (or poses
  from a geometry_msgs/PoseWithCovarianceStamped one), commands from geometry_msgs/Twist or
  TwistStamped; times are the header stamps (the log time for an unstamped Twist; do not mix the two
  where they are different clocks).

On the grid (dt, the controller's period) over the span where the commanded speed exceeds 0.1 m/s:
poses and measured speeds are interpolated linearly (yaw unwrapped), commands are a zero-order hold of
the newest one. No latency compensation: commands and poses pair on their recorded stamps.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.controller.actuator import ActuatorLag
from services.controller.experience import body_residual, body_velocity

MOVING_MPS = 0.1             # commanded speed above which the robot counts as driving
F1TENTH_WHEELBASE_M = 0.325


@dataclass(frozen=True)
class DriveLog:
    name: str
    dt: float
    t_s: np.ndarray          # (N,) grid times
    pose: np.ndarray         # (N, 3) x, y, yaw (unwrapped) in the log's fixed frame
    u: np.ndarray            # (N, 2) commanded (v, w) held over each period
    y: np.ndarray            # (N, 2) measured drive speeds (odometry); NaN where the log has none

    @property
    def travel_m(self) -> float:
        return float(np.sum(np.hypot(np.diff(self.pose[:, 0]), np.diff(self.pose[:, 1]))))


def unicycle_rate(v, delta, wheelbase_m: float):
    """The unicycle turn rate of an Ackermann command: the inverse of eq. 5.27, w = v tan(delta) / L."""
    return np.asarray(v) * np.tan(delta) / wheelbase_m


def _yaw(qx, qy, qz, qw) -> np.ndarray:
    return np.unwrap(np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz)))


def _on_grid(name: str, dt: float, t_cmd, cmd, t_pose, pose, t_speed=None, speed=None) -> DriveLog:
    """Commands (v, w) at t_cmd, poses (x, y, yaw) at t_pose, measured speeds (v, w) at t_speed."""
    moving = t_cmd[cmd[:, 0] > MOVING_MPS]
    if moving.size < 2:
        raise ValueError(f"{name}: the commanded speed never exceeds {MOVING_MPS} m/s")
    t = np.arange(max(moving[0], t_pose[0]), min(moving[-1], t_pose[-1]), dt)
    if t.size < 10:
        raise ValueError(f"{name}: fewer than 10 periods of driving with poses")
    p = np.column_stack([np.interp(t, t_pose, pose[:, i]) for i in range(3)])
    last = np.clip(np.searchsorted(t_cmd, t, side="right") - 1, 0, len(t_cmd) - 1)   # zero-order hold
    y = (np.column_stack([np.interp(t, t_speed, speed[:, i]) for i in range(2)]) if t_speed is not None
         else np.full((t.size, 2), np.nan))
    return DriveLog(name, dt, t, p, cmd[last], y)


def _csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(time s + 1e-9 ns, the data columns after the index, s and ns)."""
    raw = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return raw[:, 1] + 1e-9 * raw[:, 2], raw[:, 3:]


def load_f1tenth_csv(folder: str | Path, dt: float = 0.1, wheelbase_m: float = F1TENTH_WHEELBASE_M) -> DriveLog:
    folder = Path(folder)
    for f in ("commandData.csv", "pfPoseData.csv"):
        if not (folder / f).is_file():
            raise FileNotFoundError(f"{folder} is not an F1/10 log folder: no {f}")
    t_cmd, cmd = _csv(folder / "commandData.csv")            # V [m/s], delta [rad]
    t_pose, pf = _csv(folder / "pfPoseData.csv")             # x, y, qx, qy, qz, qw
    t0 = math.floor(t_pose[0])
    w_cmd = unicycle_rate(cmd[:, 0], cmd[:, 1], wheelbase_m)
    pose = np.column_stack([pf[:, 0], pf[:, 1], _yaw(pf[:, 2], pf[:, 3], pf[:, 4], pf[:, 5])])
    t_speed = speed = None
    if (folder / "odomData.csv").is_file():
        t_speed, odom = _csv(folder / "odomData.csv")         # vx, vy, vz, wx, wy, wz, ...
        t_speed, speed = t_speed - t0, odom[:, [0, 5]]
    return _on_grid(folder.name, dt, t_cmd - t0, np.column_stack([cmd[:, 0], w_cmd]), t_pose - t0, pose,
                    t_speed, speed)


def load_ros2_mcap(path: str | Path, dt: float = 0.1, pose_topic: str = "/odom",
                   cmd_topic: str = "/cmd_vel") -> DriveLog:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    t_cmd, cmd, t_pose, pose, t_speed, speed = [], [], [], [], [], []
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _s, channel, message, msg in reader.iter_decoded_messages(topics=[pose_topic, cmd_topic]):
            header = getattr(msg, "header", None)       # the robot's own time where stamped, else the log's
            t = header.stamp.sec + 1e-9 * header.stamp.nanosec if header is not None else message.log_time * 1e-9
            if channel.topic == cmd_topic:
                twist = getattr(msg, "twist", msg)            # TwistStamped or Twist
                t_cmd.append(t)
                cmd.append((twist.linear.x, twist.angular.z))
            else:
                p = msg.pose.pose
                q = p.orientation
                t_pose.append(t)
                pose.append((p.position.x, p.position.y, q.x, q.y, q.z, q.w))
                if hasattr(msg, "twist"):                     # nav_msgs/Odometry: the measured speeds too
                    t_speed.append(t)
                    speed.append((msg.twist.twist.linear.x, msg.twist.twist.angular.z))
    if not cmd or not pose:
        raise ValueError(f"{path}: no messages on {cmd_topic if not cmd else pose_topic}")
    t0 = math.floor(min(t_pose[0], t_cmd[0]))
    pose_a = np.array(pose)
    xyyaw = np.column_stack([pose_a[:, 0], pose_a[:, 1], _yaw(*pose_a[:, 2:].T)])
    return _on_grid(Path(path).stem, dt, np.array(t_cmd) - t0, np.array(cmd), np.array(t_pose) - t0, xyyaw,
                    np.array(t_speed) - t0 if t_speed else None, np.array(speed) if speed else None)


LOADERS = {"f1tenth-csv": load_f1tenth_csv, "ros2-mcap": load_ros2_mcap}


def residuals(log: DriveLog, lag: ActuatorLag = ActuatorLag()) -> tuple[np.ndarray, np.ndarray]:
    """Inputs a_k = (v_act_{k-1}, w_act_{k-1}, v_cmd_k, w_cmd_k, v_cmd_{k-1}, w_cmd_{k-1}) (the velocity
    and input part of eq. 5.15; a log has no taught route for the route-relative part) and the residuals
    g_k = x_{k+1} - f(x_k, u_k) of the nominal model (eq. 5.17, body frame): the unicycle driven by the
    commands through the drive lag `lag` (no lag: the plain unicycle of eq. 5.26)."""
    xi = tuple(log.u[0])
    A, G = [], []
    for k in range(len(log.t_s) - 1):
        avg, xi_next = lag.step(xi, tuple(log.u[k]))
        if k >= 1:
            v_act, w_act = body_velocity(log.pose[k - 1], log.pose[k], log.dt)
            A.append((v_act, w_act, *log.u[k], *log.u[k - 1]))
            G.append(body_residual(log.pose[k], avg[0], avg[1], log.pose[k + 1], log.dt))
        xi = xi_next
    return np.array(A, dtype=float), np.array(G, dtype=float)
