"""The teach chain's sliding-window bundle adjustment and the disparity offset it estimates (issue 21).

Synthetic geometry with a KITTI-like rig (f = 718 px, b = 0.54 m): points at known depths seen from
keyframes 1.2 m apart, every (u, v, d) with Gaussian noise of the frontend's own sigmas, every point
matched (distinct random descriptors), through `VisualTeach` as the localizer runs it. The scale bias is
the chain's length over the true one, minus 1, averaged over scenes.

A rig whose rectification is slightly off measures every disparity short (or long) by a constant:
depth from a 10 px disparity is then too far by offset / 10, and frame-to-frame registrations
over-estimate the motion by that (the +6 % of a long-range KITTI excerpt, issue 21)."""
from __future__ import annotations

import numpy as np
import pytest

from common.se3 import exp as se3_exp
from services.localizer.vision import StereoCamera, VisionSettings, VisualTeach, estimate_pose
from services.localizer.vision.features import StereoKeypoints
from services.localizer.vision.window_ba import KeyframeWindow, _model, _State

CAM = StereoCamera(fu=718.856, fv=718.856, cu=607.19, cv=185.22, baseline_m=0.5372, width=1241, height=376)
STEP_M = 1.2


def _scene(rng, near_m: float, far_m: float, n: int, frames: int) -> np.ndarray:
    """Points in the first camera's frame, ahead of the last keyframe by near..far metres."""
    z = rng.uniform(near_m, far_m, n) + frames * STEP_M
    u, v = rng.uniform(60, CAM.width - 60, n), rng.uniform(40, CAM.height - 40, n)
    return np.column_stack([(u - CAM.cu) * z / CAM.fu, (v - CAM.cv) * z / CAM.fv, z])


def _observe(rng, P: np.ndarray, desc: np.ndarray, s: VisionSettings, offset_px: float) -> StereoKeypoints:
    sig = np.array([s.sigma_uv_px, s.sigma_uv_px, s.sigma_d_px])
    uvd = CAM.project(P) + rng.standard_normal(P.shape) * sig
    uvd[:, 2] -= offset_px                       # the rig measures every disparity this much short
    return StereoKeypoints(uvd, desc, CAM.triangulate(uvd), np.tile(sig ** 2, (len(P), 1)))


def chain_scale_bias(near_m: float, far_m: float, s: VisionSettings, offset_px: float = 0.0, draws: int = 12,
                     frames: int = 8, n: int = 300, seed: int = 0) -> tuple[float, float, float]:
    """(mean, standard error) of the taught chain's scale bias and the mean estimated offset (px)."""
    rng = np.random.default_rng([seed, int(near_m), int(far_m), int(100 * offset_px)])
    bias, offsets = [], []
    for _ in range(draws):
        P = _scene(rng, near_m, far_m, n, frames)
        desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        teach = VisualTeach(CAM, s)
        for k in range(frames):
            step = teach.add(_observe(rng, P - [0.0, 0.0, STEP_M * k], desc, s, offset_px))
            assert step.ok and step.new_keyframe, step.reason
        vmap = teach.finish()
        bias.append(np.linalg.norm(vmap.keyframes[-1].T_first_this[:3, 3]) / (STEP_M * (frames - 1)) - 1.0)
        offsets.append(vmap.meta["disparity_offset_px"])
    b = np.array(bias)
    return float(b.mean()), float(b.std(ddof=1) / np.sqrt(len(b))), float(np.mean(offsets))


def test_jacobians_match_finite_differences():
    rng = np.random.default_rng(3)
    s = VisionSettings()
    P = _scene(rng, 5.0, 60.0, 80, 4)
    desc = rng.integers(0, 256, (80, 32), dtype=np.uint8)
    win = KeyframeWindow(CAM, VisionSettings(ba_window=4))
    prev = None
    for k in range(4):
        kp = _observe(rng, P - [0.0, 0.0, STEP_M * k], desc, s, 0.0)
        if prev is None:
            win.push(kp, np.eye(4), None)
        else:
            est = estimate_pose(prev.points, prev.desc, kp, CAM, s)
            win.push(kp, np.linalg.inv(est.T_live_ref), est.pairs)
        prev = kp
    prob = win._problem()
    x = _State(win._poses(), win._initial_landmarks(prob, 0.3), 0.3)
    r0, (J_l, J_j, J_a) = _model(CAM, prob, x, True)
    h = 1e-6
    for c in range(3):                                           # landmark columns
        L1, L2 = x.L.copy(), x.L.copy()
        L1[:, c] += h * max(1.0, abs(x.L[:, c]).max())
        L2[:, c] -= h * max(1.0, abs(x.L[:, c]).max())
        fd = (_model(CAM, prob, _State(x.T, L1, x.offset), False)[0]
              - _model(CAM, prob, _State(x.T, L2, x.offset), False)[0]) / (L1[0, c] - L2[0, c])
        np.testing.assert_allclose(J_l[:, :, c], fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())
    for c in range(6):                                           # frame 2's pose, as observer and as anchor
        xi = np.zeros(6)
        xi[c] = h
        Tp, Tm = x.T.copy(), x.T.copy()
        Tp[2], Tm[2] = se3_exp(xi) @ x.T[2], se3_exp(-xi) @ x.T[2]
        fd = (_model(CAM, prob, _State(Tp, x.L, x.offset), False)[0]
              - _model(CAM, prob, _State(Tm, x.L, x.offset), False)[0]) / (2 * h)
        an = np.where((prob.frame == 2)[:, None], J_j[:, :, c], 0.0) + \
            np.where((prob.anchor == 2)[:, None], J_a[:, :, c], 0.0)
        np.testing.assert_allclose(an, fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())
    fd = (_model(CAM, prob, _State(x.T, x.L, 0.3 + h), False)[0]
          - _model(CAM, prob, _State(x.T, x.L, 0.3 - h), False)[0]) / (2 * h)
    np.testing.assert_allclose(fd[:, 2], -prob.inv_sigma[:, 2], rtol=1e-6)   # by the offset: d rows only
    np.testing.assert_allclose(fd[:, :2], 0.0, atol=1e-9)


@pytest.mark.parametrize("near_m, far_m", [(5.0, 20.0), (20.0, 40.0), (40.0, 80.0)])
def test_the_bundle_adjusted_chain_is_unbiased_in_scale_at_5_to_80_m(near_m, far_m):
    """Issue 21's target: scale bias <= 0.5 %. Frame-to-frame registration alone under-estimates the
    motion at 40-80 m by ~0.65 % (its reference points' depth noise, test_vision_scale.py). The offset
    is held here: with every point in one narrow band of depth an offset and the scale are nearly
    one unknown, and a short chain cannot tell them apart (below, a scene of mixed depths can)."""
    mean, se, _ = chain_scale_bias(near_m, far_m, VisionSettings(estimate_disparity_offset=False))
    print(f"{near_m:.0f}-{far_m:.0f} m: chain scale bias {100 * mean:+.3f} % +- {100 * se:.3f} %")
    assert abs(mean) + 2 * se <= 0.005


def test_with_the_offset_estimated_a_scene_of_5_to_80_m_keeps_its_scale():
    mean, se, offset = chain_scale_bias(5.0, 80.0, VisionSettings())
    print(f"5-80 m, offset estimated: chain scale bias {100 * mean:+.3f} % +- {100 * se:.3f} %, "
          f"offset {offset:+.3f} px")
    assert abs(mean) + 2 * se <= 0.005
    assert abs(offset) < 0.05


def test_a_disparity_offset_is_estimated_and_leaves_no_scale_bias():
    """Disparities measured 1 px short at 5-80 m: without the estimate the chain is ~6 % too long."""
    off = VisionSettings(estimate_disparity_offset=False)
    mean_off, _, _ = chain_scale_bias(5.0, 80.0, off, offset_px=1.0, draws=4)
    mean, se, offset = chain_scale_bias(5.0, 80.0, VisionSettings(), offset_px=1.0)
    print(f"1 px offset: bias {100 * mean_off:+.2f} % without the estimate, {100 * mean:+.3f} % +- "
          f"{100 * se:.3f} % with it (offset {offset:.3f} px)")
    assert mean_off > 0.04
    assert abs(mean) + 2 * se <= 0.005
    assert abs(offset - 1.0) < 0.05
