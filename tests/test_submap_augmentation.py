"""Submap augmentation (thesis 2.2.3): features tracked between keyframes join the keyframe's submap.

Synthetic: a narrow stereo camera (25 deg wide) turns on the spot by 1.5 deg per frame from a keyframe;
world points spread over a wide arc at 8-30 m, each with its own descriptor, observed with the
frontend's noise. Frames 1-3 stay within the keyframe's thresholds, so they are registered against it,
and the points they track that the keyframe never saw must join its submap, placed right. A repeat view
turned 7 deg then finds more of its features in that submap."""
from __future__ import annotations

import numpy as np

from common.se3 import exp as se3_exp
from common.se3 import inverse as inv_T
from common.se3 import transform
from services.localizer.vision import StereoCamera, VisionSettings, VisualTeach, estimate_pose
from services.localizer.vision.features import StereoKeypoints

CAM = StereoCamera(fu=718.0, fv=718.0, cu=159.5, cv=119.5, baseline_m=0.5, width=320, height=240)
S = VisionSettings()


def _world(rng, n: int = 3000) -> np.ndarray:
    az = rng.uniform(-0.6, 0.6, n)
    r = rng.uniform(8.0, 30.0, n)
    return np.column_stack([r * np.sin(az), rng.uniform(-2.0, 2.0, n), r * np.cos(az)])


def _view(rng, world: np.ndarray, desc: np.ndarray, T_cam_world: np.ndarray) -> StereoKeypoints:
    p = transform(T_cam_world, world)
    uvd = CAM.project(np.where(p[:, 2:3] > 0.1, p, 1.0))
    seen = (p[:, 2] > 0.1) & (uvd[:, 0] > 5) & (uvd[:, 0] < CAM.width - 5) & (uvd[:, 1] > 5) & \
        (uvd[:, 1] < CAM.height - 5)
    sig = np.array([S.sigma_uv_px, S.sigma_uv_px, S.sigma_d_px])
    y = uvd[seen] + rng.standard_normal((int(seen.sum()), 3)) * sig
    return StereoKeypoints(y, desc[seen], CAM.triangulate(y), np.tile(sig ** 2, (len(y), 1)))


def _turned(deg: float) -> np.ndarray:
    """T_cam_world of the camera at the origin turned `deg` to the right (about its y axis)."""
    return inv_T(se3_exp(np.array([0.0, 0.0, 0.0, 0.0, np.radians(deg), 0.0])))


def _teach(rng, world, desc, augment: bool):
    teach = VisualTeach(CAM, VisionSettings(submap_augment=augment))
    for k in range(4):
        step = teach.add(_view(rng, world, desc, _turned(1.5 * k)))
        assert step.ok and step.new_keyframe == (k == 0), step.reason
    return teach.finish()


def test_features_tracked_between_keyframes_join_the_submap_where_they_are():
    rng = np.random.default_rng(5)
    world = _world(rng)
    desc = rng.integers(0, 256, (len(world), 32), dtype=np.uint8)
    plain, augmented = _teach(rng, world, desc, False), _teach(rng, world, desc, True)
    kf0, kf = plain.keyframes[0], augmented.keyframes[0]
    assert len(plain) == len(augmented) == 1
    n0 = len(kf0.points)
    added = len(kf.points) - n0
    assert added > 0.1 * n0, (n0, added)
    # every added point is a world point (by its descriptor) placed where it is, in the keyframe's frame
    truth = {bytes(d): w for d, w in zip(desc, world)}
    err = np.array([np.linalg.norm(p - truth[bytes(d)]) / np.linalg.norm(truth[bytes(d)])
                    for p, d in zip(kf.points[n0:], kf.desc[n0:])])
    assert np.median(err) < 0.02 and err.max() < 0.15
    live = _view(rng, world, desc, _turned(7.0))
    T_true = _turned(7.0)                            # keyframe points -> live frame
    counts = []
    for vmap in (plain, augmented):
        k = vmap.keyframes[0]
        est = estimate_pose(k.points, k.desc, live, vmap.camera, S, ref_cov_uvd=k.cov_uvd)
        assert est.ok, est.reason
        D = est.T_live_ref @ inv_T(T_true)
        assert np.linalg.norm(D[:3, 3]) < 0.05
        counts.append(est.inliers)
    assert counts[1] > 1.1 * counts[0], counts     # the 3 deg of new view tracked over two frames: +12 %
