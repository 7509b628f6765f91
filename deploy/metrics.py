"""Per-trial records collected from the bus and the summary metrics computed from them.

Errors are measured from simulator truth against the taught route (continuous projection on the
route polyline); the controller's own estimate is reported beside them under `*_est` names.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from common.messages import ControllerStatus, LocState, TruthPose
from common.path import Path


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
    tracking = [s for s in rec.status if s.state in ("tracking", "holding", "stopping", "stopped", "finished")]
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


def trial_metrics(path: Path, rec: TrialRecord, series: TrialSeries, lateral_limit_m: float,
                  heading_limit_rad: float, experiences_total: int) -> dict:
    """One entry of summary.json `trials` (keys as DESIGN.md, then extensions)."""
    # the repeat proper: from the start until the controller declared the end of the route
    finish = next((s.stamp_s for s in rec.status if s.state == "finished"), None)
    t0 = series.stamp_s[0] if series.stamp_s.size else 0.0
    t_end = finish if finish is not None else (series.stamp_s[-1] if series.stamp_s.size else t0)
    active = series.stamp_s <= t_end + 1e-9
    lat, head = series.lateral_m[active], series.heading_rad[active]
    violations = int(np.count_nonzero((np.abs(lat) > lateral_limit_m) | (np.abs(head) > heading_limit_rad)))
    travel = max(0.0, float(t_end - t0))
    covered = float(np.clip(series.distance_m[active].max(initial=0.0), 0.0, path.length_m))
    features = [l.matched_features for l in rec.loc if l.has_pose and l.matched_features is not None]
    est = [s for s in rec.status if s.state in ("tracking", "holding")]
    est_lat = np.array([s.lateral_m for s in est])
    est_head = np.array([s.heading_rad for s in est])
    solve = np.array([s.solve_ms for s in est])
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
        "control_steps": len(rec.status),
        "end_reason": rec.end_reason,
        "wall_time_s": rec.wall_s,
    }
