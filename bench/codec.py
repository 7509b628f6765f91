"""`lbc bench codec`: encode and decode time of the bus messages every tick carries (common/codec.py).

Every service decodes what it subscribes to and the runner's recorder decodes every message once more,
so the codec's per-message cost is paid several times per message on a lockstep tick. Each message is
built from its type's annotations with every field filled (lists of a horizon's length, experience
batches and a store window of realistic size), then encoded and decoded `--reps` times; the median of
`--rounds` timings per message is reported in microseconds. No bus, no processes.
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
import types
import typing
from typing import Any, Literal

import numpy as np

from bench.report import run_and_print
from common.codec import decode, encode
from common.messages import (Clock, ControllerStatus, Experience, ExperienceAck, ExperienceBatch, ExperienceWindow,
                             LocState, Odometry, TruthPose, VelocityCommand)

HORIZON = 10            # per-step lists of a controller status (K = 10)
BATCH = 10              # experiences per batch (one controller flush)
WINDOW = 127            # experiences in a store window (a full window, bench store)


def sample(cls: type, **given: Any) -> Any:
    """An instance of message dataclass `cls` with every field filled from its annotation."""
    hints = typing.get_type_hints(cls)
    values = {f.name: given[f.name] if f.name in given else _value(hints[f.name])
              for f in dataclasses.fields(cls)}
    return cls(**values)


def _value(tp: Any) -> Any:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal:
        return args[0]
    if origin in (typing.Union, types.UnionType):
        return _value(next(a for a in args if a is not type(None)))
    if origin is list:
        return [_value(args[0]) for _ in range(HORIZON)]
    if origin is tuple:
        return tuple(_value(args[0]) for _ in range(HORIZON)) if args[-1] is Ellipsis else tuple(map(_value, args))
    return {float: 0.123456789, int: 7, str: "husky", bool: True, bytes: b"\0" * 64}[tp]


def messages() -> dict[str, Any]:
    experience = sample(Experience, a=tuple(np.linspace(-1, 1, 9)), g=(0.01, -0.02, 0.003))
    a, g = np.random.default_rng(1).normal(size=(WINDOW, 9)), np.random.default_rng(2).normal(size=(WINDOW, 3))
    return {
        "Clock": sample(Clock), "Odometry": sample(Odometry), "TruthPose": sample(TruthPose),
        "LocState": sample(LocState, status="ok", cov_T_vertex_robot=tuple(np.eye(3).ravel() * 1e-4),
                           cov_step_T_vertex_robot=tuple(np.eye(3).ravel() * 1e-5)),
        "VelocityCommand": sample(VelocityCommand), "ControllerStatus": sample(ControllerStatus),
        "ExperienceBatch": sample(ExperienceBatch, experiences=[experience] * BATCH),
        "ExperienceAck": sample(ExperienceAck),
        "ExperienceWindow": sample(ExperienceWindow, vertices=list(range(WINDOW)), speed_bins=[1] * WINDOW,
                                   a_f64=a.tobytes(), g_f64=g.tobytes()),
    }


def _median_us(fn, reps: int, rounds: int) -> float:
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(reps):
            fn()
        times.append((time.perf_counter() - t0) / reps)
    return round(1e6 * statistics.median(times), 2)


def run(reps: int, rounds: int) -> dict:
    out: dict = {"encode_us": {}, "decode_us": {}, "bytes": {}}
    for name, msg in messages().items():
        data = encode(msg)
        if decode(type(msg), data) != msg:
            raise AssertionError(f"{name} does not survive encode/decode")
        out["encode_us"][name] = _median_us(lambda: encode(msg), reps, rounds)
        out["decode_us"][name] = _median_us(lambda: decode(type(msg), data), reps, rounds)
        out["bytes"][name] = len(data)
    out["reps"], out["rounds"] = reps, rounds
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="lbc bench codec", description=__doc__.splitlines()[0])
    p.add_argument("--reps", type=int, default=300, help="encodes/decodes per timing")
    p.add_argument("--rounds", type=int, default=7, help="timings per message (the median is reported)")
    args = p.parse_args(argv)
    return run_and_print(lambda: run(max(1, args.reps), max(1, args.rounds)))
