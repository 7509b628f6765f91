"""What "one seed gives one run" means for summary.json: with a lockstep clock, two runs of one
scenario give the same summary except for the values that measure wall-clock time, listed here and
nowhere else."""
from __future__ import annotations

from typing import Any

# summary.json keys of each trial that measure wall-clock time (solver time, the trial's wall time; with
# a realtime clock, missed periods and their jitter)
TRIAL_WALL_CLOCK_KEYS = frozenset({"solve_ms_p50", "solve_ms_p99", "wall_time_s", "deadline_misses",
                                   "period_jitter_ms_p99"})
# top-level summary.json entries, by key path, that hold a wall-clock time stamp
SUMMARY_WALL_CLOCK_PATHS = frozenset({("identified_model", "stamp_s")})


def reproducible_part(summary: dict[str, Any]) -> dict[str, Any]:
    """A copy of a summary without its wall-clock values: what two runs of one seed must share."""
    out = _without(summary, SUMMARY_WALL_CLOCK_PATHS)
    out["trials"] = [{k: v for k, v in t.items() if k not in TRIAL_WALL_CLOCK_KEYS} for t in summary.get("trials", [])]
    return out


def differences(a: Any, b: Any, where: str = "") -> list[str]:
    """Where two JSON values differ, as 'path: a != b' lines (empty: equal)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{where}.{k}: only in {'the first' if k in a else 'the second'}" for k in sorted(set(a) ^ set(b))]
        for k in sorted(set(a) & set(b)):
            out += differences(a[k], b[k], f"{where}.{k}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        out = [f"{where}: {len(a)} != {len(b)} entries"] if len(a) != len(b) else []
        for i, (x, y) in enumerate(zip(a, b)):
            out += differences(x, y, f"{where}[{i}]")
        return out
    return [] if a == b and type(a) is type(b) else [f"{where}: {a!r} != {b!r}"]


def _without(data: dict[str, Any], paths: frozenset[tuple[str, ...]]) -> dict[str, Any]:
    out = {}
    for k, v in data.items():
        inner = frozenset(p[1:] for p in paths if p[0] == k and len(p) > 1)
        if (k,) in paths:
            continue
        out[k] = _without(v, inner) if inner and isinstance(v, dict) else v
    return out
