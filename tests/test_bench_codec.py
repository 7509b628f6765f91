"""`lbc bench codec`: one JSON line with encode/decode times of every per-tick message."""
import json
import math

from bench import codec as bench_codec
from common.codec import decode, encode


def test_bench_codec_reports_every_message(capsys):
    assert bench_codec.main(["--reps", "2", "--rounds", "1"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    names = set(bench_codec.messages())
    assert {"ControllerStatus", "LocState", "ExperienceWindow"} <= names
    for key in ("encode_us", "decode_us", "bytes"):
        assert set(res[key]) == names, key
        assert all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in res[key].values()), key


def test_sampled_messages_fill_every_field_and_round_trip():
    status = bench_codec.messages()["ControllerStatus"]
    assert len(status.pred_sigma_lat_m) == bench_codec.HORIZON and status.solve_ms > 0
    for msg in bench_codec.messages().values():
        assert decode(type(msg), encode(msg)) == msg
