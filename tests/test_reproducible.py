"""One seed, one run: with the lockstep clock, two runs of a learning scenario give the same summary.json
except for the wall-clock values (deploy/reproducible.py); the snapshot of the store a lockstep
controller predicts a trial from (common/store_client.py); the helpers that compare summaries."""
from __future__ import annotations

import io
import json
import signal
import sqlite3

import numpy as np
import pytest

from common import keys
from common.bus import query_one
from common.messages import ExperienceWindow, HyperMsg
from common.store_client import ExperienceOutbox, WindowCache
from deploy.compare import compare_dirs, describe
from deploy.experiment import run_experiment
from deploy.reproducible import TRIAL_WALL_CLOCK_KEYS, differences, reproducible_part
from tests.conftest import wait_until
from tests.ros2_topics import check_standard_topics
from tests.test_store_service import N_VERTICES, rig  # noqa: F401  (the store fixture)

MODEL = "unicycle-test"

# RC-LB-NMPC across a sandy side slope, as the main job but on a ~20 m route and three trials: trial 1 has
# no model, trials 2 and 3 predict from the GP fitted on the trials before, with eviction under way
SIDESLOPE = {
    "name": "repro", "seed": 3, "robot": {"preset": "husky"},
    "path": {"waypoints": [[0, 0], [7, 0], [13, 4], [19, 4]], "teach_speed_mps": 0.5},
    "terrain": [{"kind": "side_slope", "center": [10.0, 2.0], "radius_m": 4.0, "slope_deg": 12.0,
                 "downhill_deg": 90.0},
                {"kind": "slip", "center": [10.0, 2.0], "radius_m": 3.0, "traction": 0.7}],
    "localization": {"source": "pose", "noise_m": 0.01, "delay_s": 0.1},
    "controller": {"algorithm": "rc-lb-nmpc", "nmpc": {"crab_reference": True}},
    "constraints": {"lateral_m": 0.25, "heading_deg": 15.0},
    "trials": {"count": 3, "speed": 1.0},
}


@pytest.mark.integration
@pytest.mark.slow
def test_two_lockstep_runs_of_one_seed_give_the_same_summary(tmp_path, scenario_file):
    path = scenario_file(SIDESLOPE)
    first = run_experiment(path, tmp_path / "a", progress_stream=io.StringIO())
    second = run_experiment(path, tmp_path / "b", progress_stream=io.StringIO())
    trials = first["trials"]
    # it learned: every trial completed and was followed by a fit, so trials 2 and 3 drove on a model
    assert len(trials) == 3 and all(t["completed"] for t in trials), trials
    assert all(t["experiences_fit_retained"] for t in trials), trials
    on_disk = [json.loads((tmp_path / d / "summary.json").read_text()) for d in ("a", "b")]
    compared = compare_dirs(tmp_path / "a", tmp_path / "b")       # what `lbc experiment compare` says
    assert compared.identical, "\n".join(describe(compared) + _warnings(tmp_path / "a") + _warnings(tmp_path / "b"))
    assert on_disk[0] == json.loads(json.dumps(first)) and on_disk[1] == json.loads(json.dumps(second))
    # RC-LB-NMPC's prediction and its 3-sigma band as ROS 2 markers, beside the standard topics
    topics = check_standard_topics(tmp_path / "a" / "run.mcap", "husky")
    horizons = topics["/controller/horizon"]
    assert horizons and all(m.markers[0].ns == "prediction" for m in horizons)
    banded = [m for m in horizons if len(m.markers) == 3]
    assert len(banded) > 0.9 * len(horizons)
    left, right = banded[-1].markers[1].points, banded[-1].markers[2].points
    assert len(left) == len(right) == len(banded[-1].markers[0].points) > 5


def _warnings(out_dir) -> list[str]:
    """What the services of a run warned about: where a run that differs went its own way."""
    return [f"{log.name}: {line}" for log in sorted((out_dir / "logs").glob("*.log"))
            for line in log.read_text(errors="replace").splitlines() if "WARNING" in line or "ERROR" in line]


def test_the_comparison_leaves_out_exactly_the_wall_clock_values():
    trial = {"trial": 1, "max_lateral_m": 0.1, "control_steps": 200, "solve_ms_p50": 3.0, "solve_ms_p99": 7.0,
             "wall_time_s": 2.0}
    a = {"scenario": "s", "identified_model": {"stamp_s": 1.0, "tau_v_s": 0.2}, "trials": [trial]}
    b = {"scenario": "s", "identified_model": {"stamp_s": 2.0, "tau_v_s": 0.2},
         "trials": [dict(trial, solve_ms_p50=4.0, solve_ms_p99=9.0, wall_time_s=3.0)]}
    assert differences(reproducible_part(a), reproducible_part(b)) == []
    assert {"solve_ms_p50", "solve_ms_p99", "wall_time_s"} <= TRIAL_WALL_CLOCK_KEYS
    assert "control_steps" not in TRIAL_WALL_CLOCK_KEYS and "max_lateral_m" not in TRIAL_WALL_CLOCK_KEYS
    # anything else that differs is named by its path
    c = dict(b, identified_model={"stamp_s": 2.0, "tau_v_s": 0.3}, trials=[dict(trial, control_steps=201)])
    assert differences(reproducible_part(a), reproducible_part(c)) == [
        ".identified_model.tau_v_s: 0.2 != 0.3", ".trials[0].control_steps: 200 != 201"]
    assert differences({"trials": [1]}, {"trials": [1, 2]}) == [".trials: 1 != 2 entries"]
    assert differences({"x": 1}, {"y": 1}) == [".x: only in the first", ".y: only in the second"]
    # the input is not changed
    assert a["trials"][0]["wall_time_s"] == 2.0 and a["identified_model"]["stamp_s"] == 1.0


def _drive(outbox: ExperienceOutbox, trial: int, speeds: list[float]) -> None:
    """One pass per speed over vertices 0-59, three experiences per vertex: bins overflow c_bin (4) and evict."""
    for v_cmd in speeds:
        for i in range(180):
            outbox.add(stamp_s=0.1 * i, trial=trial, path_id="dur", vertex=i // 3, v_cmd_mps=v_cmd,
                       a=[float(trial), 0.001 * i, 0.0, v_cmd, 0.0, v_cmd, 0.0, v_cmd, 0.0], g=[0.0, 0.01 * trial, 0.0])
    assert outbox.wait_acked(30)


def _store_window(rig, vertex: int, speed: float) -> np.ndarray:
    """The store's answer to a window query, as rows [a, g] in a canonical order."""
    w = query_one(rig.node.session, f"{keys.store_window('dur')}?vertex={vertex}&speed={speed}&model={MODEL}",
                  ExperienceWindow)
    return _rows(np.frombuffer(w.a_f64).reshape(-1, 9), np.frombuffer(w.g_f64).reshape(-1, 3))


def _rows(A: np.ndarray, G: np.ndarray) -> np.ndarray:
    rows = np.hstack([A, G])
    return rows[np.lexsort(rows.T[::-1])]


@pytest.mark.integration
def test_a_snapshot_is_the_store_at_prepare_and_holds_until_the_next(rig):
    _drive(ExperienceOutbox(rig.node, "r1", model="other-model"), 1, [0.5])   # another nominal model's
    outbox = ExperienceOutbox(rig.node, "r1", model=MODEL)
    _drive(outbox, 1, [0.5, 0.6, 1.0])
    snap_cache = WindowCache(rig.node.session, model=MODEL, snapshot=True)
    live_cache = WindowCache(rig.node.session, model=MODEL, lookahead_vertices=0)  # prefetch mode, for comparison
    try:
        live_cache.set_route("dur", N_VERTICES)
        snap = snap_cache.set_route("dur", N_VERTICES)
        with sqlite3.connect(rig.store_cfg.db_path) as db:     # what the store retains, read from its file
            (retained,) = db.execute("SELECT COUNT(*) FROM experiences WHERE model=?", (MODEL,)).fetchone()
        assert snap.complete and snap.experiences == retained > 0 and snap.hyper_version == 0, snap
        before = {}
        for vertex, speed in ((0, 0.5), (20, 0.55), (59, 1.0), (30, 0.75), (200, 0.5)):
            local = snap_cache.local(vertex, speed)
            assert local.missing_bins == 0
            assert np.array_equal(_rows(local.A, local.G), _store_window(rig, vertex, speed))
            # in the order a prefetching cache gives, so a GP is the same in either mode
            live_cache.set_position(vertex, speed)
            wait_until(lambda: live_cache.local(vertex, speed).missing_bins == 0, 10, "the prefetch of a window")
            prefetched = live_cache.local(vertex, speed)
            assert np.array_equal(local.A, prefetched.A) and np.array_equal(local.G, prefetched.G)
            before[(vertex, speed)] = local
        assert len(before[(20, 0.55)].A) > 0 and len(before[(200, 0.5)].A) == 0

        # mid-trial: new experiences evict old ones and new hyperparameters are published ...
        _drive(outbox, 2, [0.5])
        hyper = query_one(rig.node.session, keys.store_fit("dur"), HyperMsg, timeout_s=300)
        wait_until(lambda: live_cache.hyper is not None and live_cache.hyper.version == hyper.version, 10,
                   "the hyperparameters to reach a prefetching cache")
        assert not np.array_equal(_store_window(rig, 20, 0.55), _rows(before[(20, 0.55)].A, before[(20, 0.55)].G))
        # ... and the snapshot does not see them
        assert snap_cache.hyper is None
        for (vertex, speed), local in before.items():
            assert np.array_equal(snap_cache.local(vertex, speed).A, local.A)

        # the next prepare takes the store as it is now
        snap = snap_cache.set_route("dur", N_VERTICES)
        assert snap.complete and snap.hyper_version == hyper.version and snap_cache.hyper == hyper
        local = snap_cache.local(20, 0.55)
        assert np.array_equal(_rows(local.A, local.G), _store_window(rig, 20, 0.55)) and np.any(local.A[:, 0] == 2.0)

        # no store: the snapshot says so, and the cache prefetches as in realtime
        rig.launcher.kill("gp_store", signal.SIGKILL)
        snap_cache.timeout = 0.5
        snap = snap_cache.set_route("dur", N_VERTICES)
        assert not snap.complete and "no store answered" in snap.error and "prefetching" in snap.describe()
        assert snap_cache.local(20, 0.55).missing_bins > 0
    finally:
        snap_cache.close()
        live_cache.close()
