"""Stereo rendering in the simulator bridge, checked against independent references.

Geometry: depths triangulated from left/right matches of real ORB keypoints agree with depths from an
independent ray caster; known world points land where a pinhole model written here predicts.
Features: ORB finds plenty of keypoints spread over the image, fewer with motion blur. Terrain tilt:
a rolled, pitched and sunk robot sees the world where the independent model, its rig rotated about the
ground contact point, puts it; the level attitude is today's rendering. Plus determinism, lighting
change per trial and the path through the bridge node to the wire.
"""
from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from common.codec import decode, encode
from common.config import load_config
from common.messages import StereoFrame
from common.robot import PRESETS
from common.camera import StereoConfig
from services.bridge.config import BridgeConfig, TeachConfig
from services.bridge.render import MAX_GROUND_M, StereoRenderer, calibration, camera_pose, project
from services.bridge.terrain import LEVEL, Attitude
from services.bridge.teach_driver import smooth_waypoints
from services.bridge.world import GroundTexture, Landmark, Sky, World, build_world, mip_pyramid, raycast

WAYPOINTS = [[0.0, 0.0], [14.0, 0.0], [22.0, 7.0]]
SEED = 3


@pytest.fixture(scope="module")
def world() -> World:
    return build_world(WAYPOINTS, SEED, landmark_density=3.0)


@pytest.fixture(scope="module")
def route() -> np.ndarray:
    return smooth_waypoints(WAYPOINTS, 3.0, False)


def poses(route, n=3):
    return [tuple(route[int(i)]) for i in np.linspace(0.1, 0.8, n) * (len(route) - 1)]


# --- an independent pinhole model, written from the documented conventions -------------------------
def camera_in_world(cfg: StereoConfig, x, y, theta, right=False, attitude: Attitude = LEVEL):
    """Left (or right) camera: rotation whose columns are the camera axes in world, and its centre.

    Robot frame x forward, y left, z up; camera x right, y down, z forward, pitched `pitch_deg` down;
    the rig centre sits at (mount_x, 0, mount_z) in the robot frame, the left camera baseline/2 to the
    left of it and the right camera baseline/2 to the right. A robot tilted by the terrain: the level
    rig is rolled about the heading, then pitched (nose down) about the level left axis, both through
    the ground contact point (Rodrigues' rotations), and the contact point is lowered to z_m."""
    p = math.radians(cfg.pitch_deg)
    fwd = np.array([math.cos(theta), math.sin(theta), 0.0])
    left = np.array([-math.sin(theta), math.cos(theta), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    z_c = math.cos(p) * fwd - math.sin(p) * up
    x_c = -left
    y_c = np.cross(z_c, x_c)
    side = -0.5 if right else 0.5
    arm = cfg.mount_x_m * fwd + side * cfg.baseline_m * left + cfg.mount_z_m * up
    tilt = cv2.Rodrigues(left * attitude.pitch_rad)[0] @ cv2.Rodrigues(fwd * attitude.roll_rad)[0]
    centre = np.array([x, y, attitude.z_m]) + tilt @ arm
    return tilt @ np.column_stack([x_c, y_c, z_c]), centre


def pinhole(cfg: StereoConfig, pose, pts, right=False, attitude: Attitude = LEVEL):
    R, c = camera_in_world(cfg, *pose, right=right, attitude=attitude)
    f = 0.5 * cfg.width_px / math.tan(math.radians(cfg.hfov_deg) / 2)
    X = (np.atleast_2d(pts) - c) @ R
    return np.column_stack([f * X[:, 0] / X[:, 2] + (cfg.width_px - 1) / 2,
                            f * X[:, 1] / X[:, 2] + (cfg.height_px - 1) / 2])


def polygon_centroid(p: np.ndarray) -> np.ndarray:
    x, y = p[:, 0], p[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    a = cross.sum() / 2
    return np.array([np.sum((x + xn) * cross), np.sum((y + yn) * cross)]) / (6 * a)


# --- geometry ------------------------------------------------------------------------------------
def match_along_row(left, right, u, v, half=5, max_disp=120):
    """Sub-pixel disparity of the patch around (u, v) of `left` along row v of `right` (NCC)."""
    patch = left[v - half:v + half + 1, u - half:u + half + 1]
    lo = max(0, u - max_disp - half)
    strip = right[v - half:v + half + 1, lo:u + half + 1]
    if strip.shape[1] < 2 * half + 3 or patch.std() < 4:
        return None
    score = cv2.matchTemplate(strip, patch, cv2.TM_CCOEFF_NORMED)[0]
    k = int(np.argmax(score))
    if score[k] < 0.9 or k == 0 or k == len(score) - 1:
        return None
    others = np.delete(score, range(max(0, k - 3), min(len(score), k + 4)))
    if len(others) and others.max() > score[k] - 0.05:
        return None                      # ambiguous (repeated texture)
    a, b, c = score[k - 1], score[k], score[k + 1]
    sub = 0.5 * (a - c) / (a - 2 * b + c)
    return u - (lo + half + k + sub)


def test_triangulated_orb_depths_match_ray_cast(world, route):
    cfg = StereoConfig(noise_dn=2.0)
    ren = StereoRenderer(cfg, world, SEED)
    cal = ren.calib
    orb = cv2.ORB_create(1500)
    rel_err, hits = [], {"ground": 0, "landmark": 0}
    for pose in poses(route):
        left, right = ren.render(*pose, trial=0, tick=1)
        R, c = camera_in_world(cfg, *pose)
        for kp in orb.detect(left, None):
            u, v = int(round(kp.pt[0])), int(round(kp.pt[1]))
            if not (8 <= u < cal.width_px - 8 and 8 <= v < cal.height_px - 8):
                continue
            # true depth along this pixel's ray and around it (skip patches straddling a depth edge)
            uu, vv = np.array([u, u - 4, u + 4, u, u]), np.array([v, v, v, v - 4, v + 4])
            # = np.array([v, v, v, v - 4, v + 4])
            rays = np.column_stack([(uu - cal.cu) / cal.fu, (vv - cal.cv) / cal.fv, np.ones(5)]) @ R.T
            depth, what = raycast(world, c, rays)      # t is the camera depth: rays have unit z
            if not np.all(np.isfinite(depth)) or depth[0] > 30 or np.ptp(depth) > 0.1 * depth[0] + 0.05 \
                    or len(set(what)) > 1:
                continue
            d = match_along_row(left, right, u, v)
            if d is None or d < 1.0:
                continue
            z = cal.fu * cal.baseline_m / d
            rel_err.append(abs(z - depth[0]) / depth[0])
            hits["landmark" if what[0] >= 0 else "ground"] += 1
    rel_err = np.array(rel_err)
    print(f"triangulated {len(rel_err)} ORB keypoints {hits}: median relative depth error {np.median(rel_err):.4f}")
    assert len(rel_err) > 150, len(rel_err)
    assert hits["landmark"] > 10 and hits["ground"] > 100, hits
    assert np.median(rel_err) < 0.03, np.median(rel_err)
    assert np.mean(rel_err < 0.1) > 0.85


def blob_centroid(img, centre, half, background):
    r0, q0 = int(centre[1]) - half[1], int(centre[0]) - half[0]
    win = img[r0:r0 + 2 * half[1], q0:q0 + 2 * half[0]].astype(float) - background
    ys, xs = np.mgrid[r0:r0 + 2 * half[1], q0:q0 + 2 * half[0]]
    return np.array([np.sum(xs * win), np.sum(ys * win)]) / win.sum()


TILTED = Attitude(roll_rad=math.radians(9.0), pitch_rad=math.radians(-3.0), z_m=-0.05)


@pytest.mark.parametrize("attitude", [LEVEL, TILTED], ids=["level", "tilted"])
def test_known_points_project_where_the_pinhole_model_says(attitude):
    """Bright squares on a dark ground (one near, one far, seen through a coarser mip level) and a
    landmark with a bright square on its face: the rendered blobs and the landmark's outline sit
    where the independent pinhole model puts them, in both cameras, for the level robot and for one
    rolled, pitched and sunk by the terrain (its rig rotated about the ground contact point)."""
    res = 0.01
    tex = np.full((1000, 3000), 30, np.uint8)               # 30 m x 10 m: x in [0, 30], y in [-5, 5]
    x0, y0 = 0.0, -5.0
    squares = [(4.0, 4.2, -0.1, 0.1), (14.0, 15.5, -3.3, -2.5)]   # world x0, x1, y0, y1
    for sq in squares:
        tex[round((sq[2] - y0) / res):round((sq[3] - y0) / res), round((sq[0] - x0) / res):round((sq[1] - x0) / res)] = 230
    lm_tex = np.full((120, 200), 160, np.uint8)
    lm_tex[40:80, 80:140] = 250                                 # texels: rows 40-79, columns 80-139
    lm = Landmark(kind="wall", a=np.array([12.0, 1.8]), b=np.array([12.4, -0.2]), height_m=1.2,
                  levels=mip_pyramid(lm_tex, 2))
    sky = Sky(panorama=np.full((100, 360), 100, np.uint8), el_top_rad=math.radians(60), el_bottom_rad=math.radians(-20))
    w = World(ground=GroundTexture(levels=mip_pyramid(tex), x0=x0, y0=y0, res_m=res), landmarks=[lm], sky=sky)
    cfg = StereoConfig(noise_dn=0.0, exposure_s=0.0)
    ren = StereoRenderer(cfg, w, 0)
    pose = (0.4, 0.1, math.radians(4.0))
    for right, img in zip((False, True), ren.render(*pose, attitude=attitude)):
        for sq, half in zip(squares, ((40, 25), (30, 9))):
            poly = pinhole(cfg, pose, [(sq[0], sq[2], 0), (sq[1], sq[2], 0), (sq[1], sq[3], 0), (sq[0], sq[3], 0)],
                           right, attitude)
            cen = blob_centroid(img, polygon_centroid(poly), half, 30.0)
            assert np.all(np.abs(cen - polygon_centroid(poly)) < 0.25), (sq, cen, polygon_centroid(poly))
        # the landmark's outline against the projected rectangle
        mask = (img > 130).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        quad = cv2.approxPolyDP(max(contours, key=cv2.contourArea), 1.5, True)[:, 0, :].astype(float)
        assert len(quad) == 4
        pred = pinhole(cfg, pose, lm.corners, right, attitude)
        for p in pred:
            assert np.min(np.linalg.norm(quad - p, axis=1)) < 1.5, (p, quad)
        # the square on its face: texel (s, t) centres lie at a + (s + 0.5) sx (b - a)/|b - a|, top - (t + 0.5) sy
        d = np.array([*(lm.b - lm.a) / np.linalg.norm(lm.b - lm.a), 0.0])
        sx, sy = np.linalg.norm(lm.b - lm.a) / 200, lm.height_m / 120
        face = [np.array([*lm.a, lm.height_m]) + s * sx * d - t * sy * np.array([0, 0, 1])
                for s, t in ((80, 40), (140, 40), (140, 80), (80, 80))]
        poly = pinhole(cfg, pose, face, right, attitude)
        cen = blob_centroid(img, polygon_centroid(poly), (16, 12), 160.0)
        assert np.all(np.abs(cen - polygon_centroid(poly)) < 0.25), (cen, polygon_centroid(poly))


def test_calibration_follows_the_documented_convention():
    cfg = StereoConfig(pitch_deg=12.0, mount_x_m=0.3, mount_z_m=0.7, baseline_m=0.24)
    cal = calibration(cfg)
    T = cal.T_robot_camera
    p = math.radians(12.0)
    assert np.allclose(T[:3, :3] @ [0, 0, 1], [math.cos(p), 0, -math.sin(p)])   # optical axis: ahead, down
    assert np.allclose(T[:3, :3] @ [1, 0, 0], [0, -1, 0])                         # image right = robot right
    assert np.allclose(T[:3, 3], [0.3, 0.12, 0.7])                                  # left camera, left of centre
    assert np.allclose(T[3], [0, 0, 0, 1])
    R, c = camera_in_world(cfg, 0.0, 0.0, 0.0)
    assert np.allclose(T[:3, :3], R) and np.allclose(T[:3, 3], c)
    assert cal.fu == pytest.approx(320 / math.tan(math.radians(cfg.hfov_deg / 2)))


# --- terrain tilt --------------------------------------------------------------------------------
def test_a_level_attitude_is_todays_rendering_and_a_hair_of_tilt_barely_differs(world, route):
    """A level attitude takes the renderer's precomputed path: the same bytes as no attitude at all
    (which were checked byte for byte against the renderer from before terrain tilt, 5 rigs x 16 poses
    x 3 speeds, when it came). An attitude a hair off level goes the tilted way (per-frame bands, for a
    roll in column tiles; the sky from its grid) and draws the same picture but for a few mip choices."""
    ren = StereoRenderer(StereoConfig(lighting_change=0.5), world, SEED)
    pose = poses(route)[1]
    kw = dict(v=0.8, w=0.2, trial=1, tick=5)
    level = ren.render(*pose, **kw)
    again = ren.render(*pose, attitude=Attitude(roll_rad=0.0, pitch_rad=0.0, z_m=0.0), **kw)
    assert all(np.array_equal(a, b) for a, b in zip(level, again))
    for hair in (Attitude(roll_rad=1e-9), Attitude(pitch_rad=1e-9), Attitude(z_m=-1e-9)):
        for a, b in zip(level, ren.render(*pose, attitude=hair, **kw)):
            d = np.abs(a.astype(int) - b)
            assert d.mean() < 0.1 and np.mean(d > 2) < 0.002, (hair, d.mean(), np.mean(d > 2))


def test_a_rolled_camera_sees_sky_beyond_the_tilted_clip_line():
    """A plain world (ground 30, sky 200, no landmarks, blur or noise) from a robot rolled 12 deg,
    pitched and sunk: a pixel shows ground exactly where an independent ray cast from the tilted
    camera meets the ground within MAX_GROUND_M (camera depth), else sky, but on the clip line itself."""
    sky = Sky(panorama=np.full((100, 360), 200, np.uint8), el_top_rad=math.radians(60), el_bottom_rad=math.radians(-20))
    w = World(ground=GroundTexture(levels=mip_pyramid(np.full((200, 200), 30, np.uint8)), x0=-50.0, y0=-50.0,
                                   res_m=0.5), landmarks=[], sky=sky)
    cfg = StereoConfig(noise_dn=0.0, exposure_s=0.0)
    ren = StereoRenderer(cfg, w, 0)
    cal = ren.calib
    att = Attitude(roll_rad=math.radians(-12.0), pitch_rad=math.radians(5.0), z_m=-0.03)
    pose = (1.0, 2.0, 0.7)
    vv, uu = np.mgrid[0:cal.height_px, 0:cal.width_px]
    for right, img in zip((False, True), ren.render(*pose, attitude=att)):
        R, c = camera_in_world(cfg, *pose, right=right, attitude=att)
        rays = np.column_stack([(uu.ravel() - cal.cu) / cal.fu, (vv.ravel() - cal.cv) / cal.fv, np.ones(uu.size)])
        depth, what = raycast(w, c, rays @ R.T)
        ground = ((what == -1) & (depth <= MAX_GROUND_M)).reshape(img.shape)
        assert set(np.unique(img)) == {30, 200}
        assert np.sum(ground != (img == 30)) < cal.width_px // 4
        first_ground = np.argmax(img == 30, axis=0)
        assert first_ground[-1] - first_ground[0] > 0.15 * cal.width_px     # left side down: horizon falls to the right


def test_sky_grid_directions_match_the_exact_ones(world):
    """A tilted robot's sky directions are computed on a grid and interpolated: a few hundredths of a
    panorama pixel (0.004 deg) from the exact per-pixel directions at most, held inside the panorama
    (the sky rows of a rolled camera reach below its foot where the ground covers them)."""
    ren = StereoRenderer(StereoConfig(), world, SEED)
    R_lc, left, _ = ren._views(TILTED)
    r0, r1 = left.sky_rows
    vv, uu = np.mgrid[r0:r1, 0:ren.calib.width_px].astype(float)
    exact_x, exact_y = ren._sky_lookup(R_lc, uu, vv)
    exact_y = np.clip(exact_y, 0, world.sky.panorama.shape[0] - 1)
    for grid, exact in zip(ren._sky_maps_grid(R_lc, r0, r1), (exact_x, exact_y)):
        assert grid.shape == exact.shape and np.abs(grid - exact).max() < 0.05


def test_motion_blur_follows_the_tilted_camera(world):
    """The image motion of each blur tile's centre point during the exposure equals the difference of its
    projections (render.project) from the tilted robot's poses at the exposure's start and end."""
    ren = StereoRenderer(StereoConfig(), world, SEED)
    cal, e = ren.calib, ren.cfg.exposure_s
    x, y, th, v, w = 3.0, 0.5, 0.3, 1.2, 0.8
    _, *views = ren._views(TILTED)

    def pose_at(tau):
        a = w * tau
        dx, dy = v * math.sin(a) / w, v * (1 - math.cos(a)) / w
        return x + math.cos(th) * dx - math.sin(th) * dy, y + math.sin(th) * dx + math.cos(th) * dy, th + a

    for right, view in zip((False, True), views):
        R, t = camera_pose(cal, x, y, th, right, TILTED)
        pts = view.tile_pts_c @ R.T + t
        uv_end, uv_start = (project(cal, *pose_at(tau), pts, right, TILTED)[0] for tau in (0.5 * e, -0.5 * e))
        flows = ren._flows(right, v, w, (0.0, 0.0), view.tile_pts_c, TILTED)
        assert np.abs(flows).max() > 1.0 and np.allclose(flows, uv_end - uv_start, atol=1e-6)


# --- features ------------------------------------------------------------------------------------
def test_orb_finds_many_well_spread_keypoints_along_the_route(world, route):
    ren = StereoRenderer(StereoConfig(), world, SEED)
    orb = cv2.ORB_create(1000)
    for i, pose in enumerate(poses(route, 4)):
        left, right = ren.render(*pose, trial=0, tick=i)
        for img in (left, right):
            kps = orb.detect(img, None)
            assert len(kps) > 300
            cells = np.zeros((4, 4), int)
            for k in kps:
                cells[min(3, int(k.pt[1] * 4 / img.shape[0])), min(3, int(k.pt[0] * 4 / img.shape[1]))] += 1
            assert np.sum(cells >= 3) >= 12, cells


def test_motion_blur_grows_with_turn_rate_and_speed(world, route):
    ren = StereoRenderer(StereoConfig(), world, SEED)
    orb = cv2.ORB_create(5000)
    pose = poses(route)[1]

    def strength(v, w):
        kps = orb.detect(ren.render(*pose, v=v, w=w, trial=0, tick=7)[0], None)
        return len(kps), sum(k.response for k in kps)

    n0, r0 = strength(0.0, 0.0)
    n_turn, r_turn = strength(0.3, 1.5)
    n_fast, r_fast = strength(2.0, 0.0)
    assert n_turn < 0.85 * n0 and r_turn < 0.5 * r0, (n0, n_turn, r0, r_turn)
    assert r_fast < 0.95 * r0, (r0, r_fast)
    # the blur is centred on the exposure midpoint: it smears but does not shift the image
    a = ren.render(*pose, trial=0, tick=7)[0].astype(float)
    b = ren.render(*pose, v=0.0, w=1.0, trial=0, tick=7)[0].astype(float)
    shifts = [np.mean(np.abs(np.roll(b, s, axis=1) - a)[:, 20:-20]) for s in (-2, -1, 0, 1, 2)]
    assert int(np.argmin(shifts)) == 2


def test_same_inputs_same_images_and_lighting_differs_per_trial(world, route):
    pose = poses(route)[2]
    cfg = StereoConfig(lighting_change=0.8)
    a = StereoRenderer(cfg, world, SEED).render(*pose, v=0.8, w=0.3, trial=2, tick=40)
    b = StereoRenderer(cfg, world, SEED).render(*pose, v=0.8, w=0.3, trial=2, tick=40)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    other_tick = StereoRenderer(cfg, world, SEED).render(*pose, v=0.8, w=0.3, trial=2, tick=41)
    assert not np.array_equal(a[0], other_tick[0])                        # fresh sensor noise
    assert np.mean(np.abs(a[0].astype(float) - other_tick[0])) < 6.0       # ... and only noise
    other_trial = StereoRenderer(cfg, world, SEED).render(*pose, v=0.8, w=0.3, trial=3, tick=40)
    assert np.mean(np.abs(a[0].astype(float) - other_trial[0])) > 8.0
    # without lighting change and noise, trials look the same
    flat = StereoConfig(lighting_change=0.0, noise_dn=0.0)
    r = StereoRenderer(flat, world, SEED)
    assert np.array_equal(r.render(*pose, trial=1)[0], r.render(*pose, trial=5)[0])


@pytest.mark.parametrize("overrides", [{}, {"pitch_deg": 45.0}, {"pitch_deg": -10.0, "hfov_deg": 110.0},
                                       {"width_px": 320, "height_px": 240, "encoding": "png"}])
def test_renders_from_anywhere_with_other_camera_setups(world, overrides):
    """Poses off the texture, grazing and crossing landmarks (near-plane clipping), other rigs."""
    cfg = StereoConfig(lighting_change=0.5, **overrides)
    ren = StereoRenderer(cfg, world, 1)
    rng = np.random.default_rng(1)
    gt = world.ground
    rows, cols = gt.levels[0].shape
    poses_ = [(gt.x0 - 30.0, gt.y0 - 5.0, 0.3), (gt.x0 + cols * gt.res_m + 40, gt.y0, 2.0)]
    for lm in world.landmarks[:6]:
        d = (lm.b - lm.a) / np.linalg.norm(lm.b - lm.a)
        n = np.array([-d[1], d[0]])
        mid = 0.5 * (lm.a + lm.b)
        poses_ += [(*(mid + 0.02 * n), math.atan2(d[1], d[0]) + 0.3),          # skimming the face
                   (*(lm.a - 0.3 * d), math.atan2(d[1], d[0])),                # looking along it, edge on
                   (*(mid + 0.5 * n), math.atan2(-n[1], -n[0]))]               # nose against it
    for i, pose in enumerate(poses_):
        f = ren.frame(stamp_s=0.1 * i, tick=i, trial=1, x=pose[0], y=pose[1], theta=pose[2],
                      v=float(rng.uniform(0, 2)), w=float(rng.uniform(-1, 1)))
        back = decode(StereoFrame, encode(f))
        if cfg.encoding == "png":
            img = cv2.imdecode(np.frombuffer(back.right, np.uint8), cv2.IMREAD_UNCHANGED)
        else:
            img = np.frombuffer(back.right, np.uint8).reshape(cfg.height_px, cfg.width_px)
        assert img.shape == (cfg.height_px, cfg.width_px) and img.std() > 3


def test_landmarks_keep_clear_of_the_route(world, route):
    assert len(world.landmarks) > 20
    kinds = {lm.kind for lm in world.landmarks}
    assert kinds == {"rock", "trunk", "wall", "fence"}
    for lm in world.landmarks:
        s = np.linspace(0, 1, 50)[:, None]
        pts = lm.a + s * (lm.b - lm.a)
        d = np.min(np.linalg.norm(pts[:, None] - route[None, :, :2], axis=-1))
        assert 1.45 <= d <= 20.5
    assert world.nbytes() < 100e6


# --- the bridge node path --------------------------------------------------------------------------
class _FakeNode:
    def __init__(self):
        import logging
        self.log = logging.getLogger("test")
        self.robot = "r1"
        self.published: list[tuple[str, object]] = []

        class _Dec:
            rejected_total = 0
        self.decoder = _Dec()

    def publish(self, key, msg, droppable=False):
        self.published.append((key, msg))

    def queryable(self, *a, **k):
        pass

    def subscribe_queue(self, *a, **k):
        pass

    def liveliness_subscriber(self, *a, **k):
        pass


def test_bridge_publishes_stereo_frames_that_survive_the_codec():
    from common import keys
    from common.typecheck import to_dict
    from services.bridge.node import BridgeService
    raw = {"robot_name": "r1", "seed": 5, "robot": to_dict(PRESETS["husky"]),
           "teach": {"waypoints": [[0.0, 0.0], [8.0, 0.0]]}, "stereo": {"lighting_change": 0.3}}
    cfg = load_config(BridgeConfig, raw)
    assert cfg.stereo is not None and load_config(BridgeConfig, {k: v for k, v in raw.items() if k != "stereo"}).stereo is None
    svc = BridgeService(cfg, _FakeNode())
    svc.sim.reset(svc.reference[0], 2)
    svc.sim.command(0.5, 0.1)
    svc.sample = svc.sim.step()
    svc.mode, svc.trial, svc.running = "teach", 2, True
    svc._publish_tick()
    published = svc.node.published
    order = [k for k, _ in published]
    assert order.index(keys.stereo("r1")) < order.index(keys.truth("r1"))
    frame = dict(published)[keys.stereo("r1")]
    assert isinstance(frame, StereoFrame) and frame.stamp_s == svc.sample.stamp_s and frame.tick == svc.sample.tick
    assert frame.trial == 2 and frame.encoding == "mono8"
    assert len(frame.left) == len(frame.right) == frame.width_px * frame.height_px == 640 * 480
    back = decode(StereoFrame, encode(frame))
    assert back == frame
    T = np.array(back.T_robot_camera).reshape(4, 4)
    assert np.allclose(T, svc.renderer.calib.T_robot_camera)
    # the same sample through a PNG-encoding renderer gives the same pixels
    png = StereoRenderer(StereoConfig(lighting_change=0.3, encoding="png"), svc.renderer.world, 5)
    pf = decode(StereoFrame, encode(png.frame_for_sample(svc.sample, 2)))
    left = cv2.imdecode(np.frombuffer(pf.left, np.uint8), cv2.IMREAD_UNCHANGED)
    assert left.shape == (480, 640) and left.tobytes() == frame.left
    # a sample on tilted terrain is seen from its attitude
    tilted = dataclasses.replace(svc.sample, roll_rad=0.1, pitch_rad=-0.05, z_m=-0.02)
    s = tilted
    left, _ = svc.renderer.render(s.x, s.y, s.theta, v=s.v_ground, w=s.w_ground, trial=2, tick=s.tick,
                                  attitude=Attitude(roll_rad=0.1, pitch_rad=-0.05, z_m=-0.02))
    assert svc.renderer.frame_for_sample(tilted, 2).left == left.tobytes() != frame.left


def test_stereo_is_off_by_default():
    cfg = BridgeConfig(robot_name="r1", robot=PRESETS["husky"], teach=TeachConfig(waypoints=[(0, 0), (5, 0)]))
    assert cfg.stereo is None
    with pytest.raises(ValueError):
        StereoConfig(lighting_change=1.5)
