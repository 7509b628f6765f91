"""The experience outbox's pending experiences on disk, so that a producer which dies while no store
acknowledges (the link to the learning host down, the store restarting) re-sends them when it starts
again instead of losing them.

One SQLite file per producer: its source id and next sequence number (kept across restarts, so the
store's (source, seq) de-duplication holds for re-sends) and every experience sent but not yet
acknowledged. Writes happen on the journal's own thread, a batch per commit: the control loop that
produces experiences never waits on the disk. What a crash can lose is what was handed over in the
last moments before it and not yet committed (one commit takes milliseconds).
"""
from __future__ import annotations

import logging
import queue
import sqlite3
import threading
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from common.codec import DecodeError, decode, encode
from common.messages import Experience

log = logging.getLogger(__name__)


@dataclass
class Recovered:
    """What a journal held when it was opened."""
    source: str
    next_seq: int
    pending: list[Experience] = field(default_factory=list)
    unreadable: int = 0      # rows that no longer decode (a schema change): dropped, counted


class OutboxJournal:
    def __init__(self, path: str | Path, robot: str):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        # EXCLUSIVE: a second producer on the same file would share its source id and sequence numbers
        for pragma in ("journal_mode=WAL", "synchronous=NORMAL", "locking_mode=EXCLUSIVE"):
            self._db.execute(f"PRAGMA {pragma}")
        self._db.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        self._db.execute("CREATE TABLE IF NOT EXISTS pending (seq INTEGER PRIMARY KEY, data BLOB NOT NULL)")
        self.recovered = self._load(robot)
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="outbox-journal", daemon=True)
        self._thread.start()
        self.failures = 0

    def _load(self, robot: str) -> Recovered:
        self._db.execute("BEGIN IMMEDIATE")
        row = self._db.execute("SELECT value FROM meta WHERE key='source'").fetchone()
        source = row[0] if row else f"{robot}-{uuid.uuid4().hex[:12]}"
        row = self._db.execute("SELECT value FROM meta WHERE key='next_seq'").fetchone()
        next_seq = int(row[0]) if row else 0
        rec = Recovered(source, next_seq)
        for seq, data in self._db.execute("SELECT seq, data FROM pending ORDER BY seq").fetchall():
            try:
                rec.pending.append(decode(Experience, data))
            except DecodeError as exc:
                rec.unreadable += 1
                log.warning("outbox journal %s: dropping unreadable experience %d: %s", self.path, seq, exc)
                self._db.execute("DELETE FROM pending WHERE seq=?", (seq,))
            rec.next_seq = max(rec.next_seq, seq + 1)
        self._db.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)",
                             [("source", source), ("next_seq", str(rec.next_seq))])
        self._db.execute("COMMIT")
        return rec

    # --- called from the producer (any thread): never blocks --------------------------------------------
    def added(self, experiences: list[Experience]) -> None:
        if experiences:
            self._queue.put(("add", experiences))

    def removed(self, seqs: list[int]) -> None:
        if seqs:
            self._queue.put(("remove", seqs))

    def sync(self, timeout_s: float = 10.0) -> bool:
        """Wait until everything handed over so far is committed (not for the control loop)."""
        done = threading.Event()
        self._queue.put(("sync", done))
        return done.wait(timeout_s)

    def close(self) -> None:
        """Commit whatever is queued and close the file."""
        self._queue.put(None)
        self._thread.join(timeout=30)
        self._db.close()

    # --- the journal's thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            items = [self._queue.get()]
            while not self._queue.empty():         # everything that arrived meanwhile goes in one commit
                items.append(self._queue.get())
            done = None in items
            try:
                self._commit([i for i in items if i is not None and i[0] != "sync"])
            except sqlite3.Error as exc:   # a full disk must not kill the producer: it still has them in memory
                self.failures += 1
                log.warning("outbox journal %s: cannot write (%s); pending experiences are in memory only",
                            self.path, exc)
            for item in items:
                if item is not None and item[0] == "sync":
                    item[1].set()
            if done:
                return

    def _commit(self, items: list[tuple[str, list]]) -> None:
        if not items:
            return
        db = self._db
        db.execute("BEGIN")
        try:
            next_seq = None
            for kind, payload in items:
                if kind == "add":
                    db.executemany("INSERT OR REPLACE INTO pending VALUES (?, ?)",
                                   [(e.seq, encode(e)) for e in payload])
                    next_seq = max(next_seq or 0, max(e.seq for e in payload) + 1)
                else:
                    db.executemany("DELETE FROM pending WHERE seq=?", [(s,) for s in payload])
            if next_seq is not None:
                db.execute("UPDATE meta SET value=? WHERE key='next_seq' AND CAST(value AS INTEGER) < ?",
                           (str(next_seq), next_seq))
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise
