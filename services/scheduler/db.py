"""Schedules and the per-vertex experience they were made from, in one SQLite file (WAL, durable)."""
from __future__ import annotations

import json
import sqlite3
import threading
from pathlib import Path as FsPath

import numpy as np

from common.messages import SpeedSchedule
from common.typecheck import from_dict, to_dict
from services.scheduler.core import Proposal, VertexPasses

_SCHEMA = """
CREATE TABLE IF NOT EXISTS schedules (
    path_id TEXT NOT NULL, version INTEGER NOT NULL, stamp_s REAL NOT NULL, based_on_robot TEXT NOT NULL,
    based_on_trial INTEGER NOT NULL, body TEXT NOT NULL, PRIMARY KEY (path_id, version));
CREATE TABLE IF NOT EXISTS passes (
    path_id TEXT NOT NULL, robot TEXT NOT NULL, trial INTEGER NOT NULL, schedule_version INTEGER NOT NULL,
    body TEXT NOT NULL, PRIMARY KEY (path_id, robot, trial));
"""


def _load_schedule(body: str) -> SpeedSchedule:
    """A stored schedule body: the SpeedSchedule map as published (every version of this file wrote all
    of its keys)."""
    return from_dict(SpeedSchedule, json.loads(body))


def _load_passes(body: str) -> VertexPasses:
    """A stored trial's passes (JSON null where NaN: no data at that vertex; bodies written before the
    pass speeds were kept have no v_mps)."""
    p = json.loads(body)
    return VertexPasses(_from_list(p["e_lat_m"]), _from_list(p["e_head_rad"]), _from_list(p["w_cmd_radps"]),
                        _from_list(p["features"]), _from_list(p["v_mps"]) if "v_mps" in p else None)


def _nan_list(a: np.ndarray) -> list:
    return [None if not np.isfinite(v) else float(v) for v in a]


def _from_list(x: list) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in x], dtype=float)


class ScheduleDB:
    def __init__(self, path: str | FsPath):
        self.path = FsPath(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(_SCHEMA)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def latest(self, path_id: str) -> SpeedSchedule | None:
        with self._lock:
            row = self._db.execute("SELECT body FROM schedules WHERE path_id=? ORDER BY version DESC LIMIT 1",
                                   (path_id,)).fetchone()
        return _load_schedule(row[0]) if row else None

    def based_on(self, path_id: str, robot: str, trial: int) -> SpeedSchedule | None:
        with self._lock:
            row = self._db.execute("SELECT body FROM schedules WHERE path_id=? AND based_on_robot=? AND "
                                   "based_on_trial=? ORDER BY version DESC LIMIT 1", (path_id, robot, trial)).fetchone()
        return _load_schedule(row[0]) if row else None

    def add_schedule(self, path_id: str, proposal: Proposal, robot: str, trial: int, stamp_s: float) -> SpeedSchedule:
        """Store a proposal (made from `robot`'s `trial`; "" and 0 for the first) as the next version of
        a route's schedule; returns it as the message to publish."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                (version,) = self._db.execute("SELECT COALESCE(MAX(version), 0) + 1 FROM schedules WHERE path_id=?",
                                              (path_id,)).fetchone()
                msg = SpeedSchedule(stamp_s=stamp_s, path_id=path_id, version=version, based_on_robot=robot,
                                    based_on_trial=trial, v_mps=[float(v) for v in proposal.schedule],
                                    decisions=[int(d) for d in proposal.decisions], notes=list(proposal.notes))
                self._db.execute("INSERT INTO schedules VALUES (?, ?, ?, ?, ?, ?)",
                                 (path_id, version, stamp_s, robot, trial, json.dumps(to_dict(msg))))
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        return msg

    def save_passes(self, path_id: str, robot: str, trial: int, version: int, p: VertexPasses) -> None:
        body = json.dumps({"e_lat_m": _nan_list(p.e_lat_m), "e_head_rad": _nan_list(p.e_head_rad),
                           "w_cmd_radps": _nan_list(p.w_cmd_radps), "features": _nan_list(p.features),
                           "v_mps": _nan_list(p.v_mps)})
        with self._lock:
            self._db.execute("INSERT OR REPLACE INTO passes VALUES (?, ?, ?, ?, ?)",
                             (path_id, robot, trial, version, body))

    def history(self, path_id: str) -> list[tuple[np.ndarray, VertexPasses]]:
        """Every recorded trial of a route with the schedule it ran at, in the order they were recorded
        (for use_all_trials and the guard, which reads the latest)."""
        with self._lock:
            rows = self._db.execute("SELECT p.body, s.body FROM passes p JOIN schedules s ON s.path_id = p.path_id "
                                    "AND s.version = p.schedule_version WHERE p.path_id=? ORDER BY p.rowid",
                                    (path_id,)).fetchall()
        return [(np.array(_load_schedule(sb).v_mps), _load_passes(pb)) for pb, sb in rows]
