"""The `pose` localization source: simulator truth made to look like a real localizer.

Repeat: the estimate of tick k is the truth of tick k-D (D = delay in ticks) plus an error, stamped
with that capture time, expressed relative to the nearest taught vertex, with its covariance. The error
is what a visual teach-and-repeat localizer shows: mostly a slowly wandering offset (relocalizing
against the same keyframes gives nearly the same answer frame after frame; a first-order Gauss-Markov
process of std `noise_m` and correlation time `noise_tau_s`) plus a small frame-to-frame jitter.
Dropouts (random, seeded) publish no pose at all. Teach-pass failures (thesis 5.4.5) are stretches of
the route where the estimate is shifted sideways although the robot is not: a relocalization against
a bad keyframe, the same in every trial. Teach: the route is recorded from truth, one vertex every
`spacing` metres: this source models a localizer whose teach-pass map is exact.

Any source (this one, vision later) is a class with the same three methods; the node does not care.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from common import se2
from common.messages import LocState, TruthPose
from common.path import DEFAULT_SPACING_M, Path, RouteRecorder
from services.localizer.config import PoseSourceConfig

_CONFIG = PoseSourceConfig()


@dataclass(frozen=True)
class PoseSourceSettings:
    """The service's PoseSourceConfig in the core's units (radians, ticks); the same defaults."""
    noise_m: float = _CONFIG.noise_m
    noise_heading_rad: float = math.radians(_CONFIG.noise_heading_deg)
    noise_tau_s: float = _CONFIG.noise_tau_s          # correlation time of the wandering error
    jitter_m: float = _CONFIG.jitter_m                # independent per-frame error
    period_s: float = 0.1
    delay_ticks: int = 0
    dropout_prob: float = _CONFIG.dropout_prob
    dropout_ticks: int = round(_CONFIG.dropout_s / 0.1)
    vertex_spacing_m: float = DEFAULT_SPACING_M
    jumps: tuple[tuple[float, float, float], ...] = ()   # (at_m, length_m, lateral_m)


class PoseSource:
    name = "pose"

    def __init__(self, settings: PoseSourceSettings, rng: np.random.Generator):
        self.cfg = settings
        self.rng = rng
        self.path: Path | None = None
        self.recorder: RouteRecorder | None = None
        self._buffer: deque[TruthPose] = deque()
        self._hint: int | None = None
        self._dropout_left = 0
        self._error = np.zeros(3)
        self.trial = 0

    # --- modes -------------------------------------------------------------------------------
    def start_teach(self, trial: int) -> None:
        self.recorder = RouteRecorder(self.cfg.vertex_spacing_m)
        self.path = None
        self.trial = trial
        self._buffer.clear()
        self._error = self._std() * self.rng.standard_normal(3)

    def finish_teach(self, path_id: str, loop: bool, taught_by: str) -> Path:
        if self.recorder is None:
            raise RuntimeError("not teaching")
        path = self.recorder.finish(path_id, loop=loop, taught_by=taught_by)
        self.recorder = None
        return path

    def start_repeat(self, path: Path, trial: int, rng: np.random.Generator) -> None:
        self.path = path
        self.recorder = None
        self.trial = trial
        self.rng = rng
        self._buffer.clear()
        self._hint = 0   # a repeat starts at the beginning of the route
        self._dropout_left = 0
        self._error = self._std() * self.rng.standard_normal(3)   # stationary from the first frame

    # --- per tick ------------------------------------------------------------------------------
    def on_truth(self, truth: TruthPose, path_id: str) -> LocState:
        pose = (truth.x_world_m, truth.y_world_m, truth.theta_world_rad)
        if self.recorder is not None:
            self.recorder.add(pose)
            return self._teach_state(truth, path_id)
        if self.path is None:
            return self._no_pose(truth, path_id, "idle", "no route loaded", truth, 0)
        self._buffer.append(truth)
        if len(self._buffer) <= self.cfg.delay_ticks:
            return self._no_pose(truth, path_id, "initializing", "filling the localization delay line",
                                 truth, self._hint or 0)
        captured = self._buffer.popleft()
        if self._dropout_left > 0 or (self.cfg.dropout_prob > 0 and self.rng.random() < self.cfg.dropout_prob):
            if self._dropout_left == 0:
                self._dropout_left = self.cfg.dropout_ticks
            self._dropout_left -= 1
            return self._no_pose(truth, path_id, "dropout", "no estimate this frame", captured, self._hint or 0)
        noisy = self._noisy(captured)
        vertex, T_vr = self.path.localize(noisy, self._hint)
        self._hint = vertex
        along = float(self.path.s[vertex] + T_vr[0])
        for at_m, length_m, lateral_m in self.cfg.jumps:
            if at_m <= along < at_m + length_m:
                T_vr = T_vr + np.array([0.0, lateral_m, 0.0])
        return LocState(stamp_s=truth.stamp_s, capture_stamp_s=captured.stamp_s, tick=truth.tick,
                        capture_tick=captured.tick, trial=self.trial, path_id=path_id, source="pose", status="ok", reason="",
                        vertex=vertex, distance_m=float(self.path.s[vertex] + T_vr[0]),
                        T_vertex_robot=tuple(float(v) for v in T_vr), matched_features=None,
                        **self._covariances())

    def _noisy(self, truth: TruthPose) -> np.ndarray:
        """The truth with this source's error: a Gauss-Markov wander (e <- a e + sqrt(1 - a^2) sigma n
        keeps its std at sigma) plus independent jitter."""
        a = self._decay()
        self._error = a * self._error + math.sqrt(1.0 - a * a) * self._std() * self.rng.standard_normal(3)
        jitter = np.array([self.cfg.jitter_m, self.cfg.jitter_m, 0.0]) * self.rng.standard_normal(3)
        err = self._error + jitter
        return np.array([truth.x_world_m + err[0], truth.y_world_m + err[1],
                         float(se2.wrap(truth.theta_world_rad + err[2]))])

    def _cov(self) -> np.ndarray:
        # the error is isotropic in position, so its covariance is the same in any vertex frame
        sp2 = self.cfg.noise_m ** 2 + self.cfg.jitter_m ** 2
        return np.diag([sp2, sp2, self.cfg.noise_heading_rad ** 2])

    def _decay(self) -> float:
        """The wander's correlation from one frame to the next, a = exp(-period / tau)."""
        return math.exp(-self.cfg.period_s / self.cfg.noise_tau_s) if self.cfg.noise_tau_s > 0 else 0.0

    def _cov_step(self) -> np.ndarray:
        """The covariance of the error's change from one tick to the next: 2 sigma^2 (1 - a) of the
        wander and twice the jitter's."""
        a = self._decay()
        sp2 = 2.0 * (1.0 - a) * self.cfg.noise_m ** 2 + 2.0 * self.cfg.jitter_m ** 2
        return np.diag([sp2, sp2, 2.0 * (1.0 - a) * self.cfg.noise_heading_rad ** 2])

    def _covariances(self) -> dict[str, tuple[float, ...]]:
        return {"cov_T_vertex_robot": tuple(float(v) for v in self._cov().ravel()),
                "cov_step_T_vertex_robot": tuple(float(v) for v in self._cov_step().ravel())}

    def _teach_state(self, truth: TruthPose, path_id: str) -> LocState:
        """During teach: the estimate relative to the newest vertex, as VT&R's odometry gives it (status
        'teach': not for tracking; the controller identifies its nominal model with it)."""
        vertex = len(self.recorder.vertices) - 1
        T_vr = se2.between(np.asarray(self.recorder.vertices[vertex]), self._noisy(truth))
        return LocState(stamp_s=truth.stamp_s, capture_stamp_s=truth.stamp_s, tick=truth.tick,
                        capture_tick=truth.tick, trial=self.trial, path_id=path_id, source="pose", status="teach",
                        reason=f"teaching: {vertex + 1} vertices", vertex=vertex,
                        distance_m=self.recorder.length_m + float(T_vr[0]), T_vertex_robot=tuple(float(v) for v in T_vr),
                        matched_features=None, **self._covariances())

    def _std(self) -> np.ndarray:
        return np.array([self.cfg.noise_m, self.cfg.noise_m, self.cfg.noise_heading_rad])

    def _no_pose(self, truth: TruthPose, path_id: str, status: str, reason: str, captured: TruthPose,
                 vertex: int) -> LocState:
        distance = float(self.path.s[vertex]) if self.path is not None and vertex < len(self.path) else 0.0
        return LocState(stamp_s=truth.stamp_s, capture_stamp_s=captured.stamp_s, tick=truth.tick,
                        capture_tick=captured.tick, trial=self.trial,
                        path_id=path_id, source="pose", status=status, reason=reason, vertex=max(vertex, 0),
                        distance_m=distance, T_vertex_robot=None, cov_T_vertex_robot=None,
                        matched_features=None)
