"""The producer's and the controller's side of the experience store.

ExperienceOutbox: at-least-once delivery. Every experience keeps a per-producer seq and stays pending
until a store acknowledges it (after its durable commit); what is not acknowledged within
`resend_after_s` is sent again (the store stores a (source, seq) once). A store that is down simply
means a growing outbox, capped, never a blocked control loop. With a journal (outbox_journal.py) the
pending experiences are on disk too, and a producer restarted after a crash sends them again.

WindowCache: the local windows and hyperparameters the real-time loop reads, from memory only. Two modes:
- prefetch (realtime clock): a background thread keeps the windows ahead of the robot fetched and a
  subscription the newest hyperparameters. If the store disappears, the loop keeps the data it has.
- snapshot (lockstep clock): `set_route`, at trial prepare, copies the route's retained experiences and
  hyperparameters as the store holds them then, and nothing changes until the next prepare. Every step
  then sees the same data whatever the timing (a prefetch that has not caught up after a speed change
  gives a partial window; one that runs late can see this trial's own experiences or their evictions),
  so a run is reproducible for a seed. The windows are thus built from earlier traversals only, as in
  thesis 5.3.2. If the store does not answer, the cache falls back to prefetching and says so.
"""
from __future__ import annotations

import logging
import math
import threading
import time
import uuid
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import zenoh

from common.bins import BinPolicy
from common import keys
from common.bus import Node
from common.codec import DecodeError, decode
from common.messages import (A_DIM, G_DIM, Experience, ExperienceAck, ExperienceBatch, ExperienceWindow, HyperMsg)
from common.outbox_journal import OutboxJournal

log = logging.getLogger(__name__)


class ExperienceOutbox:
    def __init__(self, node: Node, robot: str, *, resend_after_s: float = 2.0, max_pending: int = 200_000,
                 max_batch: int = 500, source: str | None = None, model: str = "",
                 journal: OutboxJournal | None = None):
        """`journal`: keep pending experiences on disk too (outbox_journal.py); its source id and sequence
        numbers are then this outbox's, and what it held from before is sent again at the first flush."""
        self.node = node
        self.robot = robot
        self.model = model            # the nominal model `add`'s experiences are residuals of
        self.source = source or f"{robot}-{uuid.uuid4().hex[:12]}"
        self.resend_after_s = resend_after_s
        self.max_pending = max_pending
        self.max_batch = max_batch
        self._lock = threading.Condition()
        self._pending: OrderedDict[int, tuple[Experience, float]] = OrderedDict()   # seq -> (exp, last sent)
        self._new: list[Experience] = []
        self._seq = 0
        self.journal = journal
        self.recovered = 0
        if journal is not None:
            rec = journal.recovered
            self.source, self._seq, self.recovered = rec.source, rec.next_seq, len(rec.pending)
            for exp in rec.pending:
                self._pending[exp.seq] = (exp, -math.inf)
        self.acked = 0
        self.rejected = 0
        self.dropped = 0
        self._key = keys.experience(robot)
        node.subscribe(keys.experience_ack(robot), ExperienceAck, self._on_ack)

    def _on_ack(self, ack: ExperienceAck, _key: str) -> None:
        if ack.source != self.source:
            return
        done = []
        with self._lock:
            for seq in ack.seqs:
                if self._pending.pop(seq, None) is not None:
                    self.acked += 1
                    done.append(seq)
            for seq in ack.rejected:   # a store refused these: re-sending would not help
                if self._pending.pop(seq, None) is not None:
                    self.rejected += 1
                    done.append(seq)
            if self.journal is not None:
                self.journal.removed(done)
            self._lock.notify_all()
        if ack.rejected:
            log.warning("store %s rejected %d experiences: %s", ack.store, len(ack.rejected), ack.reason)

    def set_model(self, model: str) -> None:
        """The nominal model the experiences added from now on are residuals of (queued ones keep theirs)."""
        with self._lock:
            self.model = model

    def add(self, *, stamp_s: float, trial: int, path_id: str, vertex: int, v_cmd_mps: float, a, g) -> Experience:
        with self._lock:
            exp = Experience(stamp_s=stamp_s, robot=self.robot, trial=trial, path_id=path_id, seq=self._seq,
                             vertex=vertex, v_cmd_mps=v_cmd_mps, a=tuple(a), g=tuple(g), model=self.model)
            self._seq += 1
            self._new.append(exp)
            return exp

    def add_existing(self, exp: Experience) -> None:
        """Queue an experience that already has its identity (seq under this outbox's source), e.g. on
        import: the store keeps (source, seq) unique, so importing the same file twice stores it once."""
        with self._lock:
            self._new.append(exp)

    def flush(self) -> int:
        """Send new experiences and re-send stale ones; returns how many went out. Never blocks."""
        now = time.monotonic()
        with self._lock:
            out = self._new
            self._new = []
            for exp in out:
                self._pending[exp.seq] = (exp, now)
            # pending is ordered by last send: the stale ones are at the front
            stale = []
            for exp, sent in self._pending.values():
                if now - sent < self.resend_after_s or len(stale) >= 4 * self.max_batch:
                    break
                stale.append(exp)
            for exp in stale:
                self._pending[exp.seq] = (exp, now)
                self._pending.move_to_end(exp.seq)
            if self.journal is not None:      # before they go out: an acknowledgement must find them there
                self.journal.added(out)
            out = out + stale
            gone = []
            while len(self._pending) > self.max_pending:   # store gone for very long: keep the newest
                gone.append(self._pending.popitem(last=False)[0])
                self.dropped += 1
            if self.journal is not None:
                self.journal.removed(gone)
        for i in range(0, len(out), self.max_batch):
            # droppable: called from the control loop, which must never wait on a congested link;
            # a dropped batch is simply re-sent when its acknowledgement does not come
            self.node.publish(self._key, ExperienceBatch(stamp_s=time.time(), robot=self.robot, source=self.source,
                                                         experiences=out[i:i + self.max_batch]), droppable=True)
        return len(out)

    @property
    def pending(self) -> int:
        with self._lock:
            return len(self._pending) + len(self._new)

    def wait_acked(self, timeout_s: float) -> bool:
        """Block (outside the control loop) until everything sent so far is acknowledged."""
        deadline = time.monotonic() + timeout_s
        while True:
            self.flush()
            with self._lock:
                if not self._pending and not self._new:
                    return True
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._lock.wait(min(left, self.resend_after_s))


@dataclass(frozen=True)
class LocalData:
    A: np.ndarray
    G: np.ndarray
    missing_bins: int


# A snapshot reads the route in pages of this many vertices on either side of a page's centre (a page of
# 129 vertices holds a few thousand experiences: well inside ExperienceWindow's size limit) ...
SNAPSHOT_PAGE_HALF_VERTICES = 64
# ... and every speed bin on either side of bin 0: commanded speeds up to 250 m/s at 0.25 m/s bins
SNAPSHOT_SPEED_BINS = 1000
# A snapshot is taken between trials, where waiting costs nothing but a short timeout under load would
# leave a lockstep trial on whatever prefetching happens to fetch in time (one seed, two runs)
SNAPSHOT_TIMEOUT_S = 15.0


@dataclass(frozen=True)
class Snapshot:
    """What `WindowCache.set_route` took in snapshot mode: the data the whole trial predicts from."""
    path_id: str
    experiences: int        # retained experiences of the cache's nominal model on the route
    hyper_version: int      # 0: no hyperparameters fitted yet (the nominal model only)
    complete: bool          # every page and the hyperparameters were answered
    error: str = ""         # why not, when not complete

    def describe(self) -> str:
        if not self.complete:
            return f"store snapshot of {self.path_id} incomplete ({self.error}): prefetching windows instead"
        hyper = f"hyperparameters v{self.hyper_version}" if self.hyper_version else "no hyperparameters yet"
        return f"store snapshot of {self.path_id}: {self.experiences} experiences, {hyper}"


class WindowCache:
    def __init__(self, session: zenoh.Session, *, bins: BinPolicy = BinPolicy(), lookahead_vertices: int = 20,
                 query_timeout_s: float = 2.0, model: str = "", snapshot: bool = False):
        self.session = session
        # windows and hyperparameters of this nominal model's experiences only ("": the route's newest)
        self.model = model
        self.snapshot = snapshot      # snapshot mode (module docstring); else prefetch mode
        self.v_bin = bins.v_bin_mps
        self.cv = bins.c_vertex
        self.cl = bins.c_velocity
        self.lookahead = lookahead_vertices
        self.timeout = query_timeout_s
        self._lock = threading.Lock()
        self._bins: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._assembled: dict[tuple[int, int], LocalData] = {}
        self._complete = False        # the route's snapshot is in: a bin not in _bins is empty, not missing
        self._path_id: str | None = None
        self._n_vertices = 0
        self._position: tuple[int, float, float] | None = None   # vertex, driven and asked speeds
        self._hyper: HyperMsg | None = None
        self._hyper_sub = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.queries = 0
        self.failures = 0
        self.last_error = ""
        self._thread: threading.Thread | None = None
        if not snapshot:
            self._start_prefetcher()

    def _start_prefetcher(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="window-prefetch", daemon=True)
            self._thread.start()

    # --- called by the control loop: memory only ---------------------------------------------
    def speed_bin(self, v: float) -> int:
        return int(np.floor(v / self.v_bin))

    def set_position(self, vertex: int, speed_mps: float, asked_mps: float | None = None) -> None:
        """Where the robot is and the speed it drives; `asked_mps`: the speed it is asked to drive there,
        whose windows are fetched too (a law that slowed tests it: speed_ladder.py)."""
        self._position = (vertex, speed_mps, speed_mps if asked_mps is None else asked_mps)
        self._wake.set()

    def local(self, vertex: int, speed_mps: float) -> LocalData:
        """The local dataset of thesis 5.3.2 for (vertex, speed), from cache; missing bins are counted."""
        l = self.speed_bin(speed_mps)
        with self._lock:
            hit = self._assembled.get((vertex, l))
            if hit is not None:
                return hit
            A, G, missing = [], [], 0
            for v in range(vertex - self.cv, vertex + self.cv + 1):
                for b in range(l - self.cl, l + self.cl + 1):
                    entry = self._bins.get((v, b))
                    if entry is None:
                        missing += 0 if (self._complete or v < 0 or v >= self._n_vertices) else 1
                    elif len(entry[0]):
                        A.append(entry[0])
                        G.append(entry[1])
            data = LocalData(np.concatenate(A) if A else np.zeros((0, A_DIM)),
                             np.concatenate(G) if G else np.zeros((0, G_DIM)), missing)
            if missing == 0:
                self._assembled[(vertex, l)] = data
            return data

    @property
    def hyper(self) -> HyperMsg | None:
        return self._hyper

    # --- route changes (between trials) ------------------------------------------------------------
    def set_route(self, path_id: str, n_vertices: int) -> Snapshot | None:
        """Start over for a route: forget cached windows (new experiences exist), follow its hyperparameters.
        In snapshot mode, take the route's snapshot now and return what it holds: this waits on the
        store, so call it when a trial is prepared, never from the control loop."""
        with self._lock:
            self._bins.clear()
            self._assembled.clear()
            changed = path_id != self._path_id
            self._path_id, self._n_vertices = path_id, n_vertices
            self._position = None
            self._complete = False
            if changed or self.snapshot:
                self._hyper = None
        if self.snapshot:
            return self._take_snapshot(path_id, n_vertices)
        if changed:
            if self._hyper_sub is not None:
                self._hyper_sub.undeclare()
            self._hyper_sub = self.session.declare_subscriber(keys.store_hyper(path_id), self._on_hyper)
        self._wake.set()
        return None

    def set_model(self, model: str) -> None:
        """Read the windows and hyperparameters of nominal model `model` from now on (between trials;
        `set_route` then fetches them)."""
        with self._lock:
            if model != self.model:
                self.model = model
                self._bins.clear()
                self._assembled.clear()
                self._hyper = None

    def _on_hyper(self, sample: zenoh.Sample) -> None:
        try:
            msg = decode(HyperMsg, sample.payload.to_bytes())
        except DecodeError as exc:
            log.warning("rejected hyperparameters on %s: %s", sample.key_expr, exc)
            return
        if self.model and msg.model != self.model:      # fitted on another nominal model's residuals
            return
        with self._lock:
            # a snapshot's hyperparameters hold for the whole trial
            if not self._complete and msg.path_id == self._path_id and (
                    self._hyper is None or msg.version > self._hyper.version):
                self._hyper = msg

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        if self._hyper_sub is not None:
            self._hyper_sub.undeclare()

    # --- snapshot (between trials) ---------------------------------------------------------------
    def _take_snapshot(self, path_id: str, n_vertices: int) -> Snapshot:
        """Read every retained experience of the route (this model's), page by page, and the newest
        hyperparameters. The runner asks for a trial only once the store has acknowledged and fitted
        the last one's experiences, so the pages see one state of the store."""
        bins: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        errors = []
        page = 2 * SNAPSHOT_PAGE_HALF_VERTICES + 1
        for lo in range(0, max(n_vertices, 1), page):
            window = self._get_window(path_id, lo + SNAPSHOT_PAGE_HALF_VERTICES, 0.0,
                                      f"&c_vertex={SNAPSHOT_PAGE_HALF_VERTICES}&c_velocity={SNAPSHOT_SPEED_BINS}",
                                      timeout_s=SNAPSHOT_TIMEOUT_S)
            if window is None:
                errors.append(f"vertices {lo}-{lo + page - 1}: {self.last_error}")
                break       # the store is not answering: do not wait out the rest of the pages too
            bins.update(_by_bin(window))
        hyper = None
        if not errors:
            hyper, answered = self._get_hyper(path_id, SNAPSHOT_TIMEOUT_S)
            if not answered:
                errors.append("hyperparameters: no store answered")
        complete = not errors
        with self._lock:
            self._bins, self._assembled = bins, {}
            self._hyper, self._complete = hyper, complete
        snap = Snapshot(path_id=path_id, experiences=sum(len(a) for a, _ in bins.values()),
                        hyper_version=hyper.version if hyper is not None else 0, complete=complete,
                        error="; ".join(errors))
        if not complete:
            log.warning("%s", snap.describe())
            self._start_prefetcher()
            self._wake.set()
        return snap

    def _get_hyper(self, path_id: str, timeout_s: float | None = None) -> tuple[HyperMsg | None, bool]:
        """The store's newest hyperparameters of this model for the route (None: none fitted), and
        whether any store answered at all."""
        selector = keys.store_hyper(path_id) + (f"?model={self.model}" if self.model else "")
        best, answered = None, False
        for rep in self.session.get(selector, timeout=timeout_s or self.timeout):
            answered = True
            if rep.ok is None:
                continue        # no hyperparameters for this route and model yet
            try:
                msg = decode(HyperMsg, rep.ok.payload.to_bytes())
            except DecodeError as exc:
                log.warning("rejected hyperparameters on %s: %s", rep.ok.key_expr, exc)
                continue
            if msg.path_id == path_id and (not self.model or msg.model == self.model) and (
                    best is None or msg.version > best.version):
                best = msg
        return best, answered

    # --- background prefetch ---------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(timeout=0.5)
            self._wake.clear()
            if self._stop.is_set():
                return
            if self._complete:
                continue        # a snapshot holds everything this trial will ask for
            try:
                self._fetch_hyper_once()
                self._prefetch()
            except Exception as exc:  # never let the prefetcher die; the loop runs on what it has
                self.failures += 1
                self.last_error = str(exc)
                log.warning("prefetch failed: %s", exc)

    def _fetch_hyper_once(self) -> None:
        path_id = self._path_id
        if path_id is None or self._hyper is not None:
            return
        selector = keys.store_hyper(path_id) + (f"?model={self.model}" if self.model else "")
        for rep in self.session.get(selector, timeout=self.timeout):
            if rep.ok is not None:
                self._on_hyper(rep.ok)

    def _prefetch(self) -> None:
        path_id, pos = self._path_id, self._position
        if path_id is None or pos is None:
            return
        vertex, driven, asked = pos
        for speed in dict.fromkeys((driven, asked)):
            if not self._prefetch_at(path_id, vertex, speed):
                return

    def _prefetch_at(self, path_id: str, vertex: int, speed: float) -> bool:
        """Fetch the windows of `speed` from `vertex` to the lookahead; False once the route changed."""
        l = self.speed_bin(speed)
        lo = max(0, vertex - self.cv)
        hi = min(self._n_vertices - 1, vertex + self.lookahead + self.cv)
        v = lo
        while v <= hi and not self._stop.is_set():
            with self._lock:
                fetched = all((v, b) in self._bins for b in range(l - self.cl, l + self.cl + 1))
            if fetched:
                v += 1
                continue
            self._fetch(path_id, v + self.cv, speed)
            if self._path_id != path_id:
                return False
            v += 2 * self.cv + 1
        return True

    def _get_window(self, path_id: str, center: int, speed: float, extra: str = "",
                    timeout_s: float | None = None) -> ExperienceWindow | None:
        """One window query (None: no usable answer; `last_error` says why)."""
        self.queries += 1
        selector = f"{keys.store_window(path_id)}?vertex={center}&speed={speed:.6f}{extra}"
        if self.model:
            selector += f"&model={self.model}"
        window, error = None, "no store answered"
        for rep in self.session.get(selector, timeout=timeout_s or self.timeout):
            if rep.ok is None:
                self.failures += 1
                error = rep.err.payload.to_bytes().decode("utf-8", "replace")
                continue
            try:
                window = decode(ExperienceWindow, rep.ok.payload.to_bytes())
            except DecodeError as exc:
                self.failures += 1
                error = f"bad window: {exc}"
        if window is None:
            self.last_error = error
            self.failures += 1
        return window

    def _fetch(self, path_id: str, center: int, speed: float) -> None:
        window = self._get_window(path_id, center, speed)
        if window is None:
            return
        A = np.frombuffer(window.a_f64, "<f8").reshape(-1, A_DIM)
        G = np.frombuffer(window.g_f64, "<f8").reshape(-1, G_DIM)
        verts, bins = np.asarray(window.vertices), np.asarray(window.speed_bins)
        with self._lock:
            if path_id != self._path_id or self._complete:
                return
            for v in range(window.vertex_lo, window.vertex_hi + 1):
                for b in range(window.bin_lo, window.bin_hi + 1):
                    sel = (verts == v) & (bins == b)
                    self._bins[(v, b)] = (A[sel], G[sel])
            self._assembled.clear()


def _by_bin(window: ExperienceWindow) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """A window's experiences per non-empty (vertex, speed bin), each bin's in the store's order."""
    A = np.frombuffer(window.a_f64, "<f8").reshape(-1, A_DIM)
    G = np.frombuffer(window.g_f64, "<f8").reshape(-1, G_DIM)
    verts = np.asarray(window.vertices, dtype=np.int64)
    bins = np.asarray(window.speed_bins, dtype=np.int64)
    order = np.lexsort((bins, verts))     # stable: each bin keeps the store's (insertion) order
    cells = np.stack([verts[order], bins[order]], axis=1)
    starts = np.flatnonzero(np.r_[True, np.any(cells[1:] != cells[:-1], axis=1)]) if len(order) else []
    out = {}
    for i, start in enumerate(starts):
        end = starts[i + 1] if i + 1 < len(starts) else len(order)
        idx = order[start:end]
        out[(int(verts[idx[0]]), int(bins[idx[0]]))] = (A[idx], G[idx])
    return out
