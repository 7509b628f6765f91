"""Rectified stereo rendering of the simulated world: a pure core (no bus, no clock, no global RNG).

For a robot pose (x, y, theta) on the ground, its velocity (motion blur), the trial (lighting) and the
tick (sensor noise) `StereoRenderer.render` returns the left and right mono8 images, the same bytes for
the same inputs. Geometry is exact projective geometry: every surface of the world (world.py) is a
plane, and a plane maps to the image by a homography, so

* the ground is drawn with cv2.warpPerspective of its texture, in horizontal bands: each band samples
  the mip level whose texel matches the pixel footprint across the row and is supersampled vertically
  (then box-filtered) by how much the ground is foreshortened along it, so far ground neither aliases
  nor smears; the ground is clipped `MAX_GROUND_M` ahead (beyond it: the distant hills' foot);
* the sky and distant hills are a panorama at infinity, remapped by viewing direction (identical in
  both cameras, zero disparity);
* landmarks are warped into their bounding boxes with a polygon mask, far to near (painter's
  algorithm); a rectangle crossing the near plane is clipped against it.

The left and right images run through the same code; only the camera pose differs (the right camera
is the left one moved by the baseline along the camera x axis). Afterwards: a lighting change per
trial (gain, offset, smooth shading, sun direction, cloud shadows on the ground), motion blur from the
robot's speed and turn rate during the exposure (a line kernel per image tile along the exact image
motion of the ground/sky seen in that tile) and sensor noise.

Frames: robot x forward, y left, z up, on the ground plane z = 0. Camera x right, y down, z forward.
`T_robot_camera` maps left-camera coordinates into robot coordinates. Terrain side slopes tilt the real
robot in the simulator but the rendering keeps it flat (no roll/pitch from the terrain): the camera
pose is always (x, y, theta) on z = 0 composed with the fixed mount.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from common.messages import StereoFrame
from common.camera import StereoConfig
from services.bridge.config import BridgeConfig
from services.bridge.world import World, build_world

NEAR_M = 0.05             # near clipping plane
MAX_GROUND_M = 60.0       # ground farther than this (camera depth) is not drawn: distant hills instead
MAX_LANDMARK_M = 80.0     # landmarks farther than this are not drawn
MAX_SUPERSAMPLE = 6       # most vertical supersampling of far ground bands
SUPERSAMPLE_TEXELS = 1.5  # vertical supersampling: at least one sample per this many texels
BLUR_TILES = (6, 4)       # motion blur kernel varies per tile (columns, rows)
BLUR_STEP_PX = 10.0       # longest line kernel applied in one filter2D pass (keeps kernels <= 11x11)


@dataclass(frozen=True)
class StereoCalibration:
    width_px: int
    height_px: int
    fu: float
    fv: float
    cu: float
    cv: float
    baseline_m: float
    T_robot_camera: np.ndarray      # 4x4: left-camera coordinates -> robot coordinates

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fu, 0, self.cu], [0, self.fv, self.cv], [0, 0, 1.0]])


def calibration(cfg: StereoConfig) -> StereoCalibration:
    """Pinhole intrinsics from the field of view, and the left camera's mount on the robot.

    The mount position names the rig centre, midway between the cameras: the left camera sits
    baseline/2 to the left (robot +y). Pitch tilts the optical axis `pitch_deg` below the horizon."""
    w, h = cfg.width_px, cfg.height_px
    fu = 0.5 * w / math.tan(math.radians(cfg.hfov_deg) / 2)
    p = math.radians(cfg.pitch_deg)
    # columns: camera x (right), y (down), z (forward) expressed in the robot frame
    R = np.array([[0.0, -math.sin(p), math.cos(p)],
                  [-1.0, 0.0, 0.0],
                  [0.0, -math.cos(p), -math.sin(p)]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = (cfg.mount_x_m, 0.5 * cfg.baseline_m, cfg.mount_z_m)
    return StereoCalibration(width_px=w, height_px=h, fu=fu, fv=fu, cu=(w - 1) / 2, cv=(h - 1) / 2,
                             baseline_m=cfg.baseline_m, T_robot_camera=T)


def camera_pose(calib: StereoCalibration, x: float, y: float, theta: float, right: bool = False):
    """(R_world_camera, camera centre in world) for the robot at (x, y, theta) on flat ground.

    Terrain side slopes tilt the simulated robot, but the rendering stays flat: the camera never rolls
    or pitches with the terrain (the world has no slopes to see either)."""
    c, s = math.cos(theta), math.sin(theta)
    R_wr = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = calib.T_robot_camera
    R = R_wr @ T[:3, :3]
    t = np.array([x, y, 0.0]) + R_wr @ T[:3, 3]
    if right:
        t = t + R[:, 0] * calib.baseline_m
    return R, t


def project(calib: StereoCalibration, x: float, y: float, theta: float, points_world, right: bool = False):
    """Pinhole projection of world points: (uv (N, 2), camera depth z (N,))."""
    R, t = camera_pose(calib, x, y, theta, right)
    Xc = (np.atleast_2d(np.asarray(points_world, float)) - t) @ R
    z = Xc[:, 2]
    uv = np.column_stack([calib.fu * Xc[:, 0] / z + calib.cu, calib.fv * Xc[:, 1] / z + calib.cv])
    return uv, z


def _clip_near(P: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (camera coordinates) against z >= near."""
    out = []
    n = len(P)
    for i in range(n):
        a, b = P[i], P[(i + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            out.append(a + (near - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(out)


def _seg_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from 2-D point p to segments a[i]-b[i]."""
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0, 1)
    return np.linalg.norm(a + t[:, None] * ab - p, axis=1)


@lru_cache(maxsize=1024)
def _line_kernel_q(qx: int, qy: int) -> np.ndarray:
    """Normalised kernel of a centred line segment from -(dx, dy)/2 to +(dx, dy)/2 (bilinear splats),
    with (dx, dy) = (qx, qy) / 10 px; the kernel is only as tall and wide as the segment needs."""
    dx, dy = qx / 10.0, qy / 10.0
    rx, ry = int(math.ceil(abs(dx) / 2)), int(math.ceil(abs(dy) / 2))
    w, h = 2 * rx + 1, 2 * ry + 1
    s = np.linspace(-0.5, 0.5, int(math.ceil(3 * math.hypot(dx, dy))) + 2)
    px, py = rx + s * dx, ry + s * dy
    x0, y0 = np.clip(np.floor(px), 0, w - 1).astype(int), np.clip(np.floor(py), 0, h - 1).astype(int)
    fx, fy = px - x0, py - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    idx = np.concatenate([y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1])
    wgt = np.concatenate([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    k = np.bincount(idx, wgt, minlength=w * h).reshape(h, w)
    k = (k / k.sum()).astype(np.float32)
    k.setflags(write=False)
    return k


def _line_kernel(dx: float, dy: float) -> np.ndarray:
    return _line_kernel_q(int(round(dx * 10)), int(round(dy * 10)))


class StereoRenderer:
    def __init__(self, cfg: StereoConfig, world: World, seed: int = 0):
        self.cfg, self.world, self.seed = cfg, world, int(seed)
        self.calib = c = calibration(cfg)
        W, H = c.width_px, c.height_px
        self.K = c.K
        # --- ground bands: with no roll, every image row sees the ground at one camera depth -----
        down_c = c.T_robot_camera[:3, :3].T @ np.array([0.0, 0.0, -1.0])    # "down" in camera coords
        height = cfg.mount_z_m
        v = np.arange(H, dtype=float)
        nd = down_c[1] * (v - c.cv) / c.fv + down_c[2]
        with np.errstate(divide="ignore"):
            Z = np.where(nd > 1e-9, height / nd, np.inf)
        ground = Z <= MAX_GROUND_M
        self.v_clip = int(np.argmax(ground)) if ground.any() else H   # rows below are ground
        if ground.any() and not ground[self.v_clip:].all():
            raise ValueError("camera pitch puts sky below the ground in the image")
        self.row_depth = Z
        self.bands: list[tuple[int, int, int, int]] = []
        res0 = world.ground.res_m
        nlev = len(world.ground.levels)
        for r in range(self.v_clip, H):
            across = Z[r] / c.fu
            # ground distance covered by one pixel row (between the row's upper and lower edges)
            z_lo = height / (down_c[1] * (r + 0.5 - c.cv) / c.fv + down_c[2])
            nd_hi = down_c[1] * (r - 0.5 - c.cv) / c.fv + down_c[2]
            z_hi = height / nd_hi if nd_hi > 1e-9 else 1e6
            along = abs(self._ground_range(down_c, height, z_hi) - self._ground_range(down_c, height, z_lo))
            fp = max(across, along / MAX_SUPERSAMPLE)
            lev = int(np.clip(math.floor(math.log2(max(fp / res0, 1e-9)) + 0.5), 0, nlev - 1))
            ss = int(np.clip(math.ceil(along / (SUPERSAMPLE_TEXELS * res0 * 2 ** lev)), 1, MAX_SUPERSAMPLE))
            if self.bands and self.bands[-1][1] == r and self.bands[-1][2:] == (lev, ss):
                self.bands[-1] = (self.bands[-1][0], r + 1, lev, ss)
            else:
                self.bands.append((r, r + 1, lev, ss))
        # --- sky: azimuth (relative to the heading) and elevation of every pixel above the clip ---
        self._sky_maps = None
        if self.v_clip > 0:
            uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(self.v_clip, dtype=float))
            rays = np.stack([(uu - c.cu) / c.fu, (vv - c.cv) / c.fv, np.ones_like(uu)], axis=-1)
            d = rays @ c.T_robot_camera[:3, :3].T            # robot frame
            az = np.arctan2(d[..., 1], d[..., 0])
            el = np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
            daz, delv = world.sky.rad_per_px
            self._sky_maps = ((az / daz - 0.5).astype(np.float32),
                              ((world.sky.el_top_rad - el) / delv - 0.5).astype(np.float32))
        # --- motion blur tiles: centre pixel and the depth seen there ---------------------------
        nx, ny = BLUR_TILES
        xs, ys = np.linspace(0, W, nx + 1).astype(int), np.linspace(0, H, ny + 1).astype(int)
        self._tiles = [(ys[j], ys[j + 1], xs[i], xs[i + 1]) for j in range(ny) for i in range(nx)]
        ctr = np.array([[0.5 * (x0 + x1 - 1), 0.5 * (y0 + y1 - 1)] for y0, y1, x0, x1 in self._tiles])
        depth = np.array([Z[int(cy)] if int(cy) >= self.v_clip else 1e4 for _, cy in ctr])
        rays = np.column_stack([(ctr[:, 0] - c.cu) / c.fu, (ctr[:, 1] - c.cv) / c.fv, np.ones(len(ctr))])
        self._tile_pts_c = rays * depth[:, None]                   # camera coordinates
        # --- sensor noise bank (drawn once; each frame reads it at seeded offsets) ----------------
        n = W * H
        if cfg.noise_dn > 0:
            bank = np.random.default_rng([self.seed & 0xFFFFFFFF, 4401]).standard_normal(3 * n) * cfg.noise_dn
            self._noise = np.clip(np.round(bank), -127, 127).astype(np.int16)
        else:
            self._noise = None
        self._light_cache: dict[int, dict] = {}
        self._lm_cache: dict[int, tuple[list[np.ndarray], float]] = {}

    @staticmethod
    def _ground_range(down_c: np.ndarray, height: float, z: float) -> float:
        """Horizontal distance ahead of the camera of the centre-column ground point at camera depth z."""
        dy, dz = down_c[1], down_c[2]
        y_n = (height / z - dz) / dy
        return z * (dy - dz * y_n)      # the point z (0, y_n, 1) along forward = (0, -dz, dy)

    # --- public ---------------------------------------------------------------------------------
    @classmethod
    def from_bridge_config(cls, cfg: BridgeConfig) -> "StereoRenderer":
        world = build_world(cfg.teach.waypoints, cfg.seed, corner_radius_m=cfg.teach.corner_radius_m,
                            loop=cfg.teach.loop, landmark_density=cfg.stereo.landmark_density)
        return cls(cfg.stereo, world, cfg.seed)

    def render(self, x: float, y: float, theta: float, *, v: float = 0.0, w: float = 0.0,
               trial: int = 0, tick: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Left and right images (uint8, height x width) for the robot at (x, y, theta) moving at
        (v, w) during the exposure, in trial `trial` (lighting) at tick `tick` (noise)."""
        sky = self._render_sky(theta)
        light = self._lighting(trial) if self.cfg.lighting_change > 0 else None
        n = self.calib.width_px * self.calib.height_px
        rng = np.random.default_rng([self.seed & 0xFFFFFFFF, 4402, trial & 0xFFFFFFFF, tick & 0xFFFFFFFFFFFF])
        offs = rng.integers(0, 2 * n, 2)
        # bumps shake the rig: random roll and pitch rates growing with speed (robot frame, rad/s)
        shake = rng.standard_normal(2) * self.cfg.vibration_radps_per_mps * abs(v) * np.array([0.5, 1.0])
        out = []
        for i, right in enumerate((False, True)):
            img = self._render_scene(x, y, theta, right, sky, light)
            if light is not None:
                g = light["gain"] * (1.0 + light["sun_amp"] * math.cos(theta - light["sun_az"]))
                img = cv2.multiply(img, light["field"], scale=g / 128.0)
                img = cv2.addWeighted(img, 1.0, img, 0.0, light["offset"])
            img = self._motion_blur(img, right, v, w, shake)
            if self._noise is not None:
                o = int(offs[i])
                img = cv2.add(img, self._noise[o:o + n].reshape(img.shape), dtype=cv2.CV_8U)
            out.append(img)
        return out[0], out[1]

    def frame(self, *, stamp_s: float, tick: int, trial: int, x: float, y: float, theta: float,
              v: float = 0.0, w: float = 0.0) -> StereoFrame:
        left, right = self.render(x, y, theta, v=v, w=w, trial=trial, tick=tick)
        c = self.calib
        if self.cfg.encoding == "png":
            enc = [cv2.IMWRITE_PNG_COMPRESSION, 1]
            lb, rb = (cv2.imencode(".png", im, enc)[1].tobytes() for im in (left, right))
        else:
            lb, rb = left.tobytes(), right.tobytes()
        return StereoFrame(stamp_s=stamp_s, tick=tick, trial=trial, width_px=c.width_px, height_px=c.height_px,
                           encoding=self.cfg.encoding, left=lb, right=rb, fu_px=c.fu, fv_px=c.fv, cu_px=c.cu,
                           cv_px=c.cv, baseline_m=c.baseline_m,
                           T_robot_camera=tuple(float(a) for a in c.T_robot_camera.ravel()),
                           exposure_s=self.cfg.exposure_s)

    def frame_for_sample(self, sample, trial: int) -> StereoFrame:
        """The frame for a simulator sample (services.bridge.simulator.SimSample), stamped with it."""
        return self.frame(stamp_s=sample.stamp_s, tick=sample.tick, trial=trial, x=sample.x, y=sample.y,
                          theta=sample.theta, v=sample.v_ground, w=sample.w_ground)

    # --- scene ----------------------------------------------------------------------------------
    def _render_sky(self, theta: float) -> np.ndarray | None:
        if self._sky_maps is None:
            return None
        mx, my = self._sky_maps
        daz, _ = self.world.sky.rad_per_px
        shift = np.float32((theta % (2 * math.pi)) / daz)
        return cv2.remap(self.world.sky.panorama, mx + shift, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def _render_scene(self, x, y, theta, right, sky, light) -> np.ndarray:
        c = self.calib
        W, H = c.width_px, c.height_px
        img = np.empty((H, W), np.uint8)
        if sky is not None:
            img[:self.v_clip] = sky
        R, t = camera_pose(c, x, y, theta, right)
        Rt = R.T
        Hg = self.K @ np.column_stack([Rt[:, 0], Rt[:, 1], -Rt @ t])    # ground (x, y, 1) -> pixel
        gt = self.world.ground
        Hg_inv = np.linalg.inv(Hg)
        for r0, r1, lev, ss in self.bands:
            S = np.array([[1.0, 0, 0], [0, 1.0 / ss, r0 - 0.5 + 0.5 / ss], [0, 0, 1]])
            M = gt.tex_from_world(lev) @ Hg_inv @ S                       # band pixel -> texel
            band = cv2.warpPerspective(gt.levels[lev], M, (W, (r1 - r0) * ss),
                                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                       borderMode=cv2.BORDER_REFLECT_101)
            if ss > 1:
                band = cv2.resize(band, (W, r1 - r0), interpolation=cv2.INTER_AREA)
            img[r0:r1] = band
        if light is not None and self.v_clip < H:
            self._cloud_shadows(img, Hg, light)
        self._draw_landmarks(img, R, t)
        return img

    def _landmark_maps(self, i: int) -> tuple[list[np.ndarray], float]:
        """Per landmark (cached): texel -> world maps of every mip level, and the level-0 texel size."""
        if i not in self._lm_cache:
            lm = self.world.landmarks[i]
            rows0, cols0 = lm.levels[0].shape
            texel = min(float(np.linalg.norm(lm.b - lm.a)) / cols0, lm.height_m / rows0)
            self._lm_cache[i] = ([lm.world_from_tex(k) for k in range(len(lm.levels))], texel)
        return self._lm_cache[i]

    def _draw_landmarks(self, img: np.ndarray, R: np.ndarray, t: np.ndarray) -> None:
        world = self.world
        if not world.landmarks:
            return
        c = self.calib
        H, W = img.shape
        C = world.landmark_corners()
        Xc = (C - t) @ R                                  # (N, 4, 3) camera coordinates
        z = Xc[..., 2]
        zmin, zmax = z.min(axis=1), z.max(axis=1)
        cand = (zmax > NEAR_M) & (zmin < MAX_LANDMARK_M)
        # wholly in front of the near plane: project all at once
        full = np.nonzero(cand & (zmin >= NEAR_M))[0]
        P = Xc[full]
        U = c.fu * P[..., 0] / P[..., 2] + c.cu
        V = c.fv * P[..., 1] / P[..., 2] + c.cv
        x0 = np.maximum(np.floor(U.min(axis=1)), 0)
        y0 = np.maximum(np.floor(V.min(axis=1)), 0)
        x1 = np.minimum(np.ceil(U.max(axis=1)) + 1, W)
        y1 = np.minimum(np.ceil(V.max(axis=1)) + 1, H)
        vis = (x1 > x0) & (y1 > y0)
        items = [(int(i), np.column_stack([U[k], V[k]]), (int(x0[k]), int(y0[k]), int(x1[k]), int(y1[k])))
                 for k, i in enumerate(full) if vis[k]]
        # crossing the near plane: clip first
        for i in np.nonzero(cand & (zmin < NEAR_M))[0]:
            P = _clip_near(Xc[i], NEAR_M)
            if len(P) < 3:
                continue
            uv = np.column_stack([c.fu * P[:, 0] / P[:, 2] + c.cu, c.fv * P[:, 1] / P[:, 2] + c.cv])
            bx0, by0 = max(0, int(math.floor(uv[:, 0].min()))), max(0, int(math.floor(uv[:, 1].min())))
            bx1, by1 = min(W, int(math.ceil(uv[:, 0].max())) + 1), min(H, int(math.ceil(uv[:, 1].max())) + 1)
            if bx1 > bx0 and by1 > by0:
                items.append((int(i), uv, (bx0, by0, bx1, by1)))
        if not items:
            return
        idx = np.array([it[0] for it in items])
        dist = _seg_distance(t[:2], world.landmark_corners()[idx, 3, :2], world.landmark_corners()[idx, 2, :2])
        Rt = R.T
        Rt_t = np.outer(Rt @ t, [0.0, 0.0, 1.0])
        for k in np.argsort(-dist, kind="stable"):          # far to near
            i, uv, (bx0, by0, bx1, by1) = items[k]
            lm = world.landmarks[i]
            maps, texel = self._landmark_maps(i)
            zmid = max(float(np.clip(Xc[i, :, 2], NEAR_M, None).mean()), NEAR_M)
            lev = min(max(int(math.floor(math.log2(max(zmid / c.fu / texel, 1e-9)) + 0.5)), 0), len(maps) - 1)
            Ht = self.K @ (Rt @ maps[lev] - Rt_t)           # texel (s, t, 1) -> pixel
            M = np.linalg.inv(Ht)
            M = M @ np.array([[1.0, 0, bx0], [0, 1.0, by0], [0, 0, 1]])
            patch = cv2.warpPerspective(lm.levels[lev], M, (bx1 - bx0, by1 - by0),
                                        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                        borderMode=cv2.BORDER_REPLICATE)
            mask = np.zeros((by1 - by0, bx1 - bx0), np.uint8)
            cv2.fillConvexPoly(mask, np.round((uv - (bx0, by0)) * 16).astype(np.int32), 1, cv2.LINE_8, 4)
            np.copyto(img[by0:by1, bx0:bx1], patch, where=mask.view(bool))

    # --- lighting -------------------------------------------------------------------------------
    def _lighting(self, trial: int) -> dict:
        if trial in self._light_cache:
            return self._light_cache[trial]
        lc = self.cfg.lighting_change
        c = self.calib
        rng = np.random.default_rng([self.seed & 0xFFFFFFFF, 4301, trial & 0xFFFFFFFF])
        grid = rng.standard_normal((3, 4)).astype(np.float32)
        field = 1.0 + 0.3 * lc * cv2.resize(grid, (c.width_px, c.height_px), interpolation=cv2.INTER_CUBIC)
        # cloud shadows: a soft-edged field fixed on the ground for the whole trial
        gt = self.world.ground
        rows0, cols0 = gt.levels[0].shape
        res_s = 0.25
        sh_cols, sh_rows = max(2, int(cols0 * gt.res_m / res_s)), max(2, int(rows0 * gt.res_m / res_s))
        cell = rng.uniform(6.0, 14.0) / res_s
        g2 = rng.standard_normal((int(sh_rows / cell) + 3, int(sh_cols / cell) + 3)).astype(np.float32)
        noise = cv2.resize(g2, (int((g2.shape[1]) * cell), int(g2.shape[0] * cell)),
                           interpolation=cv2.INTER_CUBIC)[:sh_rows, :sh_cols]
        coverage = rng.uniform(0.2, 0.6)
        thresh = np.quantile(noise, 1.0 - coverage)
        mask = np.clip((noise - thresh) / 0.3 + 0.5, 0, 1)
        darkness = lc * rng.uniform(0.3, 0.55)
        shadow = np.clip(np.round(128 * (1.0 - darkness * mask)), 0, 255).astype(np.uint8)
        light = dict(gain=1.0 + lc * rng.uniform(-0.45, 0.3), offset=lc * rng.uniform(-25, 20),
                     sun_az=rng.uniform(0, 2 * math.pi), sun_amp=lc * rng.uniform(0.05, 0.25),
                     field=np.clip(np.round(128 * field), 0, 255).astype(np.uint8),
                     shadow=shadow)
        if len(self._light_cache) > 4:
            self._light_cache.pop(next(iter(self._light_cache)))
        self._light_cache[trial] = light
        return light

    def _cloud_shadows(self, img: np.ndarray, Hg: np.ndarray, light: dict) -> None:
        gt = self.world.ground
        sh = light["shadow"]
        rows0, cols0 = gt.levels[0].shape
        # shadow texel (j, i) centre <-> world x0 + (j + 0.5) * sx
        sx = cols0 * gt.res_m / sh.shape[1]
        sy = rows0 * gt.res_m / sh.shape[0]
        A = np.array([[sx, 0, gt.x0 + 0.5 * sx], [0, sy, gt.y0 + 0.5 * sy], [0, 0, 1]])
        H, W = img.shape
        q = 4
        rows = H - self.v_clip
        w4, h4 = (W + q - 1) // q, (rows + q - 1) // q
        S = np.array([[q, 0, 0.5 * (q - 1)], [0, q, self.v_clip + 0.5 * (q - 1)], [0, 0, 1]])
        small = cv2.warpPerspective(sh, np.linalg.inv(Hg @ A) @ S, (w4, h4),
                                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT_101)
        full = cv2.resize(small, (w4 * q, h4 * q), interpolation=cv2.INTER_LINEAR)[:rows, :W]
        img[self.v_clip:] = cv2.multiply(img[self.v_clip:], full, scale=1.0 / 128)

    # --- motion blur ----------------------------------------------------------------------------
    def _flows(self, right: bool, v: float, w: float, shake=(0.0, 0.0)) -> np.ndarray:
        """Image motion (px) of each blur tile's centre point during the exposure, for the robot moving
        at (v, w) on the ground and rolling/pitching at `shake` (rad/s, small-angle)."""
        c = self.calib
        e = self.cfg.exposure_s
        T = c.T_robot_camera
        R_rc, p_rc = T[:3, :3], T[:3, 3] + (T[:3, 0] * c.baseline_m if right else 0.0)
        X_r = self._tile_pts_c @ R_rc.T + p_rc
        uvs = []
        for tau in (-0.5 * e, 0.5 * e):
            a = w * tau
            if abs(w) > 1e-9:
                dx, dy = v * math.sin(a) / w, v * (1 - math.cos(a)) / w
            else:
                dx, dy = v * tau, 0.0
            ca, sa = math.cos(a), math.sin(a)
            q = X_r - np.array([dx, dy, 0.0])
            q = np.column_stack([ca * q[:, 0] + sa * q[:, 1], -sa * q[:, 0] + ca * q[:, 1], q[:, 2]])
            ax, ay = shake[0] * tau, shake[1] * tau         # small rotation about robot x and y
            q = q - np.column_stack([ay * q[:, 2], -ax * q[:, 2], ax * q[:, 1] - ay * q[:, 0]])
            Xc = (q - p_rc) @ R_rc
            z = np.maximum(Xc[:, 2], NEAR_M)
            uvs.append(np.column_stack([c.fu * Xc[:, 0] / z, c.fv * Xc[:, 1] / z]))
        return uvs[1] - uvs[0]

    def _motion_blur(self, img: np.ndarray, right: bool, v: float, w: float, shake=(0.0, 0.0)) -> np.ndarray:
        if self.cfg.exposure_s <= 0 or (abs(v) < 1e-4 and abs(w) < 1e-5):
            return img
        flows = self._flows(right, v, w, shake)
        lengths = np.hypot(flows[:, 0], flows[:, 1])
        if lengths.max() < 0.3:
            return img
        H, W = img.shape
        out = img.copy()
        for (y0, y1, x0, x1), (fx, fy), L in zip(self._tiles, flows, lengths):
            if L < 0.3:
                continue
            passes = max(1, int(math.ceil(L / BLUR_STEP_PX)))
            k = _line_kernel(fx / passes, fy / passes)
            my, mx = passes * (k.shape[0] // 2) + 1, passes * (k.shape[1] // 2) + 1
            ya, yb, xa, xb = max(0, y0 - my), min(H, y1 + my), max(0, x0 - mx), min(W, x1 + mx)
            region = img[ya:yb, xa:xb]
            for _ in range(passes):
                region = cv2.filter2D(region, -1, k, borderType=cv2.BORDER_REFLECT_101)
            out[y0:y1, x0:x1] = region[y0 - ya:y1 - ya, x0 - xa:x1 - xa]
        return out
