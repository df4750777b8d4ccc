"""Photometric model: a point light at the left camera (Lambert + Blinn-Phong, 1/r^2 falloff)
and the sensor (vignetting, slight optical blur, gamma, Gaussian + shot noise, uint8)."""
from __future__ import annotations

import cv2
import numpy as np

LIGHT_RGB = np.array([1.0, 0.96, 0.90], np.float32)  # warm white (xenon/LED through a scope)
SRGB_TO_LINEAR = ((np.arange(256, dtype=np.float32) / 255.0) ** 2.2).astype(np.float32)


def _dot(u, v):
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]


def _normalize(v):
    return v / (np.sqrt(_dot(v, v))[..., None] + np.float32(1e-12))


def blinn_phong(albedo: np.ndarray, P: np.ndarray, n: np.ndarray, light: np.ndarray, eye: np.ndarray,
                intensity: float, ks, shininess: float, wrap: float = 0.0, shadow=None) -> np.ndarray:
    """Linear radiance ``(H, W, 3)`` of surface points ``P`` with unit normals ``n`` lit by a point
    light at ``light`` and seen from ``eye``. ``intensity`` is the irradiance at 1 mm (so 1/r^2
    falloff); ``ks`` a scalar or per-pixel specular strength; ``wrap`` softens the terminator
    (sub-surface scattering of tissue); ``shadow`` a per-pixel factor on the light."""
    L = light.astype(np.float32) - P
    r2 = _dot(L, L)
    l = L / np.sqrt(r2)[..., None]
    v = _normalize(eye.astype(np.float32) - P)
    h = _normalize(l + v)
    ndl = _dot(n, l)
    diff = np.clip((ndl + np.float32(wrap)) / np.float32(1 + wrap), 0, None)
    ndh = np.clip(_dot(n, h), 0, 1)
    spec = ks * ndh ** np.float32(shininess) * (ndl > 0)
    E = np.float32(intensity) / r2
    if shadow is not None:
        E = E * shadow
    return (albedo * diff[..., None] + spec[..., None]) * (E[..., None] * LIGHT_RGB)


class Sensor:
    """Turns linear radiance into a noisy 8-bit image of one camera."""

    def __init__(self, rays: np.ndarray, exposure: float = 1.0, blur_px: float = 0.55, vignetting: float = 3.0):
        cos_theta = 1.0 / np.linalg.norm(rays, axis=-1)  # rays have z = 1
        self.vignette = (exposure * cos_theta ** float(vignetting)).astype(np.float32)[..., None]
        self.blur_px = blur_px

    def capture(self, radiance: np.ndarray, rng: np.random.Generator, gain: float = 1.0) -> np.ndarray:
        """The 8-bit image of linear ``radiance`` ``(H, W, 3)``, its exposure scaled by ``gain``."""
        img = radiance * self.vignette
        if gain != 1.0:
            img = img * np.float32(gain)
        if self.blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.blur_px)
        img = np.clip(img, 0, 1) ** np.float32(1 / 2.2)
        sigma = np.sqrt(np.float32((1.0 / 255) ** 2) + np.float32(1.5e-4) * img)
        img = img + sigma * rng.standard_normal(img.shape, dtype=np.float32)
        return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
