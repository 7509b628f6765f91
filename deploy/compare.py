"""`lbc experiment compare A B`: two runs of the same scenarios, side by side.

A and B are each an experiment's output directory (its summary.json) or a directory of them (the
`--out` of `lbc bench scenarios`, paired by name). Per pair it says whether the summaries are the same
run (reproducible.py: equal but for their wall-clock values, which is what one seed in lockstep must
give) and, where not, the first values that differ and each trial's figures from A to B. Pure: files
in, a typed comparison out; the command prints it.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Any

from deploy.reproducible import differences, reproducible_part

SUMMARY = "summary.json"


class CompareError(ValueError):
    """A directory that holds no run, or a summary that is not one."""


@dataclass(frozen=True)
class TrialFigures:
    """What one trial of one run gave (NaN where it has no such figure)."""
    completed: bool
    max_lateral_m: float
    travel_time_s: float
    violations: int
    end_reason: str


@dataclass(frozen=True)
class PairComparison:
    name: str
    same: bool
    differences: tuple[str, ...]
    a: tuple[TrialFigures, ...]
    b: tuple[TrialFigures, ...]


@dataclass(frozen=True)
class Comparison:
    pairs: tuple[PairComparison, ...]
    only_in_a: tuple[str, ...]
    only_in_b: tuple[str, ...]

    @property
    def identical(self) -> bool:
        return all(p.same for p in self.pairs) and not self.only_in_a and not self.only_in_b

    def to_json(self) -> dict[str, Any]:
        return {"pairs": len(self.pairs), "identical": sum(p.same for p in self.pairs),
                "different": [p.name for p in self.pairs if not p.same],
                "first_differences": {p.name: _short(p.differences[0]) for p in self.pairs if p.differences},
                "only_in_a": list(self.only_in_a), "only_in_b": list(self.only_in_b),
                "a": _totals([p.a for p in self.pairs]), "b": _totals([p.b for p in self.pairs])}


def runs_in(directory: str | FsPath) -> dict[str, FsPath]:
    """The runs a directory holds, by name: itself if it has a summary, else its subdirectories that do."""
    d = FsPath(directory)
    if not d.is_dir():
        raise CompareError(f"{d} is not a directory")
    if (d / SUMMARY).is_file():
        return {d.name: d}
    runs = {sub.name: sub for sub in sorted(d.iterdir()) if (sub / SUMMARY).is_file()}
    if not runs:
        raise CompareError(f"{d} holds no {SUMMARY}, nor do its subdirectories")
    return runs


def compare_dirs(a: str | FsPath, b: str | FsPath, ignore: frozenset[str] = frozenset()) -> Comparison:
    """Pair the runs of `a` and `b` (two single runs pair whatever their names) and compare each pair,
    leaving the keys in `ignore` out (at the summary's top level and in each trial)."""
    runs_a, runs_b = runs_in(a), runs_in(b)
    if len(runs_a) == 1 and len(runs_b) == 1 and (FsPath(a) / SUMMARY).is_file() and (FsPath(b) / SUMMARY).is_file():
        (name, da), (_, db) = next(iter(runs_a.items())), next(iter(runs_b.items()))
        return Comparison((compare_summaries(name, _load(da), _load(db), ignore),), (), ())
    pairs = tuple(compare_summaries(n, _load(runs_a[n]), _load(runs_b[n]), ignore)
                  for n in sorted(set(runs_a) & set(runs_b)))
    return Comparison(pairs, tuple(sorted(set(runs_a) - set(runs_b))), tuple(sorted(set(runs_b) - set(runs_a))))


def compare_summaries(name: str, a: dict[str, Any], b: dict[str, Any],
                      ignore: frozenset[str] = frozenset()) -> PairComparison:
    diff = differences(_without(reproducible_part(a), ignore), _without(reproducible_part(b), ignore))
    return PairComparison(name, not diff, tuple(diff), _figures(a), _figures(b))


def _without(summary: dict[str, Any], keys: frozenset[str]) -> dict[str, Any]:
    out = {k: v for k, v in summary.items() if k not in keys}
    out["trials"] = [{k: v for k, v in t.items() if k not in keys} for t in summary["trials"]]
    return out


def _load(run_dir: FsPath) -> dict[str, Any]:
    f = run_dir / SUMMARY
    try:
        data = json.loads(f.read_text())
    except (OSError, ValueError) as exc:
        raise CompareError(f"{f}: {exc}") from exc
    if not isinstance(data, dict) or not isinstance(data.get("trials"), list):
        raise CompareError(f"{f} is not an experiment summary (no list of trials)")
    return data


def _figures(summary: dict[str, Any]) -> tuple[TrialFigures, ...]:
    return tuple(TrialFigures(completed=bool(t.get("completed", False)), max_lateral_m=_number(t, "max_lateral_m"),
                              travel_time_s=_number(t, "travel_time_s"), violations=int(t.get("constraint_violations") or 0),
                              end_reason=str(t.get("end_reason", ""))) for t in summary["trials"])


def _number(trial: dict[str, Any], key: str) -> float:
    v = trial.get(key)
    return float(v) if isinstance(v, (int, float)) else math.nan


def _totals(runs: list[tuple[TrialFigures, ...]]) -> dict[str, Any]:
    trials = [t for run in runs for t in run]
    lateral = [t.max_lateral_m for t in trials if not math.isnan(t.max_lateral_m)]
    return {"trials": len(trials), "completed": sum(t.completed for t in trials),
            "violation_trials": sum(t.violations > 0 for t in trials),
            "max_lateral_m": round(max(lateral), 4) if lateral else None}


def describe(c: Comparison, shown_differences: int = 3) -> list[str]:
    """The comparison as lines for a person: one per identical pair, a trial table for each other."""
    lines = []
    for p in c.pairs:
        if p.same:
            lines.append(f"{p.name}: same run")
            continue
        more = len(p.differences) - shown_differences
        lines.append(f"{p.name}: {len(p.differences)} values differ: "
                     + "; ".join(_short(d) for d in p.differences[:shown_differences])
                     + (f"; ... {more} more" if more > 0 else ""))
        lines.append("  trial  max lateral m      travel s           violating steps  end")
        for k in range(max(len(p.a), len(p.b))):
            ta, tb = (p.a[k] if k < len(p.a) else None), (p.b[k] if k < len(p.b) else None)
            lines.append(f"  {k + 1:<5d}  {_pair(ta, tb, 'max_lateral_m', '.3f'):17s}  "
                         f"{_pair(ta, tb, 'travel_time_s', '.1f'):17s}  {_pair(ta, tb, 'violations', 'd'):15s}  "
                         f"{_ends(ta, tb)}")
    lines += [f"{n}: only in A" for n in c.only_in_a] + [f"{n}: only in B" for n in c.only_in_b]
    return lines


def _pair(a: TrialFigures | None, b: TrialFigures | None, field: str, fmt: str) -> str:
    def one(t):
        return "-" if t is None else format(getattr(t, field), fmt)
    return f"{one(a)} -> {one(b)}"


def _ends(a: TrialFigures | None, b: TrialFigures | None) -> str:
    ea, eb = (a.end_reason if a else "-"), (b.end_reason if b else "-")
    return ea if ea == eb else f"{ea} -> {eb}"


def _short(text: str, limit: int = 160) -> str:
    """A difference line cut to a readable length (a note that differs is a paragraph twice)."""
    return text if len(text) <= limit else text[:limit - 3] + "..."
