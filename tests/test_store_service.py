"""The experience store as a real process: durability under SIGKILL, rejection of bad experiences,
window queries over the bus, the controller-side cache, and fits on request."""
from __future__ import annotations

import signal
import sqlite3
import subprocess
import sys
import threading
from pathlib import Path as FsPath

import msgpack
import numpy as np
import pytest

from common import keys
from common.bus import Node, query, query_one
from common.codec import decode, encode
from common.config import dump_toml
from common.messages import Experience, ExperienceAck, ExperienceBatch, ExperienceWindow, HyperMsg
from common.path import Path
from common.outbox_journal import OutboxJournal
from common.store_client import ExperienceOutbox, WindowCache
from deploy.launcher import Launcher
from deploy.router import free_port
from common.bins import BinPolicy
from services.gp_store.config import FitConfig, StoreConfig
from services.localizer.config import LocalizerConfig
from services.localizer.routes import RouteStore
from tests.conftest import wait_until

pytestmark = pytest.mark.integration
ROOT = FsPath(__file__).resolve().parents[1]
N_VERTICES = 400


class StoreRig:
    """Router + localizer (serves the route) + gp_store, and a client node playing a robot."""

    def __init__(self, base, c_bin=4, localizer=True):
        self.base = base
        RouteStore(base / "data" / "routes").save(
            Path("dur", np.column_stack([np.arange(N_VERTICES) * 0.25, np.zeros(N_VERTICES), np.zeros(N_VERTICES)])), 0.0)
        (base / "loc.toml").write_text(dump_toml(LocalizerConfig(robot_name="r1", data_dir=str(base / "data"))))
        self.store_cfg = StoreConfig(name="s1", db_path=str(base / "data" / "exp.db"),
                                     bins=BinPolicy(c_bin=c_bin), fit=FitConfig(restarts=1, auto_after_trial=False))
        (base / "store.toml").write_text(dump_toml(self.store_cfg))
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.launcher = Launcher(self.endpoint, base / "logs")
        self.launcher.start_router(self.port)
        self.node = Node("test", "r1", self.endpoint)
        if localizer:
            self.start_localizer()
        self.start_store()

    def start_localizer(self):
        """The service that answers route queries: up (its token seen) before anything asks it."""
        self.launcher.start_service("localizer", self.base / "loc.toml")
        up = threading.Event()
        self.node.liveliness_subscriber(keys.alive("r1", "localizer"), lambda k, alive: alive and up.set())
        assert up.wait(30), "localizer did not come up"

    def start_store(self):
        self.launcher.start_service("gp_store", self.base / "store.toml")
        up = threading.Event()
        self.node.liveliness_subscriber(keys.alive(keys.STORE_ROBOT, "gp_store"), lambda k, alive: alive and up.set())
        assert up.wait(30), "store did not come up"

    def log(self):
        return (self.base / "logs" / "gp_store.log").read_text()

    def close(self):
        self.node.close()
        self.launcher.stop()


@pytest.fixture
def rig(tmp_path):
    r = StoreRig(tmp_path)
    try:
        yield r
    finally:
        r.close()


def unique_bin_experience(outbox, i):
    # one experience per (vertex, speed bin): nothing is evicted, so every acknowledged one must be there
    return outbox.add(stamp_s=0.1 * i, trial=1, path_id="dur", vertex=i % N_VERTICES, v_cmd_mps=0.25 * (i // N_VERTICES) + 0.1,
                      a=[0.01 * i] * 9, g=[0.001, -0.002, 0.0005])


def test_sigkill_during_ingestion_loses_no_acknowledged_experience(rig):
    acked: set[int] = set()
    rig.node.subscribe(keys.experience_ack("r1"), ExperienceAck, lambda m, k: acked.update(m.seqs))
    outbox = ExperienceOutbox(rig.node, "r1", resend_after_s=1.0)
    total = 3000
    for i in range(total):
        unique_bin_experience(outbox, i)
        if i % 50 == 49:
            outbox.flush()
        if i == 1500:
            wait_until(lambda: len(acked) > 500, 20, "first acknowledgements")
            rig.launcher.kill("gp_store", signal.SIGKILL)   # mid-stream: batches are still arriving
    outbox.flush()
    acked_before_restart = set(acked)
    assert 500 < len(acked_before_restart) < total
    rig.start_store()
    assert outbox.wait_acked(60), f"{outbox.pending} experiences never acknowledged"
    rig.launcher.stop()   # read the file with the store gone
    db = sqlite3.connect(rig.store_cfg.db_path)
    stored = {s for (s,) in db.execute("SELECT seq FROM experiences WHERE source=?", (outbox.source,))}
    assert acked_before_restart <= stored
    assert len(stored) == total          # re-sent after the restart, each stored once
    (max_in_bin,) = db.execute("SELECT MAX(n) FROM (SELECT COUNT(*) n FROM experiences GROUP BY path_id, vertex, "
                               "speed_bin)").fetchone()
    assert max_in_bin <= rig.store_cfg.bins.c_bin


# a producer that queues experiences while no store is up and is then killed outright
_PRODUCER = """
import os, signal, sys
from common.bus import Node
from common.outbox_journal import OutboxJournal
from common.store_client import ExperienceOutbox
from tests.test_store_service import unique_bin_experience
node = Node("producer", "r1", sys.argv[1])
outbox = ExperienceOutbox(node, "r1", journal=OutboxJournal(sys.argv[2], "r1"))
for i in range(int(sys.argv[3])):
    unique_bin_experience(outbox, i)
    if i % 50 == 49:
        outbox.flush()
outbox.flush()
assert outbox.journal.sync(30)
print(outbox.source, outbox.acked, flush=True)
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_experiences_queued_by_a_producer_that_dies_are_sent_by_its_successor(rig, tmp_path):
    """The link to the store is down (the store is stopped), the producer queues 800 experiences and is
    killed; the store comes back and a new producer on the same journal sends every one, once."""
    rig.launcher.kill("gp_store", signal.SIGKILL)
    wait_until(lambda: rig.launcher.exited(), 10, "the store to die")
    journal_path, total = tmp_path / "outbox.db", 800
    child = subprocess.run([sys.executable, "-c", _PRODUCER, rig.endpoint, str(journal_path), str(total)],
                           capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert child.returncode == -signal.SIGKILL, child.stderr
    source, acked = child.stdout.split()
    assert acked == "0"
    rig.start_store()
    journal = OutboxJournal(journal_path, "r1")
    outbox = ExperienceOutbox(rig.node, "r1", resend_after_s=1.0, journal=journal)
    assert outbox.source == source and outbox.recovered == total
    unique_bin_experience(outbox, total)             # numbered after the dead producer's
    assert outbox.wait_acked(60), f"{outbox.pending} experiences never acknowledged"
    assert journal.sync(10)
    journal.close()
    assert OutboxJournal(journal_path, "r1").recovered.pending == []
    rig.launcher.stop()
    db = sqlite3.connect(rig.store_cfg.db_path)
    stored = sorted(s for (s,) in db.execute("SELECT seq FROM experiences WHERE source=?", (source,)))
    assert stored == list(range(total + 1))


def test_crowded_bins_respect_c_bin_after_a_crash(rig):
    outbox = ExperienceOutbox(rig.node, "r1", resend_after_s=1.0)
    for i in range(1200):  # 10 vertices x 1 speed bin: 120 per bin
        outbox.add(stamp_s=0.1 * i, trial=1, path_id="dur", vertex=i % 10, v_cmd_mps=0.5, a=[0.0] * 9, g=[0.0] * 3)
        if i % 100 == 99:
            outbox.flush()
        if i == 600:
            rig.launcher.kill("gp_store", signal.SIGKILL)
            rig.start_store()
    assert outbox.wait_acked(60)
    w = query_one(rig.node.session, f"{keys.store_window('dur')}?vertex=5&speed=0.5", ExperienceWindow)
    counts = np.bincount(np.asarray(w.vertices))
    assert counts.max() == 4 and len(w.vertices) == 4 * 10


def test_bad_experiences_are_rejected_with_a_reason(rig):
    rejected: list[ExperienceAck] = []
    rig.node.subscribe(keys.experience_ack("r1"), ExperienceAck, lambda m, k: m.rejected and rejected.append(m))
    good = Experience(stamp_s=0.0, robot="r1", trial=1, path_id="dur", seq=0, vertex=1, v_cmd_mps=0.5, a=(0.0,) * 9,
                      g=(0.0,) * 3)
    body = msgpack.unpackb(encode(ExperienceBatch(stamp_s=0.0, robot="r1", source="t1", experiences=[good])))
    body["experiences"][0]["g"][0] = float("nan")
    rig.node.session.put(keys.experience("r1"), msgpack.packb(body))
    body["experiences"][0]["g"] = [0.0, 0.0]
    rig.node.session.put(keys.experience("r1"), msgpack.packb(body))
    unknown = Experience(stamp_s=0.0, robot="r1", trial=1, path_id="nope", seq=1, vertex=1, v_cmd_mps=0.5,
                         a=(0.0,) * 9, g=(0.0,) * 3)
    far = Experience(stamp_s=0.0, robot="r1", trial=1, path_id="dur", seq=2, vertex=N_VERTICES + 5, v_cmd_mps=0.5,
                     a=(0.0,) * 9, g=(0.0,) * 3)
    rig.node.publish(keys.experience("r1"), ExperienceBatch(stamp_s=0.0, robot="r1", source="t1",
                                                            experiences=[unknown, far]))
    wait_until(lambda: rejected, 15, "a rejection")
    assert sorted(rejected[0].rejected) == [1, 2]
    assert "unknown route 'nope'" in rejected[0].reason and "beyond the 400 vertices" in rejected[0].reason
    log = rig.log()
    assert "rejected message on lbc/r1/experience" in log and "must be finite" in log and "must hold 3 values" in log
    assert rig.launcher.exited() == []


def test_experiences_of_a_route_no_service_answers_for_wait_for_it_instead_of_being_rejected(tmp_path):
    """The route's service (the robot's localizer) unreachable: its experiences are neither stored nor
    rejected but sent again, and stored once the route is served."""
    rig = StoreRig(tmp_path, localizer=False)
    try:
        acks: list[ExperienceAck] = []
        rig.node.subscribe(keys.experience_ack("r1"), ExperienceAck, lambda m, k: acks.append(m))
        outbox = ExperienceOutbox(rig.node, "r1", resend_after_s=1.0)
        for i in range(20):
            outbox.add(stamp_s=0.1 * i, trial=1, path_id="dur", vertex=i, v_cmd_mps=0.5, a=[0.0] * 9, g=[0.0] * 3)
        outbox.flush()
        wait_until(lambda: "no service answered" in rig.log(), 30, "the store's route lookup")
        assert acks == [] and outbox.pending == 20 and outbox.rejected == 0
        rig.start_localizer()
        assert outbox.wait_acked(60), f"{outbox.pending} still pending"
        # the outbox's own subscriber may hear the acknowledgements before this test's does
        wait_until(lambda: sum(len(a.seqs) for a in acks) >= 20, 10, "the acknowledgements of all 20")
        assert outbox.rejected == 0 and sum(len(a.seqs) for a in acks) >= 20
    finally:
        rig.close()


def test_window_queries_out_of_range_are_answered_with_a_reason(rig):
    bad = {"vertex=1e30&speed=0.5": "vertex must be a whole number", "vertex=10000000000000000000000&speed=0.5":
           "vertex must be a whole number", "vertex=-1&speed=0.5": "vertex must be", "vertex=3&speed=1e308":
           "speed must be a number", "vertex=3&speed=nan": "speed must be", "vertex=3&speed=inf": "speed must be",
           "vertex=3&speed=0.5&c_vertex=99999999999": "c_vertex must be", "vertex=3&speed=0.5&c_velocity=-2":
           "c_velocity must be"}
    for params, reason in bad.items():
        replies = query(rig.node.session, f"{keys.store_window('dur')}?{params}", timeout_s=10)
        assert len(replies) == 1 and replies[0].error is not None and reason in replies[0].error, (params, replies)
    ok = query(rig.node.session, f"{keys.store_window('dur')}?vertex=3&speed=0.5", timeout_s=10)
    assert ok and ok[0].error is None
    log = rig.log()
    assert "Traceback" not in log and "store error" not in log
    assert rig.launcher.exited() == []


def test_cache_prefetches_windows_and_fits_on_request(rig):
    outbox = ExperienceOutbox(rig.node, "r1")
    rng = np.random.default_rng(0)
    for i in range(600):
        s = 0.05 * i
        outbox.add(stamp_s=0.1 * i, trial=1, path_id="dur", vertex=int(s / 0.25), v_cmd_mps=0.5,
                   a=[s, 0.01 * rng.standard_normal(), 0.0, 0.5, 0.0, 0.5, 0.0, 0.5, 0.0],
                   g=[0.0, 0.01 * np.sin(s) + 0.001 * rng.standard_normal(), 0.0])
    assert outbox.wait_acked(30)
    cache = WindowCache(rig.node.session, lookahead_vertices=30)
    try:
        cache.set_route("dur", N_VERTICES)
        assert cache.local(20, 0.5).missing_bins > 0           # nothing fetched yet, and no waiting for it
        cache.set_position(20, 0.5)
        wait_until(lambda: cache.local(40, 0.5).missing_bins == 0, 10, "prefetch of the windows ahead")
        local = cache.local(20, 0.5)
        assert len(local.A) == 11 * 4 and local.G.shape == (44, 3)   # 11 vertices x c_bin, one speed bin
        assert cache.local(40, 1.5).missing_bins > 0
        cache.set_position(20, 0.5, 1.5)      # asked to drive 1.5 m/s there: its windows are fetched too
        wait_until(lambda: cache.local(40, 1.5).missing_bins == 0, 10, "prefetch of the asked speed's windows")
        assert len(cache.local(40, 1.5).A) == 0 and len(cache.local(20, 0.5).A) == 44
        hyper = query_one(rig.node.session, keys.store_fit("dur"), HyperMsg, timeout_s=300)
        assert hyper.version == 1 and hyper.n_total == len(set(range(120))) * 4 or hyper.n_total > 0
        wait_until(lambda: cache.hyper is not None and cache.hyper.version == 1, 10, "hyperparameters to arrive")
        # the store goes away: the cache keeps what it has
        rig.launcher.kill("gp_store", signal.SIGKILL)
        assert len(cache.local(20, 0.5).A) == 44 and cache.hyper.version == 1
    finally:
        cache.close()


def test_windows_and_hyperparameters_over_the_bus_are_the_asking_controllers_nominal_models(rig):
    """Two controllers whose drive lags differ feed the same route; each one's window cache (and a plain
    window query naming a model) gets only experiences of its own model, and only hyperparameters fitted
    on its own model's experiences."""
    boxes = {m: ExperienceOutbox(rig.node, "r1", model=m) for m in ("unicycle-tauw0ms", "unicycle-tauw400ms")}
    for k, (m, box) in enumerate(boxes.items()):
        for i in range(30):
            box.add(stamp_s=0.1 * i, trial=1, path_id="dur", vertex=i, v_cmd_mps=0.5, a=[float(k)] * 9,
                    g=[0.0, 0.0, 0.0])
        assert box.wait_acked(30)
    w = query_one(rig.node.session, f"{keys.store_window('dur')}?vertex=10&speed=0.5&model=unicycle-tauw0ms",
                  ExperienceWindow)
    assert len(w.vertices) == 11 and set(np.frombuffer(w.a_f64)) == {0.0}
    cache = WindowCache(rig.node.session, lookahead_vertices=10, model="unicycle-tauw400ms")
    try:
        cache.set_route("dur", N_VERTICES)
        cache.set_position(10, 0.5)
        wait_until(lambda: cache.local(10, 0.5).missing_bins == 0, 10, "prefetch of the window")
        local = cache.local(10, 0.5)
        assert len(local.A) == 11 and np.all(local.A == 1.0)
    finally:
        cache.close()
    with pytest.raises(Exception, match="model"):
        query_one(rig.node.session, f"{keys.store_window('dur')}?vertex=10&speed=0.5&model=a.b", ExperienceWindow)

    # the fit is on the newest experiences' model (tauw400ms) and says so
    h1 = query_one(rig.node.session, keys.store_fit("dur"), HyperMsg, timeout_s=300)
    assert h1.model == "unicycle-tauw400ms" and h1.n_total == 30
    caches = {m: WindowCache(rig.node.session, lookahead_vertices=10, model=m) for m in boxes}
    try:
        for c in caches.values():
            c.set_route("dur", N_VERTICES)
        wait_until(lambda: caches["unicycle-tauw400ms"].hyper is not None, 10, "tauw400ms hyperparameters")
        with pytest.raises(LookupError, match="tauw0ms"):
            query_one(rig.node.session, f"{keys.store_hyper('dur')}?model=unicycle-tauw0ms", HyperMsg)
        assert caches["unicycle-tauw0ms"].hyper is None           # nothing fitted on its experiences yet
        # tauw0ms drives again: its model is the newest, the next fit is its own; the other keeps v1
        boxes["unicycle-tauw0ms"].add(stamp_s=9.0, trial=2, path_id="dur", vertex=31, v_cmd_mps=0.5, a=[0.0] * 9,
                                      g=[0.0, 0.0, 0.0])
        assert boxes["unicycle-tauw0ms"].wait_acked(30)
        h2 = query_one(rig.node.session, keys.store_fit("dur"), HyperMsg, timeout_s=300)
        assert h2.model == "unicycle-tauw0ms" and h2.version == h1.version + 1 and h2.n_total == 31
        wait_until(lambda: caches["unicycle-tauw0ms"].hyper is not None, 10, "tauw0ms hyperparameters")
        assert caches["unicycle-tauw0ms"].hyper.version == h2.version
        assert caches["unicycle-tauw400ms"].hyper.version == h1.version   # the publication of v2 was not for it
        plain = query_one(rig.node.session, keys.store_hyper("dur"), HyperMsg)   # no model: the newest's
        assert plain.version == h2.version
    finally:
        for c in caches.values():
            c.close()


def test_two_stores_split_the_routes_between_them(tmp_path):
    from common.bus import query
    from common.messages import StoreStats
    rig = StoreRig(tmp_path)   # store s1 serves every route; replace it by two stores with one route each
    try:
        rig.launcher.kill("gp_store", signal.SIGTERM)
        RouteStore(tmp_path / "data" / "routes").save(
            Path("two", np.column_stack([np.arange(50) * 0.25, np.zeros(50), np.zeros(50)])), 0.0)
        for name, route in (("a", "dur"), ("b", "two")):
            cfg = StoreConfig(name=name, db_path=str(tmp_path / f"{name}.db"), paths=[route])
            (tmp_path / f"{name}.toml").write_text(dump_toml(cfg))
            rig.launcher.start_service("gp_store", tmp_path / f"{name}.toml")
        wait_until(lambda: len([r for r in query(rig.node.session, keys.store_stats(), timeout_s=2.0)
                                if r.error is None]) == 2, 30, "both stores")
        outbox = ExperienceOutbox(rig.node, "r1")
        for i in range(40):
            outbox.add(stamp_s=0.1 * i, trial=1, path_id="dur" if i % 2 else "two", vertex=i // 2, v_cmd_mps=0.5,
                       a=[0.0] * 9, g=[0.0] * 3)
        assert outbox.wait_acked(20)
        stats = {s.store: s for s in (decode(StoreStats, r.payload)
                                      for r in query(rig.node.session, keys.store_stats()) if r.error is None)}
        assert [p.path_id for p in stats["a"].paths] == ["dur"] and stats["a"].paths[0].ingested == 20
        assert [p.path_id for p in stats["b"].paths] == ["two"] and stats["b"].paths[0].ingested == 20
        w = query_one(rig.node.session, f"{keys.store_window('two')}?vertex=5&speed=0.5", ExperienceWindow)
        assert w.path_id == "two" and len(w.vertices) == 11
    finally:
        rig.close()
