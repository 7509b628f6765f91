"""Rectified stereo rendering of the simulated world: a pure core (no bus, no clock, no global RNG).

For a robot pose (x, y, theta) on the ground, its attitude on the terrain (roll, pitch, sink: terrain.py
`Attitude`), its velocity (motion blur), the trial (lighting) and the tick (sensor noise)
`StereoRenderer.render` returns the left and right mono8 images, the same bytes for the same inputs.
Geometry is exact projective geometry: every surface of the world (world.py) is a plane, and a plane
maps to the image by a homography, so

* the ground is drawn with cv2.warpPerspective of its texture, in bands: each band samples the mip
  level whose texel matches the pixel footprint across the row and is supersampled vertically (then
  box-filtered) by how much the ground is foreshortened along it, so far ground neither aliases nor
  smears; the ground is clipped `MAX_GROUND_M` ahead (beyond it: the distant hills' foot). A level or
  only pitched camera sees one ground depth per image row, so a band is a run of whole rows; a rolled
  camera sees it along tilted lines, so its bands are cut into `GROUND_TILE_PX` wide columns, each
  with the footprint at its centre, and the sky is drawn over the ground beyond the clip line;
* the sky and distant hills are a panorama at infinity, remapped by viewing direction (identical in
  both cameras, zero disparity; for a tilted robot the directions are exact on a `SKY_GRID_PX` grid
  and interpolated bilinearly between, a few hundredths of a panorama pixel off);
* landmarks are warped into their bounding boxes with a polygon mask, far to near (painter's
  algorithm); a rectangle crossing the near plane is clipped against it.

The left and right images run through the same code; only the camera pose differs (the right camera
is the left one moved by the baseline along the camera x axis). Afterwards: a lighting change per
trial (gain, offset, smooth shading, sun direction, cloud shadows on the ground), motion blur from the
robot's speed and turn rate during the exposure (a line kernel per image tile along the exact image
motion of the ground/sky seen in that tile) and sensor noise.

Frames: robot x forward, y left, z up, its origin the ground contact point. Camera x right, y down,
z forward. `T_robot_camera` maps left-camera coordinates into robot coordinates. The world is drawn
flat and upright: the ground is the plane z = 0 and landmarks stand vertical on it. The terrain acts
on the robot only: side slopes and ruts roll and pitch the body about its ground contact point and
ruts lower it (`Attitude`, R_world_robot = Rz(theta) Ry(pitch) Rx(roll), contact point at
(x, y, z_m)), so the camera tilts and shifts as the robot's does, while the slope itself is not seen
(a documented simplification: the robot tilts, the drawn world does not).
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
from services.bridge.terrain import LEVEL, Attitude
from services.bridge.world import World, build_world

NEAR_M = 0.05             # near clipping plane
MAX_GROUND_M = 60.0       # ground farther than this (camera depth) is not drawn: distant hills instead
MAX_LANDMARK_M = 80.0     # landmarks farther than this are not drawn
MAX_SUPERSAMPLE = 6       # most vertical supersampling of far ground bands
SUPERSAMPLE_TEXELS = 1.5  # vertical supersampling: at least one sample per this many texels
BLUR_TILES = (6, 4)       # motion blur kernel varies per tile (columns, rows)
BLUR_STEP_PX = 10.0       # longest line kernel applied in one filter2D pass (keeps kernels <= 11x11)
GROUND_TILE_PX = 80       # rolled camera: ground bands are cut into columns this wide (own mip level each)
MERGE_SLACK_ROWS = 12     # rolled camera: extra supersampled rows allowed to merge a tile's bands
SKY_GRID_PX = 8           # tilted robot: sky directions computed exactly on this grid, bilinear between


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


def camera_pose(calib: StereoCalibration, x: float, y: float, theta: float, right: bool = False,
                attitude: Attitude = LEVEL):
    """(R_world_camera, camera centre in world) for the robot at (x, y, theta) with `attitude`: rolled
    and pitched about its ground contact point, which sits at height attitude.z_m."""
    c, s = math.cos(theta), math.sin(theta)
    R_wr = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    if not attitude.is_level:
        R_wr = R_wr @ attitude.R_level_body()
    T = calib.T_robot_camera
    R = R_wr @ T[:3, :3]
    t = np.array([x, y, attitude.z_m]) + R_wr @ T[:3, 3]
    if right:
        t = t + R[:, 0] * calib.baseline_m
    return R, t


def project(calib: StereoCalibration, x: float, y: float, theta: float, points_world, right: bool = False,
            attitude: Attitude = LEVEL):
    """Pinhole projection of world points: (uv (N, 2), camera depth z (N,))."""
    R, t = camera_pose(calib, x, y, theta, right, attitude)
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


def _ground_depth(nd: np.ndarray, height: float) -> np.ndarray:
    """Camera depth of the ground along rays (unit camera z) whose component along world down is nd,
    for a camera `height` above it; inf where the ray does not come down to the ground."""
    with np.errstate(divide="ignore"):
        return np.where(nd > 1e-9, height / nd, np.inf)


def _rows_of(mask: np.ndarray, margin: bool) -> tuple[int, int]:
    """[first, last + 1) of the True rows of `mask` (one run; (n, n) when none), with `margin` one row
    wider on both sides: rounding at a rolled camera's clip line is left to the pixel mask there."""
    n = len(mask)
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return n, n
    a, b = int(idx[0]), int(idx[-1]) + 1
    return (max(a - 1, 0), min(b + 1, n)) if margin else (a, b)


@dataclass(frozen=True)
class _View:
    """What one camera's rotation and height above the ground plane decide about drawing it
    (`StereoRenderer._view`): once for the level robot, per frame and camera for a tilted one."""
    down_c: np.ndarray                  # world down in camera coordinates
    height_m: float                     # camera centre above the ground plane
    ground_rows: tuple[int, int]        # image rows [a, b) with some ground within MAX_GROUND_M
    drawn_rows: tuple[int, int]         # image rows [a, b) the ground bands cover (a row more when rolled)
    sky_rows: tuple[int, int]           # image rows [a, b) with some sky (anything beyond that)
    bands: list[tuple[int, int, int, int, int, int]]   # ground: (row0, row1, col0, col1, mip level, supersampling)
    tile_pts_c: np.ndarray              # per motion-blur tile: the scene point at its centre (camera coords)


class StereoRenderer:
    def __init__(self, cfg: StereoConfig, world: World, seed: int = 0):
        self.cfg, self.world, self.seed = cfg, world, int(seed)
        self.calib = c = calibration(cfg)
        W, H = c.width_px, c.height_px
        self.K = c.K
        # --- motion blur tiles: each has its centre pixel's scene point per view -------------------
        nx, ny = BLUR_TILES
        xs, ys = np.linspace(0, W, nx + 1).astype(int), np.linspace(0, H, ny + 1).astype(int)
        self._tiles = [(ys[j], ys[j + 1], xs[i], xs[i + 1]) for j in range(ny) for i in range(nx)]
        self._tile_ctr = np.array([[0.5 * (x0 + x1 - 1), 0.5 * (y0 + y1 - 1)] for y0, y1, x0, x1 in self._tiles])
        # --- the level robot's view (both cameras alike) and its sky directions, drawn once ---------
        R_rc = c.T_robot_camera[:3, :3]
        self._level = self._view(R_rc, cfg.mount_z_m)
        g0, g1 = self._level.ground_rows
        if g0 < g1 and g1 != H:
            raise ValueError("camera pitch puts sky below the ground in the image")
        self._sky_maps = None
        v_clip = self._level.ground_rows[0]           # the sky is drawn above it
        if v_clip > 0:
            self._sky_maps = self._sky_lookup(R_rc, *np.meshgrid(np.arange(W, dtype=float),
                                                                np.arange(v_clip, dtype=float)))
        # --- sensor noise bank (drawn once; each frame reads it at seeded offsets) ----------------
        n = W * H
        if cfg.noise_dn > 0:
            bank = np.random.default_rng([self.seed & 0xFFFFFFFF, 4401]).standard_normal(3 * n) * cfg.noise_dn
            self._noise = np.clip(np.round(bank), -127, 127).astype(np.int16)
        else:
            self._noise = None
        self._light_cache: dict[int, dict] = {}
        self._lm_cache: dict[int, tuple[list[np.ndarray], float]] = {}

    # --- how a camera sees the ground plane -----------------------------------------------------
    def _nd(self, down_c: np.ndarray, u, v):
        """World down . the ray through pixel (u, v) (unit camera z): the ground is at depth height / nd."""
        c = self.calib
        return down_c[0] * (u - c.cu) / c.fu + down_c[1] * (v - c.cv) / c.fv + down_c[2]

    def _view(self, R_lc: np.ndarray, height: float) -> _View:
        """The drawing plan of a camera whose axes are the columns of R_lc in the level frame of the
        robot's heading (z up), `height` above the ground. The ground's depth is linear along an image
        row, so a column range's ground and sky rows follow from its two end columns."""
        c = self.calib
        W, H = c.width_px, c.height_px
        down_c = R_lc.T @ np.array([0.0, 0.0, -1.0])
        rolled = down_c[0] != 0.0           # then the ground's depth varies along an image row
        rows = np.arange(H, dtype=float)
        c0s = list(range(0, W, GROUND_TILE_PX)) if rolled else [0]
        c1s = [min(c0 + GROUND_TILE_PX, W) for c0 in c0s] if rolled else [W]
        # ground within MAX_GROUND_M at each tile's end columns, and at the image's (last entry)
        ends = np.array([c0s + [0], [c1 - 1 for c1 in c1s] + [W - 1]], dtype=float)
        ground = _ground_depth(self._nd(down_c, ends[:, None, :], rows[:, None]), height) <= MAX_GROUND_M
        some_ground, some_sky = ground.any(axis=0), ~ground.all(axis=0)
        # a tile's footprint is the centre column's at the same ground depth, dv rows further down
        dy = down_c[1] if abs(down_c[1]) > 1e-9 else 1e-9     # 0: image columns run along the horizon
        dv = (np.array([down_c[0] * (0.5 * (c0 + c1 - 1) - c.cu) / c.fu * c.fv / dy
                        for c0, c1 in zip(c0s, c1s)]) if rolled else np.zeros(1))
        lev, ss = self._footprint_levels(down_c, height, rows[:, None] + dv[None, :])
        bands = []
        for j, (c0, c1) in enumerate(zip(c0s, c1s)):
            ra, rb = _rows_of(some_ground[:, j], margin=rolled)
            bands += self._runs(lev[ra:rb, j], ss[ra:rb, j], ra, c0, c1, merge=rolled)
        drawn_rows = (min(b[0] for b in bands), max(b[1] for b in bands)) if bands else (H, H)
        sky_rows = _rows_of(some_sky[:, -1], margin=rolled)
        # motion blur: the ground point at each tile's centre (its row, as drawn), else far away
        ctr = self._tile_ctr
        depth = _ground_depth(self._nd(down_c, ctr[:, 0], np.floor(ctr[:, 1])), height)
        depth = np.where(depth <= MAX_GROUND_M, depth, 1e4)
        rays = np.column_stack([(ctr[:, 0] - c.cu) / c.fu, (ctr[:, 1] - c.cv) / c.fv, np.ones(len(ctr))])
        return _View(down_c=down_c, height_m=float(height), ground_rows=_rows_of(some_ground[:, -1], margin=False),
                     drawn_rows=drawn_rows, sky_rows=sky_rows, bands=bands, tile_pts_c=rays * depth[:, None])

    def _footprint_levels(self, down_c: np.ndarray, height: float, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mip level, supersampling) as int arrays for the centre-column pixels at rows v (H x tiles),
        from the pixel's ground footprint: across it (depth / fu) and along it (the ground between
        its upper and lower edges). The level matches the larger of across and along /
        MAX_SUPERSAMPLE; vertical supersampling covers the rest of along. A pixel that sees no ground
        (a rolled camera's tile corner beyond the clip) takes the nearest one's in its column that does."""
        c = self.calib
        res0, nlev = self.world.ground.res_m, len(self.world.ground.levels)
        Z = _ground_depth(self._nd(down_c, c.cu, v), height)
        nd_lo, nd_hi = self._nd(down_c, c.cu, v + 0.5), self._nd(down_c, c.cu, v - 0.5)
        # the centre column's ground points at camera depth z are P0 + z e: a row covers |dz| |e|
        dy = down_c[1] if abs(down_c[1]) > 1e-9 else 1e-9
        e = np.array([0.0, -down_c[2] / dy, 1.0])
        with np.errstate(divide="ignore", invalid="ignore"):
            z_lo = np.where(nd_lo > 1e-9, height / nd_lo, 1e6)
            z_hi = np.where(nd_hi > 1e-9, height / nd_hi, 1e6)
            along = np.abs(z_hi - z_lo) * float(np.linalg.norm(e))
            fp = np.maximum(Z / c.fu, along / MAX_SUPERSAMPLE)
            lev = np.clip(np.floor(np.log2(np.maximum(fp / res0, 1e-9)) + 0.5), 0, nlev - 1)
            ss = np.clip(np.ceil(along / (SUPERSAMPLE_TEXELS * res0 * 2.0 ** lev)), 1, MAX_SUPERSAMPLE)
        seen = Z <= MAX_GROUND_M            # one run of rows per column: depth is monotonic down a column
        n = len(v)
        first, last = np.argmax(seen, axis=0), n - 1 - np.argmax(seen[::-1], axis=0)
        k = np.clip(np.arange(n)[:, None], first, last)
        any_seen = seen.any(axis=0)
        return (np.where(any_seen, np.take_along_axis(lev, k, axis=0), nlev - 1).astype(int),
                np.where(any_seen, np.take_along_axis(ss, k, axis=0), 1).astype(int))

    @staticmethod
    def _runs(lev: np.ndarray, ss: np.ndarray, r0: int, c0: int, c1: int,
              merge: bool) -> list[tuple[int, int, int, int, int, int]]:
        """Bands (row0, row1, c0, c1, level, supersampling) of consecutive rows (the first is r0) of equal
        level and supersampling. With `merge` (a rolled camera's tiles, which would otherwise make
        many small warps) a run joins the band above it when the level is the same and supersampling
        all of it at the band's most costs at most MERGE_SLACK_ROWS extra rows."""
        if len(lev) == 0:
            return []
        key = lev * (MAX_SUPERSAMPLE + 1) + ss
        bounds = [0, *(np.flatnonzero(key[1:] != key[:-1]) + 1).tolist(), len(lev)]
        levs, sss = lev.tolist(), ss.tolist()
        bands: list[list[int]] = []           # [row0, row1, level, supersampling, supersampled rows]
        for a, b in zip(bounds[:-1], bounds[1:]):
            la, sa = levs[a], sss[a]
            if merge and bands and bands[-1][2] == la:
                top = bands[-1]
                s_max = max(top[3], sa)
                if s_max * (b - top[0]) - (top[4] + sa * (b - a)) <= MERGE_SLACK_ROWS:
                    top[1], top[3], top[4] = b, s_max, top[4] + sa * (b - a)
                    continue
            bands.append([a, b, la, sa, sa * (b - a)])
        return [(r0 + a, r0 + b, c0, c1, la, sa) for a, b, la, sa, _ in bands]

    def _views(self, attitude: Attitude) -> tuple[np.ndarray, _View, _View]:
        """(R_level_camera, left view, right view) for the robot at `attitude`: the cameras rotate
        with the body about its ground contact point, so with roll the right one sits higher or lower."""
        T = self.calib.T_robot_camera
        if attitude.is_level:
            return T[:3, :3], self._level, self._level
        R_t = attitude.R_level_body()
        R_lc = R_t @ T[:3, :3]
        h_left = attitude.z_m + float(R_t[2] @ T[:3, 3])
        h_right = h_left + R_lc[2, 0] * self.calib.baseline_m
        return R_lc, self._view(R_lc, h_left), self._view(R_lc, h_right)

    # --- public ---------------------------------------------------------------------------------
    @classmethod
    def from_bridge_config(cls, cfg: BridgeConfig) -> "StereoRenderer":
        world = build_world(cfg.teach.waypoints, cfg.seed, corner_radius_m=cfg.teach.corner_radius_m,
                            loop=cfg.teach.loop, landmark_density=cfg.stereo.landmark_density)
        return cls(cfg.stereo, world, cfg.seed)

    def render(self, x: float, y: float, theta: float, *, v: float = 0.0, w: float = 0.0,
               trial: int = 0, tick: int = 0, attitude: Attitude = LEVEL) -> tuple[np.ndarray, np.ndarray]:
        """Left and right images (uint8, height x width) for the robot at (x, y, theta) with `attitude`
        on the terrain, moving at (v, w) during the exposure, in trial `trial` (lighting) at tick
        `tick` (noise)."""
        R_lc, *views = self._views(attitude)
        sky = self._render_sky(theta, attitude, R_lc, views)
        light = self._lighting(trial) if self.cfg.lighting_change > 0 else None
        n = self.calib.width_px * self.calib.height_px
        rng = np.random.default_rng([self.seed & 0xFFFFFFFF, 4402, trial & 0xFFFFFFFF, tick & 0xFFFFFFFFFFFF])
        offs = rng.integers(0, 2 * n, 2)
        # bumps shake the rig: random roll and pitch rates growing with speed (robot frame, rad/s)
        shake = rng.standard_normal(2) * self.cfg.vibration_radps_per_mps * abs(v) * np.array([0.5, 1.0])
        out = []
        for i, right in enumerate((False, True)):
            img = self._render_scene(x, y, theta, right, attitude, views[i], sky, light)
            if light is not None:
                g = light["gain"] * (1.0 + light["sun_amp"] * math.cos(theta - light["sun_az"]))
                img = cv2.multiply(img, light["field"], scale=g / 128.0)
                img = cv2.addWeighted(img, 1.0, img, 0.0, light["offset"])
            img = self._motion_blur(img, right, v, w, shake, views[i].tile_pts_c, attitude)
            if self._noise is not None:
                o = int(offs[i])
                img = cv2.add(img, self._noise[o:o + n].reshape(img.shape), dtype=cv2.CV_8U)
            out.append(img)
        return out[0], out[1]

    def frame(self, *, stamp_s: float, tick: int, trial: int, x: float, y: float, theta: float,
              v: float = 0.0, w: float = 0.0, attitude: Attitude = LEVEL) -> StereoFrame:
        left, right = self.render(x, y, theta, v=v, w=w, trial=trial, tick=tick, attitude=attitude)
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
        """The frame for a simulator sample (services.bridge.simulator.SimSample), stamped with it and
        seen from the body's attitude on the terrain there."""
        return self.frame(stamp_s=sample.stamp_s, tick=sample.tick, trial=trial, x=sample.x, y=sample.y,
                          theta=sample.theta, v=sample.v_ground, w=sample.w_ground, attitude=sample.attitude)

    # --- scene ----------------------------------------------------------------------------------
    def _sky_lookup(self, R_lc: np.ndarray, uu: np.ndarray, vv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Panorama (column, row) of the viewing direction of pixels (uu, vv), azimuth relative to the
        heading, for a camera with axes R_lc in the heading's level frame."""
        c, sky = self.calib, self.world.sky
        rays = np.stack([(uu - c.cu) / c.fu, (vv - c.cv) / c.fv, np.ones_like(uu)], axis=-1)
        d = rays @ R_lc.T                                  # level frame of the heading
        az = np.arctan2(d[..., 1], d[..., 0])
        el = np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
        daz, delv = sky.rad_per_px
        return (az / daz - 0.5).astype(np.float32), ((sky.el_top_rad - el) / delv - 0.5).astype(np.float32)

    def _sky_maps_grid(self, R_lc: np.ndarray, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
        """`_sky_lookup` for rows [r0, r1): exact on a SKY_GRID_PX grid reaching one node beyond every
        side, bilinear in between (cv2.resize puts node k on output pixel g k + (g - 1) / 2). A robot
        pitched up on a steep slope may look above the panorama: it keeps the top row's sky there
        rather than wrap round to the hills."""
        g, W = SKY_GRID_PX, self.calib.width_px
        nu, nv = -(-W // g) + 2, -(-(r1 - r0) // g) + 2
        us = g * np.arange(nu, dtype=float) + 0.5 * (g - 1) - g
        vs = r0 + g * np.arange(nv, dtype=float) + 0.5 * (g - 1) - g
        mx, my = (cv2.resize(m, (nu * g, nv * g), interpolation=cv2.INTER_LINEAR)[g:g + r1 - r0, g:g + W]
                  for m in self._sky_lookup(R_lc, *np.meshgrid(us, vs)))
        return mx, np.clip(my, 0.0, self.world.sky.panorama.shape[0] - 1.0, out=my)

    def _render_sky(self, theta: float, attitude: Attitude, R_lc: np.ndarray,
                    views: list[_View]) -> tuple[int, np.ndarray | None]:
        """(first row, the sky image of the rows either camera needs), shared by both cameras."""
        if attitude.is_level:
            r0, maps = 0, self._sky_maps
        else:
            spans = [vw.sky_rows for vw in views if vw.sky_rows[1] > vw.sky_rows[0]]
            r0, r1 = min(a for a, _ in spans) if spans else 0, max(b for _, b in spans) if spans else 0
            maps = self._sky_maps_grid(R_lc, r0, r1) if spans else None
        if maps is None:
            return r0, None
        mx, my = maps
        daz, _ = self.world.sky.rad_per_px
        shift = np.float32((theta % (2 * math.pi)) / daz)
        return r0, cv2.remap(self.world.sky.panorama, mx + shift, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def _render_scene(self, x, y, theta, right, attitude: Attitude, view: _View, sky, light) -> np.ndarray:
        c = self.calib
        W, H = c.width_px, c.height_px
        img = np.empty((H, W), np.uint8)
        R, t = camera_pose(c, x, y, theta, right, attitude)
        Rt = R.T
        Hg = self.K @ np.column_stack([Rt[:, 0], Rt[:, 1], -Rt @ t])    # ground (x, y, 1) -> pixel
        gt = self.world.ground
        Hg_inv = np.linalg.inv(Hg)
        for r0, r1, c0, c1, lev, ss in view.bands:
            S = np.array([[1.0, 0, c0], [0, 1.0 / ss, r0 - 0.5 + 0.5 / ss], [0, 0, 1]])
            M = gt.tex_from_world(lev) @ Hg_inv @ S                       # band pixel -> texel
            band = cv2.warpPerspective(gt.levels[lev], M, (c1 - c0, (r1 - r0) * ss),
                                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                       borderMode=cv2.BORDER_REFLECT_101)
            if ss > 1:
                band = cv2.resize(band, (c1 - c0, r1 - r0), interpolation=cv2.INTER_AREA)
            img[r0:r1, c0:c1] = band
        g0, g1 = view.ground_rows
        if light is not None and g0 < g1:
            self._cloud_shadows(img, Hg, light, g0, g1)
        self._paste_sky(img, view, sky)
        self._draw_landmarks(img, R, t)
        return img

    def _paste_sky(self, img: np.ndarray, view: _View, sky: tuple[int, np.ndarray | None]) -> None:
        """The sky over its rows; in rows that also hold ground (a rolled camera) only beyond the clip,
        where the ground bands drew past the horizon."""
        s0, pano = sky
        a, b = view.sky_rows
        if pano is None or b <= a:
            return
        src = pano[a - s0:b - s0]
        o0, o1 = max(a, view.drawn_rows[0]), min(b, view.drawn_rows[1])
        if o1 <= o0:
            img[a:b] = src
            return
        img[a:o0], img[o1:b] = src[:o0 - a], src[o1 - a:]
        u = np.arange(img.shape[1], dtype=float)
        rows = np.arange(o0, o1, dtype=float)[:, None]
        ground = _ground_depth(self._nd(view.down_c, u, rows), view.height_m) <= MAX_GROUND_M
        np.copyto(img[o0:o1], src[o0 - a:o1 - a], where=~ground)

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

    def _cloud_shadows(self, img: np.ndarray, Hg: np.ndarray, light: dict, g0: int, g1: int) -> None:
        """Darken the ground in image rows [g0, g1) by the trial's cloud shadow field."""
        gt = self.world.ground
        sh = light["shadow"]
        rows0, cols0 = gt.levels[0].shape
        # shadow texel (j, i) centre <-> world x0 + (j + 0.5) * sx
        sx = cols0 * gt.res_m / sh.shape[1]
        sy = rows0 * gt.res_m / sh.shape[0]
        A = np.array([[sx, 0, gt.x0 + 0.5 * sx], [0, sy, gt.y0 + 0.5 * sy], [0, 0, 1]])
        W = img.shape[1]
        q = 4
        rows = g1 - g0
        w4, h4 = (W + q - 1) // q, (rows + q - 1) // q
        S = np.array([[q, 0, 0.5 * (q - 1)], [0, q, g0 + 0.5 * (q - 1)], [0, 0, 1]])
        small = cv2.warpPerspective(sh, np.linalg.inv(Hg @ A) @ S, (w4, h4),
                                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT_101)
        full = cv2.resize(small, (w4 * q, h4 * q), interpolation=cv2.INTER_LINEAR)[:rows, :W]
        img[g0:g1] = cv2.multiply(img[g0:g1], full, scale=1.0 / 128)

    # --- motion blur ----------------------------------------------------------------------------
    def _flows(self, right: bool, v: float, w: float, shake=(0.0, 0.0), tile_pts_c: np.ndarray | None = None,
               attitude: Attitude = LEVEL) -> np.ndarray:
        """Image motion (px) of each blur tile's centre point (`tile_pts_c`, camera coordinates; the
        level view's by default) during the exposure, for the robot at `attitude` moving at (v, w) over
        the ground (its heading's level frame: the tilt stays as it is during the exposure) and
        rolling/pitching at `shake` (rad/s, small-angle, about the body axes)."""
        c = self.calib
        e = self.cfg.exposure_s
        T = c.T_robot_camera
        R_rc, p_rc = T[:3, :3], T[:3, 3] + (T[:3, 0] * c.baseline_m if right else 0.0)
        X_r = (self._level.tile_pts_c if tile_pts_c is None else tile_pts_c) @ R_rc.T + p_rc
        tilted = not attitude.is_level
        if tilted:
            R_t, lift = attitude.R_level_body(), np.array([0.0, 0.0, attitude.z_m])
            X_r = X_r @ R_t.T + lift                        # the heading's level frame
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
            if tilted:
                q = (q - lift) @ R_t                        # back into the body, tilted as before
            ax, ay = shake[0] * tau, shake[1] * tau         # small rotation about robot x and y
            q = q - np.column_stack([ay * q[:, 2], -ax * q[:, 2], ax * q[:, 1] - ay * q[:, 0]])
            Xc = (q - p_rc) @ R_rc
            z = np.maximum(Xc[:, 2], NEAR_M)
            uvs.append(np.column_stack([c.fu * Xc[:, 0] / z, c.fv * Xc[:, 1] / z]))
        return uvs[1] - uvs[0]

    def _motion_blur(self, img: np.ndarray, right: bool, v: float, w: float, shake=(0.0, 0.0),
                     tile_pts_c: np.ndarray | None = None, attitude: Attitude = LEVEL) -> np.ndarray:
        if self.cfg.exposure_s <= 0 or (abs(v) < 1e-4 and abs(w) < 1e-5):
            return img
        flows = self._flows(right, v, w, shake, tile_pts_c, attitude)
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
