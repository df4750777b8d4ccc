"""Seeded procedural noise on fixed grids (the building block of the tissue's shape and colour).

All fields are generated at a fixed resolution in world units, so they depend on the seed
only, never on the rendered image size.
"""
from __future__ import annotations

import cv2
import numpy as np


def value_noise(rng: np.random.Generator, size: int, cell: float) -> np.ndarray:
    """Smooth zero-mean noise ``(size, size)`` float32 with features about ``cell`` texels wide.

    Random values on a coarse lattice (spacing ``cell`` texels) upsampled with bicubic
    interpolation, which is C1-continuous, so gradients of the result are continuous too.
    """
    n = max(2, int(np.ceil(size / max(cell, 1e-6))) + 1)
    lattice = rng.standard_normal((n, n)).astype(np.float32)
    # Upsample the lattice so that it spans a little more than ``size`` texels, then crop:
    # the crop keeps the feature size exactly ``cell`` whatever the rounding of n.
    full = int(round((n - 1) * cell))
    full = max(full, size)
    up = cv2.resize(lattice, (full, full), interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(up[:size, :size])


def fractal_noise(rng: np.random.Generator, size: int, cells: list[float], weights: list[float]) -> np.ndarray:
    """Weighted sum of :func:`value_noise` octaves, normalised to zero mean and unit std."""
    out = np.zeros((size, size), np.float32)
    for cell, w in zip(cells, weights):
        out += np.float32(w) * value_noise(rng, size, cell)
    out -= out.mean()
    std = float(out.std())
    return out / np.float32(std if std > 1e-9 else 1.0)


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 (x <= e0) to 1 (x >= e1)."""
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def blurred_noise(rng: np.random.Generator, size: int, feature: float) -> np.ndarray:
    """Isotropic smooth noise ``(size, size)`` float32, unit std, blobs about ``feature`` texels
    wide (Gaussian-filtered white noise: no lattice artefacts in its gradients)."""
    white = rng.standard_normal((size, size)).astype(np.float32)
    out = cv2.GaussianBlur(white, (0, 0), max(feature / 2.5, 0.5), borderType=cv2.BORDER_REFLECT_101)
    out -= out.mean()
    return out / np.float32(max(float(out.std()), 1e-9))
