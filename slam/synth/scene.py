"""The tissue: a smooth height field in world coordinates with a procedural albedo.

World frame (millimetres): the camera looks roughly along +z; the rest surface of the tissue is
``z = rest_depth_mm + h(x, y)`` over the square ``|x|, |y| <= half_extent_mm``. Everything is
defined by the seed alone, independent of the rendered image size.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from slam.synth.noise import blurred_noise, fractal_noise
from slam.synth.texture import make_albedo

HALF_EXTENT_MM = 120.0
GEO_RES_MM = 0.25  # height-field grid
TEX_RES_MM = 0.1  # albedo texel
TEX_LEVELS = 5
MAX_SLOPE = 0.45  # keeps the fixed-point ray casting contractive


@dataclass(frozen=True)
class Grid:
    """A square world-aligned grid: texel (row i, col j) is centred at
    ``x = -half + (j + 0.5) res``, ``y = -half + (i + 0.5) res``."""

    half: float
    res: float

    @property
    def size(self) -> int:
        return int(round(2 * self.half / self.res))

    def to_map(self, x, y):
        """World x/y (mm) -> float32 cv2.remap coordinates."""
        s = np.float32(1.0 / self.res)
        o = np.float32(self.half / self.res - 0.5)
        return (x * s + o).astype(np.float32, copy=False), (y * s + o).astype(np.float32, copy=False)

    def coords(self) -> tuple[np.ndarray, np.ndarray]:
        """World x, y of every texel centre, ``(size, size)`` float32 each."""
        c = (-self.half + (np.arange(self.size) + 0.5) * self.res).astype(np.float32)
        return np.meshgrid(c, c)

    def sample(self, img: np.ndarray, x: float, y: float) -> np.ndarray:
        """Bilinear sample of ``img`` at one world point (no remap quantisation)."""
        mx, my = x / self.res + self.half / self.res - 0.5, y / self.res + self.half / self.res - 0.5
        j0, i0 = int(np.floor(mx)), int(np.floor(my))
        fx, fy = mx - j0, my - i0
        n = img.shape[0] - 1
        j0c, j1c = min(max(j0, 0), n), min(max(j0 + 1, 0), n)
        i0c, i1c = min(max(i0, 0), n), min(max(i0 + 1, 0), n)
        top = img[i0c, j0c] * (1 - fx) + img[i0c, j1c] * fx
        bot = img[i1c, j0c] * (1 - fx) + img[i1c, j1c] * fx
        return np.asarray(top * (1 - fy) + bot * fy, dtype=np.float64)


@dataclass
class TissueScene:
    """Rest geometry and albedo of the tissue.

    Attributes:
        seed: the scene seed.
        rest_depth_mm: mean depth of the rest surface below the world origin (z).
        geo: grid of the height field; ``height`` ``(G, G)`` mm (relative to ``rest_depth_mm``),
            ``grad`` ``(G, G, 2)`` its x/y derivatives, ``wet`` ``(G, G)`` specular strength 0-1.
        tex: grid of level 0 of ``albedo`` (list of sRGB uint8 ``(T, T, 3)`` levels, each half the
            resolution of the previous one).
    """

    seed: int
    rest_depth_mm: float
    geo: Grid
    height: np.ndarray
    grad: np.ndarray
    wet: np.ndarray
    tex: Grid
    albedo: list

    def tex_grid(self, level: int) -> Grid:
        return Grid(self.tex.half, self.tex.res * (2 ** level))

    def rest_point(self, x: float, y: float) -> np.ndarray:
        """The rest surface point above world (x, y)."""
        return np.array([x, y, self.rest_depth_mm + float(self.geo.sample(self.height, x, y))])

    def rest_normal(self, x: float, y: float) -> np.ndarray:
        """Unit normal of the rest surface at (x, y), pointing towards the camera side (-z)."""
        gx, gy = self.geo.sample(self.grad, x, y)
        n = np.array([gx, gy, -1.0])
        return n / np.linalg.norm(n)


def _fold(rng: np.random.Generator, grid: Grid) -> np.ndarray:
    """A ridge or groove along a random smooth curve across the tissue (mm of height)."""
    size = grid.size
    n = 400
    a0 = rng.uniform(0, 2 * np.pi)
    ang = a0 + np.cumsum(rng.normal(0, 0.03, n))
    step = 1.0
    p0 = rng.uniform(-0.6, 0.6, 2) * grid.half - 0.5 * n * step * np.array([np.cos(a0), np.sin(a0)])
    pts = p0 + np.cumsum(step * np.stack([np.cos(ang), np.sin(ang)], 1), axis=0)
    canvas = np.full((size, size), 255, np.uint8)
    px = np.round((pts + grid.half) / grid.res * 8 - 4).astype(np.int32)
    cv2.polylines(canvas, [px.reshape(-1, 1, 2)], False, 0, 1, cv2.LINE_8, 3)
    dist = cv2.distanceTransform(canvas, cv2.DIST_L2, 5) * grid.res
    width = rng.uniform(5.0, 10.0)
    # a curve that misses the grid leaves no zero pixel: the transform then returns ~1e20 (whose
    # square overflows float32); beyond 10 widths the ridge is exp(-50), i.e. nothing
    dist = np.minimum(dist, 10.0 * width)
    amp = rng.uniform(3.0, 6.0) * (1 if rng.random() < 0.5 else -1)
    return (amp * np.exp(-0.5 * (dist / width) ** 2)).astype(np.float32)


def make_height(rng: np.random.Generator, grid: Grid) -> np.ndarray:
    """Rest height field ``(G, G)`` float32 mm: folds and bumps, ~8-14 mm relief, slopes <= MAX_SLOPE."""
    size = grid.size
    mm = 1.0 / grid.res
    broad = 3.0 * fractal_noise(rng, size, [45 * mm, 22 * mm], [1.0, 0.45])
    folds = _fold(rng, grid) + _fold(rng, grid)
    shape = broad + folds
    bumps = 0.6 * blurred_noise(rng, size, 7 * mm)
    fine = 0.10 * blurred_noise(rng, size, 2.5 * mm) + 0.03 * blurred_noise(rng, size, 1.2 * mm)
    c = slice(size // 2 - int(70 * mm), size // 2 + int(70 * mm))
    relief = float(np.percentile(shape[c, c], 99.5) - np.percentile(shape[c, c], 0.5))
    shape *= rng.uniform(10.0, 15.0) / max(relief, 1e-6)
    h = shape + bumps + fine
    gy, gx = np.gradient(h, grid.res)
    max_slope = float(np.percentile(np.hypot(gx, gy)[c, c], 99.9))
    if max_slope > MAX_SLOPE:
        h *= MAX_SLOPE / max_slope
    x, y = grid.coords()
    tilt = rng.normal(0, 0.05, 2)
    h = h + tilt[0] * x + tilt[1] * y
    return (h - h[c, c].mean()).astype(np.float32)


@lru_cache(maxsize=2)
def make_scene(seed: int, texture: float = 1.0) -> TissueScene:
    """The tissue of ``seed`` (cached: scenarios with the same seed share it); ``texture`` scales
    the albedo's fine structure (:func:`slam.synth.texture.make_albedo`), not the geometry."""
    geo = Grid(HALF_EXTENT_MM, GEO_RES_MM)
    tex = Grid(HALF_EXTENT_MM, TEX_RES_MM)
    rng_geo = np.random.default_rng([seed, 1])
    rng_tex = np.random.default_rng([seed, 2])
    height = make_height(rng_geo, geo)
    gy, gx = np.gradient(height, geo.res)
    grad = np.ascontiguousarray(np.stack([gx, gy], -1).astype(np.float32))
    wet_noise = blurred_noise(rng_geo, geo.size, 10 / geo.res) + 0.5 * blurred_noise(rng_geo, geo.size, 3 / geo.res)
    wet = np.clip(0.6 + 0.3 * wet_noise, 0.1, 1.0).astype(np.float32)
    rest_depth = float(76.0 + rng_geo.uniform(-3.0, 3.0))
    level0 = make_albedo(rng_tex, tex.size, tex.res, texture)
    levels = [level0]
    for _ in range(1, TEX_LEVELS):
        prev = cv2.GaussianBlur(levels[-1], (0, 0), 0.6)
        levels.append(cv2.resize(prev, (prev.shape[1] // 2, prev.shape[0] // 2), interpolation=cv2.INTER_AREA))
    return TissueScene(seed=seed, rest_depth_mm=rest_depth, geo=geo, height=height, grad=grad, wet=wet,
                       tex=tex, albedo=levels)
