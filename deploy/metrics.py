"""Per-trial records collected from the bus and the summary metrics computed from them.

Errors are measured from simulator truth against the taught route (continuous projection on the
route polyline); the controller's own estimate is reported beside them under `*_est` names.
"""
from __future__ import annotations

import math
import typing
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from common.messages import ControllerStatus, LocState, SpeedCause, TruthPose
from common.path import Path

# time_lost's keys: the causes of a tracking step (messages.SpeedCause, "" as "none": commanded the asked
# speed, the drive still following), a step holding its last command, and a safety stop's braking
TIME_LOST_KEYS = ("none",) + tuple(c for c in typing.get_args(SpeedCause) if c) + ("holding", "stopping")


@dataclass
class TrialRecord:
    """What the runner saw during one trial, in arrival order."""
    trial: int
    speed_mps: float
    truth: list[TruthPose] = field(default_factory=list)
    status: list[ControllerStatus] = field(default_factory=list)
    loc: list[LocState] = field(default_factory=list)
    completed: bool = False
    end_reason: str = ""
    wall_s: float = 0.0
    unanswered_ticks: int = 0       # stepped by the bridge without their answer (TrialEvent)

    def cut_after(self, stamp_s: float) -> None:
        """Keep only what happened up to robot time `stamp_s`: the end of a trial the runner decided at a
        status of that stamp. The ticks the bridge still runs until the runner's stop reaches it depend on
        the wall clock, so they are not part of the trial."""
        self.truth = [t for t in self.truth if t.stamp_s <= stamp_s + 1e-9]
        self.status = [s for s in self.status if s.stamp_s <= stamp_s + 1e-9]
        self.loc = [m for m in self.loc if m.stamp_s <= stamp_s + 1e-9]

    def stepped_status(self) -> list[ControllerStatus]:
        """The statuses of the ticks the bridge stepped in this trial, its last one aside: statuses from
        before the first tick (the controller's wall-clock heartbeat while it waits) and whether the
        answer to the last tick reaches the runner before the trial ends are the wall clock's choice."""
        if not self.truth:
            return self.status
        first, last = self.truth[0].tick, self.truth[-1].tick
        return [s for s in self.status if first <= s.tick < last]


@dataclass
class TrialSeries:
    """Truth-based error series of one trial, for the metrics and the report."""
    trial: int
    stamp_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    distance_m: np.ndarray
    lateral_m: np.ndarray
    heading_rad: np.ndarray
    speed_mps: np.ndarray
    cmd_distance_m: np.ndarray
    v_cmd_mps: np.ndarray
    w_cmd_radps: np.ndarray
    solve_ms: np.ndarray
    # the localizer's frames: distance, matched features (nan when none), refined against the map?
    loc_distance_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    loc_features: np.ndarray = field(default_factory=lambda: np.zeros(0))
    loc_refined: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))


def truth_series(path: Path, rec: TrialRecord) -> TrialSeries:
    hint = 0
    rows = []
    for t in rec.truth:
        pr = path.project((t.x_world_m, t.y_world_m, t.theta_world_rad), hint)
        hint = pr.vertex
        rows.append((t.stamp_s, t.x_world_m, t.y_world_m, pr.distance_m, pr.lateral_m, pr.heading_rad, t.v_mps))
    arr = np.array(rows, dtype=float).reshape(-1, 7)
    tracking = [s for s in rec.stepped_status() if s.state in ("tracking", "holding", "stopping", "stopped", "finished")]
    st = np.array([(s.distance_m, s.v_cmd_mps, s.w_cmd_radps, s.solve_ms) for s in tracking], dtype=float).reshape(-1, 4)
    loc = [(l.distance_m, np.nan if l.matched_features is None else l.matched_features, l.status == "ok")
           for l in rec.loc if l.status not in ("idle", "teach", "initializing")]
    la = np.array(loc, dtype=float).reshape(-1, 3)
    return TrialSeries(rec.trial, *arr.T, cmd_distance_m=st[:, 0], v_cmd_mps=st[:, 1], w_cmd_radps=st[:, 2],
                       solve_ms=st[:, 3], loc_distance_m=la[:, 0], loc_features=la[:, 1],
                       loc_refined=la[:, 2].astype(bool))


def _max_abs(a: np.ndarray) -> float:
    return float(np.max(np.abs(a))) if a.size else 0.0


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(a)))) if a.size else 0.0


def _pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if a.size else 0.0


def _window(rec: TrialRecord, series: TrialSeries) -> tuple[float, float, float | None]:
    """(start, end, first stop) of the repeat proper: from the start until the controller declared the end
    of the route (or the trial ended); a safety stop's time, if the controller stopped before that."""
    finish = next((s.stamp_s for s in rec.stepped_status() if s.state == "finished"), None)
    t0 = series.stamp_s[0] if series.stamp_s.size else 0.0
    t_end = finish if finish is not None else (series.stamp_s[-1] if series.stamp_s.size else t0)
    stop = next((s.stamp_s for s in rec.stepped_status() if s.state in ("stopping", "stopped")), None)
    return t0, t_end, stop


def _after_stop(series: TrialSeries, t_end: float, t_stop: float | None, lat_lim: float, head_lim: float) -> dict:
    """The seconds between a safety stop and the end of the trial, counted apart (truth)."""
    after = (series.stamp_s > t_stop) & (series.stamp_s <= t_end + 1e-9) if t_stop is not None else \
        np.zeros(series.stamp_s.shape, dtype=bool)
    lat, head = series.lateral_m[after], series.heading_rad[after]
    return {"after_stop_steps": int(np.count_nonzero(after)),
            "after_stop_violations": int(np.count_nonzero((np.abs(lat) > lat_lim) | (np.abs(head) > head_lim))),
            "max_lateral_m_after_stop": _max_abs(lat) if lat.size else None}


def trial_metrics(path: Path, rec: TrialRecord, series: TrialSeries, lateral_limit_m: float,
                  heading_limit_rad: float, experiences_total: int) -> dict:
    """One entry of summary.json `trials` (keys as DESIGN.md, then extensions). Truth and estimate are
    measured over the same window, the seconds after a safety stop included (and counted apart)."""
    t0, t_end, t_stop = _window(rec, series)
    active = series.stamp_s <= t_end + 1e-9
    lat, head = series.lateral_m[active], series.heading_rad[active]
    violations = int(np.count_nonzero((np.abs(lat) > lateral_limit_m) | (np.abs(head) > heading_limit_rad)))
    travel = max(0.0, float(t_end - t0))
    covered = float(np.clip(series.distance_m[active].max(initial=0.0), 0.0, path.length_m))
    features = [l.matched_features for l in rec.loc if l.has_pose and l.matched_features is not None]
    est = [s for s in rec.stepped_status() if s.state in ("tracking", "holding", "stopping", "stopped") and s.stamp_s <= t_end + 1e-9]
    steered = [s for s in est if s.state in ("tracking", "holding")]
    est_lat = np.array([s.lateral_m for s in est])
    est_head = np.array([s.heading_rad for s in est])
    solve = np.array([s.solve_ms for s in steered])
    w_cmd = np.array([s.w_cmd_radps for s in est])
    return {
        "trial": rec.trial,
        "completed": rec.completed,
        "max_lateral_m": _max_abs(lat),
        "rms_lateral_m": _rms(lat),
        "max_heading_rad": _max_abs(head),
        "rms_heading_rad": _rms(head),
        "travel_time_s": travel,
        "mean_speed_mps": covered / travel if travel > 0 else 0.0,
        "constraint_violations": violations,
        "mean_matched_features": float(np.mean(features)) if features else None,
        "solve_ms_p50": _pct(solve, 50),
        "solve_ms_p99": _pct(solve, 99),
        "experiences_total": experiences_total,
        # extensions
        "speed_setpoint_mps": rec.speed_mps,
        "distance_m": covered,
        "route_length_m": path.length_m,
        "max_lateral_m_est": _max_abs(est_lat),
        "rms_lateral_m_est": _rms(est_lat),
        "max_heading_rad_est": _max_abs(est_head),
        "rms_heading_rad_est": _rms(est_head),
        "max_w_cmd_radps": _max_abs(w_cmd),
        **_after_stop(series, t_end, t_stop, lateral_limit_m, heading_limit_rad),
        "control_steps": len(rec.stepped_status()),
        "end_reason": rec.end_reason,
        "unanswered_ticks": rec.unanswered_ticks,
        "wall_time_s": rec.wall_s,
    }


def time_lost(rec: TrialRecord, asked_mps: Callable[[int], float]) -> dict:
    """Where a trial's travel time went beyond its asked speed's: each controller step's period less the
    time the asked speed (`asked_mps(vertex)`) would have taken over the distance it covered, summed by
    what held its command (TIME_LOST_KEYS), over the same window as travel_time_s. `travel_time_ideal_s`:
    the covered distance at the asked speeds; the losses add up to about travel_time_s less it."""
    stepped = rec.stepped_status()
    finish = next((i for i, s in enumerate(stepped) if s.state == "finished"), len(stepped) - 1)
    lost = dict.fromkeys(TIME_LOST_KEYS, 0.0)
    ideal = 0.0
    for a, b in zip(stepped[:finish], stepped[1:finish + 1]):
        ds = max(0.0, b.distance_m - a.distance_m)
        at = ds / max(asked_mps(a.vertex), 1e-3)
        ideal += at
        key = (a.speed_held_by or "none") if a.state == "tracking" else \
            "holding" if a.state == "holding" else "stopping" if a.state in ("stopping", "stopped") else "none"
        lost[key] += (b.stamp_s - a.stamp_s) - at
    return {"travel_time_ideal_s": ideal, "time_lost_s": lost}


def outside_3sigma_fraction(route: Path, truth_path: Path, rec: TrialRecord) -> float | None:
    """The share of predictions whose realized error one horizon later (truth, lateral and heading
    against the route) left the predicted 3-sigma region; None for a law without a predicted spread.
    The prediction of the status of tick k is x_K of tick k + K in the controller's route frame. The truth
    is projected along its own progress, as truth_series does: where a loop closes, the nearest vertex
    alone can be the route's first one, whose taught heading differs from the last one's."""
    truth, hint = {}, 0
    for t in rec.truth:
        truth[t.tick] = real = truth_path.project((t.x_world_m, t.y_world_m, t.theta_world_rad), hint)
        hint = real.vertex
    checked = outside = 0
    for s in rec.stepped_status():
        if s.state != "tracking" or not s.pred_sigma_lat_m or not s.pred_x_m:
            continue
        real = truth.get(s.tick + len(s.pred_x_m))
        if real is None:
            continue
        pred = route.project((s.pred_x_m[-1], s.pred_y_m[-1], s.pred_theta_rad[-1]), s.vertex)
        d_head = math.remainder(real.heading_rad - pred.heading_rad, 2 * math.pi)
        checked += 1
        outside += (abs(real.lateral_m - pred.lateral_m) > 3.0 * s.pred_sigma_lat_m[-1]
                    or abs(d_head) > 3.0 * s.pred_sigma_head_rad[-1])
    return outside / checked if checked else None


def loop_figures(rec: TrialRecord, period_s: float, realtime: bool) -> dict:
    """summary.json extensions from the controller's statuses: how long learning was off (the store's
    data missing) and since when; with a realtime clock, the control loop's period jitter (how late
    each step started, p99) and deadline misses (steps whose command left after the next period began)."""
    steps = rec.stepped_status()
    off = [s for s in steps if s.learning_off_since_s >= 0]
    out: dict = {"learning_off_s": len(off) * period_s,
                 "learning_off_since_s": off[0].learning_off_since_s if off else None,
                 "learning_note": off[-1].learning_note if off else ""}
    if realtime:
        late = np.array([s.step_late_ms for s in steps])
        solve = np.array([s.solve_ms for s in steps])
        out["period_jitter_ms_p99"] = _pct(late, 99)
        out["deadline_misses"] = int(np.count_nonzero(late + solve > period_s * 1e3))
    return out
