"""Schedules and the per-vertex experience they were made from, in one SQLite file (WAL, durable)."""
from __future__ import annotations

import json
import sqlite3
import threading
from pathlib import Path as FsPath

import numpy as np

from services.scheduler.core import VertexPasses

_SCHEMA = """
CREATE TABLE IF NOT EXISTS schedules (
    path_id TEXT NOT NULL, version INTEGER NOT NULL, stamp_s REAL NOT NULL, based_on_robot TEXT NOT NULL,
    based_on_trial INTEGER NOT NULL, body TEXT NOT NULL, PRIMARY KEY (path_id, version));
CREATE TABLE IF NOT EXISTS passes (
    path_id TEXT NOT NULL, robot TEXT NOT NULL, trial INTEGER NOT NULL, schedule_version INTEGER NOT NULL,
    body TEXT NOT NULL, PRIMARY KEY (path_id, robot, trial));
"""


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

    def latest(self, path_id: str) -> dict | None:
        with self._lock:
            row = self._db.execute("SELECT body FROM schedules WHERE path_id=? ORDER BY version DESC LIMIT 1",
                                   (path_id,)).fetchone()
        return json.loads(row[0]) if row else None

    def based_on(self, path_id: str, robot: str, trial: int) -> dict | None:
        with self._lock:
            row = self._db.execute("SELECT body FROM schedules WHERE path_id=? AND based_on_robot=? AND "
                                   "based_on_trial=? ORDER BY version DESC LIMIT 1", (path_id, robot, trial)).fetchone()
        return json.loads(row[0]) if row else None

    def add_schedule(self, body: dict) -> dict:
        """Store the next version of a route's schedule; returns it with its version."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                (version,) = self._db.execute("SELECT COALESCE(MAX(version), 0) + 1 FROM schedules WHERE path_id=?",
                                              (body["path_id"],)).fetchone()
                body = dict(body, version=version)
                self._db.execute("INSERT INTO schedules VALUES (?, ?, ?, ?, ?, ?)",
                                 (body["path_id"], version, body["stamp_s"], body["based_on_robot"],
                                  body["based_on_trial"], json.dumps(body)))
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        return body

    def save_passes(self, path_id: str, robot: str, trial: int, version: int, p: VertexPasses) -> None:
        body = json.dumps({"e_lat_m": _nan_list(p.e_lat_m), "e_head_rad": _nan_list(p.e_head_rad),
                           "w_cmd_radps": _nan_list(p.w_cmd_radps), "features": _nan_list(p.features)})
        with self._lock:
            self._db.execute("INSERT OR REPLACE INTO passes VALUES (?, ?, ?, ?, ?)",
                             (path_id, robot, trial, version, body))

    def history(self, path_id: str) -> list[tuple[np.ndarray, VertexPasses]]:
        """Every recorded trial of a route with the schedule it ran at (for use_all_trials)."""
        with self._lock:
            rows = self._db.execute("SELECT p.body, s.body FROM passes p JOIN schedules s ON s.path_id = p.path_id "
                                    "AND s.version = p.schedule_version WHERE p.path_id=?", (path_id,)).fetchall()
        out = []
        for pb, sb in rows:
            p, s = json.loads(pb), json.loads(sb)
            out.append((np.array(s["v_mps"]), VertexPasses(_from_list(p["e_lat_m"]), _from_list(p["e_head_rad"]),
                                                            _from_list(p["w_cmd_radps"]), _from_list(p["features"]))))
        return out
