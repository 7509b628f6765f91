"""Visual Teach & Repeat on rendered stereo, against simulator truth (no bus: renderer -> vision source).

Teach drives the route; repeat drives it again with deliberate lateral offsets up to 0.5 m. The
localizer's pose relative to its vertex must match the truth pose relative to where the robot was
when that keyframe was taken (thesis 2.4: -0.3 cm mean, 2.9 cm std against DGPS)."""
from __future__ import annotations


import numpy as np
import pytest

from bench.localizer import offset_route
from common import se2
from common.camera import StereoConfig
from services.bridge.render import StereoRenderer
from services.bridge.teach_driver import smooth_waypoints
from services.bridge.world import build_world
from services.localizer.vision.settings import VisionSettings
from services.localizer.vision_source import VisionSource

WAYPOINTS = [[0.0, 0.0], [6.0, 0.0], [11.0, 3.0], [16.0, 3.0]]
STEP_M = 0.05           # 0.5 m/s at 10 Hz

pytestmark = pytest.mark.slow   # the module's taught route is rendered and localized frame by frame


@pytest.fixture(scope="module")
def taught(tmp_path_factory):
    cfg = StereoConfig()
    renderer = StereoRenderer(cfg, build_world(WAYPOINTS, seed=3), seed=3)
    ref = smooth_waypoints(WAYPOINTS, 3.0, False, step_m=STEP_M)
    source = VisionSource(VisionSettings(), tmp_path_factory.mktemp("routes"))
    source.start_teach(0)
    kf_truth = []
    for k, pose in enumerate(ref):
        n_before = len(source.teach.keyframes) if source.teach is not None else 0
        loc = source.on_frame(renderer.frame(stamp_s=0.1 * k, tick=k, trial=0, x=pose[0], y=pose[1],
                                             theta=pose[2], v=0.5), "simroute")
        assert loc.status == "teach", loc.reason
        if len(source.teach.keyframes) > n_before:
            kf_truth.append(pose)
    path = source.finish_teach("simroute", loop=False, taught_by="test")
    assert len(path) == len(kf_truth)
    return renderer, source, path, np.array(kf_truth), ref


def test_taught_route_follows_the_driven_one(taught):
    _, _, path, kf_truth, ref = taught
    # vertex poses from chained VO against the truth of the same keyframes, both relative to the first
    est = path.poses
    tru = se2.between(kf_truth[0], kf_truth)
    drift = np.hypot(*(est[-1, :2] - tru[-1, :2]))
    assert drift <= 0.02 * path.length_m, (drift, path.length_m)
    assert abs(path.length_m - np.sum(np.hypot(*np.diff(ref[:, :2], axis=0).T))) < 0.5


def test_repeat_with_lateral_offsets_matches_truth(taught):
    renderer, source, path, kf_truth, ref = taught
    source.start_repeat(path, 1)
    drive = offset_route(ref, 0.5)
    err_lat, err_head, ok = [], [], 0
    for k, pose in enumerate(drive):
        loc = source.on_frame(renderer.frame(stamp_s=0.1 * k, tick=k, trial=1, x=pose[0], y=pose[1],
                                             theta=pose[2], v=0.5), "simroute")
        if loc.status != "ok":
            continue
        ok += 1
        truth = se2.between(kf_truth[loc.vertex], pose)
        err_lat.append(loc.T_vertex_robot[1] - truth[1])
        err_head.append(se2.wrap(loc.T_vertex_robot[2] - truth[2]))
        cov = np.asarray(loc.cov_T_vertex_robot).reshape(3, 3)
        assert np.all(np.linalg.eigvalsh(cov) > 0)
    err_lat, err_head = np.array(err_lat), np.array(err_head)
    assert ok >= 0.99 * len(drive), f"relocalized {ok} of {len(drive)} frames"
    assert abs(err_lat.mean()) <= 0.01, err_lat.mean()
    assert err_lat.std() <= 0.02, err_lat.std()
    assert np.degrees(np.abs(err_head)).max() <= 2.0
