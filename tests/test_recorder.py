"""The run recorder (deploy/recorder.py) through a real router: everything a service would accept is
recorded as it travelled, and a flood of traffic no service would accept is kept only up to a budget."""
from __future__ import annotations

import pytest
import zenoh
from mcap.reader import make_reader

from common import keys
from common.bus import open_session
from common.codec import DecodeError, decode, encode
from common.messages import TruthPose
from deploy.launcher import Launcher
from deploy.recorder import REJECTED_KEEP_BYTES, REJECTED_KEEP_MESSAGES, McapRecorder
from deploy.router import free_port
from tests.conftest import wait_until


def _truth(tick: int) -> TruthPose:
    return TruthPose(stamp_s=0.1 * tick, tick=tick, trial=1, x_world_m=0.01 * tick, y_world_m=0.0,
                     theta_world_rad=0.0, v_mps=0.1, w_radps=0.0, lateral_slip_mps=0.0)


@pytest.mark.integration
def test_the_recorder_keeps_every_good_message_and_bounds_the_garbage(tmp_path):
    port = free_port()
    launcher = Launcher(f"tcp/127.0.0.1:{port}", tmp_path / "logs")
    launcher.start_router(port)
    try:
        rec_session = open_session(f"tcp/127.0.0.1:{port}", timeout_s=20)
        pub_session = open_session(f"tcp/127.0.0.1:{port}", timeout_s=20)
        recorder = McapRecorder(tmp_path / "run.mcap", rec_session)
        good_key, n_good, n_junk = keys.truth("r1"), 300, 5000
        pub = pub_session.declare_publisher(good_key, congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: pub.matching_status.matching, 10, "the recorder's subscription")
        for i in range(n_junk):
            # garbage of three kinds: unknown keys, a known key with bad msgpack, a known key with a big payload
            key, payload = [(f"lbc/r1/junk/{i}", b"\x01\x02"), (good_key, b"\xc1"),
                            (good_key, b"\x00" * 70_000)][i % 3]
            pub_session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
            if i % 10 == 0 and i // 10 < n_good:
                pub.put(encode(_truth(i // 10)))
        for tick in range(n_junk // 10, n_good):
            pub.put(encode(_truth(tick)))
        wait_until(lambda: recorder.count + recorder.rejected_skipped >= n_good + n_junk, 30,
                   "every message to reach the recorder", lambda: f"recorded {recorder.count}, rejected "
                   f"{recorder.rejected}, not recorded {recorder.rejected_skipped}")
        recorder.close()
        rec_session.close()
        pub_session.close()
    finally:
        launcher.stop()

    assert recorder.rejected == n_junk
    with open(tmp_path / "run.mcap", "rb") as fh:
        messages = [(ch.topic, m.data) for _, ch, m in make_reader(fh).iter_messages()]
    truth = [decode(TruthPose, data) for topic, data in messages if topic == good_key and _decodes(data)]
    assert [t.tick for t in truth] == list(range(n_good))          # every good message, in order
    junk = [data for topic, data in messages if not (topic == good_key and _decodes(data))]
    assert 0 < len(junk) <= REJECTED_KEEP_MESSAGES and sum(map(len, junk)) <= REJECTED_KEEP_BYTES
    assert recorder.rejected_skipped == n_junk - len(junk)


def _decodes(data: bytes) -> bool:
    try:
        decode(TruthPose, data)
        return True
    except DecodeError:
        return False
