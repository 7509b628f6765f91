"""Teach and repeat on vision alone through the real services: the bridge renders stereo, the localizer
teaches a keyframe map and relocalizes against it, the controller tracks the route it made."""
from __future__ import annotations

import json
import os

import pytest
from mcap.reader import make_reader

from common.codec import decode
from common.messages import LocState
from deploy.experiment import run_experiment
from tests.ros2_topics import check_standard_topics

pytestmark = pytest.mark.integration


@pytest.mark.slow
def test_a_route_taught_and_repeated_on_vision(tmp_path, scenario_file):
    out = tmp_path / "out"
    run_experiment(scenario_file({
        "name": "vision1", "seed": 4, "robot": {"preset": "husky"},
        "path": {"waypoints": [[0, 0], [8, 0], [14, 4]], "teach_speed_mps": 0.5},
        "terrain": [{"kind": "side_slope", "center": [8.0, 1.0], "radius_m": 4.0, "slope_deg": 10.0,
                     "downhill_deg": -90.0}],
        "localization": {"source": "vision", "camera": {"lighting_change": 0.3}},
        "controller": {"algorithm": "fl"}, "trials": {"count": 1, "speed": 0.5}}),
        out, progress_stream=open(os.devnull, "w"))
    t = json.loads((out / "summary.json").read_text())["trials"][0]
    assert t["completed"] and t["constraint_violations"] == 0
    assert t["mean_matched_features"] > 50
    # the estimate the controller tracked agrees with truth (errors are measured on the truth teach pass)
    assert abs(t["max_lateral_m_est"] - t["max_lateral_m"]) < 0.03, t
    assert t["max_lateral_m"] < 0.2
    statuses = []
    with open(out / "run.mcap", "rb") as fh:
        for _, ch, msg in make_reader(fh).iter_messages():
            if not ch.topic.endswith("/loc/state"):
                continue
            loc = decode(LocState, msg.data)
            if loc.trial == 1:
                statuses.append(loc.status)
    assert statuses and statuses.count("ok") >= 0.99 * len(statuses), {s: statuses.count(s) for s in set(statuses)}
    assert (out / "data" / "routes" / "vision1.vmap").exists()
    # the standard ROS 2 topics, stereo frames included, read by an independent ROS 2 decoder
    topics = check_standard_topics(out / "run.mcap", "husky")
    for side in ("left", "right"):
        raw, png = topics.get(f"/stereo/{side}/image_raw", []), topics.get(f"/stereo/{side}/image_raw/compressed", [])
        assert raw or png, sorted(topics)
        for img in raw[:3]:
            assert img.encoding == "mono8" and len(img.data) == img.width * img.height == img.step * img.height
        for img in png[:3]:
            assert img.format == "png" and bytes(img.data[:8]) == b"\x89PNG\r\n\x1a\n"
    assert "<h2>Localization</h2>" in (out / "report.html").read_text()
