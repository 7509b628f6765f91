"""Iterative Learning Control in parallel with feedback linearization (thesis 3.2.2-3.2.3).

The feedforward angular rate is a sequence indexed by route vertex, so it stays valid when the speed
changes between trials. During a trial the law adds w_ff[i] of the nearest vertex i to the FL command
and records the (initial-condition smoothed) errors at every vertex; after the trial, eq. 3.14 with the
lookahead errors of eq. 3.15 updates the sequence:

    w_ff[i] <- gamma_u w_ff[i] + (-gamma_L eps_L[i] - gamma_H sin eps_H[i]) / cos eps_H[i],
    eps[i]  =  mean of the errors at vertices i+1 .. i+kappa.

(Signs in this project's convention, see fl.py: e_L is left of the route, e_H counter-clockwise of it,
so a robot left of the route needs a negative, rightward, correction.) The sequence is saved per route
(one file, codec-versioned) and loaded at the next trial, so learning survives restarts. The lifted
update leaves out errors of saturated stretches and reverts a feedforward whose trial got worse
(ilc_monitor.py); its baseline is saved beside the feedforward.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path as FsPath
from typing import ClassVar, Literal

import numpy as np

from common.atomic_file import write_atomically
from common.codec import DecodeError, Message, decode, encode
from common.messages import check_name
from services.controller.actuator import ActuatorLag
from services.controller.fl import FLGains
from services.controller.ilc_lifted import (MIN_SPEED_MPS, ILCPlant, LiftedWeights, lifted_model, mean_speeds,
                                            norm_optimal_change)
from services.controller.ilc_monitor import (MIN_STEP_SCALE, ILCBaseline, after_saturation, recovery_s,
                                             trial_cost)
from services.controller.laws import LawResult, StepContext, fl_command

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ILCGains:
    """The update's settings; also the controller config's [ilc] table. `update = "lifted"` (default):
    the norm-optimal change from the lifted model of the closed loop (ilc_lifted.py), whose drive lag
    and estimate age come from the identified model and the trial; `"thesis"`: eq. 3.14-3.15 with the
    gains below."""
    update: Literal["lifted", "thesis"] = "lifted"
    gamma_L: float = 0.8      # thesis: rad/s per m of lookahead lateral error
    gamma_H: float = 0.4      # thesis: rad/s per unit sin(heading error)
    gamma_u: float = 1.0      # forgetting factor (thesis exp. 1: 1.0; < 1 forgets non-repeating disturbances)
    lookahead: int = 4        # thesis: kappa, vertices
    ic_vertices: int = 8      # m_ic of eq. 3.16
    step: float = LiftedWeights.step      # lifted: share of the optimal change taken per trial
    q_head: float = LiftedWeights.q_head  # lifted: weight of heading (1/rad^2) against lateral error (1/m^2)
    revert_margin: float = 0.1   # lifted: a trial whose error cost grew by more reverts its feedforward; 0: never

    def __post_init__(self):
        if self.lookahead < 1 or self.ic_vertices < 0 or not 0.0 <= self.gamma_u <= 1.0:
            raise ValueError("lookahead >= 1, ic_vertices >= 0 and gamma_u in [0, 1] required")
        if self.update not in ("lifted", "thesis"):
            raise ValueError(f"update must be 'lifted' or 'thesis', not {self.update!r}")
        if not 0.0 < self.step <= 1.0 or self.q_head < 0 or self.revert_margin < 0:
            raise ValueError("step in (0, 1], q_head >= 0 and revert_margin >= 0 required")

    def weights(self) -> LiftedWeights:
        return LiftedWeights(q_head=self.q_head, step=self.step)


@dataclass(frozen=True, kw_only=True)
class ILCFeedforward(Message):
    """The learned feedforward of one route, as stored on disk."""
    MAX_BYTES: ClassVar[int] = 16 * 1024 * 1024
    path_id: str
    trials: int
    w_ff_radps: list[float]

    def __post_init__(self):
        check_name("path_id", self.path_id)


@dataclass(frozen=True)
class ILCUpdate:
    """What one update did."""
    change_radps: float          # the largest change of the feedforward
    reverted: bool = False       # the trial got worse: back to the baseline's feedforward
    route_changed: bool = False  # worse, but not because of the feedforward: accepted (ilc_monitor.py)
    cost: float = 0.0            # the trial's error cost (ilc_monitor.trial_cost), and the baseline's
    baseline_cost: float = 0.0
    step_scale: float = 1.0
    saturated_vertices: int = 0  # vertices where the command reached its limit

    def describe(self) -> str:
        if self.reverted:
            what = (f"reverted to the last accepted feedforward: error cost {self.cost:.4g} against "
                    f"{self.baseline_cost:.4g}, step now x{self.step_scale:.3g}")
        elif self.route_changed:
            what = (f"accepted although its error cost {self.cost:.4g} exceeds the baseline's "
                    f"{self.baseline_cost:.4g}: half the step did not shrink the excess, so the route changed; "
                    f"largest change {self.change_radps:.3f} rad/s")
        else:
            what = f"largest change {self.change_radps:.3f} rad/s"
        sat = f", {self.saturated_vertices} saturated vertices left out" if self.saturated_vertices else ""
        return what + sat


class ILCMemory:
    def __init__(self, path_id: str, n_vertices: int, w_ff: np.ndarray | None = None, trials: int = 0,
                 baseline: ILCBaseline | None = None):
        self.path_id = path_id
        self.w_ff = np.zeros(n_vertices) if w_ff is None else np.asarray(w_ff, dtype=float).copy()
        self.trials = trials
        self.baseline = baseline
        self._sum = np.zeros((n_vertices, 2))
        self._count = np.zeros(n_vertices)
        self._speed = np.zeros(n_vertices)
        self._saturated = np.zeros(n_vertices, dtype=bool)
        self._age = (0.0, 0)         # sum of the estimates' ages, steps
        self._noise = np.zeros(2)    # sum of the estimates' lateral and heading variances

    def record(self, vertex: int, e_lat: float, e_head: float, v_mps: float = 0.0, age_s: float = 0.0,
               saturated: bool = False, var_lat_head: tuple[float, float] = (0.0, 0.0)) -> None:
        self._sum[vertex] += (e_lat, e_head)
        self._count[vertex] += 1
        self._speed[vertex] += v_mps
        self._saturated[vertex] |= saturated
        self._age = (self._age[0] + age_s, self._age[1] + 1)
        self._noise += var_lat_head

    def noise_cost(self, wt: LiftedWeights) -> float:
        """The trial cost the estimates' own error alone would give (their mean variances, weighted as in
        trial_cost): a change of cost below it is not the route's."""
        n = self._age[1]
        return float(wt.q_lat * self._noise[0] + wt.q_head * self._noise[1]) / n if n else 0.0

    @property
    def mean_age_s(self) -> float:
        """The mean age of the estimates the feedback used this trial."""
        return self._age[0] / self._age[1] if self._age[1] else 0.0

    def vertex_errors(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean (e_L, e_H) per vertex this trial, and which vertices were seen."""
        seen = self._count > 0
        mean = np.zeros_like(self._sum)
        mean[seen] = self._sum[seen] / self._count[seen, None]
        return mean, seen

    def update(self, gains: ILCGains, plant: ILCPlant | None = None, distances_m: np.ndarray | None = None) -> ILCUpdate:
        """The feedforward for the next trial from this trial's errors. `plant` and the route's vertex
        `distances_m` are the lifted update's (without them, or with gains.update = "thesis": eq.
        3.14-3.15, unguarded). Vertices the robot never reached keep their feedforward (only the
        forgetting factor applies)."""
        if gains.update == "lifted" and plant is not None and distances_m is not None:
            return self._update_lifted(gains, plant, distances_m)
        return ILCUpdate(self._update_thesis(gains))

    def _update_lifted(self, gains: ILCGains, plant: ILCPlant, distances_m: np.ndarray) -> ILCUpdate:
        err, seen = self.vertex_errors()
        speeds = mean_speeds(self._speed, self._count, 1.0)
        wt = gains.weights()
        cost = trial_cost(err[:, 0], err[:, 1], seen, wt)
        speed = float(np.mean(speeds[seen])) if np.any(seen) else 0.0
        b = self.baseline
        worse = (b is not None and gains.revert_margin > 0 and b.comparable(speed)
                 and cost > (1.0 + gains.revert_margin) * b.cost)
        changed = worse and b.route_changed(cost, self.noise_cost(wt))
        worse = worse and not changed
        n_sat = int(np.sum(self._saturated & seen))
        if worse:
            b = replace(b, step_scale=max(b.step_scale / 2.0, MIN_STEP_SCALE), reverted_cost=cost)
        else:
            learn = seen & ~after_saturation(self._saturated, distances_m, speeds, recovery_s(plant))
            scale = min(1.0, 2.0 * b.step_scale) if b is not None else 1.0
            b = ILCBaseline(path_id=self.path_id, w_ff_radps=self.w_ff.tolist(), e_lat_m=err[:, 0].tolist(),
                            e_head_rad=err[:, 1].tolist(), learn_from=learn.tolist(), speeds_mps=speeds.tolist(),
                            cost=cost, speed_mps=speed, step_scale=scale)
        prev_cost = self.baseline.cost if self.baseline is not None else cost
        self.baseline = b
        w0 = np.asarray(b.w_ff_radps)
        model = lifted_model(distances_m, np.asarray(b.speeds_mps), plant)
        dw = norm_optimal_change(w0, np.asarray(b.e_lat_m), np.asarray(b.e_head_rad), np.asarray(b.learn_from),
                                 model, wt)
        change = self._apply(gains.gamma_u * w0 + b.step_scale * dw)
        return ILCUpdate(change, worse, changed, cost, prev_cost, b.step_scale, n_sat)

    def _update_thesis(self, gains: ILCGains) -> float:
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
        return self._apply(new)

    def _apply(self, new: np.ndarray) -> float:
        """Take `new` as the feedforward, start a new trial's record; the largest change."""
        change = float(np.max(np.abs(new - self.w_ff))) if len(new) else 0.0
        self.w_ff = new
        self.trials += 1
        self._sum[:] = 0.0
        self._count[:] = 0.0
        self._speed[:] = 0.0
        self._saturated[:] = False
        self._age = (0.0, 0)
        self._noise[:] = 0.0
        return change

    # --- persistence -------------------------------------------------------------------------
    @staticmethod
    def file_of(directory: str | FsPath, path_id: str, suffix: str = ".ilc") -> FsPath:
        return FsPath(directory) / f"{check_name('path_id', path_id)}{suffix}"

    def save(self, directory: str | FsPath) -> FsPath:
        """The feedforward, and the baseline the next trial is judged against (written first: a crash
        between the two leaves an older feedforward with a newer baseline, which only costs one revert)."""
        if self.baseline is not None:
            write_atomically(self.file_of(directory, self.path_id, ".ilc-baseline"), encode(self.baseline))
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
        fb = cls.file_of(directory, path_id, ".ilc-baseline")
        try:
            baseline = decode(ILCBaseline, fb.read_bytes()) if fb.exists() else None
        except DecodeError as exc:                # e.g. written by an older version: judge afresh
            log.warning("%s not used (%s): the next trial becomes the baseline", fb, exc)
            baseline = None
        if baseline is not None and len(baseline.w_ff_radps) != n_vertices:
            baseline = None                       # from before the route was taught again: judge afresh
        return cls(path_id, n_vertices, np.array(msg.w_ff_radps), msg.trials, baseline)


class ILCLaw:
    """FL feedback (eq. 3.5) plus the vertex-indexed feedforward; records errors for the update."""
    name = "ilc"

    def __init__(self, fl: FLGains, memory: ILCMemory, lag: ActuatorLag | None = None):
        self.fl = fl
        self.memory = memory
        self.lag = lag or ActuatorLag()     # the drive the command goes through (actuator.py; fl.py, ILCPlant)

    def angular(self, ctx: StepContext) -> LawResult:
        w_fb = fl_command(ctx, self.fl, self.lag)
        w_ff = float(self.memory.w_ff[ctx.vertex])
        w = w_fb + w_ff
        var = (0.0, 0.0) if ctx.pose_cov is None else (float(ctx.pose_cov[1, 1]), float(ctx.pose_cov[2, 2]))
        self.memory.record(ctx.vertex, ctx.e_lat_m, ctx.e_head_rad, ctx.v_mps, ctx.loc_age_s,
                           saturated=ctx.v_mps > MIN_SPEED_MPS and abs(w) > ctx.w_limit, var_lat_head=var)
        return LawResult(w, feedforward_radps=w_ff)

