"""Experience store service (thesis 5.2.2-5.3.2): the shared memory of every robot.

- ingests `lbc/*/experience` batches (any robot) for the routes it serves, in group commits, and
  acknowledges each stored seq on `lbc/<robot>/experience/ack` only after the commit; experiences of a
  route no service answers for right now (the robot's localizer unreachable or slow) are left
  unacknowledged, so their producer sends them again, rather than rejected and lost;
- answers local-window queries `lbc/store/<path>/window?vertex=i&speed=v[&model=m]` (one nominal
  model's experiences, db.py; without `model`, those of the route's newest experience), the newest
  hyperparameters `hyper[?model=m]` (fitted on that model's experiences), `dump` and `stats`;
- fits GP hyperparameters on the route's newest model in a worker process after a repeat trial ends
  (or on a `fit` query) and publishes the new version, naming its model, on `lbc/store/<path>/hyper`.

Several stores can split the routes between them (`paths` in the config): each declares queryables
only for its own routes, so Zenoh routes every query to the store that holds the data.
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import queue
import threading
import time
from dataclasses import dataclass, field

import zenoh

from common import keys
from common.bus import Node, float_param, int_param, query, query_params
from common.codec import DecodeError, decode, encode
from common.lifecycle import die_with_parent
from common.messages import (ExperienceAck, ExperienceBatch, ExperienceWindow, RouteMsg, StoreStats, TrialEvent,
                             check_name)
from common.service import Control, Service, service_main
from common.typecheck import to_dict
from services.gp_store.authority import AuthorityRule
from services.gp_store.config import StoreConfig
from services.gp_store.db import ExperienceDB
from services.gp_store.fitting import FitResult, fit_route

DUMP_CHUNK = 2000
# window queries beyond these are malformed, not large: no route has 10 million vertices, no robot 1000 m/s
MAX_VERTEX = 10_000_000
MAX_SPEED_MPS = 1000.0
MAX_SPEED_BINS = 100_000


@dataclass
class _FitState:
    running: cf.Future | None = None
    rerun: bool = False
    waiting: list[zenoh.Query] = field(default_factory=list)
    retained_at_fit: int = 0


ROUTE_QUERY_S = 2.0       # how long a route lookup waits for its service
ROUTE_RECHECK_S = 10.0    # an unknown or unanswered route is asked again after this long


@dataclass(frozen=True)
class _RouteLookup:
    n: int | None             # the route's vertex count (None: no such route, or no answer)
    answered: bool            # its service answered (False: ask again later, keep the experiences)
    at: float                 # monotonic time of the lookup
    reason: str = ""          # why there is no count


class StoreService(Service):
    name = "gp_store"

    def __init__(self, cfg: StoreConfig, node: Node):
        super().__init__(node)
        self.cfg = cfg
        self.policy = cfg.bins
        self.db = ExperienceDB(cfg.db_path, self.policy)
        self.serve_all = "*" in cfg.paths
        self.paths = {check_name("path_id", p) for p in cfg.paths if p != "*"}
        self.fits: dict[str, _FitState] = {}
        self._pool: cf.ProcessPoolExecutor | None = None
        self._ingest_q: queue.Queue[ExperienceBatch] = queue.Queue()
        self._routes: dict[str, _RouteLookup] = {}
        node.subscribe(f"{keys.ROOT}/*/experience", ExperienceBatch, lambda m, k: self._ingest_q.put(m))
        node.subscribe(f"{keys.ROOT}/*/trial/event", TrialEvent, lambda m, k: self.inbox.put(("trial", m)))
        for p in (["*"] if self.serve_all else sorted(self.paths)):
            node.queryable(keys.store_window(p), self._on_window)
            node.queryable(keys.store_hyper(p), self._on_hyper)
            node.queryable(keys.store_dump(p), self._on_dump)
            node.queryable(keys.store_fit(p), lambda q: self.inbox.put(("fit", q)))
        node.queryable(keys.store_stats(), self._on_stats)
        self.log.info("store %s on %s serving %s", cfg.name, cfg.db_path, "all routes" if self.serve_all else sorted(self.paths))

    def serves(self, path_id: str) -> bool:
        return self.serve_all or path_id in self.paths

    # --- ingestion (the service's own thread) ------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self._ingest_pending(timeout=0.05)
            while True:
                try:
                    key, item = self.inbox.get_nowait()
                except queue.Empty:
                    break
                self.dispatch(key, item)

    def _ingest_pending(self, timeout: float) -> None:
        try:
            batches = [self._ingest_q.get(timeout=timeout)]
        except queue.Empty:
            return
        while len(batches) < 64:  # group commit: one fsync for whatever has queued up
            try:
                batches.append(self._ingest_q.get_nowait())
            except queue.Empty:
                break
        by_source: dict[tuple[str, str], tuple[list, list, set]] = {}
        for b in batches:
            good, bad, reasons = by_source.setdefault((b.robot, b.source), ([], [], set()))
            for e in b.experiences:
                if not self.serves(e.path_id):
                    continue  # another store's route
                n, answered = self._route_vertices(e.path_id)
                if not answered:
                    continue  # no one to ask whether the route exists: the producer sends it again
                problem = self._check(e, n)
                if problem:
                    bad.append(e.seq)
                    reasons.add(problem)
                else:
                    good.append(e)
        for (robot, source), (good, bad, reasons) in by_source.items():
            try:
                stored = self.db.ingest(source, good)
            except Exception as exc:  # a disk error must not be acknowledged as stored
                self.log.error("cannot store %d experiences from %s: %s", len(good), source, exc)
                continue
            if bad:
                self.log.warning("rejected %d experiences from %s: %s", len(bad), source, "; ".join(sorted(reasons)))
            if stored or bad:
                self.node.publish(keys.experience_ack(robot), ExperienceAck(
                    stamp_s=time.time(), store=self.cfg.name, source=source, seqs=stored, rejected=bad,
                    reason="; ".join(sorted(reasons))))

    def _check(self, e, n: int | None) -> str:
        """Why an experience cannot be stored, or '' (field types and finiteness the codec checked); `n`:
        its route's vertex count, None where the route's service answered that it has no such route."""
        if n is None:
            return f"unknown route {e.path_id!r}: {self._routes[e.path_id].reason}"
        if e.vertex >= n:
            return f"vertex {e.vertex} beyond the {n} vertices of route {e.path_id!r}"
        if e.v_cmd_mps < 0 or e.trial < 0:
            return "negative commanded speed or trial"
        return ""

    def _route_vertices(self, path_id: str) -> tuple[int | None, bool]:
        """(vertex count of a taught route or None, whether its service answered at all), looked up once
        on the bus; an unknown or unanswered id is asked again after ROUTE_RECHECK_S."""
        known = self._routes.get(path_id)
        if known is None or (known.n is None and time.monotonic() - known.at > ROUTE_RECHECK_S):
            known = self._routes[path_id] = self._look_up(path_id)
        return known.n, known.answered

    def _look_up(self, path_id: str) -> _RouteLookup:
        """Every service that serves routes answers (several robots' localizers may): the route is known
        if one holds it, unknown if all that answered do not, unanswered if none did."""
        now = time.monotonic()
        errors = []
        for rep in query(self.node.session, keys.route(path_id), timeout_s=ROUTE_QUERY_S):
            if rep.error is not None:
                errors.append(rep.error)
                continue
            try:
                return _RouteLookup(len(decode(RouteMsg, rep.payload).x_m), True, now)
            except DecodeError as exc:
                errors.append(f"not readable: {exc}")
        if errors:
            self.log.warning("route %s not found: %s", path_id, "; ".join(errors))
            return _RouteLookup(None, True, now, "; ".join(errors))
        self.log.warning("route %s: no service answered within %.0f s; its experiences wait for it",
                         path_id, ROUTE_QUERY_S)
        return _RouteLookup(None, False, now, "no service answered")

    # --- queries (on Zenoh's threads: short reads on the reader connection) ----------------------
    @staticmethod
    def _path_of(query: zenoh.Query) -> str:
        return str(query.key_expr).split("/")[2]

    def _answer(self, query: zenoh.Query, fn) -> None:
        try:
            fn()
        except (ValueError, KeyError, TypeError) as exc:
            query.reply_err(f"bad query {query.selector}: {exc}".encode())
        except Exception as exc:
            self.log.exception("query %s failed", query.selector)
            query.reply_err(f"store error: {exc}".encode())
        finally:
            query.drop()

    def _on_window(self, query: zenoh.Query) -> None:
        def answer():
            path_id = check_name("path_id", self._path_of(query))
            params = query_params(query)
            if "vertex" not in params or "speed" not in params:
                raise ValueError("window queries need vertex=<i> and speed=<m/s>")
            vertex = int_param(params, "vertex", 0, MAX_VERTEX)
            speed = float_param(params, "speed", -MAX_SPEED_MPS, MAX_SPEED_MPS)
            cv = int_param(params, "c_vertex", 0, MAX_VERTEX)
            cl = int_param(params, "c_velocity", 0, MAX_SPEED_BINS)
            model = params.get("model")           # the asking controller's nominal model (db.py); none given:
            if model:                               # the route's current one
                check_name("model", model)
            w = self.db.window(path_id, vertex, speed, cv, cl, model=model)
            query.reply(keys.store_window(path_id), encode(ExperienceWindow(
                stamp_s=time.time(), path_id=path_id, vertex_lo=w.vertex_lo, vertex_hi=w.vertex_hi, bin_lo=w.bin_lo,
                bin_hi=w.bin_hi, v_bin_mps=self.policy.v_bin_mps, vertices=w.vertices.tolist(),
                speed_bins=w.speed_bins.tolist(), a_f64=w.A.astype("<f8").tobytes(), g_f64=w.G.astype("<f8").tobytes())))
        self._answer(query, answer)

    def _on_hyper(self, query: zenoh.Query) -> None:
        def answer():
            path_id = check_name("path_id", self._path_of(query))
            model = query_params(query).get("model")  # the asking controller's model; none given: the route's
            if model:                                 # newest experiences'
                check_name("model", model)
            else:
                model = self.db.current_model(path_id)
            hyper = self.db.latest_hyper(path_id, model)
            if hyper is None:
                query.reply_err(f"no hyperparameters for {path_id} (model {model or 'untagged'}) yet".encode())
            else:
                query.reply(keys.store_hyper(path_id), encode(hyper))
        self._answer(query, answer)

    def _on_dump(self, query: zenoh.Query) -> None:
        """Every retained experience of a route, in chunks, each batch under its producer's source so
        that an import elsewhere keeps the (source, seq) identity."""
        def answer():
            path_id = check_name("path_id", self._path_of(query))
            after = 0
            while True:
                rows = self.db.experiences(path_id, after, DUMP_CHUNK)
                if not rows:
                    break
                after = rows[-1][0]
                by_source: dict[str, list] = {}
                for _, source, e in rows:
                    by_source.setdefault(source, []).append(e)
                for source, exps in by_source.items():
                    query.reply(keys.store_dump(path_id), encode(ExperienceBatch(
                        stamp_s=time.time(), robot=keys.STORE_ROBOT, source=source, experiences=exps)))
        self._answer(query, answer)

    def _on_stats(self, query: zenoh.Query) -> None:
        def answer():
            stats = [s for s in self.db.stats() if self.serves(s.path_id)]
            query.reply(f"{keys.store_stats()}", encode(StoreStats(stamp_s=time.time(), store=self.cfg.name,
                                                                    db_path=str(self.db.path), paths=stats)))
        self._answer(query, answer)

    # --- fitting ------------------------------------------------------------------------------
    def on_message(self, key: str, item) -> None:
        if key == "trial":
            ev: TrialEvent = item
            if ev.event == "ended" and ev.mode == "repeat" and self.cfg.fit.auto_after_trial and self.serves(ev.path_id):
                self._ingest_pending(timeout=0.0)
                state = self.fits.get(ev.path_id, _FitState())
                retained = self.db.count(ev.path_id, self.db.current_model(ev.path_id))
                if abs(retained - state.retained_at_fit) >= self.cfg.fit.min_new or state.running is not None:
                    self._start_fit(ev.path_id)
        elif key == "fit":
            query: zenoh.Query = item
            try:
                path_id = check_name("path_id", self._path_of(query))
            except ValueError as exc:
                query.reply_err(str(exc).encode())
                query.drop()
                return
            self._ingest_pending(timeout=0.0)   # include what has already arrived
            self._start_fit(path_id, query)
        elif key == "fit_done":
            self._fit_done(*item)

    def _start_fit(self, path_id: str, query: zenoh.Query | None = None) -> None:
        state = self.fits.setdefault(path_id, _FitState())
        if query is not None:
            state.waiting.append(query)
        if state.running is not None:
            state.rerun = True  # fit again with what arrives meanwhile once this one is done
            return
        model = self.db.current_model(path_id)
        A, G, tiles = self.db.all_of(path_id, model)
        if len(A) == 0:
            for q in state.waiting:
                q.reply_err(f"no experiences for {path_id}".encode())
                q.drop()
            state.waiting.clear()
            return
        # warm start from this model's last fit, else the route's (the terrain is the same)
        prev = self.db.latest_hyper(path_id, model) or self.db.latest_hyper(path_id)
        f = self.cfg.fit
        if self._pool is None:
            # spawn, not fork: the parent has Zenoh threads
            self._pool = cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                                initializer=die_with_parent, initargs=(os.getpid(),))
        self.log.info("fitting GP hyperparameters for %s on %d experiences (nominal model %s)", path_id, len(A),
                      model or "untagged")
        state.retained_at_fit = len(A)
        teach_only = self.db.trials_of(path_id, model) == {0}
        rule = None if teach_only else AuthorityRule.for_model(model, f.min_turn_authority,
                                                               f.teach_min_lengthscale_other)
        state.running = self._pool.submit(fit_route, path_id, A, G, tiles if f.local_windows else None,
                                          f.restarts, f.max_points, f.seed, prev.dims if prev else None,
                                          f.floors(teach_only), rule, f.ceilings(teach_only))
        state.running.add_done_callback(lambda fut: self.inbox.put(("fit_done", (path_id, model, fut))))

    def _fit_done(self, path_id: str, model: str, fut: cf.Future) -> None:
        state = self.fits[path_id]
        state.running = None
        waiting, state.waiting = state.waiting, []
        try:
            fit: FitResult = fut.result()
            msg = self.db.save_hyper(fit, model, time.time())
            self.node.publish(keys.store_hyper(path_id), msg)
            self.log.info("%s: hyperparameters v%d from %d/%d experiences in %.1f s (LML %s)", path_id, msg.version,
                          msg.n_used, msg.n_total, msg.fit_s, [round(x, 1) for x in msg.lml])
            if msg.note:
                self.log.warning("%s: hyperparameters v%d: %s", path_id, msg.version, msg.note)
            for q in waiting:
                q.reply(keys.store_fit(path_id), encode(msg))
        except Exception as exc:
            self.log.exception("fit for %s failed", path_id)
            for q in waiting:
                q.reply_err(f"fit failed: {exc}".encode())
        finally:
            for q in waiting:
                q.drop()
        if state.rerun:
            state.rerun = False
            self._start_fit(path_id)

    def on_control(self, ctl: Control) -> None:
        if ctl.request.action == "ping":
            # the text the ping always gave: one plain mapping per route
            return self.reply(ctl, True, f"store {self.cfg.name}: {[to_dict(s) for s in self.db.stats()]}")
        return self.reply(ctl, True, "the store is shared; trial control does not apply")

    def close(self) -> None:
        if self._pool is not None:
            # a fit may take a while: do not make shutdown wait for it
            for proc in list(getattr(self._pool, "_processes", {}).values()):
                proc.terminate()
            self._pool.shutdown(wait=True, cancel_futures=True)
        for state in self.fits.values():
            for q in state.waiting:
                q.reply_err(b"store shutting down")
                q.drop()
        self.db.close()


def main(argv: list[str] | None = None) -> int:
    return service_main("gp_store", StoreConfig, StoreService, lambda c: keys.STORE_ROBOT, argv)
