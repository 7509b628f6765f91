"""The textured world the simulated stereo camera sees: a pure, seeded function of the taught route.

Three parts, all fixed for a scenario seed (the world does not change from trial to trial; lighting
does, see render.py):

* the ground, a flat plane z = 0 with a procedurally generated texture in world coordinates covering
  the route's bounding box plus a margin: multi-scale noise, dirt and grass regions with sharp
  borders, grass blades, pebbles, stones with shadows and large irregular blotches, so that corners
  exist at every scale a camera 0.7 m up sees between 1 and 15 m. It is stored with a mip pyramid so
  the renderer can pick a pre-filtered level per image row (no aliasing far away). Outside the
  texture the ground mirrors it (BORDER_REFLECT_101), which keeps it a fixed function of position.
* landmarks: rocks, tree trunks, walls and fences as vertical textured rectangles standing on the
  ground, 1.5-20 m from the route and never within 1.5 m of it, each with its own texture;
* a far background: sky with soft clouds above three layers of distant hills, a panorama at
  infinity (a function of viewing direction only, so it shows no stereo disparity).

`raycast` intersects rays with the same ground plane and landmark rectangles; it is independent of the
image renderer and only serves to check it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np
from scipy.spatial import cKDTree

from services.bridge.teach_driver import smooth_waypoints

GROUND_RES_M = 0.012          # level-0 texel size of the ground texture (coarser only for huge routes)
MAX_GROUND_TEXELS = 40_000_000  # level-0 budget: 40 MB + 13 MB of pyramid
MAX_TEXTURE_SIDE = 30_000     # warpPerspective addresses source pixels with 16-bit integers
MARGIN_M = 25.0               # textured ground around the route's bounding box
LANDMARK_MIN_M = 1.5          # clearance between landmarks and the route line
LANDMARK_MAX_M = 20.0         # farthest landmark from the route
LANDMARK_TEXEL_M = 0.01       # landmark texture resolution (coarser for big landmarks)
MAX_LANDMARKS = 1500          # keeps the textures of a very long route within ~50 MB
SKY_WIDTH_PX = 4096           # panorama columns over 360 degrees
SKY_EL_TOP_DEG = 40.0         # panorama covers elevations from here ...
SKY_EL_BOTTOM_DEG = -10.0     # ... down to here (below the horizon: distant ground beyond the clip)
_STRIP_ROWS = 256


def mip_pyramid(img: np.ndarray, min_side: int = 4) -> list[np.ndarray]:
    """Level 0 is `img`; level k halves level k-1 with a Gaussian pre-filter (cv2.pyrDown)."""
    levels = [img]
    while min(levels[-1].shape[:2]) >= 2 * min_side:
        levels.append(cv2.pyrDown(levels[-1], borderType=cv2.BORDER_REFLECT_101))
    return levels


@dataclass
class GroundTexture:
    levels: list[np.ndarray]     # uint8 mip pyramid; row index grows with world y, column with world x
    x0: float                    # world x of the outer edge of texel column 0
    y0: float                    # world y of the outer edge of texel row 0
    res_m: float                 # level-0 texel size

    def tex_from_world(self, level: int) -> np.ndarray:
        """3x3 affine map from world (x, y, 1) on the ground to level-`level` texel coordinates.

        Integer coordinates are texel centres (as OpenCV's warps assume); cv2.pyrDown centres texel i
        of level L on texel 2^L i of level 0, whose centre is at x0 + (2^L i + 0.5) res_m."""
        r = self.res_m * 2 ** level
        h = 0.5 * self.res_m
        return np.array([[1 / r, 0, -(self.x0 + h) / r], [0, 1 / r, -(self.y0 + h) / r], [0, 0, 1]])


@dataclass
class Landmark:
    """A vertical textured rectangle standing on the ground from base point `a` to base point `b`.

    Texel (col 0, row 0) is the top corner above `a`; columns run towards `b`, rows downwards."""
    kind: str
    a: np.ndarray                # (2,) world xy
    b: np.ndarray                # (2,) world xy
    height_m: float
    levels: list[np.ndarray]     # uint8 mip pyramid of the face texture

    @property
    def corners(self) -> np.ndarray:
        """(4, 3) world corners in texture order: top-a, top-b, bottom-b, bottom-a."""
        h = self.height_m
        return np.array([[*self.a, h], [*self.b, h], [*self.b, 0.0], [*self.a, 0.0]])

    def world_from_tex(self, level: int) -> np.ndarray:
        """3x3 map from level-`level` texel coordinates (s, t, 1) to world points: P = M @ (s, t, 1).
        Level-L texel (s, t) is centred on level-0 texel (2^L s, 2^L t) (cv2.pyrDown)."""
        rows, cols = self.levels[0].shape
        length = float(np.linalg.norm(self.b - self.a))
        d = np.array([*(self.b - self.a) / length, 0.0])
        sx, sy = length / cols, self.height_m / rows
        k = 2.0 ** level
        top_a = np.array([*self.a, self.height_m])
        return np.column_stack([d * sx * k, np.array([0, 0, -sy * k]), top_a + 0.5 * sx * d - 0.5 * sy * np.array([0, 0, 1])])


@dataclass
class Sky:
    panorama: np.ndarray         # uint8 (rows, SKY_WIDTH_PX): columns = world azimuth, rows = elevation
    el_top_rad: float
    el_bottom_rad: float

    @property
    def rad_per_px(self) -> tuple[float, float]:
        rows, cols = self.panorama.shape
        return 2 * math.pi / cols, (self.el_top_rad - self.el_bottom_rad) / rows


@dataclass
class World:
    ground: GroundTexture
    landmarks: list[Landmark]
    sky: Sky
    route_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))   # dense taught route
    _corners: np.ndarray | None = field(default=None, repr=False)

    def landmark_corners(self) -> np.ndarray:
        """(N, 4, 3) world corners of all landmarks (cached)."""
        if self._corners is None or len(self._corners) != len(self.landmarks):
            self._corners = (np.stack([lm.corners for lm in self.landmarks]) if self.landmarks
                             else np.zeros((0, 4, 3)))
        return self._corners

    def nbytes(self) -> int:
        n = sum(a.nbytes for a in self.ground.levels) + self.sky.panorama.nbytes
        return n + sum(a.nbytes for lm in self.landmarks for a in lm.levels)


# --- checking -----------------------------------------------------------------------------------
def raycast(world: World, origins: np.ndarray, dirs: np.ndarray, ground: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Nearest intersection of rays o + t d (t > 0) with the ground plane and the landmark rectangles.

    Returns (t, what): `t` in units of |d| (inf when nothing is hit), `what` = landmark index, -1 for the
    ground, -2 for nothing (sky). Independent of the renderer; used to check its geometry."""
    o = np.atleast_2d(np.asarray(origins, float))
    d = np.atleast_2d(np.asarray(dirs, float))
    o = np.broadcast_to(o, d.shape)
    n = len(d)
    t_best = np.full(n, np.inf)
    what = np.full(n, -2)
    if ground:
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = np.where(d[:, 2] < 0, -o[:, 2] / d[:, 2], np.inf)
        hit = (tg > 0) & (tg < t_best)
        t_best[hit], what[hit] = tg[hit], -1
    for i, lm in enumerate(world.landmarks):
        ab = lm.b - lm.a
        length = float(np.linalg.norm(ab))
        u = ab / length
        nrm = np.array([-u[1], u[0]])
        denom = d[:, :2] @ nrm
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((lm.a - o[:, :2]) @ nrm) / denom
        p = o + t[:, None] * d
        s = (p[:, :2] - lm.a) @ u
        ok = (np.abs(denom) > 1e-12) & (t > 0) & (s >= 0) & (s <= length) & (p[:, 2] >= 0) & (p[:, 2] <= lm.height_m)
        hit = ok & (t < t_best)
        t_best[hit], what[hit] = t[hit], i
    return t_best, what


# --- building -----------------------------------------------------------------------------------
def build_world(waypoints, seed: int, *, corner_radius_m: float = 3.0, loop: bool = False,
                landmark_density: float = 3.0, ground_res_m: float = GROUND_RES_M,
                max_ground_texels: int = MAX_GROUND_TEXELS, margin_m: float = MARGIN_M) -> World:
    """The world around the route through `waypoints`, a pure function of its arguments."""
    seed = int(seed) & 0xFFFFFFFF       # numpy seeds are non-negative
    route = smooth_waypoints(waypoints, corner_radius_m, loop)[:, :2]
    pts = np.vstack([route, np.asarray(waypoints, float)])
    lo, hi = pts.min(axis=0) - margin_m, pts.max(axis=0) + margin_m
    res = ground_res_m
    area = float(np.prod(hi - lo))
    res = max(res, math.sqrt(area / max_ground_texels), float(np.max(hi - lo)) / MAX_TEXTURE_SIDE)
    ground = _make_ground(seed, lo, hi, res)
    landmarks = _place_landmarks(np.random.default_rng([seed, 5101]), route, landmark_density)
    sky = _make_sky(np.random.default_rng([seed, 5102]))
    return World(ground=ground, landmarks=landmarks, sky=sky, route_xy=route)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


class _Noise:
    """Seeded value noise on a coarse grid of `cell_m` spacing anchored at the texture origin, sampled
    with bicubic interpolation; the same function of world position whichever strip asks for it."""

    def __init__(self, rng: np.random.Generator, cell_m: float, size_m: np.ndarray):
        self.cell = cell_m
        rows, cols = int(size_m[1] / cell_m) + 6, int(size_m[0] / cell_m) + 6
        self.grid = rng.standard_normal((rows, cols)).astype(np.float32) * 1.35  # ~unit std after interpolation

    def strip(self, res: float, i0: int, rows: int, cols: int) -> np.ndarray:
        k = res / self.cell
        M = np.array([[k, 0, 0.5 * k + 2.0], [0, k, (i0 + 0.5) * k + 2.0]])
        return cv2.warpAffine(self.grid, M, (cols, rows), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REFLECT_101)

    def at(self, res: float, cols_px: np.ndarray, rows_px: np.ndarray) -> np.ndarray:
        """Values at level-0 texel coordinates (same interpolation as `strip`)."""
        k = res / self.cell
        n = len(cols_px)
        if n == 0:
            return np.zeros(0, np.float32)
        pad = (-n) % 1024                      # remap wants both map sides below 32767
        mx = np.pad(cols_px * k + 0.5 * k + 2.0, (0, pad)).astype(np.float32).reshape(-1, 1024)
        my = np.pad(rows_px * k + 0.5 * k + 2.0, (0, pad)).astype(np.float32).reshape(-1, 1024)
        return cv2.remap(self.grid, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT_101).ravel()[:n]


def _blob_polygons(rng: np.random.Generator, n: int, cx, cy, radius, k: int, jitter: float) -> np.ndarray:
    """(n, k, 2) irregular star-shaped polygons around centres (cx, cy) (arrays in texels)."""
    ang = np.sort(rng.uniform(0, 2 * np.pi, (n, k)), axis=1)
    r = radius[:, None] * (1.0 + jitter * rng.uniform(-1, 1, (n, k)))
    return np.stack([cx[:, None] + r * np.cos(ang), cy[:, None] + r * np.sin(ang)], axis=-1)


def _make_ground(seed: int, lo: np.ndarray, hi: np.ndarray, res: float) -> GroundTexture:
    """Built in strips of `_STRIP_ROWS` texel rows so that the float work arrays stay small; the
    primitives (blotches, stones, pebbles, grass blades) are drawn per strip from the same per-band
    seeded lists, so strips join without seams."""
    size = hi - lo
    cols, rows = int(math.ceil(size[0] / res)), int(math.ceil(size[1] / res))
    noise = _ground_noise(seed, size, res)
    level0 = np.empty((rows, cols), np.uint8)
    cache: dict[int, dict] = {}
    for s_idx, i0 in enumerate(range(0, rows, _STRIP_ROWS)):
        h = min(_STRIP_ROWS, rows - i0)
        # primitives centred in the neighbouring bands reach into this strip too
        for b in (s_idx - 1, s_idx, s_idx + 1):
            if b not in cache:
                cache[b] = _ground_band(seed, b, cols, res, noise)
        cache.pop(s_idx - 2, None)
        near = [cache[b] for b in (s_idx - 1, s_idx, s_idx + 1)]
        level0[i0:i0 + h] = _ground_strip(seed, s_idx, i0, h, cols, res, noise, near)
    return GroundTexture(levels=mip_pyramid(level0), x0=float(lo[0]), y0=float(lo[1]), res_m=res)


class _GroundNoise(NamedTuple):
    macro8: _Noise               # broad brightness swells
    macro3: _Noise
    region: _Noise               # decides dirt against grass
    mid6: _Noise                 # finer mottling
    mid2: _Noise


def _ground_noise(seed: int, size: np.ndarray, res: float) -> _GroundNoise:
    # all layers draw from one generator in this order; reordering them would change every world
    rng = np.random.default_rng([seed, 5100])
    return _GroundNoise(_Noise(rng, 8.0, size), _Noise(rng, 3.0, size), _Noise(rng, 1.6, size),
                        _Noise(rng, 0.6, size), _Noise(rng, max(0.2, 3 * res), size))


def _primitive_scale(res: float) -> float:
    # a huge route gets coarser texels: small primitives then grow with them (same count per texel),
    # so the texture keeps its corners and the work stays bounded by the texel budget
    return max(1.0, res / GROUND_RES_M)


def _grass_at(noise: _GroundNoise, res: float, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Grass cover (0 = dirt, 1 = grass) at level-0 texel coordinates, as `_ground_tones` computes it."""
    macro = 0.6 * noise.macro8.at(res, c, r) + 0.4 * noise.macro3.at(res, c, r)
    return _smoothstep((noise.region.at(res, c, r) + 0.3 * macro - 0.15) / 0.08 + 0.5)


def _ground_tones(noise: _GroundNoise, res: float, i0: int, rows: int, cols: int) -> np.ndarray:
    """float32 base brightness of texel rows [i0, i0 + rows): noisy dirt blended into darker grass."""
    macro = 0.6 * noise.macro8.strip(res, i0, rows, cols) + 0.4 * noise.macro3.strip(res, i0, rows, cols)
    grass = _smoothstep((noise.region.strip(res, i0, rows, cols) + 0.3 * macro - 0.15) / 0.08 + 0.5)
    mid = 0.6 * noise.mid6.strip(res, i0, rows, cols) + 0.4 * noise.mid2.strip(res, i0, rows, cols)
    return (135.0 + 22.0 * macro + 14.0 * mid) * (1.0 - grass) + (88.0 + 15.0 * macro + 10.0 * mid) * grass


def _ground_band(seed: int, b: int, cols: int, res: float, noise: _GroundNoise) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Primitives centred in texel rows [b * _STRIP_ROWS, (b + 1) * _STRIP_ROWS): per kind the
    polygons/segments (n, k, 2) in level-0 texels and their tones."""
    g = np.random.default_rng([seed, 5300, b + 1])
    y_off = np.array([0.0, b * _STRIP_ROWS])
    area = cols * _STRIP_ROWS * res * res  # m^2 of the band
    k = _primitive_scale(res)
    # the kinds draw from `g` one after the other, in this order
    out = {}
    c = _band_centres(g, 0.15 * area, cols) + y_off
    out["blob"] = _band_blobs(g, c, (0.25, 1.0), 1.0, res, 9, 0.35, [-28.0, -16.0, 16.0, 26.0])
    c = _band_centres(g, 1.5 / k ** 2 * area, cols) + y_off
    out["stone"] = _band_blobs(g, c, (0.03, 0.12), k, res, 7, 0.3, [70.0, 105.0, 160.0, 200.0])
    c = _band_centres(g, 60.0 / k ** 2 * area, cols) + y_off
    c = c[_grass_at(noise, res, c[:, 0], c[:, 1]) < 0.5]      # pebbles lie on dirt
    out["pebble"] = _band_blobs(g, c, (0.01, 0.03), k, res, 5, 0.3, [60.0, 95.0, 175.0, 215.0])
    c = _band_centres(g, 350.0 / k ** 2 * area, cols) + y_off
    c = c[_grass_at(noise, res, c[:, 0], c[:, 1]) > 0.5]      # blades grow on grass
    out["blade"] = _band_blades(g, c, k, res)
    return out


def _band_centres(g: np.random.Generator, mean_count: float, cols: int) -> np.ndarray:
    """(n, 2) uniform texel positions in a band, n Poisson distributed."""
    n = g.poisson(mean_count)
    return g.uniform([0, 0], [cols, _STRIP_ROWS], (n, 2))


def _band_blobs(g, c, size_m, scale, res, vertices, jitter, tones) -> tuple[np.ndarray, np.ndarray]:
    """Irregular polygons of radius `scale` x uniform(size_m) metres around `c`, with random tones."""
    n = len(c)
    radius = scale * g.uniform(*size_m, n) / res
    return _blob_polygons(g, n, c[:, 0], c[:, 1], radius, vertices, jitter), g.choice(tones, n)


def _band_blades(g, c, k, res) -> tuple[np.ndarray, np.ndarray]:
    """Grass blades as (n, 2, 2) segments 3-9 cm long through `c`, with random tones."""
    n = len(c)
    ang = g.uniform(0, np.pi, n)
    dxy = np.column_stack([np.cos(ang), np.sin(ang)]) * (k * g.uniform(0.015, 0.045, n) / res)[:, None]
    return np.stack([c - dxy, c + dxy], axis=1), g.choice([40.0, 62.0, 125.0], n)


def _ground_strip(seed: int, s_idx: int, i0: int, rows: int, cols: int, res: float, noise: _GroundNoise,
                  near: list[dict]) -> np.ndarray:
    """uint8 texel rows [i0, i0 + rows) of strip number `s_idx`, with the primitives of the bands `near`."""
    base = _ground_tones(noise, res, i0, rows, cols)
    delta = np.zeros((rows, cols), np.float32)
    _draw_primitives(delta, i0, [p["blob"] for p in near])
    base += delta
    # contact shadows under stones and pebbles, then their faces, then grass blades
    k = _primitive_scale(res)
    shadow_off = (0.35 * 0.06 * k / res, 0.25 * 0.06 * k / res)
    shade = np.zeros((rows, cols), np.uint8)
    _draw_primitives(shade, i0, [p["stone"] for p in near], shadow_off, tone=1.0)
    _draw_primitives(shade, i0, [p["pebble"] for p in near], (shadow_off[0] / 3, shadow_off[1] / 3), tone=1.0)
    base[shade > 0] *= 0.55
    del shade, delta
    _draw_primitives(base, i0, [p["stone"] for p in near])
    _draw_primitives(base, i0, [p["pebble"] for p in near])
    _draw_primitives(base, i0, [p["blade"] for p in near], lines=True)
    grain = np.random.default_rng([seed, 5200, s_idx]).standard_normal((rows, cols), dtype=np.float32)
    base += 14.0 * cv2.GaussianBlur(grain, (0, 0), 0.7)
    return np.clip(base, 0, 255).astype(np.uint8)


_DRAW_SHIFT = 2                  # drawing with 1/4-texel precision


def _draw_primitives(img, i0, items, offset=(0.0, 0.0), lines=False, tone=None) -> None:
    """Draw primitives (list of (polys, tones)) into strip `img` whose first row is texel row i0.
    Polygons go in two batches fixed per polygon (OpenCV fills overlaps of one call even-odd)."""
    polys = np.concatenate([p for p, _ in items])
    tones = np.concatenate([t for _, t in items]) if tone is None else np.full(len(polys), tone)
    if len(polys) == 0:
        return
    ys = polys[:, :, 1] + offset[1]
    sel = (ys.max(axis=1) >= i0 - 2) & (ys.min(axis=1) <= i0 + img.shape[0] + 2)
    q = np.round((polys[sel] + np.array([offset[0], offset[1] - i0])) * (1 << _DRAW_SHIFT)).astype(np.int32)
    t = tones[sel]
    batch = np.round(polys[sel, 0, 0] * 8).astype(np.int64) % 2   # fixed per polygon
    for tv in np.unique(t):
        for bt in (0, 1):
            part = q[(t == tv) & (batch == bt)]
            if len(part) == 0:
                continue
            if lines:
                cv2.polylines(img, part, False, float(tv), 1, cv2.LINE_8, _DRAW_SHIFT)
            else:
                cv2.fillPoly(img, part, float(tv), cv2.LINE_8, _DRAW_SHIFT)


# --- landmarks ----------------------------------------------------------------------------------
_KINDS = ("rock", "trunk", "wall", "fence")
_KIND_P = (0.35, 0.3, 0.15, 0.2)


def _landmark_size(rng, kind) -> tuple[float, float]:
    if kind == "rock":
        return rng.uniform(0.5, 2.5), rng.uniform(0.3, 1.4)
    if kind == "trunk":
        return rng.uniform(0.2, 0.6), rng.uniform(2.5, 6.0)
    if kind == "wall":
        return rng.uniform(2.0, 5.0), rng.uniform(0.8, 2.2)
    return rng.uniform(2.0, 4.0), rng.uniform(0.9, 1.6)


def _seg_points(a, b, step=0.1):
    n = max(2, int(np.linalg.norm(b - a) / step) + 1)
    return a + np.linspace(0, 1, n)[:, None] * (b - a)


def _seg_dist(p1, p2, q1, q2) -> float:
    """Distance between two 2-D segments (sampled; exact enough for placement)."""
    a, b = _seg_points(p1, p2, 0.05), _seg_points(q1, q2, 0.05)
    return float(np.min(np.linalg.norm(a[:, None] - b[None], axis=-1)))


def _place_landmarks(rng: np.random.Generator, route: np.ndarray, density: float) -> list[Landmark]:
    tree = cKDTree(route)
    seglen = np.hypot(*np.diff(route, axis=0).T)
    length = float(seglen.sum())
    band_area = length * 2 * (LANDMARK_MAX_M - LANDMARK_MIN_M) + math.pi * LANDMARK_MAX_M ** 2
    n_target = min(MAX_LANDMARKS, int(round(density * band_area / 100.0)))
    centres: list[np.ndarray] = []
    widths: list[float] = []
    cum = np.concatenate([[0.0], np.cumsum(seglen)])
    out: list[Landmark] = []
    tries = 0
    while len(out) < n_target and tries < 30 * n_target + 100:
        tries += 1
        kind = _KINDS[rng.choice(len(_KINDS), p=_KIND_P)]
        width, height = _landmark_size(rng, kind)
        # a point along the route, pushed sideways by 1.5-20 m (denser near the route)
        s = rng.uniform(0, length)
        i = min(int(np.searchsorted(cum, s, side="right")) - 1, len(route) - 2)
        p, q = route[i], route[i + 1]
        tangent = (q - p) / max(1e-9, np.linalg.norm(q - p))
        normal = np.array([-tangent[1], tangent[0]])
        off = LANDMARK_MIN_M + (LANDMARK_MAX_M - LANDMARK_MIN_M) * rng.uniform() ** 1.5
        c = p + (s - cum[i]) * tangent + rng.choice([-1.0, 1.0]) * (off + 0.5 * width) * normal
        if kind in ("wall", "fence") and rng.uniform() < 0.6:
            yaw = math.atan2(tangent[1], tangent[0]) + rng.normal(0, 0.2)   # along the route
        else:
            yaw = rng.uniform(0, 2 * np.pi)
        d = np.array([math.cos(yaw), math.sin(yaw)]) * 0.5 * width
        a, b = c - d, c + d
        dist, _ = tree.query(_seg_points(a, b))
        if dist.min() < LANDMARK_MIN_M or dist.min() > LANDMARK_MAX_M:
            continue
        if out:
            near = np.nonzero(np.linalg.norm(np.array(centres) - c, axis=1) < 0.5 * (width + np.array(widths)) + 0.5)[0]
            if any(_seg_dist(a, b, out[j].a, out[j].b) < 0.3 for j in near):
                continue
        tex = _landmark_texture(rng, kind, width, height)
        out.append(Landmark(kind=kind, a=a, b=b, height_m=height, levels=mip_pyramid(tex, 2)))
        centres.append(c)
        widths.append(width)
    return out


def _noise_img(rng, rows, cols, cell_r, cell_c) -> np.ndarray:
    g = rng.standard_normal((max(2, int(rows / cell_r) + 2), max(2, int(cols / cell_c) + 2))).astype(np.float32)
    return cv2.resize(g, (cols, rows), interpolation=cv2.INTER_CUBIC)


def _landmark_texture(rng: np.random.Generator, kind: str, width: float, height: float) -> np.ndarray:
    texel = max(LANDMARK_TEXEL_M, width / 512, height / 512)
    cols, rows = max(8, int(round(width / texel))), max(8, int(round(height / texel)))
    px = 1.0 / texel  # texels per metre
    # the grain is drawn before the face so that every kind takes the same first draws
    grain = cv2.GaussianBlur(rng.standard_normal((rows, cols)).astype(np.float32), (0, 0), 0.7)
    face = {"rock": _rock_face, "trunk": _trunk_face, "wall": _wall_face}.get(kind, _fence_face)
    img = face(rng, rows, cols, px, width, height)
    img = img + 8 * grain
    return np.clip(img, 0, 255).astype(np.uint8)


def _random_pixel(rng: np.random.Generator, rows: int, cols: int) -> tuple[int, int]:
    return int(rng.uniform(0, cols)), int(rng.uniform(0, rows))


def _rock_face(rng, rows, cols, px, width, height) -> np.ndarray:
    img = 120 + 30 * _noise_img(rng, rows, cols, 0.4 * px, 0.4 * px) + 18 * _noise_img(rng, rows, cols, 0.08 * px, 0.08 * px)
    for _ in range(int(4 + 6 * width)):          # cracks
        p = rng.uniform([0, 0], [cols, rows])
        pts = [p]
        for _ in range(rng.integers(3, 8)):
            p = p + rng.normal(0, 0.08 * px, 2)
            pts.append(p)
        cv2.polylines(img, [np.array(pts, np.int32)], False, float(rng.uniform(30, 60)), int(rng.integers(1, 3)))
    for _ in range(int(30 * width * height)):    # lichen and pits
        cv2.circle(img, _random_pixel(rng, rows, cols), int(rng.uniform(0.01, 0.04) * px),
                   float(rng.choice([55.0, 200.0])), -1)
    img *= np.linspace(1.05, 0.7, rows, dtype=np.float32)[:, None]   # darker towards the ground
    return img


def _trunk_face(rng, rows, cols, px, width, height) -> np.ndarray:
    img = 85 + 25 * _noise_img(rng, rows, cols, 0.5 * px, 0.03 * px) + 10 * _noise_img(rng, rows, cols, 0.1 * px, 0.1 * px)
    for _ in range(int(8 * height)):             # bark furrows
        x = rng.uniform(0, cols)
        y = rng.uniform(0, rows)
        pts = [(x, y)]
        for _ in range(rng.integers(2, 6)):
            x, y = x + rng.normal(0, 0.01 * px), y + rng.uniform(0.05, 0.2) * px
            pts.append((x, y))
        cv2.polylines(img, [np.array(pts, np.int32)], False, float(rng.uniform(25, 50)), int(rng.integers(1, 3)))
    for _ in range(int(1 + 1.5 * height)):       # knots and broken branches
        cv2.ellipse(img, _random_pixel(rng, rows, cols),
                    (int(rng.uniform(0.02, 0.06) * px), int(rng.uniform(0.03, 0.08) * px)), 0, 0, 360,
                    float(rng.uniform(20, 45)), -1)
    for _ in range(int(3 * height)):             # lighter patches of lichen
        cv2.circle(img, _random_pixel(rng, rows, cols), int(rng.uniform(0.01, 0.05) * px),
                   float(rng.uniform(140, 190)), -1)
    return img


def _wall_face(rng, rows, cols, px, width, height) -> np.ndarray:
    img = np.full((rows, cols), 175.0, np.float32)   # mortar
    bh, bw = rng.uniform(0.06, 0.09) * px, rng.uniform(0.18, 0.26) * px
    y, row = 0.0, 0
    while y < rows:                              # courses of bricks, every other one offset
        x = -rng.uniform(0, bw) if row % 2 else -0.5 * bw
        while x < cols:
            w = bw * rng.uniform(0.8, 1.2)
            cv2.rectangle(img, (int(x + 1), int(y + 1)), (int(x + w - 1), int(y + bh - 1)),
                          float(rng.uniform(60, 150)), -1)
            x += w
        y += bh
        row += 1
    img += 10 * _noise_img(rng, rows, cols, 0.3 * px, 0.3 * px)
    for _ in range(int(2 * width)):              # stains
        cv2.circle(img, _random_pixel(rng, rows, cols), int(rng.uniform(0.05, 0.2) * px),
                   float(rng.uniform(40, 80)), -1)
    return img


def _fence_face(rng, rows, cols, px, width, height) -> np.ndarray:
    """Vertical planks with gaps, grain, nails and two rails."""
    img = np.full((rows, cols), 35.0, np.float32)   # dark gaps between planks
    x = 0.0
    while x < cols:
        w = rng.uniform(0.09, 0.15) * px
        top = int(rng.uniform(0, 0.06) * px)
        tone = float(rng.uniform(100, 170))
        cv2.rectangle(img, (int(x), top), (int(x + w - 0.02 * px), rows - 1), tone, -1)
        for _ in range(2):
            yn = int(rng.uniform(0.1, 0.9) * rows)
            cv2.circle(img, (int(x + 0.5 * w), yn), max(1, int(0.006 * px)), 30.0, -1)
        x += w
    img += 14 * _noise_img(rng, rows, cols, 0.4 * px, 0.015 * px)
    for yr in (0.25, 0.75):
        y0 = int(yr * rows)
        cv2.rectangle(img, (0, y0), (cols - 1, y0 + int(0.08 * px)), float(rng.uniform(80, 130)), -1)
    return img


# --- sky and distant hills ---------------------------------------------------------------------
def _make_sky(rng: np.random.Generator) -> Sky:
    cols = SKY_WIDTH_PX
    px_per_deg = cols / 360.0
    rows = int(round((SKY_EL_TOP_DEG - SKY_EL_BOTTOM_DEG) * px_per_deg))
    el = SKY_EL_TOP_DEG - (np.arange(rows) + 0.5) / px_per_deg   # elevation of each row, degrees

    def wrap_noise(grid_rows: int, grid_cols: int, out_rows: int) -> np.ndarray:
        """Bicubic value noise of (out_rows, cols) that wraps around in azimuth (columns)."""
        g = rng.standard_normal((grid_rows, grid_cols)).astype(np.float32)
        g = np.hstack([g[:, -3:], g, g[:, :3]])
        cell = cols / grid_cols
        big = cv2.resize(g, (int(round((grid_cols + 6) * cell)), out_rows), interpolation=cv2.INTER_CUBIC)
        off = int(round(3 * cell))
        return big[:, off:off + cols]

    img = (205.0 - 1.6 * np.clip(el, 0, None))[:, None] * np.ones((1, cols), np.float32)
    img += 14.0 * wrap_noise(6, 24, rows) * np.clip(el / 10.0, 0, 1)[:, None]          # soft clouds
    # three ridgelines, far to near: higher and hazier behind, darker and more textured in front
    for base_deg, amp_deg, tone, contrast, cells in ((5.0, 3.0, 160.0, 10.0, 16), (2.5, 2.0, 125.0, 20.0, 32),
                                                     (0.8, 1.2, 90.0, 28.0, 64)):
        prof = base_deg + amp_deg * (wrap_noise(1, cells, 1)[0] + 0.35 * wrap_noise(1, cells * 4, 1)[0])
        ridge_row = (SKY_EL_TOP_DEG - prof) * px_per_deg
        mask = np.arange(rows)[:, None] >= ridge_row[None, :]
        tex = tone + contrast * (0.6 * wrap_noise(rows // 6, cols // 6, rows) + 0.4 * wrap_noise(rows // 24, cols // 24, rows))
        img = np.where(mask, tex, img)
    return Sky(panorama=np.clip(img, 0, 255).astype(np.uint8), el_top_rad=math.radians(SKY_EL_TOP_DEG),
               el_bottom_rad=math.radians(SKY_EL_BOTTOM_DEG))
