"""`lbc bench scenarios`: the scenario distribution, the figures from summaries, a run end to end."""
import json
import math
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench import scenarios
from bench.scenario_draw import BODY_FACTORS, FAMILIES, draw
from common.robot import PRESETS
from common.scenario import load_scenario, parse_scenario
from deploy.experiment import check_supported
from services.bridge.teach_driver import smooth_waypoints
from tests.conftest import wait_until

SEEDS, PER_SEED = (101, 202), 150
DRAWS = [(seed, i) for seed in SEEDS for i in range(PER_SEED)]


def _dense(path: dict) -> np.ndarray:
    return smooth_waypoints(path["waypoints"], path["corner_radius_m"], path["loop"])


def _arc_length(ref: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref[:, :2], axis=0).T))])


def test_draw_is_deterministic_for_a_seed_and_independent_of_n():
    a = draw(np.random.default_rng([5, 3]), 3)
    assert a == draw(np.random.default_rng([5, 3]), 3)
    assert a != draw(np.random.default_rng([6, 3]), 3)
    few, more = scenarios.scenario_tables(3, 5), scenarios.scenario_tables(6, 5)
    assert more[:len(few)] == few
    (i0, _, lb), (i1, twin1, off) = few[0], few[1]
    assert (i0, i1, twin1) == (0, 0, "learning_off")
    assert off == {**lb, "name": lb["name"] + "-nolearn", "trials": {**lb["trials"], "learning": False}}
    (i2, _, sched), (i3, twin3, rule) = few[2], few[3]       # scenario 1: lb-nmpc-scheduled
    assert (i2, i3, twin3) == (1, 1, "guard_off")
    assert rule == {**sched, "name": sched["name"] + "-thesisrule", "scheduler": {**sched["scheduler"], "guard": False}}
    assert parse_scenario(rule).scheduler.guard is False and parse_scenario(sched).scheduler.guard is True
    assert [t[1] for t in few[4:]] == [""]                    # scenario 2: rc-lb-nmpc, no twin
    (i5, _, ilc), (i6, twin6, ilc_off) = scenarios.scenario_tables(4, 5)[-2:]   # scenario 3: ilc
    assert (i5, i6, twin6) == (3, 3, "learning_off") and ilc["controller"]["algorithm"] == "ilc"
    assert ilc_off == {**ilc, "name": ilc["name"] + "-nolearn", "trials": {**ilc["trials"], "learning": False}}
    # --family keeps the draws of those families only, each the same draw as without it
    only = scenarios.scenario_tables(6, 5, families=["lb-nmpc-scheduled", "rc-lb-nmpc"])
    assert [(i, twin) for i, twin, _ in only] == [(1, ""), (1, "guard_off"), (2, ""), (5, ""), (5, "guard_off")]
    assert only == [t for t in more if t[0] in (1, 2, 5)]


def test_perturbed_robots_change_only_the_hidden_physics_within_their_factors():
    """--robots perturbed: the same draws (route, terrain, speeds, limits) on robots around the presets."""
    plain = scenarios.scenario_tables(8, 77)
    own = scenarios.scenario_tables(8, 77, robots="perturbed")
    assert own == scenarios.scenario_tables(8, 77, robots="perturbed")
    assert [(i, twin) for i, twin, _ in own] == [(i, twin) for i, twin, _ in plain]
    for (_, _, a), (_, _, b) in zip(plain, own):
        assert {k: v for k, v in a.items() if k != "robot"} == {k: v for k, v in b.items() if k != "robot"}
        preset = PRESETS[a["robot"]["preset"]]
        overrides = {k: v for k, v in b["robot"].items() if k != "preset"}
        assert overrides and set(overrides) <= set(BODY_FACTORS)
        for name, value in overrides.items():
            lo, hi = BODY_FACTORS[name]
            ratio = value / getattr(preset, name)
            assert lo - 1e-3 <= ratio <= hi + 1e-3 or (name == "turn_efficiency" and value == 1.0), name
        params = parse_scenario(b).robot.params
        assert (params.v_max_mps, params.w_max_radps, params.steer_max_deg) == \
            (preset.v_max_mps, preset.w_max_radps, preset.steer_max_deg)
        assert params.tau_v_s != preset.tau_v_s and (preset.drive == "ackermann") == (params.tau_steer_s > 0)
    with pytest.raises(ValueError, match="robots"):
        scenarios.scenario_tables(1, 77, robots="custom")


def test_families_and_presets_take_turns():
    """Index i: family i mod 4; every 16 indices hold each (family, preset) pair once."""
    pairs = []
    for i in range(16):
        sc = parse_scenario(draw(np.random.default_rng([9, i]), i))
        fam = FAMILIES[i % 4]
        assert sc.controller.algorithm == fam.algorithm and sc.trials.count == fam.trials
        assert sc.scheduler.enabled == fam.scheduled
        pairs.append((fam.name, sc.robot.preset))
    assert len(set(pairs)) == 16


def _min_radius(preset: str) -> float:
    p = PRESETS[preset]
    steer = 1.5 * p.wheelbase_m / math.tan(math.radians(p.steer_max_deg)) if p.drive == "ackermann" else 0.0
    return max(2.0, steer, 1.2 * p.v_max_mps / p.w_max_radps)


def _check_route(table: dict) -> None:
    path, preset = table["path"], table["robot"]["preset"]
    ref = _dense(path)   # the teach driver's own smoothing: raises on a cusp
    s = _arc_length(ref)
    assert 30.0 <= s[-1] <= 120.0
    assert _min_radius(preset) - 0.01 <= path["corner_radius_m"] <= 8.0
    # no corner sharper than the declared radius (none was cut short by a short leg)
    turn = np.abs(np.angle(np.exp(1j * np.diff(ref[:, 2]))))
    step = np.maximum(np.diff(s), 1e-9)
    assert np.max(turn / step) <= 1.05 / path["corner_radius_m"]
    # points more than 5 m apart along the route stay 2 m apart: it never crosses or grazes itself
    pts, s_pts = ref[::4, :2], s[::4]
    ds = np.abs(s_pts[:, None] - s_pts[None, :])
    if path["loop"]:
        ds = np.minimum(ds, s[-1] - ds)
    gap = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    assert np.all(gap[ds > 5.0] >= 2.0)
    v_max = PRESETS[preset].v_max_mps
    assert 0.3 * v_max - 0.005 <= path["teach_speed_mps"] <= min(1.0, 0.5 * v_max) + 0.005


def _check_terrain(table: dict) -> None:
    ref = _dense(table["path"])
    assert 1 <= len(table["terrain"]) <= 3
    for patch in table["terrain"]:
        assert 3.0 <= patch["radius_m"] <= 8.0
        off_route = np.min(np.hypot(ref[:, 0] - patch["center"][0], ref[:, 1] - patch["center"][1]))
        assert off_route <= 0.5 * patch["radius_m"] + 0.05
        kind = patch["kind"]
        if kind == "side_slope":
            assert 3.0 <= patch["slope_deg"] <= 15.0 and -180.0 <= patch["downhill_deg"] <= 180.0
        elif kind == "slip":
            assert 0.5 <= patch["traction"] <= 0.9
        elif kind == "rough":
            assert 0.05 <= patch["amplitude"] <= 0.2
        else:
            assert kind == "rut" and patch["depth_m"] == 0.0
            assert 0.004 <= patch["growth_m_per_pass"] <= 0.01 and 0.04 <= patch["max_depth_m"] <= 0.08


def _check_rest(table: dict, index: int) -> None:
    sc = parse_scenario(table)
    check_supported(sc)
    assert sc.localization.source == "pose"
    assert 0.005 <= sc.localization.noise_m <= 0.03 and 0.0 <= sc.localization.delay_s <= 0.2
    assert 0.15 <= sc.constraints.lateral_m <= 0.5 and 8.0 <= sc.constraints.heading_deg <= 20.0
    assert table["controller"] == {"algorithm": FAMILIES[index % 4].algorithm}   # every setting at its default
    v_max = sc.robot.params.v_max_mps
    lo, hi = {"lb-nmpc": (0.3, 0.8), "lb-nmpc-scheduled": (0.6, 1.0), "rc-lb-nmpc": (0.7, 1.0),
              "ilc": (0.3, 0.8)}[FAMILIES[index % 4].name]
    speed = sc.scheduler.v_max if sc.scheduler.enabled else sc.trials.speed
    assert lo * v_max - 0.005 <= speed <= hi * v_max + 0.005 and speed <= v_max


@pytest.mark.parametrize("seed", SEEDS)
def test_every_draw_parses_and_stays_within_the_distribution(seed):
    for index in range(PER_SEED):
        table = draw(np.random.default_rng([seed, index]), index)
        try:
            _check_route(table)
            _check_terrain(table)
            _check_rest(table, index)
        except AssertionError as exc:
            raise AssertionError(f"seed {seed}, scenario {index}: {table}") from exc


def test_the_draws_cover_loops_terrain_alone_and_combined():
    tables = [draw(np.random.default_rng([s, i]), i) for s, i in DRAWS]
    loops = sum(t["path"]["loop"] for t in tables)
    assert 0.25 * len(tables) <= loops <= 0.42 * len(tables)     # 1/3 expected (binomial sd 0.027)
    counts = {k: sum(len(t["terrain"]) == k for t in tables) for k in (1, 2, 3)}
    assert min(counts.values()) >= 0.25 * len(tables)
    kinds = {p["kind"] for t in tables for p in t["terrain"]}
    assert kinds == {"side_slope", "slip", "rough", "rut"}


# --- the figures, on hand-made summaries ------------------------------------------------------------
def _job(tmp: Path, name: str, family: str = "lb-nmpc", twin: str = "", planned: int = 3,
         index: int = 0) -> scenarios.Job:
    return scenarios.Job(index=index, family=family, twin=twin, name=name, preset="husky",
                         scenario_file=tmp / f"{name}.toml", run_dir=tmp / name, log_file=tmp / f"{name}.log",
                         planned_trials=planned, lateral_limit_m=0.2, heading_limit_rad=math.radians(10.0))


def _outcome(tmp: Path, job: scenarios.Job, trials: list[tuple], returncode: int = 0, log: str = "",
             wall_s: float = 10.0) -> scenarios.RunOutcome:
    """trials: (max lateral m, max heading deg, travel s, violations, end reason or '' if completed)."""
    job.run_dir.mkdir()
    entries = [{"trial": k, "completed": not end, "max_lateral_m": lat, "rms_lateral_m": lat / 2,
                "max_heading_rad": math.radians(head), "travel_time_s": travel,
                "constraint_violations": viol, "end_reason": end or "end of route"}
               for k, (lat, head, travel, viol, end) in enumerate(trials, start=1)]
    (job.run_dir / "summary.json").write_text(json.dumps({"scenario": job.name, "algorithm": "x", "trials": entries}))
    job.log_file.write_text(log)
    return scenarios.read_outcome(job, returncode, wall_s)


def _hand_made(tmp: Path) -> list[scenarios.RunOutcome]:
    ok = ""
    stop = "controller stopped: outside the corridor"
    return [
        # learning gains 0.5, 0.75, -0.2, 0.3 (median 0.4); travel gains 0.2, 0.3, 0.0, 0.5 (median 0.25)
        _outcome(tmp, _job(tmp, "a"), [(0.2, 5, 50, 0, ok), (0.15, 5, 45, 0, ok), (0.1, 5, 40, 0, ok)]),
        _outcome(tmp, _job(tmp, "b", index=1), [(0.3, 4, 100, 7, ok), (0.2, 4, 90, 0, ok), (0.075, 4, 70, 0, ok)]),
        _outcome(tmp, _job(tmp, "c", index=2), [(0.1, 12, 20, 3, ok), (0.1, 6, 20, 0, ok), (0.12, 6, 20, 0, ok)]),
        _outcome(tmp, _job(tmp, "e", index=3), [(0.1, 2, 80, 0, ok), (0.09, 2, 60, 0, ok), (0.07, 2, 40, 0, ok)]),
        # a self-stop in its last trial: no gains from it
        _outcome(tmp, _job(tmp, "d", index=4), [(0.1, 2, 30, 0, ok), (0.1, 2, 30, 0, ok), (0.05, 2, 12, 0, stop)]),
        # a run that failed after one trial that hit the time limit
        _outcome(tmp, _job(tmp, "f", index=5), [(0.1, 2, 99, 0, "time limit reached")], returncode=1,
                 log="trial 1/3 NOT COMPLETED\nlbc experiment: bridge exited with code 1\n"),
        _outcome(tmp, _job(tmp, "a-off", twin="learning_off"), [(0.2, 5, 50, 0, ok), (0.19, 5, 50, 0, ok),
                                                           (0.18, 5, 50, 0, ok)]),
        # ILC on a route that gets harder every pass: worse than its trial 1, better than without learning
        _outcome(tmp, _job(tmp, "i", family="ilc", planned=2, index=6), [(0.2, 5, 30, 0, ok), (0.3, 5, 30, 0, ok)]),
        _outcome(tmp, _job(tmp, "i-off", family="ilc", twin="learning_off", planned=2, index=6),
                 [(0.2, 5, 30, 0, ok), (0.5, 5, 30, 0, ok)]),
        _outcome(tmp, _job(tmp, "s", family="lb-nmpc-scheduled", planned=2), [(0.1, 3, 60, 0, ok), (0.1, 3, 30, 0, ok)]),
        _outcome(tmp, _job(tmp, "s-rule", family="lb-nmpc-scheduled", twin="guard_off", planned=2),
                 [(0.1, 3, 60, 0, ok), (0.3, 12, 28, 4, ok)]),
    ]


def test_figures_from_hand_made_summaries(tmp_path):
    result = scenarios.bench_result(_hand_made(tmp_path), n=7, seed=3, wall_s=100.0)
    lb = result["lb-nmpc"]
    assert (result["n"], result["seed"]) == (7, 3)
    assert lb["trials"] == 16 and lb["trials_planned"] == 18
    assert lb["completion_rate"] == pytest.approx(14 / 18, abs=1e-4)
    assert lb["violation_trials"] == 2                      # b trial 1, c trial 1
    assert lb["worst_excursion_ratio"] == pytest.approx(1.5)   # b trial 1: 0.3 m in a 0.2 m corridor
    assert lb["learning_gain_median"] == pytest.approx(0.4)
    assert lb["travel_time_gain_median"] == pytest.approx(0.25)
    assert lb["gain_scenarios"] == 4
    assert lb["self_stops"] == [{"scenario": "d", "trial": 3, "reason": "outside the corridor"}]
    assert lb["other_stops"] == [{"scenario": "f", "trial": 1, "reason": "time limit reached"}]
    assert lb["failed_scenarios"] == [{"scenario": "f", "reason": "exit 1: lbc experiment: bridge exited with code 1"}]
    assert [s["scenario"] for s in lb["scenarios"]] == ["a", "b", "c", "e", "d", "f"]
    off = lb["learning_off"]
    assert off["trials"] == 3 and off["completion_rate"] == 1.0
    # only "a" has a learning-off twin: last trial 0.1 m against 0.18 m without learning
    assert [s["last_trial_vs_learning_off"] for s in lb["scenarios"]] == [pytest.approx(1 - 0.1 / 0.18, abs=1e-4)] \
        + [None] * 5
    assert lb["last_trial_vs_learning_off_median"] == pytest.approx(1 - 0.1 / 0.18, abs=1e-4)
    assert off["last_trial_vs_learning_off_median"] is None
    ilc = result["ilc"]
    assert ilc["learning_gain_median"] == pytest.approx(-0.5)
    assert ilc["last_trial_vs_learning_off_median"] == pytest.approx(0.4)
    assert ilc["learning_off"]["learning_gain_median"] == pytest.approx(-1.5)
    assert off["learning_gain_median"] == pytest.approx(0.1) and off["travel_time_gain_median"] == 0.0
    sched = result["lb-nmpc-scheduled"]
    assert sched["travel_time_gain_median"] == pytest.approx(0.5) and sched["learning_gain_median"] == 0.0
    assert sched["worst_excursion_ratio"] == pytest.approx(0.5)   # heading 3 of 10 deg, lateral 0.1 of 0.2 m
    rule = sched["guard_off"]
    assert rule["violation_trials"] == 1 and rule["worst_excursion_ratio"] == pytest.approx(1.5)
    assert rule["travel_time_gain_median"] == pytest.approx(0.5333, abs=1e-4) and rule["trials"] == 2
    for fam in ("rc-lb-nmpc",):
        assert result[fam]["trials"] == 0 and result[fam]["completion_rate"] is None
        assert result[fam]["learning_gain_median"] is None and result[fam]["self_stops"] == []
    travel = (50 + 45 + 40) + (100 + 90 + 70) + 3 * 20 + (80 + 60 + 40) + (30 + 30 + 12) + 99 + 3 * 50 + (60 + 30) \
        + (60 + 28) + 4 * 30
    assert result["sim_speedup"] == pytest.approx(travel / 100.0, abs=1e-3)


def test_travel_against_the_requested_speed_and_calibration_figures(tmp_path):
    """Extensions read from summary.json's own extensions: route length over the setpoint, and the
    share of predictions outside 3 sigma per trial."""
    def run(name, trials):
        job = _job(tmp_path, name, family="rc-lb-nmpc", planned=len(trials))
        job.run_dir.mkdir()
        entries = [{"trial": k, "completed": True, "max_lateral_m": 0.1, "max_heading_rad": 0.05,
                    "travel_time_s": travel, "constraint_violations": 0, "end_reason": "end of route",
                    "route_length_m": 100.0, "speed_setpoint_mps": 2.0, "outside_3sigma_fraction": out,
                    "unanswered_ticks": 2 * (name == "b"),
                    "time_lost_s": {"none": 1.0, "ladder-lateral": travel - 51.0, "place-corridor": 0.0}}
                   for k, (travel, out) in enumerate(trials, start=1)]
        (job.run_dir / "summary.json").write_text(json.dumps({"trials": entries}))
        return scenarios.read_outcome(job, 0, 10.0)
    # ideal 50 s: last trials 55 s (1.1) and 75 s (1.5), median 1.3; outside: 0.004, 0.02, 0.0, 0.012, None
    outcomes = [run("a", [(80.0, 0.004), (55.0, 0.02)]), run("b", [(90.0, 0.0), (80.0, 0.012), (75.0, None)])]
    result = scenarios.bench_result(outcomes, n=2, seed=1, wall_s=10.0)
    assert result["unanswered_ticks"] == 3 * 2     # b's three trials: runs that can differ
    rc = result["rc-lb-nmpc"]
    assert [s["travel_over_ideal"] for s in rc["scenarios"]] == [pytest.approx(1.1), pytest.approx(1.5)]
    assert rc["travel_over_ideal_median"] == pytest.approx(1.3)
    assert rc["outside_3sigma_median"] == pytest.approx(0.008) and rc["outside_3sigma_max"] == pytest.approx(0.02)
    assert rc["outside_3sigma_over_1pct"] == 2
    assert [s["outside_3sigma_max"] for s in rc["scenarios"]] == [pytest.approx(0.02), pytest.approx(0.012)]
    # 380 s of travel: 5 x 1 s with the drive catching up, 380 - 5 x 51 s held by the ladder, nothing by the cap
    assert rc["time_lost_share"] == {"none": pytest.approx(5 / 380, abs=1e-4),
                                     "ladder-lateral": pytest.approx((380 - 5 * 51) / 380, abs=1e-4)}
    (tmp_path / "old").mkdir()
    lb = scenarios.bench_result(_hand_made(tmp_path / "old"), n=7, seed=3, wall_s=100.0)["lb-nmpc"]
    assert lb["travel_over_ideal_median"] is None and lb["outside_3sigma_max"] is None   # older summaries
    assert lb["outside_3sigma_over_1pct"] == 0 and lb["time_lost_share"] == {}


# --- end to end ---------------------------------------------------------------------------------------
@pytest.mark.integration
@pytest.mark.slow
def test_bench_scenarios_runs_end_to_end(tmp_path, capsys):
    out = tmp_path / "bench"
    assert scenarios.main(["--n", "2", "--trials", "2", "--route-m", "15", "20", "--jobs", "2",
                           "--out", str(out)]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result == json.loads((out / "bench.json").read_text())
    assert result["overrides"] == {"trials": 2, "route_m": [15.0, 20.0]}
    for fam, runs in (("lb-nmpc", 1), ("lb-nmpc-scheduled", 1), ("rc-lb-nmpc", 0), ("ilc", 0)):
        stats = result[fam]
        assert stats["trials_planned"] == 2 * runs and len(stats["scenarios"]) == runs
        assert stats["failed_scenarios"] == []
    assert result["lb-nmpc"]["learning_off"]["trials"] == 2
    assert result["lb-nmpc-scheduled"]["guard_off"]["trials"] == 2
    assert result["sim_speedup"] > 0 and result["unanswered_ticks"] == 0
    # every run can be replayed: its scenario file loads and its summary is there
    names = [s["scenario"] for fam in ("lb-nmpc", "lb-nmpc-scheduled") for s in result[fam]["scenarios"]]
    names += [s["scenario"] for s in result["lb-nmpc"]["learning_off"]["scenarios"]]
    names += [s["scenario"] for s in result["lb-nmpc-scheduled"]["guard_off"]["scenarios"]]
    for name in names:
        assert load_scenario(out / f"{name}.toml").name == name
        assert len(json.loads((out / name / "summary.json").read_text())["trials"]) == 2


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            children.setdefault(ppid, []).append(int(entry.name))
    found, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            found.add(c)
            todo.append(c)
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.integration
def test_sigterm_stops_every_run_and_its_services(tmp_path):
    out = tmp_path / "bench"
    proc = subprocess.Popen([sys.executable, "-m", "bench.scenarios", "--n", "1", "--jobs", "2", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        def both_up() -> bool:
            logs = list(out.glob("*.log")) if out.exists() else []
            return len(logs) == 2 and all("services up" in p.read_text(errors="replace") for p in logs)
        wait_until(both_up, 120.0, "both runs' services")
        family = _descendants(proc.pid)
        assert len(family) >= 2 * 6    # per run: the experiment, its router and four services
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert not [pid for pid in family if _alive(pid)]
    for log in out.glob("*.log"):
        assert "interrupted; services stopped" in log.read_text(errors="replace")
