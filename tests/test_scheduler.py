"""The speed scheduler (thesis eq. 4.2-4.5) on small schedules worked by hand."""
import math

import numpy as np
import pytest

from services.scheduler.core import (DECREASE, INCREASE, KEEP, PassCollector, SchedulerParams, VertexPasses,
                                     a_priori_limits, acceleration_limits, decide, failure_speeds, initial_schedule,
                                     next_schedule, prune_isolated, vertex_distances)

P = SchedulerParams(lambda_L=0.15, lambda_H=10.0, lambda_omega=1.0, lambda_feat=30.0, lambda_db=1.1,
                    gamma1=0.2, gamma2=0.24)


def passes(e_lat, e_head_deg, w, feat=None):
    n = len(e_lat)
    return VertexPasses(np.array(e_lat, dtype=float), np.radians(np.array(e_head_deg, dtype=float)),
                        np.array(w, dtype=float), np.full(n, np.nan) if feat is None else np.array(feat, dtype=float))


def test_eq_4_2_rules_with_the_deadband():
    # vertex: 0 all good | 1 lateral in the deadband (0.15 < 0.16 < 0.165) | 2 lateral beyond it
    #         3 heading beyond 11 deg | 4 omega beyond 1.1 | 5 heading in its deadband | 6 not passed
    pa = passes([0.05, 0.16, 0.17, 0.0, 0.0, 0.0, np.nan], [1, 1, 1, 11.5, 1, 10.5, np.nan],
                [0.1, 0.1, 0.1, 0.1, 1.2, 0.1, np.nan])
    d, notes = decide(pa, P)
    assert d.tolist() == [INCREASE, KEEP, DECREASE, DECREASE, DECREASE, KEEP, KEEP]
    assert any("feature criterion is skipped" in n for n in notes) and any("1 vertices not passed" in n for n in notes)


def test_eq_4_2_feature_criterion_when_counts_exist():
    # 40 features: fine; 29: below 30 but above 30/1.1 = 27.3 -> deadband; 25: decrease; NaN: no data here
    pa = passes([0.0] * 4, [0.0] * 4, [0.0] * 4, feat=[40, 29, 25, np.nan])
    d, notes = decide(pa, P)
    assert d.tolist() == [INCREASE, KEEP, DECREASE, INCREASE]
    assert not any("feature" in n for n in notes)


def test_isolated_increases_are_pruned():
    s = np.arange(12) * 0.5                       # vertices 0.5 m apart
    d = np.array([1, 0, 1, 1, 0, 1, 1, 1, 1, 0, -1, 1])
    # runs: [0] 0.5 m, [2,3] 1.0 m, [5..8] 2.0 m, [11] 0.5 m; keep runs of >= 2.0 m
    out = prune_isolated(d, s, 2.0)
    assert out.tolist() == [0, 0, 0, 0, 0, 1, 1, 1, 1, 0, -1, 0]
    assert prune_isolated(d, s, 0.0).tolist() == d.tolist()


def test_eq_4_3_start_and_end_limits():
    s = np.arange(0, 30.5, 0.5)
    lim = a_priori_limits(s, SchedulerParams(v_max=2.0, v_start=0.4, start_m=5.0, v_end=0.6, end_m=3.0))
    assert np.all(lim[s <= 5.0] == 0.4) and np.all(lim[(s > 5.0) & (s < 27.0)] == 2.0) and np.all(lim[s >= 27.0] == 0.6)


def test_eq_4_4_forward_and_backward_sweeps():
    xy = np.column_stack([np.arange(5.0), np.zeros(5)])   # 1 m between vertices (eq. 4.5)
    d = vertex_distances(xy)
    assert d.tolist() == [1.0] * 4
    v = acceleration_limits(np.array([0.5, 2.0, 2.0, 2.0, 0.5]), d, a_max=0.5, a_min=-0.5)
    # forward: sqrt(0.25 + 1) = 1.118, sqrt(1.25 + 1) = 1.5, sqrt(2.25 + 1) = 1.803
    # backward from 0.5 at the end: sqrt(0.25 + 1) = 1.118 at vertex 3; vertex 2 stays 1.5
    np.testing.assert_allclose(v, [0.5, math.sqrt(1.25), 1.5, math.sqrt(1.25), 0.5])
    dv2 = np.diff(v ** 2)
    assert np.all(dv2 <= 2 * 0.5 * d + 1e-12) and np.all(-dv2 <= 2 * 0.5 * d + 1e-12)
    # a gentle deceleration limit reaches far back: 2.0 -> 0.4 at |a| = 0.05 needs 38.4 m
    v = acceleration_limits(np.array([2.0] * 40 + [0.4]), np.ones(40), a_max=0.2, a_min=-0.05)
    assert v[-2] == pytest.approx(math.sqrt(0.16 + 0.1)) and v[2] == pytest.approx(math.sqrt(0.16 + 3.8))
    assert v[1] == 2.0 and v[0] == 2.0


def test_a_whole_trial_to_trial_update():
    n = 21
    s = np.arange(n) * 0.5
    xy = np.column_stack([s, np.zeros(n)])
    p = SchedulerParams(v_init=0.5, v_max=2.0, gamma1=0.2, gamma2=0.24, v_start=0.4, start_m=1.0, v_end=0.4,
                        end_m=1.0, a_max=10.0, a_min=-10.0, prune_min_m=1.0)
    first = initial_schedule(s, xy, p)
    assert first.schedule[0] == 0.4 and first.schedule[10] == 0.5 and first.schedule[-1] == 0.4
    e_lat = np.full(n, 0.05)
    e_lat[12] = 0.3                                  # one bad vertex
    prop = next_schedule(first.schedule, passes(e_lat, [1] * n, [0.2] * n), s, xy, p)
    assert prop.schedule[12] == pytest.approx(0.5 - 0.24)
    assert prop.schedule[10] == pytest.approx(0.7)   # raised by gamma1
    assert prop.schedule[0] == 0.4 and prop.schedule[-1] == 0.4   # start/end limits hold


def test_use_all_trials_never_raises_a_vertex_to_where_it_failed_before():
    n = 10
    s = np.arange(n) * 1.0
    xy = np.column_stack([s, np.zeros(n)])
    p = SchedulerParams(v_init=1.0, v_max=3.0, gamma1=0.2, gamma2=0.2, v_start=3.0, start_m=0.0, v_end=3.0,
                        end_m=0.0, a_max=10.0, a_min=-10.0, prune_min_m=0.0, use_all_trials=True)
    sched_fast = np.full(n, 1.2)
    bad = passes([0.05] * 5 + [0.3] + [0.05] * 4, [1] * n, [0.1] * n)   # failed at vertex 5 at 1.2 m/s
    failed = failure_speeds([(sched_fast, bad)], p)
    assert failed[5] == 1.2 and np.isinf(failed[0])
    good = passes([0.05] * n, [1] * n, [0.1] * n)
    prop = next_schedule(np.full(n, 1.0), good, s, xy, p, failed_at=failed)
    assert prop.schedule[5] == pytest.approx(1.0) and prop.schedule[0] == pytest.approx(1.2)
    plain = next_schedule(np.full(n, 1.0), good, s, xy, SchedulerParams(**{**p.__dict__, "use_all_trials": False}))
    assert plain.schedule[5] == pytest.approx(1.2)


def test_pass_collector_keeps_the_worst_of_each_vertex():
    c = PassCollector(3)
    c.add(1, 0.05, -0.02, 0.3, 40)
    c.add(1, -0.08, 0.01, -0.1, 35)
    c.add(5, 1.0, 1.0, 1.0, 1)                     # off the route: ignored
    p = c.passes
    assert p.e_lat_m[1] == pytest.approx(0.08) and p.e_head_rad[1] == pytest.approx(0.02)
    assert p.w_cmd_radps[1] == pytest.approx(0.3) and p.features[1] == 35
    assert p.seen.tolist() == [False, True, False]


def test_the_database_keeps_schedules_as_messages_and_loads_bodies_written_as_dicts(tmp_path):
    """Schedules and passes survive reopening; a schedule body as the scheduler wrote it before schedules
    were typed (a dict in the node's key order) loads as the same message."""
    import json
    import sqlite3

    from common.messages import SpeedSchedule
    from services.scheduler.db import ScheduleDB

    path = tmp_path / "sched.db"
    ScheduleDB(path).close()
    old = {"stamp_s": 5.0, "path_id": "r", "based_on_robot": "", "based_on_trial": 0, "v_mps": [0.4, 0.5, 0.4],
           "decisions": [0, 0, 0], "notes": ["trial 1 at v_init = 0.5 m/s"], "version": 1}
    con = sqlite3.connect(path)
    con.execute("INSERT INTO schedules VALUES ('r', 1, 5.0, '', 0, ?)", (json.dumps(old),))
    con.commit()
    con.close()
    db = ScheduleDB(path)
    first = SpeedSchedule(**old)
    assert db.latest("r") == first and db.based_on("r", "", 0) == first and db.latest("other") is None
    s = np.array([0.0, 0.25, 0.5])
    pa = passes([0.05, np.nan, 0.3], [1, 1, 1], [0.1, 0.1, 0.1])
    proposal = next_schedule(np.array(first.v_mps), pa, s, np.column_stack([s, np.zeros(3)]), P)
    db.save_passes("r", "r1", 1, first.version, pa)
    second = db.add_schedule("r", proposal, "r1", 1, 6.0)
    assert second == SpeedSchedule(stamp_s=6.0, path_id="r", version=2, based_on_robot="r1", based_on_trial=1,
                                   v_mps=proposal.schedule.tolist(), decisions=proposal.decisions.tolist(),
                                   notes=proposal.notes)
    db.close()
    db = ScheduleDB(path)
    assert db.latest("r") == second and db.based_on("r", "r1", 1) == second
    [(v, kept)] = db.history("r")
    assert v.tolist() == first.v_mps and np.array_equal(kept.e_lat_m, pa.e_lat_m, equal_nan=True)
    db.close()
