"""The producer's and the controller's side of the experience store.

ExperienceOutbox: at-least-once delivery. Every experience keeps a per-producer seq and stays pending
until a store acknowledges it (after its durable commit); what is not acknowledged within
`resend_after_s` is sent again (the store stores a (source, seq) once). A store that is down simply
means a growing outbox, capped, never a blocked control loop.

WindowCache: keeps the local windows ahead of the robot prefetched in a background thread, plus the
latest hyperparameters, so the real-time loop reads only memory. If the store disappears, the loop
keeps the data it has.
"""
from __future__ import annotations

import logging
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

log = logging.getLogger(__name__)


class ExperienceOutbox:
    def __init__(self, node: Node, robot: str, *, resend_after_s: float = 2.0, max_pending: int = 200_000,
                 max_batch: int = 500, source: str | None = None, model: str = ""):
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
        self.acked = 0
        self.rejected = 0
        self.dropped = 0
        self._key = keys.experience(robot)
        node.subscribe(keys.experience_ack(robot), ExperienceAck, self._on_ack)

    def _on_ack(self, ack: ExperienceAck, _key: str) -> None:
        if ack.source != self.source:
            return
        with self._lock:
            for seq in ack.seqs:
                if self._pending.pop(seq, None) is not None:
                    self.acked += 1
            for seq in ack.rejected:   # a store refused these: re-sending would not help
                if self._pending.pop(seq, None) is not None:
                    self.rejected += 1
            self._lock.notify_all()
        if ack.rejected:
            log.warning("store %s rejected %d experiences: %s", ack.store, len(ack.rejected), ack.reason)

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
            out = out + stale
            while len(self._pending) > self.max_pending:   # store gone for very long: keep the newest
                self._pending.popitem(last=False)
                self.dropped += 1
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


class WindowCache:
    def __init__(self, session: zenoh.Session, *, bins: BinPolicy = BinPolicy(), lookahead_vertices: int = 20,
                 query_timeout_s: float = 2.0, model: str = ""):
        self.session = session
        # windows and hyperparameters of this nominal model's experiences only ("": the route's newest)
        self.model = model
        self.v_bin = bins.v_bin_mps
        self.cv = bins.c_vertex
        self.cl = bins.c_velocity
        self.lookahead = lookahead_vertices
        self.timeout = query_timeout_s
        self._lock = threading.Lock()
        self._bins: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._assembled: dict[tuple[int, int], LocalData] = {}
        self._path_id: str | None = None
        self._n_vertices = 0
        self._position: tuple[int, float] | None = None
        self._hyper: HyperMsg | None = None
        self._hyper_sub = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.queries = 0
        self.failures = 0
        self.last_error = ""
        self._thread = threading.Thread(target=self._run, name="window-prefetch", daemon=True)
        self._thread.start()

    # --- called by the control loop: memory only ---------------------------------------------
    def speed_bin(self, v: float) -> int:
        return int(np.floor(v / self.v_bin))

    def set_position(self, vertex: int, speed_mps: float) -> None:
        self._position = (vertex, speed_mps)
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
                        missing += 0 if (v < 0 or v >= self._n_vertices) else 1
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
    def set_route(self, path_id: str, n_vertices: int) -> None:
        """Start over for a route: forget cached windows (new experiences exist), follow its hyperparameters."""
        with self._lock:
            self._bins.clear()
            self._assembled.clear()
            changed = path_id != self._path_id
            self._path_id, self._n_vertices = path_id, n_vertices
            self._position = None
            if changed:
                self._hyper = None
        if changed:
            if self._hyper_sub is not None:
                self._hyper_sub.undeclare()
            self._hyper_sub = self.session.declare_subscriber(keys.store_hyper(path_id), self._on_hyper)
        self._wake.set()

    def _on_hyper(self, sample: zenoh.Sample) -> None:
        try:
            msg = decode(HyperMsg, sample.payload.to_bytes())
        except DecodeError as exc:
            log.warning("rejected hyperparameters on %s: %s", sample.key_expr, exc)
            return
        if self.model and msg.model != self.model:      # fitted on another nominal model's residuals
            return
        if msg.path_id == self._path_id and (self._hyper is None or msg.version > self._hyper.version):
            self._hyper = msg

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5)
        if self._hyper_sub is not None:
            self._hyper_sub.undeclare()

    # --- background prefetch ---------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(timeout=0.5)
            self._wake.clear()
            if self._stop.is_set():
                return
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
        vertex, speed = pos
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
                return
            v += 2 * self.cv + 1

    def _fetch(self, path_id: str, center: int, speed: float) -> None:
        self.queries += 1
        selector = f"{keys.store_window(path_id)}?vertex={center}&speed={speed:.6f}"
        if self.model:
            selector += f"&model={self.model}"
        window = None
        for rep in self.session.get(selector, timeout=self.timeout):
            if rep.ok is None:
                self.failures += 1
                self.last_error = rep.err.payload.to_bytes().decode("utf-8", "replace")
                continue
            try:
                window = decode(ExperienceWindow, rep.ok.payload.to_bytes())
            except DecodeError as exc:
                self.failures += 1
                self.last_error = f"bad window: {exc}"
        if window is None:
            if not self.last_error:
                self.last_error = "no store answered"
            self.failures += 1
            return
        A = np.frombuffer(window.a_f64, "<f8").reshape(-1, A_DIM)
        G = np.frombuffer(window.g_f64, "<f8").reshape(-1, G_DIM)
        verts, bins = np.asarray(window.vertices), np.asarray(window.speed_bins)
        with self._lock:
            if path_id != self._path_id:
                return
            for v in range(window.vertex_lo, window.vertex_hi + 1):
                for b in range(window.bin_lo, window.bin_hi + 1):
                    sel = (verts == v) & (bins == b)
                    self._bins[(v, b)] = (A[sel], G[sel])
            self._assembled.clear()
