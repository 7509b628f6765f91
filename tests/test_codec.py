"""Codec: every message round-trips; malformed, oversized, wrongly typed or non-finite payloads are
rejected with a reason, counted, and never raise out of a service's decoder."""
import logging
import math

import msgpack
import pytest

from common import messages as m
from common.codec import Decoder, DecodeError, decode, encode

EXAMPLES = [
    m.Clock(stamp_s=1.5, tick=15, period_s=0.1, mode="lockstep", trial=2),
    m.Odometry(stamp_s=1.0, tick=10, v_mps=0.5, w_radps=-0.1, x_odom_m=1.0, y_odom_m=2.0, theta_odom_rad=0.3),
    m.TruthPose(stamp_s=1.0, tick=10, trial=1, x_world_m=1.0, y_world_m=2.0, theta_world_rad=3.0, v_mps=0.5,
                w_radps=0.1, lateral_slip_mps=0.01),
    m.LocState(stamp_s=1.0, capture_stamp_s=0.8, tick=10, capture_tick=8, trial=1, path_id="p1", source="pose", status="ok",
               reason="", vertex=4, distance_m=1.1, T_vertex_robot=(0.1, -0.02, 0.01),
               cov_T_vertex_robot=(1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-5), matched_features=None),
    m.LocState(stamp_s=1.0, capture_stamp_s=0.8, tick=10, capture_tick=8, trial=1, path_id="p1", source="pose", status="dropout",
               reason="no estimate", vertex=4, distance_m=1.1, T_vertex_robot=None, cov_T_vertex_robot=None,
               matched_features=37),
    m.VelocityCommand(stamp_s=1.0, tick=10, trial=1, v_mps=0.5, w_radps=0.2, source="fl"),
    m.ControllerStatus(stamp_s=1.0, tick=10, trial=1, algorithm="fl", state="tracking", reason="", path_id="p1",
                       vertex=3, distance_m=0.9, lateral_m=0.01, heading_rad=0.02, v_cmd_mps=0.5,
                       w_cmd_radps=0.1, solve_ms=0.05, iterations=0, loc_age_s=0.1, rejected_msgs=0,
                       experiences_sent=10, experiences_pending=1, window_experiences=44, hyper_version=2,
                       w_ff_radps=0.01, pred_x_m=[1.0, 1.1], pred_y_m=[0.0, 0.01], pred_theta_rad=[0.0, 0.02], sigma_lat_m=0.02,
                       sigma_head_rad=0.03, solver_status="converged", spread_factors=[1.0, 1.5],
                       pred_sigma_lat_m=[0.01, 0.02], pred_sigma_head_rad=[0.01, 0.03], learning_off_since_s=-1.0, learning_note="",
                       step_late_ms=0.2, turn_cap_mps=1.1, turn_loss_per_mps2=0.2,
                       speed_held_by="ladder-lateral"),
    m.BridgeStatus(stamp_s=1.0, tick=10, trial=1, mode="repeat", running=True, watchdog_tripped=False,
                   cmd_age_s=0.1, v_cmd_applied_mps=0.5, w_cmd_applied_radps=0.0, rejected_msgs=3),
    m.TrialEvent(stamp_s=1.0, trial=1, mode="repeat", event="ended", reason="time limit", path_id="p1"),
    m.ControlRequest(stamp_s=1.0, action="prepare", mode="repeat", trial=1, path_id="p1", speed_mps=0.5,
                     max_duration_s=100.0, learning=True, loop=False, schedule=True),
    m.ControlReply(stamp_s=1.0, service="bridge", ok=True, detail="ready"),
    m.RouteMsg(path_id="p1", loop=False, vertex_spacing_m=0.25, x_m=[0.0, 0.25], y_m=[0.0, 0.0],
               theta_rad=[0.0, 0.0], taught_by="husky", stamp_s=0.0),
]
EXP = m.Experience(stamp_s=2.0, robot="r1", trial=1, path_id="p1", seq=7, vertex=3, v_cmd_mps=0.5,
                   a=tuple(0.1 * i for i in range(9)), g=(0.01, -0.002, 0.003))
HYPER_DIM = m.HyperDim(lengthscales=[1.0] * 9, signal_std=0.01, noise_std=0.001)
EXAMPLES += [
    EXP,
    m.ExperienceBatch(stamp_s=2.0, robot="r1", source="r1-abc", experiences=[EXP, EXP]),
    m.ExperienceAck(stamp_s=2.0, store="store1", source="r1-abc", seqs=[1, 2, 3], rejected=[4], reason="unknown route"),
    WINDOW := m.ExperienceWindow(stamp_s=2.0, path_id="p1", vertex_lo=0, vertex_hi=10, bin_lo=1, bin_hi=3,
                                 v_bin_mps=0.25, vertices=[2], speed_bins=[2], a_f64=bytes(72), g_f64=bytes(24)),
    HYPER_DIM,
    m.HyperMsg(stamp_s=2.0, path_id="p1", version=3, n_used=100, n_total=120, fit_s=1.5, lml=[1.0, 2.0, 3.0],
               dims=[HYPER_DIM] * 3),
    m.PathStats(path_id="p1", retained=10, ingested=20, bins=5, hyper_version=1),
    m.AliveEvent(stamp_s=2.0, alive=False),
    m.SpeedSchedule(stamp_s=2.0, path_id="p1", version=2, based_on_robot="r1", based_on_trial=1,
                    v_mps=[0.4, 0.7, 0.4], decisions=[0, 1, 0], notes=["trial 1"]),
    m.ScheduleUpdate(stamp_s=2.0, path_id="p1", robot="r1", trial=1),
    m.CorridorUpdate(stamp_s=2.0, path_id="p1", from_m=10.0, to_m=20.0, left_m=0.2, right_m=-0.1, heading_rad=0.3),
    m.StoreStats(stamp_s=2.0, store="store1", db_path="/tmp/x.db",
                 paths=[m.PathStats(path_id="p1", retained=10, ingested=20, bins=5, hyper_version=1)]),
]


def test_every_message_type_has_an_example():
    assert {type(e) for e in EXAMPLES} == set(m.ALL_MESSAGES)


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda e: type(e).__name__)
def test_round_trip(msg):
    data = encode(msg)
    assert decode(type(msg), data) == msg
    assert msgpack.unpackb(data)["v"] == type(msg).SCHEMA_VERSION


def _tampered(msg, **changes):
    body = msgpack.unpackb(encode(msg))
    body.update(changes)
    return msgpack.packb(body)


CLOCK = EXAMPLES[0]
BAD = {
    "not msgpack": b"\xc1\xff\x00garbage",
    "truncated": encode(CLOCK)[:-3],
    "not a map": msgpack.packb([1, 2, 3]),
    "wrong version": _tampered(CLOCK, v=99),
    "no version": msgpack.packb({k: v for k, v in msgpack.unpackb(encode(CLOCK)).items() if k != "v"}),
    "missing field": msgpack.packb({k: v for k, v in msgpack.unpackb(encode(CLOCK)).items() if k != "tick"}),
    "unknown field": _tampered(CLOCK, extra=1),
    "string for float": _tampered(CLOCK, stamp_s="1.0"),
    "bool for int": _tampered(CLOCK, tick=True),
    "float for int": _tampered(CLOCK, tick=1.5),
    "NaN": _tampered(CLOCK, stamp_s=float("nan")),
    "inf": _tampered(CLOCK, period_s=float("inf")),
    "bad literal": _tampered(CLOCK, mode="turbo"),
    "oversized": b"\x00" * (m.Clock.MAX_BYTES + 1),
}


@pytest.mark.parametrize("name", BAD)
def test_rejects_bad_payloads_with_reason(name):
    with pytest.raises(DecodeError) as exc:
        decode(m.Clock, BAD[name])
    assert str(exc.value)


def test_rejects_invalid_nested_values():
    loc = EXAMPLES[3]
    with pytest.raises(DecodeError, match="cov_T_vertex_robot"):
        decode(m.LocState, _tampered(loc, cov_T_vertex_robot=[1.0, 2.0]))
    with pytest.raises(DecodeError, match="T_vertex_robot"):
        decode(m.LocState, _tampered(loc, T_vertex_robot=[0.0, float("nan"), 0.0]))
    with pytest.raises(DecodeError, match="requires T_vertex_robot"):
        decode(m.LocState, _tampered(loc, T_vertex_robot=None))
    with pytest.raises(DecodeError, match="path_id"):
        decode(m.ControlRequest, _tampered(EXAMPLES[9], path_id="../../etc"))
    with pytest.raises(DecodeError, match="equal lengths"):
        decode(m.RouteMsg, _tampered(EXAMPLES[11], y_m=[0.0]))
    # experiences: wrong dimension, non-finite values inside a batch, bad window arrays
    with pytest.raises(DecodeError, match="a must hold 9 values"):
        decode(m.Experience, _tampered(EXP, a=[0.0] * 8))
    bad_batch = msgpack.unpackb(encode(m.ExperienceBatch(stamp_s=0.0, robot="r1", source="s", experiences=[EXP])))
    bad_batch["experiences"][0]["g"][1] = float("nan")
    with pytest.raises(DecodeError, match=r"experiences\[0\]\.g\[1\]: must be finite"):
        decode(m.ExperienceBatch, msgpack.packb(bad_batch))
    for value, where in (([True] + [0.0] * 8, r"a\[0\]: expected a number"), ([0.0] * 8 + [float("inf")], r"a\[8\]: must be finite"),
                         ([0.0] * 3 + ["1"] + [0.0] * 5, r"a\[3\]: expected a number")):
        with pytest.raises(DecodeError, match=where):            # the checked path names the element
            decode(m.Experience, _tampered(EXP, a=value))
    win = WINDOW
    with pytest.raises(DecodeError, match="do not hold"):
        decode(m.ExperienceWindow, _tampered(win, a_f64=bytes(8)))
    with pytest.raises(DecodeError, match="non-finite"):
        decode(m.ExperienceWindow, _tampered(win, a_f64=b"\x00" * 64 + b"\x00\x00\x00\x00\x00\x00\xf8\x7f"))


def test_a_flood_on_many_keys_neither_floods_the_log_nor_grows_the_counters(caplog):
    now = [0.0]
    dec = Decoder(logging.getLogger("test"), window_s=5.0, burst=3, total_burst=20, max_keys=100,
                  clock=lambda: now[0])
    with caplog.at_level(logging.WARNING):
        for i in range(20_000):                      # unique keys: a per-key limit alone would log them all
            assert dec(m.Clock, b"\xc1", f"lbc/r/junk/{i}") is None
        for _ in range(50):
            dec(m.Clock, b"\xc1", "lbc/r/clock")
        lines = caplog.records[:]
        now[0] = 6.0                                 # the next window: a summary of what was not logged
        dec(m.Clock, b"\xc1", "lbc/r/clock")
    assert dec.rejected_total == 20_051
    assert len(dec.rejected) == 101 and dec.rejected[Decoder.OTHER_KEYS] == 20_000 + 51 - 100
    assert len(lines) == 20 + 1                      # 20 reasons and one "logging at most" line
    summary = [r.getMessage() for r in caplog.records[len(lines):]]
    assert summary[0].startswith("20030 rejected messages not logged in the last 5 s")
    assert "rejected message on lbc/r/clock" in summary[1]   # a fresh window logs again


def test_encode_refuses_oversized_message():
    big = m.RouteMsg(path_id="p", loop=False, vertex_spacing_m=0.25, x_m=[0.0] * 800_000, y_m=[0.0] * 800_000,
                     theta_rad=[0.0] * 800_000, taught_by="", stamp_s=0.0)
    with pytest.raises(ValueError, match="limit"):
        encode(big)


def test_decoder_logs_counts_and_never_raises(caplog):
    dec = Decoder(logging.getLogger("test"), window_s=60.0, burst=5)
    with caplog.at_level(logging.WARNING):
        for payload in BAD.values():
            assert dec(m.Clock, payload, "lbc/r/clock") is None
    assert dec.rejected["lbc/r/clock"] == len(BAD)
    assert dec.rejected_total == len(BAD)
    assert caplog.text.count("rejected message on lbc/r/clock") == 5   # a flood does not flood the log
    assert "logging at most 5" in caplog.text
    assert dec(m.Clock, encode(CLOCK), "lbc/r/clock") == CLOCK
    assert math.isclose(CLOCK.stamp_s, 1.5)
