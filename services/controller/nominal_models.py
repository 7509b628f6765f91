"""The nominal model of each route the robot was taught: recorded during the teach pass, identified at
its end (identification.py), kept on disk (one file per route, written atomically) so that later trials
and restarts use it."""
from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path as FsPath

from common.atomic_file import write_atomically
from common.codec import DecodeError, decode, encode
from common.messages import BridgeStatus, LocState, NominalModel, Odometry, check_name
from common.path import Path
from services.controller.identification import TeachRecorder, identify

log = logging.getLogger(__name__)


def model_file(directory: str | FsPath, path_id: str) -> FsPath:
    return FsPath(directory) / f"{check_name('path_id', path_id)}.model"


def save_model(directory: str | FsPath, model: NominalModel) -> FsPath:
    return write_atomically(model_file(directory, model.path_id), encode(model))


class NominalModels:
    def __init__(self, robot: str, dt: float, directory: str | FsPath | None,
                 curvature_rate_max_per_ms: float = 0.0, w_limit: Callable[[float], float] | None = None):
        self.robot = robot
        self.dt = dt
        self.curvature_rate_max_per_ms = curvature_rate_max_per_ms   # the robot's, for its Ackermann steering
        self.w_limit = w_limit          # the robot's turn-rate limit at a speed, for the teach pass's share of it
        self.directory = FsPath(directory) if directory else None
        self.teach: TeachRecorder | None = None
        self._known: dict[str, NominalModel] = {}

    def start_teach(self) -> None:
        self.teach = TeachRecorder(self.dt)

    def record(self, msg: BridgeStatus | Odometry | LocState) -> None:
        """What the teach pass shows: applied commands, wheel odometry, teach-time pose estimates."""
        rec = self.teach
        if rec is None:
            return
        if isinstance(msg, BridgeStatus):
            if msg.mode == "teach" and msg.running:
                rec.add_applied(msg.tick, msg.v_cmd_applied_mps, msg.w_cmd_applied_radps)
        elif isinstance(msg, Odometry):
            rec.add_odometry(msg.tick, msg.v_mps, msg.w_radps)
        elif msg.status == "teach":
            rec.add_estimate(msg)

    def finish_teach(self, path: Path, stamp_s: float) -> NominalModel:
        """Identify the model of the pass just recorded on `path`, keep it (and on disk) for the route."""
        if self.teach is None:
            raise ValueError("no teach pass was recorded")
        model = identify(self.teach, path, self.robot, stamp_s,
                         curvature_rate_max_per_ms=self.curvature_rate_max_per_ms, w_limit=self.w_limit)
        self.teach = None
        self._known[path.path_id] = model
        if self.directory is not None:
            save_model(self.directory, model)
        return model

    def of(self, path_id: str) -> NominalModel | None:
        """The route's identified model, or None when it was not taught here (or by an older version,
        whose model lacks what this one identifies: teach the route again)."""
        if path_id not in self._known and self.directory is not None:
            f = model_file(self.directory, path_id)
            if f.exists():
                try:
                    self._known[path_id] = decode(NominalModel, f.read_bytes())
                except DecodeError as exc:
                    log.warning("%s not used (%s): the route runs on the default model until it is taught again",
                                f, exc)
                    return None
        return self._known.get(path_id)
