"""The experience database: an SQLite file in WAL mode with durable (synchronous=FULL) commits.

Experiences are binned by (route, vertex, commanded-speed bin l = floor(v_cmd / v_bin)) and each bin
keeps only its newest `c_bin` experiences (thesis 5.3.2): constant-size local models, and old
experiences of a changing world (ruts) are forgotten. Experiences from every robot on a route share
the bins (fleet learning). `ingest` returns only after the commit, so whatever it reports as stored
survives a crash. A (source, seq) pair is stored once, ever, so producers may safely re-send.

Each experience carries the nominal model it is a residual of (`Experience.model`): the bins are kept
per model, a window holds one model's experiences, hyperparameters are fitted on the model of a
route's newest experiences and kept per model (their version numbers count per route, across models).
A controller whose drive lag was retuned thus starts learning afresh while the old model's experiences
and hyperparameters stay on file (and count again if the old model comes back). Experiences and
hyperparameters from before tags existed (schema 1 and 2 files, migrated in place) have model "".
"""
from __future__ import annotations

import json
import logging
import sqlite3
import struct
import threading
from collections import Counter
from dataclasses import dataclass
from pathlib import Path as FsPath

import numpy as np

from common.bins import BinPolicy
from common.messages import A_DIM, G_DIM, Experience, HyperMsg, PathStats
from common.typecheck import from_dict, to_dict
from services.gp_store.fitting import FitResult

SCHEMA_VERSION = 3
_PACK_A, _PACK_G = struct.Struct(f"<{A_DIM}d"), struct.Struct(f"<{G_DIM}d")
log = logging.getLogger(__name__)

_SCHEMA = f"""
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS experiences (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    path_id TEXT NOT NULL, vertex INTEGER NOT NULL, speed_bin INTEGER NOT NULL,
    robot TEXT NOT NULL, trial INTEGER NOT NULL, source TEXT NOT NULL, seq INTEGER NOT NULL,
    stamp_s REAL NOT NULL, v_cmd_mps REAL NOT NULL,
    a BLOB NOT NULL CHECK (length(a) = {8 * A_DIM}), g BLOB NOT NULL CHECK (length(g) = {8 * G_DIM}),
    model TEXT NOT NULL DEFAULT '');
-- every (source, seq) ever stored, evicted or not: a late re-send is recognised, never stored twice
CREATE TABLE IF NOT EXISTS seen (source TEXT NOT NULL, seq INTEGER NOT NULL, PRIMARY KEY (source, seq)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS ingested (path_id TEXT PRIMARY KEY, total INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS hypers (
    path_id TEXT NOT NULL, version INTEGER NOT NULL, stamp_s REAL NOT NULL, body TEXT NOT NULL,
    model TEXT NOT NULL DEFAULT '', PRIMARY KEY (path_id, version));
"""


@dataclass(frozen=True)
class Window:
    vertex_lo: int
    vertex_hi: int
    bin_lo: int
    bin_hi: int
    vertices: np.ndarray
    speed_bins: np.ndarray
    A: np.ndarray      # (n, A_DIM)
    G: np.ndarray      # (n, G_DIM)


class ExperienceDB:
    def __init__(self, path: str | FsPath, policy: BinPolicy = BinPolicy()):
        self.path = FsPath(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.policy = policy
        # a writer and a reader connection: in WAL mode queries are answered while a batch commits
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(_SCHEMA)
        self._rlock = threading.Lock()
        self._rdb = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        # route -> nominal model of its newest experience, kept by `ingest` (the file's one writer): every
        # window query without a model needs it, and SQLite finds it only by sorting the route's rows
        self._newest_model: dict[str, str] = {}
        row = self._db.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
        if row is None:
            self._db.execute("INSERT INTO meta VALUES ('schema', ?)", (str(SCHEMA_VERSION),))
        elif int(row[0]) in (1, 2):
            self._migrate_from(int(row[0]))
        elif int(row[0]) != SCHEMA_VERSION:
            raise RuntimeError(f"{self.path}: schema version {row[0]}, this store reads {SCHEMA_VERSION}")
        self._db.execute("CREATE INDEX IF NOT EXISTS model_bins ON experiences (path_id, model, vertex, speed_bin, id)")

    def _migrate_from(self, version: int) -> None:
        """Schema 1 -> 3 (model column of experiences) and 2 -> 3 (model column of hyperparameters),
        in one transaction; what was stored before has model ""."""
        cur = self._db.cursor()
        cur.execute("BEGIN IMMEDIATE")
        try:
            for table in ("experiences", "hypers"):
                if "model" not in [r[1] for r in cur.execute(f"PRAGMA table_info({table})")]:
                    cur.execute(f"ALTER TABLE {table} ADD COLUMN model TEXT NOT NULL DEFAULT ''")
            cur.execute("DROP INDEX IF EXISTS bins")
            cur.execute("UPDATE meta SET value=? WHERE key='schema'", (str(SCHEMA_VERSION),))
            cur.execute("COMMIT")
        except BaseException:
            cur.execute("ROLLBACK")
            raise
        (n,) = self._db.execute("SELECT COUNT(*) FROM experiences").fetchone()
        (h,) = self._db.execute("SELECT COUNT(*) FROM hypers").fetchone()
        log.info("%s: migrated from schema %d to %d; its %d experiences and %d hyperparameter sets have no model "
                 "tag (model '')", self.path, version, SCHEMA_VERSION, n, h)

    def close(self) -> None:
        with self._lock, self._rlock:
            self._rdb.close()
            self._db.close()

    # --- writing ------------------------------------------------------------------------------
    def ingest(self, source: str, experiences: list[Experience]) -> list[int]:
        """Store a batch in one transaction, then evict beyond c_bin in every touched bin.
        Returns the seqs now durably stored (including ones stored before: re-sends)."""
        if not experiences:
            return []
        p = self.policy
        pack_a, pack_g = _PACK_A.pack, _PACK_G.pack   # the layout np.frombuffer(..., "<f8") reads back
        rows = [(e.path_id, e.vertex, p.speed_bin(e.v_cmd_mps), e.robot, e.trial, source, e.seq, e.stamp_s,
                 e.v_cmd_mps, pack_a(*e.a), pack_g(*e.g), e.model) for e in experiences]
        with self._lock:
            cur = self._db.cursor()
            cur.execute("BEGIN IMMEDIATE")
            try:
                new = []
                for r in rows:
                    cur.execute("INSERT OR IGNORE INTO seen VALUES (?, ?)", (source, r[6]))
                    if cur.rowcount:   # else a re-send of something already stored (and perhaps since evicted)
                        new.append(r)
                cur.executemany("INSERT INTO experiences (path_id, vertex, speed_bin, robot, trial, source, seq, "
                                "stamp_s, v_cmd_mps, a, g, model) VALUES (?,?,?,?,?,?,?,?,?,?,?,?)", new)
                new_per_path = Counter(r[0] for r in new)
                newest = {r[0]: r[11] for r in new}
                cur.executemany("INSERT INTO ingested VALUES (?, ?) ON CONFLICT(path_id) "
                                "DO UPDATE SET total = total + excluded.total", list(new_per_path.items()))
                for path_id, vertex, speed_bin, model in {(r[0], r[1], r[2], r[11]) for r in rows}:
                    bin_ = (path_id, model, vertex, speed_bin)
                    cur.execute("DELETE FROM experiences WHERE path_id=? AND model=? AND vertex=? AND speed_bin=? AND "
                                "id NOT IN (SELECT id FROM experiences WHERE path_id=? AND model=? AND vertex=? AND "
                                "speed_bin=? ORDER BY id DESC LIMIT ?)", bin_ + bin_ + (p.c_bin,))
                cur.execute("COMMIT")
            except BaseException:
                cur.execute("ROLLBACK")
                raise
            self._newest_model.update(newest)   # eviction keeps each bin's newest (c_bin >= 1)
        return [e.seq for e in experiences]

    def save_hyper(self, fit: FitResult, model: str, stamp_s: float) -> HyperMsg:
        """Store a fit on the experiences of nominal model `model` as the route's next version (one more
        than its newest of any model); returns it as the message to publish."""
        with self._lock:
            cur = self._db.cursor()
            cur.execute("BEGIN IMMEDIATE")
            try:
                (version,) = cur.execute("SELECT COALESCE(MAX(version), 0) + 1 FROM hypers WHERE path_id=?",
                                         (fit.path_id,)).fetchone()
                msg = fit.message(version=version, stamp_s=stamp_s, model=model)
                cur.execute("INSERT INTO hypers (path_id, version, stamp_s, body, model) VALUES (?, ?, ?, ?, ?)",
                            (msg.path_id, version, stamp_s, json.dumps(to_dict(msg)), model))
                cur.execute("COMMIT")
            except BaseException:
                cur.execute("ROLLBACK")
                raise
        return msg

    # --- reading ------------------------------------------------------------------------------
    def window(self, path_id: str, vertex: int, v_cmd_mps: float, c_vertex: int | None = None,
               c_velocity: int | None = None, model: str | None = None) -> Window:
        """The local dataset of eq. 5.3.2: bins of vertices i +- c_vertex and speed bins l +- c_velocity,
        of one nominal model's experiences (default: `current_model`)."""
        model = self.current_model(path_id) if model is None else model
        p = self.policy
        cv = p.c_vertex if c_vertex is None else c_vertex
        cl = p.c_velocity if c_velocity is None else c_velocity
        l = p.speed_bin(v_cmd_mps)
        lo, hi, blo, bhi = vertex - cv, vertex + cv, l - cl, l + cl
        with self._rlock:
            rows = self._rdb.execute("SELECT vertex, speed_bin, a, g FROM experiences WHERE path_id=? AND model=? "
                                    "AND vertex BETWEEN ? AND ? AND speed_bin BETWEEN ? AND ? ORDER BY id",
                                    (path_id, model, lo, hi, blo, bhi)).fetchall()
        return Window(lo, hi, blo, bhi, np.array([r[0] for r in rows], dtype=int),
                      np.array([r[1] for r in rows], dtype=int), _stack([r[2] for r in rows], A_DIM),
                      _stack([r[3] for r in rows], G_DIM))

    def current_model(self, path_id: str) -> str:
        """The nominal model of a route's newest experience ("" without any)."""
        model = self._newest_model.get(path_id)
        if model is None:   # first ask for this route since the file was opened
            with self._rlock:
                row = self._rdb.execute("SELECT model FROM experiences WHERE id = (SELECT MAX(id) FROM experiences "
                                        "WHERE path_id=?)", (path_id,)).fetchone()
            if row is None:
                return ""   # not cached: any name may be asked for, and the route's first ingest sets it
            # setdefault: an ingest that committed after this read has already put the newer model there
            model = self._newest_model.setdefault(path_id, row[0])
        return model

    def count(self, path_id: str, model: str) -> int:
        """Retained experiences of a route and nominal model."""
        with self._rlock:
            return self._rdb.execute("SELECT COUNT(*) FROM experiences WHERE path_id=? AND model=?",
                                     (path_id, model)).fetchone()[0]

    def all_of(self, path_id: str, model: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every retained experience of a route and one nominal model (default: `current_model`) as
        (A, G, window tile label), for hyperparameter fitting: the tiles are disjoint windows of the size
        the controller uses (5.3.2)."""
        model = self.current_model(path_id) if model is None else model
        with self._rlock:
            rows = self._rdb.execute("SELECT a, g, vertex, speed_bin FROM experiences WHERE path_id=? AND model=? "
                                     "ORDER BY id", (path_id, model)).fetchall()
        p = self.policy
        tiles = np.array([(r[2] // (2 * p.c_vertex + 1)) * 100_000 + (r[3] // (2 * p.c_velocity + 1)) for r in rows],
                         dtype=np.int64)
        return _stack([r[0] for r in rows], A_DIM), _stack([r[1] for r in rows], G_DIM), tiles

    def trials_of(self, path_id: str, model: str) -> set[int]:
        """The trials whose experiences of one nominal model are retained on a route (0: the teach pass)."""
        with self._rlock:
            rows = self._rdb.execute("SELECT DISTINCT trial FROM experiences WHERE path_id=? AND model=?",
                                     (path_id, model)).fetchall()
        return {int(r[0]) for r in rows}

    def experiences(self, path_id: str, after_id: int = 0, limit: int = 5000) -> list[tuple[int, str, Experience]]:
        """Stored experiences as (row id, source, experience), in insertion order (for export)."""
        with self._rlock:
            rows = self._rdb.execute("SELECT id, robot, trial, path_id, seq, vertex, v_cmd_mps, stamp_s, a, g, source, "
                                    "model FROM experiences WHERE path_id=? AND id > ? ORDER BY id LIMIT ?",
                                    (path_id, after_id, limit)).fetchall()
        return [(r[0], r[10], Experience(stamp_s=r[7], robot=r[1], trial=r[2], path_id=r[3], seq=r[4], vertex=r[5],
                                         v_cmd_mps=r[6], a=tuple(np.frombuffer(r[8], "<f8").tolist()),
                                         g=tuple(np.frombuffer(r[9], "<f8").tolist()), model=r[11])) for r in rows]

    def latest_hyper(self, path_id: str, model: str | None = None) -> HyperMsg | None:
        """The newest fit of a route for one nominal model (None: of any model)."""
        sql, args = "SELECT body, model FROM hypers WHERE path_id=?", (path_id,)
        if model is not None:
            sql, args = sql + " AND model=?", args + (model,)
        with self._rlock:
            row = self._rdb.execute(sql + " ORDER BY version DESC LIMIT 1", args).fetchone()
        return _hyper_from_row(*row) if row else None

    def stats(self) -> list[PathStats]:
        with self._rlock:
            kept = dict(self._rdb.execute("SELECT path_id, COUNT(*) FROM experiences GROUP BY path_id").fetchall())
            bins = dict(self._rdb.execute("SELECT path_id, COUNT(*) FROM (SELECT DISTINCT path_id, vertex, speed_bin "
                                         "FROM experiences) GROUP BY path_id").fetchall())
            total = dict(self._rdb.execute("SELECT path_id, total FROM ingested").fetchall())
            hyper = dict(self._rdb.execute("SELECT path_id, MAX(version) FROM hypers GROUP BY path_id").fetchall())
        paths = sorted(set(kept) | set(total) | set(hyper))
        return [PathStats(path_id=p, retained=kept.get(p, 0), ingested=total.get(p, 0), bins=bins.get(p, 0),
                          hyper_version=hyper.get(p, 0)) for p in paths]

    def max_bin_count(self, path_id: str) -> int:
        with self._rlock:
            row = self._rdb.execute("SELECT MAX(n) FROM (SELECT COUNT(*) AS n FROM experiences WHERE path_id=? "
                                   "GROUP BY model, vertex, speed_bin)", (path_id,)).fetchone()
        return row[0] or 0


def _hyper_from_row(body: str, model: str) -> HyperMsg:
    """A stored fit as the HyperMsg it was published as. Bodies written before schema 3 have no "model":
    the column has it for every row (migrated ones: "")."""
    return from_dict(HyperMsg, dict(json.loads(body), model=model))


def _stack(blobs: list[bytes], dim: int) -> np.ndarray:
    if not blobs:
        return np.zeros((0, dim))
    return np.frombuffer(b"".join(blobs), dtype="<f8").reshape(-1, dim).copy()
