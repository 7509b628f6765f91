"""Experiences (eq. 5.15, 5.17) from estimates and commands, and the store's database core."""
import dataclasses
import math

import numpy as np
import pytest

from common.messages import Experience, HyperDim, HyperMsg, PathStats
from common.path import Path
from services.controller.actuator import ActuatorLag
from services.controller.experience import ExperienceBuilder, body_residual, body_velocity, unicycle_step
from common.bins import BinPolicy
from services.gp_store.db import ExperienceDB
from services.gp_store.fitting import FitResult

DT = 0.1
ROUTE = Path("r", np.column_stack([np.arange(0, 20, 0.25), np.zeros(80), np.zeros(80)]))


def drive(builder, v, w, drift_left_mps, steps=30, y0=0.05, th0=0.02):
    """A robot obeying the unicycle plus a body-frame leftward slide; estimates are exact."""
    pose = np.array([1.0, y0, th0])
    out = []
    for k in range(steps):
        vertex = ROUTE.nearest_vertex(pose)
        T = np.array([pose[0] - ROUTE.poses[vertex, 0], pose[1], pose[2]])
        obs = builder.add_estimate(k, k * DT, vertex, T)
        if obs is not None:
            out.append(obs)
        builder.add_command(k, v, w)
        nxt = unicycle_step(pose, v, w, DT)
        nxt[:2] += DT * drift_left_mps * np.array([-math.sin(pose[2]), math.cos(pose[2])])
        pose = nxt
    return out


def test_nominal_motion_has_zero_disturbance_and_a_holds_eq_5_15():
    obs = drive(ExperienceBuilder(ROUTE, DT), 0.5, 0.1, 0.0)
    assert len(obs) == 28
    for o in obs:
        np.testing.assert_allclose(o.g, 0.0, atol=1e-12)
    a = obs[5].a
    assert a[3] == pytest.approx(0.5) and a[4] == pytest.approx(0.1)   # v_{k-1} from estimates
    assert a[5:] == (0.5, 0.1, 0.5, 0.1)                               # u_k, u_{k-1}
    assert a[0] == pytest.approx(1.0 + 0.5 * DT * 6, abs=0.02)        # s along the route
    assert obs[5].v_cmd_mps == 0.5


def test_a_sideways_slide_shows_up_as_a_body_frame_lateral_disturbance():
    obs = drive(ExperienceBuilder(ROUTE, DT), 0.5, 0.0, 0.08, th0=0.3)
    for o in obs:
        np.testing.assert_allclose(o.g, [0.0, 0.08 * DT, 0.0], atol=1e-12)


def test_gaps_and_standstill_yield_no_experience():
    b = ExperienceBuilder(ROUTE, DT)
    b.add_command(0, 0.5, 0.0)
    b.add_command(1, 0.5, 0.0)
    assert b.add_estimate(0, 0.0, 4, (0.0, 0.0, 0.0)) is None
    assert b.add_estimate(1, 0.1, 4, (0.05, 0.0, 0.0)) is None
    assert b.add_estimate(3, 0.3, 5, (0.0, 0.0, 0.0)) is None   # tick 2 dropped out
    assert drive(ExperienceBuilder(ROUTE, DT), 0.0, 0.0, 0.0) == []


def test_residual_helpers():
    g = body_residual((0, 0, math.pi / 2), 1.0, 0.0, (0.0, 0.1, math.pi / 2), 0.1)
    np.testing.assert_allclose(g, 0.0, atol=1e-12)
    assert body_velocity((0, 0, math.pi / 2), (0.0, 0.1, math.pi / 2 + 0.01), 0.1) == pytest.approx((1.0, 0.1))


# --- database -------------------------------------------------------------------------------------
def exp(seq, vertex, v=0.5, path="p", robot="r1"):
    return Experience(stamp_s=seq * 0.1, robot=robot, trial=1, path_id=path, seq=seq, vertex=vertex, v_cmd_mps=v,
                      a=tuple(float(seq + i) for i in range(9)), g=(0.001 * seq, 0.0, 0.0))


def fit(lml, path="p"):
    return FitResult(path_id=path, n_used=20, n_total=20, fit_s=0.5, lml=(lml, lml, lml),
                     dims=tuple(HyperDim(lengthscales=[1.0 + j] * 9, signal_std=0.01, noise_std=0.001)
                                for j in range(3)))


# a fit's stored body as the store wrote it before fits were typed (the dict of fit_route plus the node's
# keys, in that order); schema 1 and 2 files have no "model" in it
OLD_BODY = {"path_id": "p", "n_used": 20, "n_total": 25, "fit_s": 1.5, "lml": [10.5, 11.0, -3.25],
            "dims": [{"lengthscales": [0.5 + i for i in range(9)], "signal_std": 0.02, "noise_std": 0.003}] * 3,
            "stamp_s": 7.0, "version": 1}
OLD_MSG = HyperMsg(stamp_s=7.0, path_id="p", version=1, n_used=20, n_total=25, fit_s=1.5, lml=[10.5, 11.0, -3.25],
                   dims=[HyperDim(lengthscales=[0.5 + i for i in range(9)], signal_std=0.02, noise_std=0.003)] * 3)


def test_bins_keep_the_newest_c_bin_and_windows_follow_5_3_2(tmp_path):
    db = ExperienceDB(tmp_path / "x.db", BinPolicy(v_bin_mps=0.25, c_bin=4, c_vertex=2, c_velocity=1))
    db.ingest("s1", [exp(i, vertex=i % 10, v=0.5 + 0.3 * (i % 3)) for i in range(300)])
    assert db.max_bin_count("p") == 4
    # bin of vertex 3 at 0.5 m/s (l=2): newest 4 of the seqs that landed there
    w = db.window("p", 3, 0.55, c_vertex=0, c_velocity=0)
    assert (w.vertex_lo, w.vertex_hi, w.bin_lo, w.bin_hi) == (3, 3, 2, 2)
    expected = sorted([i for i in range(300) if i % 10 == 3 and i % 3 == 0])[-4:]
    assert sorted(int(round(a[0])) for a in w.A) == expected
    # full window: vertices 1..5, speed bins 1..3 (0.5 m/s -> l=2; 0.8 -> 3; 1.1 -> 4 is outside)
    w = db.window("p", 3, 0.5)
    assert set(w.vertices) == {1, 2, 3, 4, 5} and set(w.speed_bins) == {2, 3}
    assert len(w.A) == 5 * 2 * 4 and w.G.shape == (40, 3)
    assert db.stats() == [PathStats(path_id="p", retained=10 * 3 * 4, ingested=300, bins=30, hyper_version=0)]


def test_resends_are_stored_once_even_after_eviction_and_robots_pool(tmp_path):
    db = ExperienceDB(tmp_path / "x.db", BinPolicy(c_bin=2))
    db.ingest("s1", [exp(i, vertex=0) for i in range(5)])
    assert db.ingest("s1", [exp(0, vertex=0), exp(4, vertex=0)]) == [0, 4]   # acknowledged again ...
    assert db.stats()[0].ingested == 5                                        # ... but not stored again
    db.ingest("s2", [exp(0, vertex=0, robot="r2")])                            # another robot, same bin
    w = db.window("p", 0, 0.5, c_vertex=0, c_velocity=0)
    assert len(w.A) == 2 and db.stats()[0].ingested == 6


def test_database_survives_reopening_and_versions_hyperparameters(tmp_path):
    path = tmp_path / "x.db"
    db = ExperienceDB(path)
    db.ingest("s1", [exp(i, vertex=i) for i in range(20)])
    assert db.save_hyper(fit(1.0), "", 1.0).version == 1
    saved = db.save_hyper(fit(2.0), "", 2.0)
    assert saved == fit(2.0).message(version=2, stamp_s=2.0)
    db.close()
    db = ExperienceDB(path)
    assert db.stats()[0].retained == 20 and db.stats()[0].hyper_version == 2 and db.latest_hyper("p") == saved
    A, G, tiles = db.all_of("p")
    assert A.shape == (20, 9) and G[7, 0] == pytest.approx(0.007)
    assert len(set(tiles.tolist())) == 2   # vertices 0..19 in tiles of 2 * 5 + 1 vertices
    assert [e.seq for _, src, e in db.experiences("p", limit=5)] == [0, 1, 2, 3, 4]


def test_each_nominal_model_keeps_its_own_bins_windows_and_fit_data(tmp_path):
    """A retuned drive lag changes the model the residuals g are measured against: the store keeps each
    model's experiences apart (bins, eviction, windows) and fits on the model of the newest ones."""
    old, new = ActuatorLag(0.0, 0.0, 0.1).model_tag, ActuatorLag(0.0, 0.4, 0.1).model_tag
    assert old == "unicycle-dt100ms-tauv0ms-tauw0ms" and new != old
    db = ExperienceDB(tmp_path / "x.db", BinPolicy(c_bin=3, c_vertex=0, c_velocity=0))
    db.ingest("s1", [dataclasses.replace(exp(i, vertex=0), model=old) for i in range(5)])
    assert db.current_model("p") == old and len(db.all_of("p")[0]) == 3
    db.ingest("s2", [dataclasses.replace(exp(i, vertex=0), model=new) for i in range(2)])
    # the new model's two did not evict the old model's three, and each window sees only its own
    assert len(db.window("p", 0, 0.5, model=old).A) == 3 and len(db.window("p", 0, 0.5, model=new).A) == 2
    assert len(db.window("p", 0, 0.5, model="").A) == 0                         # untagged: none here
    assert len(db.window("p", 0, 0.5).A) == 2                                   # default: the current model
    assert db.current_model("p") == new and len(db.all_of("p")[0]) == 2 and db.count("p", old) == 3
    assert {e.model for _, _, e in db.experiences("p")} == {old, new}
    with pytest.raises(ValueError):
        dataclasses.replace(exp(0, vertex=0), model="tau=0.4 s")                # not a plain name


def test_hyperparameters_are_kept_per_nominal_model_with_versions_counted_per_route(tmp_path):
    db = ExperienceDB(tmp_path / "x.db")
    assert db.save_hyper(fit(1.0), "m-a", 1.0).version == 1
    assert db.save_hyper(fit(2.0), "m-b", 2.0).version == 2
    assert db.save_hyper(fit(3.0), "m-a", 3.0).version == 3
    assert db.save_hyper(fit(4.0, "q"), "", 4.0).version == 1            # another route counts its own
    assert db.latest_hyper("p", "m-a").lml == [3.0] * 3 and db.latest_hyper("p", "m-b").version == 2
    assert db.latest_hyper("p", "m-c") is None and db.latest_hyper("p").model == "m-a"
    assert db.latest_hyper("q", "") == fit(4.0, "q").message(version=1, stamp_s=4.0, model="")


def test_a_schema_1_database_is_migrated_in_place_with_its_experiences_untagged(tmp_path):
    import sqlite3
    path = tmp_path / "v1.db"
    con = sqlite3.connect(path)
    con.executescript("""
        CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
        INSERT INTO meta VALUES ('schema', '1');
        CREATE TABLE experiences (id INTEGER PRIMARY KEY AUTOINCREMENT, path_id TEXT NOT NULL,
            vertex INTEGER NOT NULL, speed_bin INTEGER NOT NULL, robot TEXT NOT NULL, trial INTEGER NOT NULL,
            source TEXT NOT NULL, seq INTEGER NOT NULL, stamp_s REAL NOT NULL, v_cmd_mps REAL NOT NULL,
            a BLOB NOT NULL, g BLOB NOT NULL);
        CREATE INDEX bins ON experiences (path_id, vertex, speed_bin, id);""")
    a, g = np.arange(9, dtype="<f8").tobytes(), np.zeros(3, dtype="<f8").tobytes()
    con.execute("INSERT INTO experiences (path_id, vertex, speed_bin, robot, trial, source, seq, stamp_s, v_cmd_mps, "
                "a, g) VALUES ('p', 0, 2, 'r1', 1, 's1', 0, 0.0, 0.5, ?, ?)", (a, g))
    con.commit()
    con.close()
    db = ExperienceDB(path, BinPolicy(c_vertex=0, c_velocity=0))
    assert db.window("p", 0, 0.5).A.tolist() == [list(range(9))] and db.current_model("p") == ""
    db.ingest("s2", [dataclasses.replace(exp(1, vertex=0), model="unicycle-dt100ms-tauv0ms-tauw0ms")])
    db.close()
    db = ExperienceDB(path)                                          # reopened: schema 3 now, both kept
    assert db.stats()[0].retained == 2 and db.current_model("p") == "unicycle-dt100ms-tauv0ms-tauw0ms"


def test_a_schema_2_database_keeps_its_hyperparameters_untagged(tmp_path):
    import json
    import sqlite3
    path = tmp_path / "v2.db"
    db = ExperienceDB(path)
    db.ingest("s1", [exp(0, vertex=0)])
    db.close()
    con = sqlite3.connect(path)                       # back to how schema 2 stored hyperparameters
    con.executescript("""DROP TABLE hypers;
        CREATE TABLE hypers (path_id TEXT NOT NULL, version INTEGER NOT NULL, stamp_s REAL NOT NULL,
            body TEXT NOT NULL, PRIMARY KEY (path_id, version));
        UPDATE meta SET value='2' WHERE key='schema';""")
    con.execute("INSERT INTO hypers VALUES ('p', 1, 7.0, ?)", (json.dumps(OLD_BODY),))
    con.commit()
    con.close()
    db = ExperienceDB(path)
    assert db.latest_hyper("p", "") == OLD_MSG and db.latest_hyper("p") == OLD_MSG
    assert db.save_hyper(fit(2.0), "m-a", 1.0).version == 2 and db.latest_hyper("p", "m-a").version == 2
    db.close()
    con = sqlite3.connect(path)
    assert con.execute("SELECT value FROM meta WHERE key='schema'").fetchone() == ("3",)
    con.close()


def test_a_schema_3_fit_stored_as_a_dict_loads_as_its_message(tmp_path):
    """Schema 3 files written before fits were typed hold the same body plus "model" (and the column)."""
    import json
    import sqlite3
    path = tmp_path / "x.db"
    ExperienceDB(path).close()
    con = sqlite3.connect(path)
    con.execute("INSERT INTO hypers (path_id, version, stamp_s, body, model) VALUES ('p', 1, 7.0, ?, 'm-a')",
                (json.dumps(dict(OLD_BODY, model="m-a")),))
    con.commit()
    con.close()
    db = ExperienceDB(path)
    assert db.latest_hyper("p", "m-a") == dataclasses.replace(OLD_MSG, model="m-a")
    assert db.save_hyper(fit(2.0), "m-a", 8.0).version == 2


def test_an_export_written_before_model_tags_imports_untagged():
    import msgpack
    from common.codec import encode
    from common.messages import ExperienceBatch
    from deploy.store_cli import _decode_batch
    body = msgpack.unpackb(encode(ExperienceBatch(stamp_s=1.0, robot="r1", source="s1", experiences=[exp(0, 0)])))
    del body["experiences"][0]["model"]                             # as the previous version wrote it
    batch = _decode_batch(msgpack.packb(body))
    assert batch.experiences[0].model == "" and batch.experiences[0].seq == 0
    body["experiences"][0]["a"] = [float("nan")] * 9                 # still checked like any other batch
    with pytest.raises(Exception):
        _decode_batch(msgpack.packb(body))


def test_a_fit_is_a_picklable_value_that_warm_starts_the_next():
    """fit_route runs in a spawned worker: its result crosses back pickled, and the store hands the last
    fit's dimensions to the next one."""
    import pickle
    from services.gp_store.fitting import fit_route
    rng = np.random.default_rng(0)
    A, G = rng.normal(size=(40, 9)), 0.01 * rng.normal(size=(40, 3))
    first = fit_route("p", A, G, None, 0, 100, 0, None, None)
    assert pickle.loads(pickle.dumps(first)) == first
    assert (first.path_id, first.n_used, first.n_total, len(first.dims), len(first.lml)) == ("p", 40, 40, 3, 3)
    again = fit_route("p", A, G, None, 0, 100, 0, list(first.message(version=1, stamp_s=0.0).dims), None)
    # started at the optimum with no restarts: it stays there (up to the optimizer's tolerance)
    assert again.lml == pytest.approx(first.lml, rel=1e-6)
    for d, d0 in zip(again.dims, first.dims):
        assert d.lengthscales == pytest.approx(d0.lengthscales, rel=1e-3)
        assert d.signal_std == pytest.approx(d0.signal_std, rel=1e-3)
