"""The vision source on bad input: corrupted or truncated frames, a wrong calibration, an empty or
foreign map file. Each gives a clear error or a 'lost' status, never a crash and never a made-up pose."""
from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from common.camera import StereoConfig
from common.codec import DecodeError, decode, encode
from common.messages import StereoFrame
from services.bridge.render import StereoRenderer
from services.bridge.world import build_world
from services.localizer.vision.settings import VisionSettings
from services.localizer.vision_source import VisionSource

WAYPOINTS = [[0.0, 0.0], [4.0, 0.0]]


@pytest.fixture(scope="module")
def taught(tmp_path_factory):
    renderer = StereoRenderer(StereoConfig(), build_world(WAYPOINTS, seed=2), seed=2)
    maps = tmp_path_factory.mktemp("routes")
    src = VisionSource(VisionSettings(), maps)
    src.start_teach(0)
    for k, x in enumerate(np.arange(0.0, 3.0, 0.05)):
        src.on_frame(renderer.frame(stamp_s=0.1 * k, tick=k, trial=0, x=x, y=0.0, theta=0.0, v=0.5), "r")
    path = src.finish_teach("r", loop=False, taught_by="test")
    return renderer, maps, path


def repeat_source(taught) -> VisionSource:
    _, maps, path = taught
    src = VisionSource(VisionSettings(), maps)
    src.start_repeat(path, 1)
    return src


def good_frame(renderer, tick=0, x=0.5, y=0.1) -> StereoFrame:
    return renderer.frame(stamp_s=0.1 * tick, tick=tick, trial=1, x=x, y=y, theta=0.02, v=0.5)


def test_a_good_frame_localizes(taught):
    renderer, _, _ = taught
    loc = repeat_source(taught).on_frame(good_frame(renderer), "r")
    assert loc.status == "ok" and abs(loc.T_vertex_robot[1] - 0.1) < 0.02 and loc.matched_features > 50


def test_corrupted_png_and_truncated_frames_are_lost_not_crashes(taught):
    renderer, _, _ = taught
    src = repeat_source(taught)
    f = good_frame(renderer)
    png = StereoRenderer(dataclasses.replace(renderer.cfg, encoding="png"), renderer.world, 2).frame(
        stamp_s=0.0, tick=0, trial=1, x=0.5, y=0.1, theta=0.0)
    broken = dataclasses.replace(png, left=png.left[: len(png.left) // 3])
    loc = src.on_frame(broken, "r")
    assert loc.status == "lost" and "bad stereo frame" in loc.reason and loc.T_vertex_robot is None
    garbage = dataclasses.replace(png, right=b"\x89PNG not really")
    assert src.on_frame(garbage, "r").status == "lost"
    # a mono8 payload of the wrong length cannot even be built or decoded
    body = msgpack.unpackb(encode(f), raw=False)
    body["left"] = body["left"][:-7]
    with pytest.raises(DecodeError, match="width\\*height"):
        decode(StereoFrame, msgpack.packb(body, use_bin_type=True))
    # an all-black frame (lens cap): no features, no pose
    black = dataclasses.replace(f, left=bytes(len(f.left)), right=bytes(len(f.right)))
    loc = src.on_frame(black, "r")
    assert loc.T_vertex_robot is None or loc.status == "vo"
    # and the source carries on with good frames afterwards
    assert src.on_frame(good_frame(renderer, tick=3, x=0.6), "r").status in ("ok", "vo")


def test_a_frame_with_another_calibration_is_refused(taught):
    renderer, _, _ = taught
    src = repeat_source(taught)
    f = good_frame(renderer)
    for change in ({"fu_px": f.fu_px * 1.1}, {"baseline_m": 0.3}, {"T_robot_camera": tuple(np.eye(4).ravel())}):
        loc = src.on_frame(dataclasses.replace(f, **change), "r")
        assert loc.status == "lost" and "calibration" in loc.reason and loc.T_vertex_robot is None


@pytest.mark.parametrize("content", [b"", b"\x00\x01garbage", msgpack.packb({"format": "something else"}),
                                     msgpack.packb([1, 2, 3])])
def test_an_empty_or_foreign_map_file_refuses_the_repeat(taught, tmp_path, content):
    _, maps, path = taught
    (tmp_path / "r.vmap").write_bytes(content)
    with pytest.raises(ValueError, match="r.vmap"):
        VisionSource(VisionSettings(), tmp_path).start_repeat(path, 1)


def test_a_missing_map_or_one_of_another_route_refuses_the_repeat(taught, tmp_path):
    _, maps, path = taught
    with pytest.raises(ValueError, match="no vision map"):
        VisionSource(VisionSettings(), tmp_path).start_repeat(path, 1)
    other = type(path)("r", path.poses[:-2], spacing_m=path.spacing_m)
    with pytest.raises(ValueError, match="not taught together"):
        VisionSource(VisionSettings(), maps).start_repeat(other, 1)
