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


# --- the guard (services/scheduler/core.py, module doc G1-G7), worked by hand -----------------------------
from services.scheduler.core import (GuardCaps, apply_guard, growing_errors, growth_cap, guard_caps,  # noqa: E402
                                     guard_limits, neighbourhoods, plan, worst_nearby)


def straight(n: int, spacing: float = 1.0):
    s = np.arange(n) * spacing
    return s, np.column_stack([s, np.zeros(n)])


def no_limits(**kw) -> SchedulerParams:
    """Eq. 4.3-4.4 out of the way (no start/end segments, no acceleration limits, no pruning)."""
    base = dict(v_init=0.5, v_max=3.0, gamma1=0.2, gamma2=0.24, v_start=3.0, start_m=0.0, v_end=3.0, end_m=0.0,
                a_max=100.0, a_min=-100.0, prune_min_m=0.0)
    return SchedulerParams(**{**base, **kw})


def test_guard_limits_are_a_share_of_eq_4_2_thresholds_and_of_the_robots_turn_rate_limit():
    p = SchedulerParams(lambda_L=0.5, lambda_H=20.0, lambda_omega=1.0, guard_share=0.8, w_max=1.2)
    # turn rate: min(lambda_omega 1.0, 0.8 * 1.2) = 0.96
    np.testing.assert_allclose(guard_limits(p), [0.4, 0.8 * math.radians(20.0), 0.96])
    assert guard_limits(SchedulerParams(lambda_omega=1.0, w_max=2.0))[2] == pytest.approx(1.0)   # lambda_omega
    assert guard_limits(SchedulerParams(lambda_omega=1.5))[2] == pytest.approx(1.5)   # w_max unknown


def test_proportional_growth_caps_the_turn_that_overshot():
    """The turn of issue 18: 0.86 rad/s at 0.7 m/s, limit 1.2 rad/s. Eq. 4.2 (0.86 < lambda_omega 1.0)
    raises it to 0.9 m/s, where w = 0.86 * 0.9 / 0.7 = 1.106 rad/s; the guard allows w <= 0.8 * 1.2 = 0.96,
    reached at v = 0.96 * 0.7 / 0.86 = 0.7814 m/s."""
    cap = growth_cap(np.array([[0.7]]), np.array([[0.86]]), 0.96, 0.1)
    assert cap[0] == pytest.approx(0.96 * 0.7 / 0.86) == pytest.approx(0.78140, abs=1e-5)
    # a robot limited to 1.0 rad/s: the bound is 0.8 * 1.0, no raise above 0.8 * 0.7 / 0.86 = 0.651
    assert growth_cap(np.array([[0.7]]), np.array([[0.86]]), 0.8, 0.1)[0] == pytest.approx(0.65116, abs=1e-5)
    # nothing seen, or a zero turn rate: nothing to cap
    assert np.isinf(growth_cap(np.array([[np.nan]]), np.array([[np.nan]]), 0.8, 0.1)[0])
    assert np.isinf(growth_cap(np.array([[0.7]]), np.array([[0.0]]), 0.8, 0.1)[0])


def test_a_line_rising_faster_than_proportional_caps_lower():
    """Lateral errors 0.05, 0.09, 0.17 m at 0.5, 0.7, 0.9 m/s, bound 0.24 m. Proportional from the latest:
    0.24 * 0.9 / 0.17 = 1.2706. Least squares: mean v 0.7, mean e 0.10333; S_vv = 0.08,
    S_ve = (-0.2)(-0.05333) + 0.2 * 0.06667 = 0.024, slope 0.3; e = 0.24 at 0.7 + 0.13667 / 0.3 = 1.1556."""
    V = np.array([[0.5], [0.7], [0.9]])
    E = np.array([[0.05], [0.09], [0.17]])
    assert growth_cap(V, E, 0.24, 0.1)[0] == pytest.approx(0.7 + (0.24 - 0.31 / 3) / 0.3) == pytest.approx(1.15556,
                                                                                                      abs=1e-5)
    assert growth_cap(V[2:], E[2:], 0.24, 0.1)[0] == pytest.approx(0.24 * 0.9 / 0.17)
    # speeds closer than min_spread (0.9, 0.95): no line, proportional from the latest (0.24 * 0.95 / 0.2)
    assert growth_cap(np.array([[0.9], [0.95]]), np.array([[0.1], [0.2]]), 0.24, 0.1)[0] == pytest.approx(1.14)
    # errors that fell with speed (learning): no line either; 0.24 * 0.7 / 0.1
    assert growth_cap(np.array([[0.5], [0.7]]), np.array([[0.2], [0.1]]), 0.24, 0.1)[0] == pytest.approx(1.68)
    # a vertex missed in the latest trial: its latest pass is the one before (0.24 * 0.7 / 0.12)
    assert growth_cap(np.array([[0.7], [np.nan]]), np.array([[0.12], [np.nan]]), 0.24, 0.1)[0] == pytest.approx(1.4)


def test_the_worst_pass_nearby_and_its_speed():
    s = np.arange(5.0)                                 # 1 m apart, radius 1 m: a vertex and its two neighbours
    lo, hi = neighbourhoods(s, 1.0)
    assert lo.tolist() == [0, 0, 1, 2, 3] and hi.tolist() == [2, 3, 4, 5, 5]
    # |value| / speed: 0.1, 0.25, 0.0667, -, 0.06; vertex 3 sees 0.2 at 3 m/s (0.0667) over 0.3 at 5 (0.06)
    worst, at_v = worst_nearby(np.array([0.1, -0.5, 0.2, np.nan, 0.3]), np.array([1.0, 2.0, 3.0, 4.0, 5.0]), lo, hi)
    assert worst.tolist() == [0.5, 0.5, 0.5, 0.2, 0.3] and at_v.tolist() == [2.0, 2.0, 2.0, 3.0, 5.0]
    worst, _ = worst_nearby(np.array([0.1, np.nan, np.nan, np.nan, np.nan]), np.ones(5), *neighbourhoods(s, 0.0))
    assert worst[0] == 0.1 and np.all(np.isnan(worst[1:]))


def test_the_guard_only_lowers_increases_and_never_below_the_last_speed():
    prev = np.array([0.7, 0.7, 0.7, 0.7])
    dec = np.array([INCREASE, INCREASE, INCREASE, DECREASE])
    sugg = np.array([0.9, 0.9, 0.9, 0.46])
    caps = GuardCaps(np.array([0.78, 0.5, np.inf, 0.1]), np.array([2, 0, -1, 0]))
    out, note = apply_guard(sugg, prev, dec, caps)
    np.testing.assert_allclose(out, [0.78, 0.7, 0.9, 0.46])
    assert note == "guard: 2 increases capped (lateral error 1, turn rate 1), 1 of them kept at their speed"
    out, note = apply_guard(sugg, prev, dec, GuardCaps(np.full(4, np.inf), np.full(4, -1)))
    assert out.tolist() == sugg.tolist() and note == ""


def passes_v(e_lat, e_head_deg, w, v):
    pa = passes(e_lat, e_head_deg, w)
    pa.v_mps = np.array(v, dtype=float)
    return pa


def test_a_sharp_turn_is_held_where_eq_4_2_alone_raises_it():
    """21 vertices 1 m apart at 0.7 m/s; a turn at vertex 10 took 0.86 rad/s, 0.2 elsewhere; lambda_omega
    1.0, w_max 1.2. Eq. 4.2 raises every vertex to 0.9. The guard: bound min(1.0, 0.8 * 1.2) = 0.96 rad/s;
    within 3 m of the turn the cap is 0.96 * 0.7 / 0.86 = 0.7814; beyond, 0.96 * 0.7 / 0.2 = 3.36."""
    n = 21
    s, xy = straight(n)
    w = np.full(n, 0.2)
    w[10] = 0.86
    pa = passes_v([0.02] * n, [1.0] * n, w, [0.7] * n)
    prev = np.full(n, 0.7)
    history = [(prev, pa)]
    on = plan(prev, pa, history, s, xy, no_limits(w_max=1.2))
    expect = np.where(np.abs(s - 10) <= 3.0, 0.96 * 0.7 / 0.86, 0.9)
    np.testing.assert_allclose(on.schedule, expect)
    assert on.decisions.tolist() == [INCREASE] * n        # eq. 4.2's decisions, reported as they were
    assert on.caps.by[10] == 2 and on.caps.v_cap[10] == pytest.approx(0.78140, abs=1e-5)
    assert "guard: 7 increases capped (turn rate 7), 0 of them kept at their speed" in on.notes
    # a robot limited to 1.0 rad/s: bound 0.8, cap 0.8 * 0.7 / 0.86 = 0.651 < 0.7: kept at 0.7
    held = plan(prev, pa, history, s, xy, no_limits(w_max=1.0))
    np.testing.assert_allclose(held.schedule, np.where(np.abs(s - 10) <= 3.0, 0.7, 0.9))
    assert "guard: 7 increases capped (turn rate 7), 7 of them kept at their speed" in held.notes
    off = plan(prev, pa, history, s, xy, no_limits(w_max=1.2, guard=False))
    np.testing.assert_allclose(off.schedule, 0.9)
    assert off.caps is None and not any("guard" in n_ for n_ in off.notes)


def test_with_the_guard_off_plan_is_the_thesis_rule():
    """Eq. 4.2-4.5 unchanged: the worked trial-to-trial update of test_a_whole_trial_to_trial_update."""
    n = 21
    s = np.arange(n) * 0.5
    xy = np.column_stack([s, np.zeros(n)])
    p = SchedulerParams(v_init=0.5, v_max=2.0, gamma1=0.2, gamma2=0.24, v_start=0.4, start_m=1.0, v_end=0.4,
                        end_m=1.0, a_max=10.0, a_min=-10.0, prune_min_m=1.0, guard=False, w_max=1.2)
    first = initial_schedule(s, xy, p)
    e_lat = np.full(n, 0.05)
    e_lat[12] = 0.3
    pa = passes_v(e_lat, [1] * n, [0.9] * n, first.schedule)   # turn rates eq. 4.2 lets through
    prop = plan(first.schedule, pa, [(first.schedule, pa)], s, xy, p)
    thesis = next_schedule(first.schedule, pa, s, xy, p)
    np.testing.assert_array_equal(prop.schedule, thesis.schedule)
    assert prop.schedule[12] == pytest.approx(0.26) and prop.schedule[10] == pytest.approx(0.7)
    # the guard on, bound min(1.0, 0.8 * 1.2) = 0.96 rad/s: within 3 m of the start and end segments (s <= 4,
    # s >= 6) the 0.9 rad/s passed at 0.4 m/s reach it at 0.96 * 0.4 / 0.9 = 0.427 m/s; within 3 m of
    # vertex 12 its 0.3 m reach 0.8 * 0.15 = 0.12 m at 0.2 m/s; both caps lie below v_init 0.5, which is
    # their floor (G4): every increase is kept at its speed
    guarded = plan(first.schedule, pa, [(first.schedule, pa)], s, xy, SchedulerParams(**{**p.__dict__, "guard": True}))
    np.testing.assert_allclose(guarded.schedule, np.where(np.arange(n) == 12, 0.26, first.schedule))
    assert guarded.caps.v_cap[4] == pytest.approx(0.5) and guarded.caps.v_cap[10] == pytest.approx(0.5)
    assert guarded.caps.by[4] == 2 and guarded.caps.by[10] == 0


def test_a_vertex_lowered_to_a_crawl_rises_again_as_under_the_thesis_rule():
    """Seed 6143's Husky on a 14.7 deg side slope: eq. 4.2 lowered vertices to 0.05 m/s, where the
    lateral error was 0.10 m (lambda_L 0.15: met, so eq. 4.2 raises them to 0.25). Proportional growth from
    0.05 m/s would cap them at 0.12 * 0.05 / 0.10 = 0.06 and hold them at the crawl for good (those runs:
    lateral errors 0.14-0.38 m at the crawl, 175 steps beyond the limit). G4: the pass counts as at 0.5
    (v_init): cap max(0.5, 0.12 * 0.5 / 0.10) = 0.6, and the thesis rule's 0.25 stands. A pass at 0.6 m/s
    with the same 0.10 m is still capped at 0.12 * 0.6 / 0.10 = 0.72 < 0.8."""
    n = 11
    s, xy = straight(n)
    prev = np.full(n, 0.05)
    crawl = passes_v([0.10] * n, [1.0] * n, [0.05] * n, prev)
    out = plan(prev, crawl, [(prev, crawl)], s, xy, no_limits(lambda_L=0.15, w_max=1.2))
    np.testing.assert_allclose(out.schedule, 0.25)
    np.testing.assert_allclose(out.caps.v_cap, 0.6)
    fast = np.full(n, 0.6)
    at_speed = passes_v([0.10] * n, [1.0] * n, [0.05] * n, fast)
    np.testing.assert_allclose(plan(fast, at_speed, [(fast, at_speed)], s, xy,
                                    no_limits(lambda_L=0.15, w_max=1.2)).schedule, 0.72)


def test_the_guard_reads_the_latest_trials_of_the_history():
    """Lateral errors 0.05, 0.09, 0.17 m at 0.5, 0.7, 0.9 m/s everywhere (lambda_L 0.3, bound 0.24): the
    line over the three trials caps at 1.1556 (test above), so 0.9 + 0.2 = 1.1 passes. With guard_trials 2,
    the line through (0.7, 0.09), (0.9, 0.17) has slope 0.4 and reaches 0.24 at 0.9 + 0.07 / 0.4 = 1.075."""
    n = 11
    s, xy = straight(n)
    hist = [(np.full(n, v), passes_v([e] * n, [1.0] * n, [0.1] * n, [v] * n))
            for v, e in ((0.5, 0.05), (0.7, 0.09), (0.9, 0.17))]
    prev, last = hist[-1]
    p = no_limits(lambda_L=0.3, w_max=1.2)
    np.testing.assert_allclose(plan(prev, last, hist, s, xy, p).schedule, 1.1)
    np.testing.assert_allclose(plan(prev, last, hist, s, xy, SchedulerParams(**{**p.__dict__, "guard_trials": 2})
                                    ).schedule, 1.075)
    caps = guard_caps(hist, s, p)
    assert np.all(caps.by == 0) and caps.v_cap[5] == pytest.approx(1.15556, abs=1e-5)


def test_the_guard_never_raises_a_vertex_again_to_where_it_failed():
    """G7, bench seed 1931's MATS s93349841 in small: 11 vertices 1 m apart; trial 1 at 0.9 m/s swung
    12 deg at vertex 5 (beyond lambda_H 10 * lambda_db 1.1 = 11 deg), trials 2-4 at 0.7 m/s took 2 deg
    everywhere. Eq. 4.2 raises every vertex to 0.9; G2 over the latest three trials (all at 0.7, 2 deg)
    caps nothing (0.8 * 10 deg is reached at 2.8 m/s). G7 keeps vertex 5 and those within guard_radius_m
    (3 m: vertices 2-8) below the 0.9 it failed at: max(0.7, 0.9 - gamma2) = 0.7. With the guard off, eq.
    4.2 alone: 0.9 everywhere; with use_all_trials alone, vertex 5 only. A failure at v_init (0.5 m/s)
    caps nothing (G4)."""
    n = 11
    s, xy = straight(n)
    head = [2.0] * n
    head[5] = 12.0
    hist = [(np.full(n, 0.9), passes_v([0.01] * n, head, [0.1] * n, [0.9] * n))]
    hist += [(np.full(n, 0.7), passes_v([0.01] * n, [2.0] * n, [0.1] * n, [0.7] * n)) for _ in range(3)]
    prev, last = hist[-1]
    p = no_limits(lambda_L=0.3, lambda_H=10.0, w_max=1.2)
    on = plan(prev, last, hist, s, xy, p)
    np.testing.assert_allclose(on.schedule, np.where(abs(np.arange(n) - 5) <= 3, 0.7, 0.9))
    assert "7 increases capped below speeds that failed in earlier trials" in on.notes
    np.testing.assert_allclose(on.caps.v_cap, 2.8)     # G2: 2 deg * v / 0.7 reaches 8 deg at 2.8 m/s
    off = plan(prev, last, hist, s, xy, SchedulerParams(**{**p.__dict__, "guard": False}))
    np.testing.assert_allclose(off.schedule, 0.9)
    alone = plan(prev, last, hist, s, xy, SchedulerParams(**{**p.__dict__, "guard": False, "use_all_trials": True}))
    np.testing.assert_allclose(alone.schedule, np.where(np.arange(n) == 5, 0.7, 0.9))
    at_v_init = [(np.full(n, 0.5), passes_v([0.01] * n, head, [0.1] * n, [0.5] * n))] + hist[1:]
    np.testing.assert_allclose(plan(prev, last, at_v_init, s, xy, p).schedule, 0.9)


def test_a_failure_at_v_init_is_remembered_once_a_slower_pass_met_the_criteria():
    """G7 at trial 1's speed, bench seed 2029's Husky s1330754404 in small (a side slope whose heading error
    grows with speed): 11 vertices 1 m apart, trial 1 at v_init 0.5 m/s swung 12 deg at vertex 5 (beyond
    lambda_H 10 * lambda_db 1.1 = 11 deg), trial 2 at 0.26 m/s took 6 deg everywhere. Eq. 4.2 raises every
    vertex to 0.46 m/s; G2 caps nothing (both passes count at v_init, G4: no line; 8 deg is reached at
    0.5 * 8 / 6 = 0.67 m/s). G7: vertex 5 failed at 0.5 and was met at 0.26, so vertices 2-8 stay within
    gamma2 below 0.5: max(0.26, 0.5 - 0.24) = 0.26. Where trial 2 ran faster than the failure (0.7 m/s, the
    test above), the failure at v_init still caps nothing, and a failure below v_init (an end segment's 0.4
    m/s) never does."""
    n = 11
    s, xy = straight(n)
    head = [6.0] * n
    head[5] = 12.0
    hist = [(np.full(n, 0.5), passes_v([0.01] * n, head, [0.1] * n, [0.5] * n)),
            (np.full(n, 0.26), passes_v([0.01] * n, [6.0] * n, [0.1] * n, [0.26] * n))]
    prev, last = hist[-1]
    p = no_limits(lambda_L=0.3, lambda_H=10.0, w_max=1.2)
    on = plan(prev, last, hist, s, xy, p)
    np.testing.assert_allclose(on.schedule, np.where(abs(np.arange(n) - 5) <= 3, 0.26, 0.46))
    assert "7 increases capped below speeds that failed in earlier trials" in on.notes
    off = plan(prev, last, hist, s, xy, SchedulerParams(**{**p.__dict__, "guard": False}))
    np.testing.assert_allclose(off.schedule, 0.46)
    # the thesis's use_all_trials alone caps only a raise that reaches the failed speed
    alone = plan(prev, last, hist, s, xy, SchedulerParams(**{**p.__dict__, "guard": False, "use_all_trials": True}))
    np.testing.assert_allclose(alone.schedule, 0.46)
    below = [(np.full(n, 0.4), hist[0][1]), hist[1]]
    np.testing.assert_allclose(plan(prev, last, below, s, xy, p).schedule, 0.46)


def test_a_vertex_goes_back_to_a_faster_pass_where_slowing_made_it_worse():
    """G5b, bench seed 3607's Grizzly s584978763 in small (a side slope and slip that slide the robot per
    second): 11 vertices 1 m apart, lambda_L 0.15 m (deadband to 0.165 m). Trial 1 at 0.5 m/s: 0.17 m
    everywhere (share 1.13, eq. 4.2 lowers by gamma2 to 0.26); trial 2 at 0.26 m/s: 0.30 m (share 2.0). Eq.
    4.2 lowers again; G5 withholds it (1.13 * (1 - 0.5 (1 - 0.26 / 0.5)) = 0.86 < 2.0), which alone keeps
    0.26; G5b puts it back at trial 1's 0.5 m/s, the faster pass with the smaller share. The plain rule:
    0.26 - 0.24, at its 0.05 m/s floor."""
    n = 11
    s, xy = straight(n)
    hist = [(np.full(n, v), passes_v([e] * n, [1.0] * n, [0.1] * n, [v] * n)) for v, e in ((0.5, 0.17), (0.26, 0.30))]
    prev, last = hist[-1]
    p = no_limits(lambda_L=0.15, lambda_H=10.0, w_max=1.2)
    on = plan(prev, last, hist, s, xy, p)
    np.testing.assert_allclose(on.schedule, 0.5)
    assert "guard: 11 vertices back at an earlier pass's speed where slowing down made the tracking error larger" \
        in on.notes
    np.testing.assert_allclose(plan(prev, last, hist, s, xy, SchedulerParams(**{**p.__dict__, "guard": False})
                                    ).schedule, 0.05)
    # where the slower pass did better (0.12 m: share 0.8), nothing goes back
    better = [hist[0], (np.full(n, 0.26), passes_v([0.12] * n, [1.0] * n, [0.1] * n, [0.26] * n))]
    assert np.all(plan(better[-1][0], better[-1][1], better, s, xy, p).schedule < 0.5)


def test_pass_speeds_are_collected_and_stored(tmp_path):
    import json
    import sqlite3

    from services.scheduler.core import pass_speeds
    from services.scheduler.db import ScheduleDB

    c = PassCollector(3)
    c.add(0, 0.01, 0.0, 0.1, v_cmd=0.5)
    c.add(0, 0.01, 0.0, 0.1, v_cmd=0.7)
    c.add(1, 0.01, 0.0, 0.1)
    assert c.passes.v_mps[0] == 0.7 and np.isnan(c.passes.v_mps[1])
    # the commanded speed where recorded, the scheduled one elsewhere
    assert pass_speeds(np.array([0.4, 0.4, 0.4]), c.passes).tolist() == [0.7, 0.4, 0.4]
    db = ScheduleDB(tmp_path / "s.db")
    s = np.array([0.0, 1.0, 2.0])
    first = db.add_schedule("r", initial_schedule(s, np.column_stack([s, np.zeros(3)]), SchedulerParams()), "", 0, 1.0)
    db.save_passes("r", "r1", 1, first.version, c.passes)
    db.save_passes("r", "r1", 0, first.version, passes([0.1] * 3, [1] * 3, [0.1] * 3))   # recorded later
    [(_, kept), (_, later)] = db.history("r")
    assert np.array_equal(kept.v_mps, c.passes.v_mps, equal_nan=True) and later.e_lat_m[0] == 0.1
    db.close()
    # a body written before the pass speeds were kept loads with none
    con = sqlite3.connect(tmp_path / "s.db")
    body = json.dumps({"e_lat_m": [0.1, None, 0.2], "e_head_rad": [0, 0, 0], "w_cmd_radps": [0, 0, 0],
                       "features": [None] * 3})
    con.execute("UPDATE passes SET body=? WHERE trial=1", (body,))
    con.commit()
    con.close()
    db = ScheduleDB(tmp_path / "s.db")
    old = db.history("r")[0][1]
    assert np.all(np.isnan(old.v_mps)) and np.isnan(old.e_lat_m[1])
    db.close()


@pytest.mark.parametrize("kw, match", [({"w_max": 0.0}, "w_max"), ({"guard_share": 0.0}, "guard_share"),
                                       ({"guard_share": 1.2}, "guard_share"), ({"guard_radius_m": -1.0}, "guard"),
                                       ({"guard_trials": 0}, "guard_trials")])
def test_guard_settings_are_checked(kw, match):
    with pytest.raises(ValueError, match=match):
        SchedulerParams(**kw)


def test_the_deployment_gives_the_scheduler_the_robots_turn_rate_limit():
    from common.scenario import parse_scenario
    from deploy.configs import service_configs

    base = {"name": "g", "robot": {"preset": "grizzly"}, "path": {"waypoints": [[0, 0], [10, 0]]}}
    cfg = service_configs(parse_scenario({**base, "scheduler": {"enabled": True}}), "/tmp/unused")
    assert cfg["scheduler"].params.w_max == 1.2 and cfg["scheduler"].params.guard
    # a w_max written in [scheduler] is a ceiling under the robot's own, like v_max
    for written, used in ((0.9, 0.9), (2.0, 1.2)):
        sc = parse_scenario({**base, "scheduler": {"enabled": True, "w_max": written, "guard": False}})
        params = service_configs(sc, "/tmp/unused")["scheduler"].params
        assert params.w_max == used and not params.guard


def test_a_decrease_that_did_not_help_is_not_repeated():
    """A perturbed Grizzly on an 8.5 deg side slope (bench scenarios --seed 7741 --robots perturbed,
    scenario 5): 0.34 m at 0.5 m/s, then 0.32 m at 0.26 m/s (lambda_L 0.15; the deadband ends at 0.165).
    Eq. 4.2 lowers the slope again, to 0.02 -> the 0.05 floor, where that run crawled 200 s a trial with
    errors up to 0.64 m. G5: proportional fall 1 - 0.26 / 0.5 = 48 %, half of it asked (guard_help 0.5):
    the error must fall below 0.34 (1 - 0.24) = 0.2584 m; 0.32 m did not: withheld at 0.26, and still in
    the trial after, driven at 0.26 again (the faster pass of trial 1 still counts). Had the error fallen
    to 0.25 m, or had the turn rate broken its criterion (1.2 > 1.1 rad/s), it is lowered as eq. 4.2 says;
    with one trial, or the guard off, nothing is withheld."""
    n = 11
    s, xy = straight(n)
    first, second = np.full(n, 0.5), np.full(n, 0.26)
    at_first = passes_v([0.34] * n, [2.0] * n, [0.3] * n, first)
    p = no_limits(lambda_L=0.15, lambda_H=10.0, lambda_omega=1.0, w_max=1.2)

    def after(e_lat, w=0.3, params=p, history_of=2, repeat=False):
        at_second = passes_v([e_lat] * n, [2.0] * n, [w] * n, second)
        history = [(first, at_first), (second, at_second)] + ([(second, at_second)] if repeat else [])
        return plan(second, at_second, history[-history_of:] if history_of == 1 else history, s, xy, params)

    held = after(0.32)
    np.testing.assert_allclose(held.schedule, 0.26)
    assert held.decisions.tolist() == [DECREASE] * n       # eq. 4.2's decisions, reported as they were
    assert "guard: 11 decreases withheld where slowing down did not cut the tracking error" in held.notes
    np.testing.assert_allclose(after(0.32, repeat=True).schedule, 0.26)
    np.testing.assert_allclose(after(0.25).schedule, 0.05)
    np.testing.assert_allclose(after(0.32, w=1.2).schedule, 0.05)
    np.testing.assert_allclose(after(0.32, history_of=1).schedule, 0.05)
    np.testing.assert_allclose(after(0.32, params=no_limits(lambda_L=0.15, w_max=1.2, guard=False)).schedule, 0.05)
    with pytest.raises(ValueError, match="guard_help"):
        no_limits(guard_help=0.0)


def test_errors_growing_towards_the_limit_at_one_speed_lower_the_vertex():
    """G6, worked by hand. lambda_L 0.15 m, 11 vertices passed at 1.3 m/s in two trials. Lateral errors
    0.10 then 0.13 m: shares 0.667 and 0.867 (>= guard_share 0.8); the speed explains none of the growth,
    d = 0.2, and the next pass is predicted at 1.067 of the limit: lowered by gamma2 to 1.06. Eq. 4.2 alone
    raises them to 1.5 (0.13 < 0.15); without G6 the guard's cap (0.12 * 1.3 / 0.13 = 1.2 < 1.3) keeps 1.3.
    When trial 1 ran at 1.0 m/s, proportional growth to 1.3 m/s explains the 0.13 m (d = 0): kept at 1.3.
    Below guard_share (0.06 -> 0.11 m, share 0.733, predicted 1.07): not lowered, capped at 0.12 * 1.3 / 0.11.
    Near the limit (0.1485 m) the increases' cap, below the lowered speed, does not undo the lowering.
    A first pass faster (1.6 m/s, 0.10 m) makes the growth d = 0.867 - 0.667 * 1.3 / 1.6 = 0.325: lowered,
    unless G5 holds it back (slowed by 0.3 m/s, the error rose): then it stays at 1.3. From 0.6 m/s it goes
    to v_init, 0.5, not 0.36; at 0.45 m/s (below v_init) it stays at 0.45, where eq. 4.2 raises it to 0.65
    and G4's floor on the caps would let it reach 0.5."""
    n = 11
    s, xy = straight(n)
    p = no_limits(lambda_L=0.15, lambda_H=10.0, w_max=1.2)

    def after(e0, e1, v0=1.3, params=p, v1=1.3):
        first, second = np.full(n, v0), np.full(n, v1)
        history = [(first, passes_v([e0] * n, [1.0] * n, [0.3] * n, first)),
                   (second, passes_v([e1] * n, [1.0] * n, [0.3] * n, second))]
        return plan(second, history[-1][1], history, s, xy, params)

    lowered = after(0.10, 0.13)
    np.testing.assert_allclose(lowered.schedule, 1.06)
    assert lowered.decisions.tolist() == [INCREASE] * n      # eq. 4.2's decisions, reported as they were
    assert "guard: 11 vertices lowered where the errors grew towards the limit from trial to trial" in lowered.notes
    np.testing.assert_allclose(after(0.10, 0.13, params=no_limits(lambda_L=0.15, w_max=1.2, guard=False)).schedule, 1.5)
    np.testing.assert_allclose(after(0.10, 0.13, v0=1.0).schedule, 1.3)
    # 0.1485 m (share 0.99): the guard's cap for an increase, 0.12 * 1.3 / 0.1485 = 1.05, lies below the
    # lowered 1.06; the lowering stands (the cap, which keeps an increase at its speed, is not applied to it)
    np.testing.assert_allclose(after(0.10, 0.1485).schedule, 1.06)
    np.testing.assert_allclose(after(0.06, 0.11).schedule, 0.12 * 1.3 / 0.11)
    assert growing_errors([(np.full(n, 1.6), passes_v([0.10] * n, [1.0] * n, [0.3] * n, [1.6] * n)),
                           (np.full(n, 1.3), passes_v([0.13] * n, [1.0] * n, [0.3] * n, [1.3] * n))], s, p).all()
    held = after(0.10, 0.13, v0=1.6)
    np.testing.assert_allclose(held.schedule, 1.3)
    assert not any("vertices lowered" in n_ for n_ in held.notes)       # held back by G5: not said to be lowered
    floored = after(0.10, 0.13, v0=0.6, v1=0.6)
    np.testing.assert_allclose(floored.schedule, 0.5)                                   # v_init, not 0.36
    assert "guard: 11 vertices whose errors grew kept at v_init, or at their speed below it" in floored.notes
    kept = after(0.10, 0.13, v0=0.45, v1=0.45)
    np.testing.assert_allclose(kept.schedule, 0.45)
    assert "guard: 11 vertices whose errors grew kept at v_init, or at their speed below it" in kept.notes


def test_an_ackermann_turning_at_its_limit_against_a_slope_is_not_slowed_below_v_init():
    """G8, worked by hand. A MATS (kappa_max = tan 30 deg / 1.9 m = 0.3039 1/m; at the limit from 0.9 of
    it, 0.2735 1/m) on 11 vertices of straight route 1 m apart, 0.25 m off at every vertex (beyond
    lambda_L 0.15 and its deadband: eq. 4.2 lowers all by gamma2). At 0.5 m/s it turned at 0.15 rad/s
    (0.30 1/m, at the limit) at vertices 4-6, 0.05 elsewhere: vertices 1-9 lie within 3 m of those and
    stay at 0.5 (bench seed 9973's MATS s1638813658 slid 0.51 m at the 0.26 m/s eq. 4.2 chose); 0 and 10
    go to 0.26. From 0.9 m/s (0.27 rad/s, 0.30 1/m) eq. 4.2's 0.66 stands, above v_init; from 0.6 m/s
    (0.18 rad/s) it stops at v_init, 0.5, not 0.36. Not at the limit (0.13 rad/s at 0.5 m/s: 0.26 1/m),
    on a route that itself turns at 0.2 1/m (> kappa_max / 2), on a robot with no curvature limit, with
    no route curvature given, or with the guard off: 0.26 everywhere, as eq. 4.2 says."""
    n = 11
    s, xy = straight(n)
    k_max = math.tan(math.radians(30.0)) / 1.9
    p = no_limits(lambda_L=0.15, lambda_H=10.0, lambda_omega=1.0, w_max=1.0, kappa_max=k_max)
    straight_k = np.zeros(n)

    def after(v, w_peak, params=p, route_kappa=straight_k):
        sched = np.full(n, v)
        w = np.full(n, 0.05)
        w[4:7] = w_peak
        pa = passes_v([0.25] * n, [2.0] * n, w, sched)
        return plan(sched, pa, [(sched, pa)], s, xy, params, route_kappa)

    held = after(0.5, 0.15)
    np.testing.assert_allclose(held.schedule, [0.26] + [0.5] * 9 + [0.26])
    assert held.decisions.tolist() == [DECREASE] * n
    assert ("guard: 9 vertices not lowered below v_init where the robot turned at its curvature limit against "
            "a disturbance") in held.notes
    np.testing.assert_allclose(after(0.9, 0.27).schedule, 0.66)
    np.testing.assert_allclose(after(0.6, 0.18).schedule, [0.36] + [0.5] * 9 + [0.36])
    np.testing.assert_allclose(after(0.5, 0.13).schedule, 0.26)
    np.testing.assert_allclose(after(0.5, 0.15, route_kappa=np.full(n, 0.2)).schedule, 0.26)
    np.testing.assert_allclose(after(0.5, 0.15, route_kappa=None).schedule, 0.26)
    np.testing.assert_allclose(after(0.5, 0.15, params=no_limits(lambda_L=0.15, w_max=1.0)).schedule, 0.26)
    np.testing.assert_allclose(after(0.5, 0.15, params=no_limits(lambda_L=0.15, kappa_max=k_max, guard=False))
                               .schedule, 0.26)
    with pytest.raises(ValueError, match="kappa_max"):
        no_limits(kappa_max=0.0)


def test_the_deployment_gives_the_scheduler_an_ackermanns_curvature_limit():
    from common.scenario import parse_scenario
    from deploy.configs import service_configs

    def params(preset, **kw):
        sc = parse_scenario({"name": "k", "robot": {"preset": preset}, "path": {"waypoints": [[0, 0], [10, 0]]},
                             "scheduler": {"enabled": True, **kw}})
        return service_configs(sc, "/tmp/unused")["scheduler"].params

    assert params("mats").kappa_max == pytest.approx(math.tan(math.radians(30.0)) / 1.9)
    assert params("grizzly").kappa_max is None
    assert params("mats", kappa_max=0.1).kappa_max == 0.1 and params("mats", kappa_max=2.0).kappa_max < 0.31
    assert params("husky", kappa_max=0.5).kappa_max == 0.5
