"""The run's bus messages as the standard ROS 2 topics, so that Foxglove and the ROS 2 tools show a run
without knowing this project: what the recorder writes beside the project's own channels.

Frames: `world` is the simulator's (truth), `map` the taught route's (the localizer's estimates, the
route, the corridor and the controller's prediction), `odom` the wheel odometry's. Robot frames are
`<robot>/base_link` (the estimate) and `<robot>/truth`. Stamps are robot time (the bridge's clock).

Topics: /tf (tf2_msgs/TFMessage: world -> truth, map -> estimate), /odom (nav_msgs/Odometry), /cmd_vel
(geometry_msgs/TwistStamped), /route (nav_msgs/Path), /corridor and /controller/horizon
(visualization_msgs/MarkerArray: the corridor's edges; the predicted poses with their 3-sigma lateral
band), /localization/pose (geometry_msgs/PoseWithCovarianceStamped), /stereo/{left,right}/image_raw
(sensor_msgs/Image, or .../compressed for PNG frames). And /controller/tracking (JSON: errors, command,
spread, solve time; no ROS 2 message holds a path tracker's errors). deploy/foxglove/ has a layout.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.messages import ControllerStatus, LocState, Odometry, RouteMsg, StereoFrame, TruthPose, VelocityCommand


@dataclass(frozen=True)
class Ros2Message:
    topic: str
    datatype: str         # a ROS 2 type (encoding cdr), or the name of a JSON Schema in JSON_SCHEMAS (json)
    message: dict
    stamp_s: float
    encoding: str = "cdr"


# No ROS 2 message carries a path tracker's errors: they go out as JSON (which Foxglove plots), with a schema
TRACKING = "lbc/Tracking"
JSON_SCHEMAS = {TRACKING: {
    "type": "object", "title": TRACKING,
    "description": "The controller's view of one step: errors against the taught route (estimate), command, "
                   "predicted 1-sigma lateral spread, solve time",
    "properties": {"stamp_s": {"type": "number"}, "trial": {"type": "integer"}, "state": {"type": "string"},
                   "distance_m": {"type": "number"}, "lateral_m": {"type": "number"},
                   "heading_deg": {"type": "number"}, "v_cmd_mps": {"type": "number"},
                   "w_cmd_radps": {"type": "number"}, "sigma_lat_m": {"type": "number"},
                   "solve_ms": {"type": "number"}}}}


# every topic a run can have but the camera's (raw or compressed, depending on the frames), with its type
TOPICS = {"/tf": "tf2_msgs/TFMessage", "/odom": "nav_msgs/Odometry", "/cmd_vel": "geometry_msgs/TwistStamped",
          "/route": "nav_msgs/Path", "/corridor": "visualization_msgs/MarkerArray",
          "/controller/horizon": "visualization_msgs/MarkerArray",
          "/localization/pose": "geometry_msgs/PoseWithCovarianceStamped", "/controller/tracking": TRACKING}


def announcement(topic: str) -> Ros2Message:
    """An empty message of one of TOPICS: what a channel for it needs to be declared before data flows."""
    datatype = TOPICS[topic]
    return Ros2Message(topic, datatype, {}, 0.0, "json" if datatype in JSON_SCHEMAS else "cdr")


def _time(stamp_s: float) -> dict:
    sec = math.floor(stamp_s)
    return {"sec": int(sec), "nanosec": min(int(round((stamp_s - sec) * 1e9)), 999_999_999)}


def _header(stamp_s: float, frame: str) -> dict:
    return {"stamp": _time(stamp_s), "frame_id": frame}


def _yaw(theta: float) -> dict:
    return {"x": 0.0, "y": 0.0, "z": math.sin(theta / 2), "w": math.cos(theta / 2)}


def _pose(x: float, y: float, theta: float) -> dict:
    return {"position": {"x": x, "y": y, "z": 0.0}, "orientation": _yaw(theta)}


def _colour(r: float, g: float, b: float, a: float = 1.0) -> dict:
    return {"r": r, "g": g, "b": b, "a": a}


def _line(stamp_s: float, ns: str, i: int, xy: np.ndarray, colour: dict, width_m: float) -> dict:
    """A LINE_STRIP marker through the points `xy` (N, 2) in the map frame."""
    return {"header": _header(stamp_s, "map"), "ns": ns, "id": i, "type": 4, "action": 0,
            "pose": _pose(0.0, 0.0, 0.0), "scale": {"x": width_m, "y": 0.0, "z": 0.0}, "color": colour,
            "points": [{"x": float(x), "y": float(y), "z": 0.0} for x, y in xy]}


def _offset(x: np.ndarray, y: np.ndarray, theta: np.ndarray, d) -> np.ndarray:
    """Points moved `d` to the left of their heading."""
    return np.column_stack([x - np.sin(theta) * d, y + np.cos(theta) * d])


class Ros2Export:
    """Converts one run's messages as they arrive; the estimates need the taught route, so it keeps it."""

    def __init__(self, robot: str, corridor_lateral_m: float):
        self.robot = robot
        self.corridor_lateral_m = corridor_lateral_m
        self.routes: dict[str, np.ndarray] = {}     # path_id -> (N, 3) vertex poses in the map frame

    def convert(self, msg) -> list[Ros2Message]:
        for cls, fn in ((TruthPose, self._truth), (LocState, self._estimate), (Odometry, self._odom),
                        (VelocityCommand, self._cmd), (RouteMsg, self._route), (ControllerStatus, self._status),
                        (StereoFrame, self._stereo)):
            if isinstance(msg, cls):
                return fn(msg)
        return []

    def _tf(self, stamp_s: float, parent: str, child: str, x: float, y: float, theta: float) -> Ros2Message:
        t = {"header": _header(stamp_s, parent), "child_frame_id": child,
             "transform": {"translation": {"x": x, "y": y, "z": 0.0}, "rotation": _yaw(theta)}}
        return Ros2Message("/tf", "tf2_msgs/TFMessage", {"transforms": [t]}, stamp_s)

    def _truth(self, m: TruthPose) -> list[Ros2Message]:
        return [self._tf(m.stamp_s, "world", f"{self.robot}/truth", m.x_world_m, m.y_world_m, m.theta_world_rad)]

    def _estimate(self, m: LocState) -> list[Ros2Message]:
        route = self.routes.get(m.path_id)
        if m.T_vertex_robot is None or m.cov_T_vertex_robot is None or route is None or not 0 <= m.vertex < len(route):
            return []
        xv, yv, tv = route[m.vertex]
        dx, dy, dth = m.T_vertex_robot
        c, s = math.cos(tv), math.sin(tv)
        x, y, th = xv + c * dx - s * dy, yv + s * dx + c * dy, tv + dth
        # the covariance in the vertex frame, rotated into the map's (x, y, yaw of a 6x6 row-major)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        cov3 = R @ np.asarray(m.cov_T_vertex_robot, dtype=float).reshape(3, 3) @ R.T
        cov6 = np.zeros((6, 6))
        idx = [0, 1, 5]
        cov6[np.ix_(idx, idx)] = cov3
        pose = {"header": _header(m.stamp_s, "map"), "pose": {"pose": _pose(x, y, th), "covariance": cov6.ravel().tolist()}}
        return [self._tf(m.stamp_s, "map", f"{self.robot}/base_link", x, y, th),
                Ros2Message("/localization/pose", "geometry_msgs/PoseWithCovarianceStamped", pose, m.stamp_s)]

    def _odom(self, m: Odometry) -> list[Ros2Message]:
        msg = {"header": _header(m.stamp_s, "odom"), "child_frame_id": f"{self.robot}/base_link",
               "pose": {"pose": _pose(m.x_odom_m, m.y_odom_m, m.theta_odom_rad), "covariance": [0.0] * 36},
               "twist": {"twist": {"linear": {"x": m.v_mps, "y": 0.0, "z": 0.0},
                                   "angular": {"x": 0.0, "y": 0.0, "z": m.w_radps}}, "covariance": [0.0] * 36}}
        return [Ros2Message("/odom", "nav_msgs/Odometry", msg, m.stamp_s)]

    def _cmd(self, m: VelocityCommand) -> list[Ros2Message]:
        msg = {"header": _header(m.stamp_s, f"{self.robot}/base_link"),
               "twist": {"linear": {"x": m.v_mps, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": m.w_radps}}}
        return [Ros2Message("/cmd_vel", "geometry_msgs/TwistStamped", msg, m.stamp_s)]

    def _route(self, m: RouteMsg) -> list[Ros2Message]:
        poses = np.column_stack([m.x_m, m.y_m, m.theta_rad])
        self.routes[m.path_id] = poses
        path = {"header": _header(m.stamp_s, "map"),
                "poses": [{"header": _header(m.stamp_s, "map"), "pose": _pose(*map(float, p))} for p in poses]}
        x, y, th, d = poses[:, 0], poses[:, 1], poses[:, 2], self.corridor_lateral_m
        edges = [_line(m.stamp_s, "corridor", i, _offset(x, y, th, side * d), _colour(0.85, 0.2, 0.2, 0.8), 0.03)
                 for i, side in enumerate((1.0, -1.0))]
        return [Ros2Message("/route", "nav_msgs/Path", path, m.stamp_s),
                Ros2Message("/corridor", "visualization_msgs/MarkerArray", {"markers": edges}, m.stamp_s)]

    def _status(self, m: ControllerStatus) -> list[Ros2Message]:
        tracking = {"stamp_s": m.stamp_s, "trial": m.trial, "state": m.state, "distance_m": m.distance_m,
                    "lateral_m": m.lateral_m, "heading_deg": math.degrees(m.heading_rad), "v_cmd_mps": m.v_cmd_mps,
                    "w_cmd_radps": m.w_cmd_radps, "sigma_lat_m": m.sigma_lat_m, "solve_ms": m.solve_ms}
        return [Ros2Message("/controller/tracking", TRACKING, tracking, m.stamp_s, "json")] + self._horizon(m)

    def _horizon(self, m: ControllerStatus) -> list[Ros2Message]:
        if not m.pred_x_m:
            return []
        x, y, th = (np.asarray(v, dtype=float) for v in (m.pred_x_m, m.pred_y_m, m.pred_theta_rad))
        markers = [_line(m.stamp_s, "prediction", 0, np.column_stack([x, y]), _colour(0.1, 0.6, 0.1), 0.03)]
        sigma = np.asarray(m.pred_sigma_lat_m, dtype=float)
        if sigma.size == x.size:
            band = _colour(0.1, 0.6, 0.1, 0.5)
            markers += [_line(m.stamp_s, "prediction_3sigma", i, _offset(x, y, th, side * 3.0 * sigma), band, 0.015)
                        for i, side in enumerate((1.0, -1.0))]
        return [Ros2Message("/controller/horizon", "visualization_msgs/MarkerArray", {"markers": markers}, m.stamp_s)]

    def _stereo(self, m: StereoFrame) -> list[Ros2Message]:
        out = []
        for side, data in (("left", m.left), ("right", m.right)):
            header = _header(m.stamp_s, f"{self.robot}/camera_{side}")
            if m.encoding == "png":
                out.append(Ros2Message(f"/stereo/{side}/image_raw/compressed", "sensor_msgs/CompressedImage",
                                       {"header": header, "format": "png", "data": data}, m.stamp_s))
            else:
                out.append(Ros2Message(f"/stereo/{side}/image_raw", "sensor_msgs/Image",
                                       {"header": header, "height": m.height_px, "width": m.width_px,
                                        "encoding": "mono8", "is_bigendian": 0, "step": m.width_px, "data": data},
                                       m.stamp_s))
        return out
