"""`lbc bench scenarios --n N --seed S [--out DIR] [--jobs J]`: how well the learning controllers
generalize, on N random scenarios run through the real services.

Scenario i is drawn by `bench.scenario_draw.draw(default_rng([S, i]), i)` (the distribution is
documented there): algorithm families in turn, lb-nmpc (fixed speed, 5 trials), lb-nmpc-scheduled
(8 trials), rc-lb-nmpc (high requested speed, 5 trials), ilc (6 trials). Every lb-nmpc and ilc scenario
also runs a second time with `[trials] learning = false` (same seed, same world; ILC then keeps its
feedforward at zero): the learning-off comparison; every lb-nmpc-scheduled one a second time with `[scheduler] guard = false`: the thesis's
rule (eq. 4.2-4.5) without the guard against overshooting increases. Each run is its own `lbc experiment run SCENARIO --out RUN` child process (its own router
on a free port and its own services), `--jobs` of them at a time; a finished run prints one line on
stderr. `--out DIR` keeps, per run, `DIR/<name>.toml` (replay: `lbc experiment run DIR/<name>.toml
--out NEW`), `DIR/<name>/` (summary.json, report.html, run.mcap, logs), `DIR/<name>.log` (its console)
and at the end `DIR/bench.json`; without `--out` all of it lives in a temporary directory.

Figures per family, from each run's summary.json (trial k of a run: its k-th entry):
- `trials`: trials run; `trials_planned`: scenarios x trials per scenario;
- `completion_rate`: completed trials / planned trials (a run that failed leaves its missing trials
  uncompleted); `violation_trials`: trials with any truth corridor violation;
- `worst_excursion_ratio`: max over trials of max(max_lateral_m / corridor half-width,
  max_heading_rad / heading limit);
- `learning_gain_median`: median over scenarios of 1 - max_lateral_m(last trial) / max_lateral_m(trial 1),
  `travel_time_gain_median` the same of travel_time_s; only scenarios whose first and last trials
  both completed count (`gain_scenarios` of them); 0.5 means half the error (or time) of trial 1;
- `travel_over_ideal_median`: median over those scenarios of the last trial's travel time / (route
  length / its speed setpoint): how near the requested speed learning got (a trial 1 already at it leaves
  no travel-time gain to make; a scheduled trial's setpoint is its schedule's mean speed, so there the
  ratio also holds the schedule's own slow stretches);
- `outside_3sigma_median`, `outside_3sigma_max`, `outside_3sigma_over_1pct`: over trials of laws with a
  predicted spread, the share of steps whose truth at 1 s left the predicted 3 sigma (summary.json's
  `outside_3sigma_fraction`), and the trials above 1 %;
- `self_stops`: trials that ended because the controller stopped itself, with its reason;
  `other_stops`: trials that did not complete for another reason (time limit, ...);
  `failed_scenarios`: runs that exited with an error, with its last console line;
- `last_trial_vs_learning_off_median` (lb-nmpc, ilc): median over scenarios of 1 - max_lateral_m of
  the last trial / that of the learning-off run's last trial: what learning did where the route itself
  changes from trial to trial (ruts deepen every pass), which the gain over trial 1 mixes in;
- `time_lost_share`: by cause, the seconds summary.json's `time_lost_s` counts over every trial, as a share
  of their travel time: what held the robots below the asked speeds (RC-LB-NMPC's speed ladder by the check
  that failed, the place cap, the turn cap, the end of the route; "none": the drive catching up);
- `scenarios`: the same per scenario; lb-nmpc and ilc add `learning_off`, these figures for their
  learning-off runs, and lb-nmpc-scheduled `guard_off`, for its runs under the plain thesis rule.
`--family NAME` (repeatable) runs only the draws of those families, scenario i being the same draw as
without it; the JSON lists them under `families` (null: all) and the others' figures are empty.
`--robots perturbed` draws each robot's hidden physics (lags, acceleration limits, slip, slope response,
noise) around its preset, the rest of every draw unchanged: robots nobody tuned for; the JSON says
which under `robots` ("presets" or "perturbed").
`sim_speedup` = simulated seconds of all repeat trials (summary.json travel_time_s; teach passes and
fits not counted) / wall seconds of the whole benchmark (`--jobs` runs at a time).
`unanswered_ticks`: repeat ticks the lockstep bridge stepped without their answer, over all runs (0
unless a machine was too loaded to answer within `sim.lockstep_timeout_s`: those runs can differ).
The last stdout line is the JSON object. Ctrl-C (or SIGTERM) stops every run cleanly, services
included. `--trials` and `--route-m` shrink the benchmark for smoke tests only: the JSON then says
so under `overrides`, and its figures are not the benchmark's.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import queue
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Callable, Sequence

import numpy as np

from bench.report import run_and_print
from bench.scenario_draw import BOUNDS, FAMILIES, ROBOTS, Bounds, draw, family_of
from common.config import dump_toml
from common.lifecycle import PARENT_ENV
from common.messages import CONTROLLER_STOPPED
from common.scenario import parse_scenario
from common.typecheck import to_dict

CHILD_STOP_S = 60.0       # a run given SIGTERM stops its services and exits well within this
SELF_STOP = f"{CONTROLLER_STOPPED}: "   # how a trial the controller ended is worded (summary.json end_reason)
# the comparison runs per family, each under its own key in the family's figures (module docstring)
TWINS = {"lb-nmpc": ("learning_off",), "lb-nmpc-scheduled": ("guard_off",), "ilc": ("learning_off",)}


@dataclass(frozen=True, kw_only=True)
class Job:
    """One experiment run of the benchmark."""
    index: int
    family: str
    twin: str              # "" for the benchmark's own run, else which comparison (TWINS)
    name: str
    preset: str
    scenario_file: FsPath
    run_dir: FsPath
    log_file: FsPath
    planned_trials: int
    lateral_limit_m: float
    heading_limit_rad: float


@dataclass(frozen=True, kw_only=True)
class TrialResult:
    """The public summary.json keys of one trial that the benchmark reads."""
    trial: int
    completed: bool
    max_lateral_m: float
    max_heading_rad: float
    travel_time_s: float
    constraint_violations: int
    end_reason: str
    ideal_travel_s: float | None = None     # route length / the trial's speed setpoint (its mean if scheduled)
    outside_3sigma: float | None = None     # outside_3sigma_fraction (laws with a predicted spread)
    unanswered_ticks: int = 0               # stepped by the lockstep bridge without their answer
    time_lost_s: dict[str, float] = field(default_factory=dict)   # summary.json's, by cause

    @classmethod
    def from_summary(cls, entry: dict) -> "TrialResult":
        # end_reason, route_length_m, speed_setpoint_mps, outside_3sigma_fraction are summary.json's
        # extensions: older summaries lack them
        length, speed, outside = (entry.get(k) for k in ("route_length_m", "speed_setpoint_mps",
                                                           "outside_3sigma_fraction"))
        return cls(trial=int(entry["trial"]), completed=bool(entry["completed"]),
                   max_lateral_m=float(entry["max_lateral_m"]), max_heading_rad=float(entry["max_heading_rad"]),
                   travel_time_s=float(entry["travel_time_s"]),
                   constraint_violations=int(entry["constraint_violations"]),
                   end_reason=str(entry.get("end_reason", "")),
                   ideal_travel_s=float(length) / float(speed) if length and speed and speed > 0 else None,
                   outside_3sigma=None if outside is None else float(outside),
                   unanswered_ticks=int(entry.get("unanswered_ticks") or 0),
                   time_lost_s={str(k): float(v) for k, v in (entry.get("time_lost_s") or {}).items()})


@dataclass(frozen=True, kw_only=True)
class RunOutcome:
    job: Job
    trials: tuple[TrialResult, ...]
    error: str          # "" when the run exited normally
    wall_s: float


@dataclass(frozen=True, kw_only=True)
class Stop:
    scenario: str
    trial: int
    reason: str


@dataclass(frozen=True, kw_only=True)
class Failure:
    scenario: str
    reason: str


@dataclass(frozen=True, kw_only=True)
class ScenarioResult:
    scenario: str
    preset: str
    trials: int
    completed: int
    violation_trials: int
    worst_excursion_ratio: float | None
    learning_gain: float | None       # 1 - max lateral of the last trial / of trial 1
    travel_time_gain: float | None    # 1 - travel time of the last trial / of trial 1
    error: str
    travel_over_ideal: float | None = None   # travel time of the last trial / route length at its setpoint
    outside_3sigma_max: float | None = None  # the largest outside_3sigma_fraction of its trials
    last_trial_vs_learning_off: float | None = None   # 1 - max lateral of the last trial / the learning-off run's


@dataclass(frozen=True, kw_only=True)
class FamilyStats:
    """One family's figures (module docstring); the first seven keys are DESIGN.md's."""
    trials: int
    completion_rate: float | None
    violation_trials: int
    worst_excursion_ratio: float | None
    learning_gain_median: float | None
    travel_time_gain_median: float | None
    self_stops: list[Stop]
    trials_planned: int
    gain_scenarios: int
    travel_over_ideal_median: float | None = None
    outside_3sigma_median: float | None = None    # over trials
    outside_3sigma_max: float | None = None
    outside_3sigma_over_1pct: int = 0             # trials with more than 1 % outside (issue 18's target)
    other_stops: list[Stop] = field(default_factory=list)
    failed_scenarios: list[Failure] = field(default_factory=list)
    scenarios: list[ScenarioResult] = field(default_factory=list)
    last_trial_vs_learning_off_median: float | None = None
    time_lost_share: dict[str, float] = field(default_factory=dict)   # of all trials' travel time, by cause


# --- scenarios and runs ---------------------------------------------------------------------------
def _twin(table: dict, twin: str) -> dict:
    """The comparison run of a drawn scenario: the same world and seed with one thing changed."""
    if twin == "learning_off":
        return {**table, "name": table["name"] + "-nolearn", "trials": {**table["trials"], "learning": False}}
    return {**table, "name": table["name"] + "-thesisrule", "scheduler": {**table["scheduler"], "guard": False}}


def scenario_tables(n: int, seed: int, bounds: Bounds = BOUNDS, trials: int | None = None,
                    families: Sequence[str] | None = None, robots: str = "presets") -> list[tuple[int, str, dict]]:
    """(index, twin, scenario table) of every run: the N draws, each followed by its family's twins;
    with `families`, only the draws of those (scenario i stays the same draw); `robots` "perturbed":
    each robot's physics drawn around its preset (scenario_draw.perturbed_body)."""
    if robots not in ROBOTS:
        raise ValueError(f"robots: {robots!r} is not one of {ROBOTS}")
    out = []
    for index in range(n):
        if families and family_of(index).name not in families:
            continue
        body = np.random.default_rng([seed, index, 1]) if robots == "perturbed" else None
        table = draw(np.random.default_rng([seed, index]), index, bounds, body)
        if trials is not None:
            table["trials"]["count"] = trials
        out.append((index, "", table))
        out += [(index, twin, _twin(table, twin)) for twin in TWINS.get(family_of(index).name, ())]
    return out


def write_jobs(tables: list[tuple[int, str, dict]], out: FsPath, seed: int) -> list[Job]:
    """Write each scenario file into `out`; the jobs that run them."""
    jobs = []
    for index, twin, table in tables:
        sc = parse_scenario(table, table["name"])
        path = out / f"{sc.name}.toml"
        path.write_text(f"# lbc bench scenarios --seed {seed}: scenario {index} ({family_of(index).name})\n"
                        f"# replay: lbc experiment run {path.name} --out DIR\n" + dump_toml(table))
        jobs.append(Job(index=index, family=family_of(index).name, twin=twin, name=sc.name,
                        preset=sc.robot.preset, scenario_file=path, run_dir=out / sc.name,
                        log_file=out / f"{sc.name}.log", planned_trials=sc.trials.count,
                        lateral_limit_m=sc.constraints.lateral_m,
                        heading_limit_rad=math.radians(sc.constraints.heading_deg)))
    return jobs


def load_trials(summary_file: FsPath) -> tuple[TrialResult, ...]:
    if not summary_file.exists():
        return ()
    return tuple(TrialResult.from_summary(e) for e in json.loads(summary_file.read_text())["trials"])


def _last_line(log_file: FsPath) -> str:
    lines = [ln.strip() for ln in log_file.read_text(errors="replace").splitlines() if ln.strip()] \
        if log_file.exists() else []
    return lines[-1] if lines else "no output"


def read_outcome(job: Job, returncode: int, wall_s: float) -> RunOutcome:
    error = "" if returncode == 0 else f"exit {returncode}: {_last_line(job.log_file)}"
    return RunOutcome(job=job, trials=load_trials(job.run_dir / "summary.json"), error=error, wall_s=wall_s)


class Runner:
    """Runs jobs as `lbc experiment run` child processes, `parallel` at a time. Each child dies with
    this process (common.lifecycle) and has a session of its own, so a Ctrl-C reaches it once, from
    here, as SIGTERM: the runner's own clean stop."""

    def __init__(self, parallel: int, on_done: Callable[[RunOutcome, int, int], None]):
        self.parallel = parallel
        self.on_done = on_done

    def run(self, jobs: Sequence[Job]) -> list[RunOutcome]:
        pending, running, outcomes = deque(jobs), {}, []
        finished: queue.Queue[tuple[str, int]] = queue.Queue()
        try:
            while pending or running:
                while pending and len(running) < self.parallel:
                    job = pending.popleft()
                    running[job.name] = (self._start(job, finished), job, time.monotonic())
                name, returncode = finished.get()
                _, job, t0 = running.pop(name)
                outcomes.append(read_outcome(job, returncode, time.monotonic() - t0))
                self.on_done(outcomes[-1], len(outcomes), len(jobs))
        finally:
            _stop_children([proc for proc, _, _ in running.values()])
        return outcomes

    @staticmethod
    def _start(job: Job, finished: queue.Queue) -> subprocess.Popen:
        env = dict(os.environ, **{PARENT_ENV: str(os.getpid())})
        with open(job.log_file, "wb") as log:
            proc = subprocess.Popen([sys.executable, "-m", "bench.scenarios", "--child", str(job.scenario_file),
                                     "--child-out", str(job.run_dir)], stdin=subprocess.DEVNULL, stdout=log,
                                    stderr=subprocess.STDOUT, env=env, start_new_session=True)
        threading.Thread(target=lambda: finished.put((job.name, proc.wait())), daemon=True).start()
        return proc


def _stop_children(procs: list[subprocess.Popen]) -> None:
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    for proc in procs:
        try:
            proc.wait(CHILD_STOP_S)
        except subprocess.TimeoutExpired:
            proc.kill()    # its services and router die with it (common.lifecycle)
            proc.wait()


def _run_child(scenario_file: str, run_dir: str) -> int:
    from common.lifecycle import die_with_parent
    from deploy.cli import main as lbc_main
    die_with_parent()
    return lbc_main(["experiment", "run", scenario_file, "--out", run_dir])


# --- figures --------------------------------------------------------------------------------------
def _excursion(job: Job, t: TrialResult) -> float:
    return max(t.max_lateral_m / job.lateral_limit_m, t.max_heading_rad / job.heading_limit_rad)


def _gain(first: float, last: float) -> float | None:
    return round(1.0 - last / first, 4) if first > 0 else None


def _last_completed(o: RunOutcome) -> TrialResult | None:
    last = next((t for t in o.trials if t.trial == o.job.planned_trials), None)
    return last if last is not None and last.completed else None


def scenario_result(o: RunOutcome, learning_off: RunOutcome | None = None) -> ScenarioResult:
    """One scenario's figures; `learning_off`: its learning-off twin, if it ran."""
    by_trial = {t.trial: t for t in o.trials}
    first, last = by_trial.get(1), by_trial.get(o.job.planned_trials)
    both = first is not None and last is not None and first.completed and last.completed
    off_last = _last_completed(learning_off) if learning_off is not None else None
    return ScenarioResult(
        scenario=o.job.name, preset=o.job.preset, trials=len(o.trials),
        completed=sum(t.completed for t in o.trials),
        violation_trials=sum(t.constraint_violations > 0 for t in o.trials),
        worst_excursion_ratio=round(max(_excursion(o.job, t) for t in o.trials), 4) if o.trials else None,
        learning_gain=_gain(first.max_lateral_m, last.max_lateral_m) if both else None,
        travel_time_gain=_gain(first.travel_time_s, last.travel_time_s) if both else None,
        error=o.error,
        travel_over_ideal=round(last.travel_time_s / last.ideal_travel_s, 4)
        if both and last.ideal_travel_s else None,
        outside_3sigma_max=_max([t.outside_3sigma for t in o.trials]),
        last_trial_vs_learning_off=_gain(off_last.max_lateral_m, last.max_lateral_m)
        if off_last is not None and last is not None and last.completed else None)


def _median(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return round(statistics.median(known), 4) if known else None


def _max(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return round(max(known), 4) if known else None


def _stops(outcomes: Sequence[RunOutcome], own: bool) -> list[Stop]:
    return [Stop(scenario=o.job.name, trial=t.trial, reason=t.end_reason.removeprefix(SELF_STOP))
            for o in outcomes for t in o.trials
            if not t.completed and t.end_reason.startswith(SELF_STOP) == own]


def _time_lost_share(trials: list[TrialResult]) -> dict[str, float]:
    """The share of the trials' travel time each cause held the robot below its asked speed (causes that
    cost something only)."""
    total = sum(t.travel_time_s for t in trials)
    lost: dict[str, float] = {}
    for t in trials:
        for k, v in t.time_lost_s.items():
            lost[k] = lost.get(k, 0.0) + v
    return {k: round(v / total, 4) for k, v in lost.items() if v > 0.0} if total > 0 else {}


def family_stats(outcomes: Sequence[RunOutcome], learning_off: dict[int, RunOutcome] | None = None) -> FamilyStats:
    """A family's figures; `learning_off`: its learning-off twins by scenario index."""
    per = [scenario_result(o, (learning_off or {}).get(o.job.index)) for o in outcomes]
    planned = sum(o.job.planned_trials for o in outcomes)
    excursions = [s.worst_excursion_ratio for s in per if s.worst_excursion_ratio is not None]
    outside = [t.outside_3sigma for o in outcomes for t in o.trials]
    return FamilyStats(
        trials=sum(s.trials for s in per),
        completion_rate=round(sum(s.completed for s in per) / planned, 4) if planned else None,
        violation_trials=sum(s.violation_trials for s in per),
        worst_excursion_ratio=max(excursions) if excursions else None,
        learning_gain_median=_median([s.learning_gain for s in per]),
        travel_time_gain_median=_median([s.travel_time_gain for s in per]),
        self_stops=_stops(outcomes, own=True), trials_planned=planned,
        gain_scenarios=sum(s.learning_gain is not None for s in per),
        travel_over_ideal_median=_median([s.travel_over_ideal for s in per]),
        outside_3sigma_median=_median(outside), outside_3sigma_max=_max(outside),
        outside_3sigma_over_1pct=sum(v > 0.01 for v in outside if v is not None),
        other_stops=_stops(outcomes, own=False),
        failed_scenarios=[Failure(scenario=o.job.name, reason=o.error) for o in outcomes if o.error],
        scenarios=per,
        last_trial_vs_learning_off_median=_median([s.last_trial_vs_learning_off for s in per]),
        time_lost_share=_time_lost_share([t for o in outcomes for t in o.trials]))


def bench_result(outcomes: Sequence[RunOutcome], n: int, seed: int, wall_s: float) -> dict:
    """The benchmark's JSON object (keys of DESIGN.md first)."""
    result: dict = {"n": n, "seed": seed}
    for fam in FAMILIES:
        mine = [o for o in outcomes if o.job.family == fam.name]
        off = {o.job.index: o for o in mine if o.job.twin == "learning_off"}
        result[fam.name] = to_dict(family_stats([o for o in mine if not o.job.twin], off))
        for twin in TWINS.get(fam.name, ()):
            result[fam.name][twin] = to_dict(family_stats([o for o in mine if o.job.twin == twin]))
    sim_s = sum(t.travel_time_s for o in outcomes for t in o.trials)
    result["sim_speedup"] = round(sim_s / wall_s, 3) if wall_s > 0 else None
    result.update({"sim_s": round(sim_s, 1), "wall_s": round(wall_s, 1), "runs": len(outcomes),
                   "unanswered_ticks": sum(t.unanswered_ticks for o in outcomes for t in o.trials)})
    return result


# --- command line ---------------------------------------------------------------------------------
def progress_line(o: RunOutcome, done: int, total: int) -> str:
    s = scenario_result(o)
    text = f"bench scenarios [{done}/{total}] {o.job.name}: {s.completed}/{o.job.planned_trials} completed"
    if o.trials:
        first, last = o.trials[0], o.trials[-1]
        text += (f", {s.violation_trials} with violations, worst {s.worst_excursion_ratio:.2f} of the corridor, "
                 f"max lateral {first.max_lateral_m:.3f} -> {last.max_lateral_m:.3f} m, "
                 f"travel {first.travel_time_s:.1f} -> {last.travel_time_s:.1f} s")
    text += f" (wall {o.wall_s:.0f} s)"
    return text + (f"; FAILED: {o.error}" if o.error else "")


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def run_bench(args: argparse.Namespace) -> dict:
    bounds = Bounds(route_m=tuple(args.route_m)) if args.route_m else BOUNDS
    overrides = {k: v for k, v in (("trials", args.trials), ("route_m", args.route_m)) if v is not None}
    where = nullcontext(args.out) if args.out else tempfile.TemporaryDirectory(prefix="lbc-bench-scenarios-")
    with where as out_name:
        out = FsPath(out_name)
        out.mkdir(parents=True, exist_ok=True)
        jobs = write_jobs(scenario_tables(args.n, args.seed, bounds, args.trials, args.family, args.robots),
                          out, args.seed)
        _say(f"bench scenarios: {args.n} scenarios, {len(jobs)} runs, {args.jobs} at a time, in {out}"
             + (f" (only {', '.join(args.family)})" if args.family else "")
             + (" (robots perturbed from their presets)" if args.robots == "perturbed" else "")
             + (f" (overrides {overrides}: not the benchmark's figures)" if overrides else ""))
        t0 = time.monotonic()
        outcomes = Runner(args.jobs, lambda o, done, total: _say(progress_line(o, done, total))).run(jobs)
        result = bench_result(outcomes, args.n, args.seed, time.monotonic() - t0)
        result.update({"jobs": args.jobs, "out": str(out) if args.out else None, "overrides": overrides or None,
                       "families": list(args.family) if args.family else None, "robots": args.robots})
        if args.out:
            (out / "bench.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lbc bench scenarios", description="how well the learning controllers "
                                     "generalize: N random scenarios through the real services (distribution: "
                                     "bench/scenario_draw.py)")
    parser.add_argument("--n", type=int, default=8, help="scenarios to draw (default 8)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, metavar="DIR", help="keep scenario files and runs here (new or empty)")
    parser.add_argument("--jobs", type=int, default=1, help="runs at a time (default 1)")
    parser.add_argument("--family", action="append", choices=[f.name for f in FAMILIES], default=None,
                        help="run only the draws of this family (repeatable); the others' figures stay empty")
    parser.add_argument("--robots", choices=ROBOTS, default="presets",
                        help="perturbed: each robot's hidden physics drawn around its preset (a user's own robot)")
    parser.add_argument("--trials", type=int, default=None, help="smoke tests only: every run has this many trials")
    parser.add_argument("--route-m", type=float, nargs=2, default=None, metavar=("MIN", "MAX"),
                        help="smoke tests only: route lengths in this range")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--child-out", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        return _run_child(args.child, args.child_out)
    if args.n < 1 or args.jobs < 1 or (args.trials is not None and args.trials < 1):
        parser.error("--n, --jobs and --trials must be >= 1")
    if args.out and FsPath(args.out).exists() and any(FsPath(args.out).iterdir()):
        parser.error(f"--out {args.out} is not empty: choose a new directory")
    return run_and_print(lambda: run_bench(args))


if __name__ == "__main__":
    raise SystemExit(main())
