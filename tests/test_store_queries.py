"""The store's reads stay local: the work SQLite does for a window query does not grow with the number of
experiences a route holds, and every statement a window query or an ingest runs searches an index.
Work is counted in SQLite virtual-machine steps (deterministic), not timed."""
from __future__ import annotations

import sqlite3

import pytest

from common.messages import Experience
from common.bins import BinPolicy
from services.gp_store.db import ExperienceDB

MODEL = "unicycle-dt100ms-tauv0ms-tauw400ms"


def filled(path, n_vertices: int, model: str = MODEL) -> ExperienceDB:
    """A route with 6 experiences in each of 3 speed bins at every vertex (c_bin 4 evicts 2 per bin)."""
    db = ExperienceDB(path, BinPolicy(c_bin=4))
    batch = [Experience(stamp_s=0.1 * seq, robot="r1", trial=1, path_id="p", seq=seq, vertex=seq // 18,
                        v_cmd_mps=0.3 + 0.25 * (seq % 3), a=(0.01 * (seq % 18),) * 9, g=(0.001, 0.0, 0.0), model=model)
             for seq in range(18 * n_vertices)]
    for i in range(0, len(batch), 1800):
        db.ingest("s1", batch[i:i + 1800])
    return db


def vm_steps(con: sqlite3.Connection, fn) -> int:
    steps = [0]

    def count() -> int:
        steps[0] += 1
        return 0
    con.set_progress_handler(count, 1)
    try:
        fn()
    finally:
        con.set_progress_handler(None, 1)
    return steps[0]


def traced(db: ExperienceDB, fn) -> list[str]:
    """The SQL (values bound) that `fn` runs on either of the database's connections."""
    seen: list[str] = []
    for con in (db._db, db._rdb):
        con.set_trace_callback(seen.append)
    try:
        fn()
    finally:
        for con in (db._db, db._rdb):
            con.set_trace_callback(None)
    return seen


def test_a_window_query_costs_the_same_on_a_long_route_as_on_a_short_one(tmp_path):
    """A query without a model reads the route's current model too: that lookup had sorted every
    experience of the route on each query."""
    short, long_ = filled(tmp_path / "short.db", 20), filled(tmp_path / "long.db", 1000)
    try:
        work = {}
        for name, db in (("short", short), ("long", long_)):
            db.window("p", 10, 0.6)                     # the first ask of a route since opening reads the file
            work[name] = vm_steps(db._rdb, lambda: db.window("p", 10, 0.6))
            w = db.window("p", 10, 0.6)
            assert len(w.A) == 11 * 3 * 4               # the same full window in both
        assert work["long"] <= 1.2 * work["short"], work
        assert short.current_model("p") == long_.current_model("p") == MODEL
    finally:
        short.close()
        long_.close()


def test_window_and_ingest_statements_search_the_bins_index(tmp_path):
    db = filled(tmp_path / "x.db", 50)
    extra = [Experience(stamp_s=99.0, robot="r1", trial=2, path_id="p", seq=10_000 + k, vertex=5, v_cmd_mps=0.6,
                        a=(0.0,) * 9, g=(0.0,) * 3, model=MODEL) for k in range(3)]
    try:
        statements = traced(db, lambda: (db.window("p", 10, 0.6), db.window("p", 10, 0.6, model=MODEL),
                                         db.ingest("s1", extra)))
        plans = {}
        for sql in statements:
            if "experiences" in sql and not sql.startswith("INSERT"):
                plans[sql] = [r[3] for r in db._db.execute("EXPLAIN QUERY PLAN " + sql)]
        assert plans, statements
        for sql, plan in plans.items():
            on_experiences = [step for step in plan if " experiences " in f" {step} "]
            assert on_experiences and all(step.startswith("SEARCH") for step in on_experiences), (sql, plan)
            # narrowed to the bins of a window or of one bin, not to a whole route or model
            assert all("vertex" in step or "rowid" in step for step in on_experiences), (sql, plan)
    finally:
        db.close()


def test_the_current_model_follows_ingests_and_survives_reopening(tmp_path):
    path = tmp_path / "x.db"
    db = filled(path, 3, model="m-a")
    try:
        assert db.current_model("p") == "m-a" and db.current_model("q") == ""
        db.ingest("s2", [Experience(stamp_s=9.0, robot="r2", trial=1, path_id="p", seq=0, vertex=1, v_cmd_mps=0.5,
                                    a=(0.0,) * 9, g=(0.0,) * 3, model="m-b")])
        assert db.current_model("p") == "m-b" and len(db.window("p", 1, 0.5).A) == 1
        # a re-send of an older experience stores nothing and does not make its model current again
        db.ingest("s1", [Experience(stamp_s=0.0, robot="r1", trial=1, path_id="p", seq=0, vertex=0, v_cmd_mps=0.3,
                                    a=(0.0,) * 9, g=(0.0,) * 3, model="m-a")])
        assert db.current_model("p") == "m-b"
    finally:
        db.close()
    db = ExperienceDB(path)
    try:
        assert db.current_model("p") == "m-b"
    finally:
        db.close()


@pytest.mark.parametrize("n_vertices", [1, 30])
def test_blobs_read_back_as_written(tmp_path, n_vertices):
    db = filled(tmp_path / "x.db", n_vertices)
    try:
        w = db.window("p", 0, 0.3, c_vertex=0, c_velocity=0)
        assert w.A.shape == (4, 9) and w.G.shape == (4, 3)
        assert w.A[:, 0].tolist() == pytest.approx([0.06, 0.09, 0.12, 0.15]) and w.G[0].tolist() == [0.001, 0.0, 0.0]
    finally:
        db.close()
