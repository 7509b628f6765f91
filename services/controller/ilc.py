"""Iterative Learning Control in parallel with feedback linearization (thesis 3.2.2-3.2.3).

The feedforward angular rate is a sequence indexed by route vertex, so it stays valid when the speed
changes between trials. During a trial the law adds w_ff[i] of the nearest vertex i to the FL command
and records the (initial-condition smoothed) errors at every vertex; after the trial, eq. 3.14 with the
lookahead errors of eq. 3.15 updates the sequence:

    w_ff[i] <- gamma_u w_ff[i] + (-gamma_L eps_L[i] - gamma_H sin eps_H[i]) / cos eps_H[i],
    eps[i]  =  mean of the errors at vertices i+1 .. i+kappa.

(Signs in this project's convention, see fl.py: e_L is left of the route, e_H counter-clockwise of it,
so a robot left of the route needs a negative, rightward, correction.) The sequence is saved per route
(one file, codec-versioned) and loaded at the next trial, so learning survives restarts.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import ClassVar

import numpy as np

from common.atomic_file import write_atomically
from common.codec import Message, decode, encode
from common.messages import check_name
from services.controller.fl import FLGains, fl_angular_rate
from services.controller.laws import LawResult, StepContext


@dataclass(frozen=True, kw_only=True)
class ILCGains:
    """Eq. 3.14-3.16 gains; also the controller config's [ilc] table."""
    gamma_L: float = 0.8      # rad/s per m of lookahead lateral error
    gamma_H: float = 0.4      # rad/s per unit sin(heading error)
    gamma_u: float = 1.0      # forgetting factor (thesis exp. 1: 1.0; < 1 forgets non-repeating disturbances)
    lookahead: int = 4        # kappa, vertices
    ic_vertices: int = 8      # m_ic of eq. 3.16

    def __post_init__(self):
        if self.lookahead < 1 or self.ic_vertices < 0 or not 0.0 <= self.gamma_u <= 1.0:
            raise ValueError("lookahead >= 1, ic_vertices >= 0 and gamma_u in [0, 1] required")


@dataclass(frozen=True, kw_only=True)
class ILCFeedforward(Message):
    """The learned feedforward of one route, as stored on disk."""
    MAX_BYTES: ClassVar[int] = 16 * 1024 * 1024
    path_id: str
    trials: int
    w_ff_radps: list[float]

    def __post_init__(self):
        check_name("path_id", self.path_id)


class ILCMemory:
    def __init__(self, path_id: str, n_vertices: int, w_ff: np.ndarray | None = None, trials: int = 0):
        self.path_id = path_id
        self.w_ff = np.zeros(n_vertices) if w_ff is None else np.asarray(w_ff, dtype=float).copy()
        self.trials = trials
        self._sum = np.zeros((n_vertices, 2))
        self._count = np.zeros(n_vertices)

    def record(self, vertex: int, e_lat: float, e_head: float) -> None:
        self._sum[vertex] += (e_lat, e_head)
        self._count[vertex] += 1

    def vertex_errors(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean (e_L, e_H) per vertex this trial, and which vertices were seen."""
        seen = self._count > 0
        mean = np.zeros_like(self._sum)
        mean[seen] = self._sum[seen] / self._count[seen, None]
        return mean, seen

    def update(self, gains: ILCGains) -> float:
        """Eq. 3.14-3.15 from this trial's errors; returns the largest change (rad/s). Vertices the robot
        never reached keep their feedforward (only the forgetting factor applies)."""
        err, seen = self.vertex_errors()
        n, kappa = len(self.w_ff), max(1, gains.lookahead)
        # lookahead means over i+1..i+kappa of the vertices that were seen
        csum = np.vstack([np.zeros((1, 2)), np.cumsum(err * seen[:, None], axis=0)])
        cseen = np.concatenate([[0.0], np.cumsum(seen)])
        lo = np.minimum(np.arange(n) + 1, n)
        hi = np.minimum(np.arange(n) + 1 + kappa, n)
        cnt = cseen[hi] - cseen[lo]
        eps = np.zeros((n, 2))
        ok = cnt > 0
        eps[ok] = (csum[hi] - csum[lo])[ok] / cnt[ok, None]
        new = gains.gamma_u * self.w_ff
        new[ok] += (-gains.gamma_L * eps[ok, 0] - gains.gamma_H * np.sin(eps[ok, 1])) / np.cos(eps[ok, 1])
        change = float(np.max(np.abs(new - self.w_ff))) if n else 0.0
        self.w_ff = new
        self.trials += 1
        self._sum[:] = 0.0
        self._count[:] = 0.0
        return change

    # --- persistence -------------------------------------------------------------------------
    @staticmethod
    def file_of(directory: str | FsPath, path_id: str) -> FsPath:
        return FsPath(directory) / f"{check_name('path_id', path_id)}.ilc"

    def save(self, directory: str | FsPath) -> FsPath:
        msg = ILCFeedforward(path_id=self.path_id, trials=self.trials, w_ff_radps=self.w_ff.tolist())
        return write_atomically(self.file_of(directory, self.path_id), encode(msg))

    @classmethod
    def load(cls, directory: str | FsPath, path_id: str, n_vertices: int) -> "ILCMemory":
        """The stored feedforward of a route, or a fresh (zero) one when there is none yet. A file for
        a different number of vertices (the route was taught again) is not used."""
        f = cls.file_of(directory, path_id)
        if not f.exists():
            return cls(path_id, n_vertices)
        msg = decode(ILCFeedforward, f.read_bytes())
        if len(msg.w_ff_radps) != n_vertices:
            raise ValueError(f"{f} holds {len(msg.w_ff_radps)} vertices but route {path_id} has {n_vertices}; "
                             "remove it to start learning afresh")
        return cls(path_id, n_vertices, np.array(msg.w_ff_radps), msg.trials)


class ILCLaw:
    """FL feedback (eq. 3.5) plus the vertex-indexed feedforward; records errors for the update."""
    name = "ilc"

    def __init__(self, fl: FLGains, memory: ILCMemory):
        self.fl = fl
        self.memory = memory

    def angular(self, ctx: StepContext) -> LawResult:
        kappa = float(ctx.path.curvature[ctx.vertex])
        w_fb = fl_angular_rate(ctx.v_mps, ctx.e_lat_m, ctx.e_head_rad, kappa, self.fl)
        w_ff = float(self.memory.w_ff[ctx.vertex])
        self.memory.record(ctx.vertex, ctx.e_lat_m, ctx.e_head_rad)
        return LawResult(w_fb + w_ff, feedforward_radps=w_ff)

