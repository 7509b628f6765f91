"""`lbc experiment compare`: two runs side by side, judged by what one seed in lockstep must reproduce."""
import json
import subprocess
import sys
from pathlib import Path

from deploy.cli import main

ROOT = Path(__file__).resolve().parents[1]


def summary(name, *trials):
    return {"scenario": name, "algorithm": "ilc", "identified_model": {"stamp_s": 12.5, "tau_w_s": 0.31},
            "trials": [dict(trial=k + 1, completed=True, max_lateral_m=lat, travel_time_s=30.0 + k, end_reason="end of route",
                            constraint_violations=viol, control_steps=300 + k, solve_ms_p50=2.0, wall_time_s=4.0)
                       for k, (lat, viol) in enumerate(trials)]}


def write(run_dir, data):
    run_dir.mkdir(parents=True)
    (run_dir / "summary.json").write_text(json.dumps(data))


def last_json(capsys):
    out = capsys.readouterr().out.strip().splitlines()
    return out[:-1], json.loads(out[-1])


def test_runs_that_differ_only_in_their_wall_clock_values_are_the_same_run(tmp_path, capsys):
    a = summary("s1", (0.10, 0), (0.05, 0))
    b = json.loads(json.dumps(a))
    b["identified_model"]["stamp_s"] = 99.0
    for t in b["trials"]:
        t["solve_ms_p50"], t["wall_time_s"] = 7.5, 9.0
    write(tmp_path / "a" / "x", a)
    write(tmp_path / "b" / "y", b)
    assert main(["experiment", "compare", str(tmp_path / "a" / "x"), str(tmp_path / "b" / "y")]) == 0
    lines, out = last_json(capsys)
    assert lines == ["x: same run"] and out["pairs"] == 1 and out["identical"] == 1 and out["different"] == []


def test_bench_directories_pair_by_name_and_show_each_trial_where_they_differ(tmp_path, capsys):
    write(tmp_path / "a" / "s1", summary("s1", (0.10, 0), (0.05, 0)))
    write(tmp_path / "b" / "s1", summary("s1", (0.10, 0), (0.05, 0)))
    write(tmp_path / "a" / "s2", summary("s2", (0.30, 12), (0.20, 0)))
    write(tmp_path / "b" / "s2", summary("s2", (0.30, 12), (0.41, 7)))
    write(tmp_path / "a" / "s3", summary("s3", (0.1, 0)))
    (tmp_path / "b" / "notes").mkdir()                      # no summary: not a run
    assert main(["experiment", "compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 1
    lines, out = last_json(capsys)
    assert out["pairs"] == 2 and out["identical"] == 1 and out["different"] == ["s2"]
    assert out["first_differences"]["s2"] == ".trials[1].constraint_violations: 0 != 7"
    assert out["only_in_a"] == ["s3"] and out["only_in_b"] == []
    assert out["a"]["violation_trials"] == 1 and out["b"]["violation_trials"] == 2 and out["b"]["max_lateral_m"] == 0.41
    assert "s1: same run" in lines and "s3: only in A" in lines
    row = next(line for line in lines if line.strip().startswith("2 "))
    assert "0.200 -> 0.410" in row and "0 -> 7" in row


def test_a_directory_without_a_run_is_a_clear_error(tmp_path, capsys):
    write(tmp_path / "a", summary("s1", (0.1, 0)))
    (tmp_path / "empty").mkdir()
    assert main(["experiment", "compare", str(tmp_path / "a"), str(tmp_path / "empty")]) == 2
    assert "holds no summary.json" in capsys.readouterr().err
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "summary.json").write_text('{"scenario": "x"}')
    assert main(["experiment", "compare", str(tmp_path / "a"), str(tmp_path / "bad")]) == 2
    assert "not an experiment summary" in capsys.readouterr().err


def test_keys_left_out_of_the_judgement(tmp_path, capsys):
    """A change that only rewords each trial's note: different as written, the same run without the note."""
    a = summary("s1", (0.10, 0), (0.05, 0))
    b = json.loads(json.dumps(a))
    for t in b["trials"]:
        t["controller_note"] = "turn drive: no acceleration limit met"
    write(tmp_path / "a", a)
    write(tmp_path / "b", b)
    assert main(["experiment", "compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 1
    capsys.readouterr()
    assert main(["experiment", "compare", "--ignore", "controller_note", str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    assert last_json(capsys)[1]["identical"] == 1


def test_a_reader_that_stops_early_ends_the_command_quietly(tmp_path):
    """`lbc experiment compare A B | head -1`: the pipe closes under the command, which ends without a traceback."""
    for side in ("a", "b"):
        for k in range(400):                       # more lines than a pipe's buffer holds
            write(tmp_path / side / f"s{k:03d}", summary(f"s{k:03d}", (0.1 if side == "a" else 0.2, 0)))
    cmd = [sys.executable, "-m", "deploy.cli", "experiment", "compare", str(tmp_path / "a"), str(tmp_path / "b")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    assert proc.stdout.readline()                  # the first line, then the reader goes away
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141 and "Traceback" not in err and "BrokenPipe" not in err, err
