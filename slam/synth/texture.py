"""Procedural albedo of the tissue surface: pink/red base, branching vessels, fat patches.

The texture is a square sRGB uint8 image over the tissue's world x/y extent at a fixed texel
size (so it is defined by the seed alone, never by the rendered image size).
"""
from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.signal import lfilter

from slam.synth.noise import blurred_noise, fractal_noise, smoothstep

# sRGB colours in [0, 1]
TISSUE_PALE = np.array([0.88, 0.50, 0.45], np.float32)
TISSUE_RED = np.array([0.78, 0.27, 0.23], np.float32)
VESSEL_SUPERFICIAL = np.array([0.50, 0.07, 0.10], np.float32)
CAPILLARY = np.array([0.62, 0.10, 0.12], np.float32)
VESSEL_DEEP = np.array([0.52, 0.22, 0.33], np.float32)
FAT = np.array([0.93, 0.79, 0.47], np.float32)

_SHIFT = 3  # cv2 drawing sub-pixel bits


def _grow_tree(rng: np.random.Generator, start: np.ndarray, angle: float, width: float,
               length_per_mm: float, min_width: float, out: list, branch_rate: float = 0.07) -> None:
    """Grow one branching vessel tree from ``start`` (mm) and append ``(points_mm, width_mm)``
    chunks to ``out``. Vectorised per branch; the loop runs over branches only."""
    stack = [(start.astype(np.float64), angle, width)]
    step = 0.5
    guard = 0
    while stack and guard < 4000:
        guard += 1
        p0, a0, w = stack.pop()
        length = length_per_mm * (0.6 + 0.8 * rng.random()) * max(w, 0.05) ** 0.6
        n = max(3, int(length / step))
        # meandering without loops; thin vessels are more tortuous
        wiggle = 0.010 * float(np.clip(0.4 / max(w, 1e-3), 1.0, 2.5))
        omega = lfilter([1.0], [1.0, -0.8], rng.normal(0.0, wiggle, n))
        ang = a0 + np.cumsum(omega)
        pts = p0 + np.cumsum(step * np.stack([np.cos(ang), np.sin(ang)], 1), axis=0)
        pts = np.vstack([p0[None], pts])
        widths = w * np.exp(-np.linspace(0.0, 0.6, n + 1))  # slow taper
        chunk = 12
        for k in range(0, n, chunk):
            out.append((pts[k:k + chunk + 1], float(widths[k])))
        # children
        n_child = rng.poisson(length * branch_rate)
        for _ in range(n_child):
            idx = int(rng.integers(2, n))
            cw = float(widths[idx]) * rng.uniform(0.4, 0.75)
            if cw < min_width:
                continue
            side = 1.0 if rng.random() < 0.5 else -1.0
            stack.append((pts[idx], float(ang[idx - 1]) + side * rng.uniform(0.35, 0.95), cw))


def _draw_vessels(rng, size: int, res: float, half: float, n_trees: int, w_range, length_per_mm,
                  min_width: float, branch_rate: float = 0.07) -> np.ndarray:
    """Rasterise a set of vessel trees into a float32 coverage map in [0, 1]."""
    canvas = np.zeros((size, size), np.uint8)
    chunks: list = []
    for _ in range(n_trees):
        start = rng.uniform(-half * 1.05, half * 1.05, 2)
        _grow_tree(rng, start, rng.uniform(0, 2 * math.pi), rng.uniform(*w_range), length_per_mm,
                   min_width, chunks, branch_rate)
    scale = (1 << _SHIFT) / res
    for pts, w in chunks:
        px = np.round((pts + half) * scale - 0.5 * (1 << _SHIFT)).astype(np.int32)
        thick_px = w / res
        thickness = max(1, int(round(thick_px)))
        value = int(round(255 * min(1.0, thick_px))) if thick_px < 1 else 255
        cv2.polylines(canvas, [px.reshape(-1, 1, 2)], False, value, thickness, cv2.LINE_AA, _SHIFT)
    return canvas.astype(np.float32) / 255.0


def _sparse_patches(rng: np.random.Generator, size: int, mm: float, share: float) -> np.ndarray:
    """A soft mask ``(size, size)`` in [0, 1] that is 1 over about ``share`` of the area, in
    blobs some 15 mm wide (drawn after every other texture draw, so it changes none of them)."""
    field = blurred_noise(rng, size, 15 * mm)
    cut = float(np.quantile(field[::8, ::8], 1.0 - share))
    return smoothstep(cut - 0.15, cut + 0.15, field).astype(np.float32)


def make_albedo(rng: np.random.Generator, size: int, res: float, texture: float = 1.0) -> np.ndarray:
    """The albedo texture: ``(size, size, 3)`` uint8 sRGB (RGB order), texel ``res`` mm.

    ``texture`` in [0, 1] scales the contrast of the fine structure (grain, blush, capillaries,
    deep vessels) and, below 1, keeps the superficial vessels only inside sparse patches that
    cover ``0.2 + 0.8 * texture`` of the tissue: 0 is smooth tissue with a few thin vessels. The
    random draws do not depend on ``texture``, so one seed gives the same vessels at every level.
    """
    t = float(texture)
    half = size * res / 2.0
    mm = 1.0 / res  # texels per mm

    # base: pale/red mix at low frequency, brightness grain at several scales
    low = fractal_noise(rng, size, [40 * mm, 15 * mm], [1.0, 0.5])
    mix = smoothstep(-1.2, 1.2, low)[..., None]
    col = TISSUE_PALE * (1 - mix) + TISSUE_RED * mix
    grain = fractal_noise(rng, size, [6 * mm, 2 * mm, 0.8 * mm, 0.3 * mm], [0.6, 0.8, 0.7, 0.5])
    col *= (1.0 + 0.05 * t * grain)[..., None]
    # faint reddish mottling (capillary blush)
    blush = smoothstep(0.3, 1.8, fractal_noise(rng, size, [4 * mm, 1.5 * mm], [1.0, 0.6]))
    col = col * (1 - 0.25 * t * blush[..., None]) + TISSUE_RED * 0.85 * (0.25 * t * blush[..., None])

    # deep vessels: wide, faint, bluish, blurred (sub-surface)
    deep = _draw_vessels(rng, size, res, half, n_trees=7, w_range=(1.0, 1.8), length_per_mm=60.0,
                         min_width=0.4)
    deep = cv2.GaussianBlur(deep, (0, 0), 0.35 * mm)
    col = col * (1 - 0.35 * t * deep[..., None]) + VESSEL_DEEP * (0.35 * t * deep[..., None])

    # fat patches (yellowish, lobular), covering the deep vessels
    fat_field = fractal_noise(rng, size, [50 * mm, 20 * mm, 6 * mm], [1.0, 0.45, 0.15])
    fat = smoothstep(0.9, 1.5, fat_field)
    lob = blurred_noise(rng, size, 1.5 * mm)
    lob = smoothstep(-1.5, 1.5, lob)
    fat_col = FAT[None, None, :] * (0.86 + 0.16 * (t * lob + (1 - t) * 0.5))[..., None]
    col = col * (1 - fat[..., None]) + fat_col * fat[..., None]

    # superficial vessels: branching, dark red, sharp, from medium vessels down to capillaries
    vis = (1.0 - 0.6 * fat)[..., None]  # vessels fade inside fat
    cap = _draw_vessels(rng, size, res, half, n_trees=400, w_range=(0.1, 0.2), length_per_mm=22.0,
                        min_width=0.05, branch_rate=0.2)
    cap = cv2.GaussianBlur(cap, (0, 0), 0.06 * mm + 0.5)[..., None] * vis
    col = col * (1 - 0.6 * t * cap) + CAPILLARY * (0.6 * t * cap)
    sup = _draw_vessels(rng, size, res, half, n_trees=40, w_range=(0.25, 0.7), length_per_mm=60.0,
                        min_width=0.12)
    sup = cv2.GaussianBlur(sup, (0, 0), 0.06 * mm + 0.5)[..., None] * vis
    if t < 1.0:
        sup = sup * _sparse_patches(rng, size, mm, 0.2 + 0.8 * t)[..., None]
    col = col * (1 - 0.85 * sup) + VESSEL_SUPERFICIAL * (0.85 * sup)

    return np.clip(col * 255.0 + 0.5, 0, 255).astype(np.uint8)
