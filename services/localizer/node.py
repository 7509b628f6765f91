"""Localizer service: turns sensor data into the pose relative to the nearest taught vertex.

The source is a pure object with start_teach / finish_teach / start_repeat and a per-tick input:
`pose` (simulator truth made to look like a localizer) takes truth, `vision` (stereo VT&R) takes
stereo frames. This node feeds it, publishes its LocState per tick, keeps the taught routes on disk
and serves them to any service on `lbc/paths/<path_id>`.
"""
from __future__ import annotations

import math

import numpy as np
import zenoh

from common import keys
from common.bus import Latest, Node
from common.codec import encode
from common.config import ConfigError
from common.messages import StereoFrame, TruthPose
from common.service import Control, Service, service_main
from services.localizer.config import LocalizerConfig
from services.localizer.pose_source import PoseSource, PoseSourceSettings
from services.localizer.routes import RouteStore


def make_source(cfg: LocalizerConfig):
    if cfg.source == "vision":
        from services.localizer.vision_source import VisionSource   # OpenCV only where it is used

        if abs(cfg.vision.keyframe_dist_m - cfg.vertex_spacing_m) > 1e-9:
            raise ConfigError(f"vision.keyframe_dist_m ({cfg.vision.keyframe_dist_m}) must equal "
                              f"vertex_spacing_m ({cfg.vertex_spacing_m}): keyframes are the route's vertices")
        return VisionSource(cfg.vision, f"{cfg.data_dir}/routes")
    p = cfg.pose
    settings = PoseSourceSettings(
        noise_m=p.noise_m, noise_heading_rad=math.radians(p.noise_heading_deg), noise_tau_s=p.noise_tau_s,
        jitter_m=p.jitter_m, period_s=cfg.period_s,
        delay_ticks=int(round(p.delay_s / cfg.period_s)), dropout_prob=p.dropout_prob,
        dropout_ticks=max(1, int(round(p.dropout_s / cfg.period_s))), vertex_spacing_m=cfg.vertex_spacing_m,
        jumps=tuple(p.jumps))
    return PoseSource(settings, np.random.default_rng([cfg.seed, 2, 0]))


FRAME = "__frame__"


class LocalizerService(Service):
    name = "localizer"

    def __init__(self, cfg: LocalizerConfig, node: Node):
        super().__init__(node)
        self.cfg = cfg
        self.source = make_source(cfg)
        self.routes = RouteStore(f"{cfg.data_dir}/routes")
        self.mode = "idle"
        self.trial = 0
        self.path_id = ""
        self.loop = False
        self.k_loc = keys.loc_state(cfg.robot_name)
        self.frames_dropped = 0
        self._frame_seq = 0
        if cfg.source == "vision":
            # only the newest frame matters: when localization falls behind (realtime mode), older frames
            # are skipped rather than queued, so the latency stays one frame (lockstep never skips)
            self._frame = Latest()
            node.subscribe(keys.stereo(cfg.robot_name), StereoFrame,
                           lambda msg, _k: (self._frame.set(msg), self.inbox.put((FRAME, None))))
        else:
            node.subscribe_queue(keys.truth(cfg.robot_name), TruthPose, self.inbox)
        node.queryable(f"{keys.ROOT}/paths/*", self._serve_route)

    def _serve_route(self, query: zenoh.Query) -> None:
        """Answer `lbc/paths/<id>` from disk (on Zenoh's thread: a cached read, no heavy work)."""
        try:
            path_id = str(query.key_expr).rsplit("/", 1)[-1]
            if path_id == "*":
                for pid in self.routes.ids():
                    query.reply(keys.route(pid), encode(self.routes.load_msg(pid)))
                return
            try:
                msg = self.routes.load_msg(path_id)
            except (KeyError, ValueError) as exc:
                query.reply_err(str(exc).encode())
                return
            query.reply(keys.route(path_id), encode(msg))
        except Exception as exc:  # never let a bad query take the service down
            self.log.warning("route query %s failed: %s", query.key_expr, exc)
        finally:
            query.drop()

    def on_message(self, key: str, msg: TruthPose | None) -> None:
        if key == FRAME:
            frame, seq = self._frame.get()
            if seq == self._frame_seq:
                return          # already handled (a newer frame's wake-up took it)
            skipped = max(seq - self._frame_seq - 1, 0)
            if skipped and self.frames_dropped // 100 != (self.frames_dropped + skipped) // 100:
                self.log.warning("localization is slower than the camera: %d stale frames skipped so far",
                                 self.frames_dropped + skipped)
            self.frames_dropped += skipped
            self._frame_seq = seq
            if self.mode != "idle" and frame.trial == self.trial:
                self.node.publish(self.k_loc, self.source.on_frame(frame, self.path_id))
            return
        if self.mode == "idle" or msg.trial != self.trial:
            return
        self.node.publish(self.k_loc, self.source.on_truth(msg, self.path_id))

    def on_control(self, ctl: Control) -> None:
        req = ctl.request
        if req.action == "ping":
            return self.reply(ctl, True, f"mode={self.mode} routes={self.routes.ids()}")
        if req.action == "prepare":
            if req.mode == "teach":
                self.source.start_teach(req.trial)
                self.mode, self.trial, self.path_id, self.loop = "teach", req.trial, req.path_id, req.loop
                return self.reply(ctl, True, f"recording route {req.path_id}")
            if req.mode == "repeat":
                try:
                    path = self.routes.load(req.path_id)
                except (KeyError, ValueError) as exc:
                    self.mode = "idle"
                    return self.reply(ctl, False, str(exc))
                try:
                    self.source.start_repeat(path, req.trial, np.random.default_rng([self.cfg.seed, 2, req.trial]))
                except ValueError as exc:
                    self.mode = "idle"
                    return self.reply(ctl, False, str(exc))
                self.mode, self.trial, self.path_id = "repeat", req.trial, req.path_id
                return self.reply(ctl, True, f"route {req.path_id}: {len(path)} vertices, {path.length_m:.1f} m")
            return self.reply(ctl, False, "prepare needs mode teach or repeat")
        if req.action == "stop":
            if self.mode == "teach":
                self.mode = "idle"
                try:
                    path = self.source.finish_teach(self.path_id, loop=self.loop, taught_by=self.cfg.robot_name)
                except ValueError as exc:
                    return self.reply(ctl, False, str(exc))
                where = self.routes.save(path, 0.0)
                return self.reply(ctl, True, f"route {path.path_id}: {len(path)} vertices, "
                                  f"{path.length_m:.1f} m, saved to {where}")
            self.mode = "idle"
            return self.reply(ctl, True, "idle")
        if req.action == "start":
            return self.reply(ctl, True, "")
        return self.reply(ctl, False, f"unsupported action {req.action}")


def main(argv: list[str] | None = None) -> int:
    return service_main("localizer", LocalizerConfig, LocalizerService, lambda c: c.robot_name, argv)
