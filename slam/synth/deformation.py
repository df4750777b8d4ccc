"""Non-rigid motion of the tissue: breathing and instrument indentation.

The tissue point with rest coordinates ``(x, y)`` (rest surface point ``(x, y, D0 + h(x, y))``)
moves to ``rest + u(x, y, t)``. The fields are evaluated per pixel on the rest coordinates that
the ray caster is solving for, so they only use cheap closed forms and maps sampled together
with the height field.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from slam.synth.noise import fractal_noise, smoothstep
from slam.synth.scene import TissueScene


@dataclass
class Breathing:
    """Periodic breathing along the surface normal plus a little lateral motion.

    ``u = A(x, y) * b(x, y, t) * (n(x, y) + lateral)`` where ``A`` is a smooth amplitude map (mm,
    some regions move a lot, others hardly), ``n`` the rest normal (towards the camera) and
    ``b = (1 - cos(theta)) / 2`` with ``theta = 2 pi t / period + phase0 - k . (x, y)`` (a slow
    travelling wave, so the motion is not a rigid bobbing of the whole surface).
    """

    amp: np.ndarray  # (G, G) float32 mm
    amp_grad: np.ndarray  # (G, G, 2) float32
    period_s: float
    phase0: float
    k: np.ndarray  # (2,) rad/mm
    lateral: np.ndarray  # (3,)

    def theta(self, t: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.float32(2 * np.pi * t / self.period_s + self.phase0) - np.float32(self.k[0]) * x - np.float32(self.k[1]) * y


def tissue_look(scene: TissueScene, blur_mm: float = 3.0) -> np.ndarray:
    """How red (parenchyma-like) the tissue looks at each height-field texel: ``(G, G)`` float32,
    zero mean and unit std over the grid; positive where the albedo is red, negative where it is
    pale or fatty (minus the green/red ratio of the albedo, blurred to the organ scale)."""
    g = scene.geo
    level = min(range(len(scene.albedo)), key=lambda k: abs(scene.tex_grid(k).res - g.res))
    rgb = cv2.resize(scene.albedo[level], (g.size, g.size), interpolation=cv2.INTER_AREA).astype(np.float32)
    look = -(rgb[..., 1] + 1.0) / (rgb[..., 0] + 1.0)
    look = cv2.GaussianBlur(look, (0, 0), blur_mm / g.res, borderType=cv2.BORDER_REFLECT_101)
    look -= look.mean()
    return look / np.float32(max(float(look.std()), 1e-9))


def make_breathing(scene: TissueScene, seed: int, follows_tissue: float = 0.0) -> Breathing:
    """The breathing of ``seed``'s tissue (period 3-5 s, peak amplitude 1.5-3 mm).

    ``follows_tissue`` in [0, 1] is the correlation of the amplitude map with how the tissue looks
    (:func:`tissue_look`: red parenchyma breathes most, pale and fatty tissue least), as when
    the view holds organs that move differently; 0 (the default) makes the amplitude independent
    of the image. The random draws do not depend on it, so 0 gives the sequences of earlier
    versions bit for bit.
    """
    if not 0.0 <= follows_tissue <= 1.0:
        raise ValueError(f"follows_tissue must be in [0, 1], got {follows_tissue}")
    rng = np.random.default_rng([seed, 4])
    g = scene.geo
    field = fractal_noise(rng, g.size, [40 / g.res, 18 / g.res], [1.0, 0.4])
    if follows_tissue > 0.0:
        mixed = follows_tissue * tissue_look(scene) + np.sqrt(1.0 - follows_tissue ** 2) * field
        field = (mixed / np.float32(max(float(mixed.std()), 1e-9))).astype(np.float32)
    amp_max = rng.uniform(1.5, 3.0)
    amp = (amp_max * (0.05 + 0.95 * smoothstep(-1.2, 1.0, field))).astype(np.float32)
    ay, ax = np.gradient(amp, g.res)
    ang = rng.uniform(0, 2 * np.pi)
    k = 0.008 * np.array([np.cos(ang), np.sin(ang)])
    lat_ang = rng.uniform(0, 2 * np.pi)
    lateral = 0.25 * np.array([np.cos(lat_ang), np.sin(lat_ang), 0.0])
    return Breathing(amp=amp, amp_grad=np.stack([ax, ay], -1).astype(np.float32), period_s=rng.uniform(3.2, 4.8),
                     phase0=rng.uniform(0, 2 * np.pi), k=k, lateral=lateral)


@dataclass
class Indentation:
    """A Gaussian dent ``u = depth * exp(-|xy - center|^2 / (2 sigma^2)) * direction``."""

    center: np.ndarray  # (2,) rest x, y (mm)
    depth: float  # mm
    sigma: float  # mm
    direction: np.ndarray  # (3,) unit, into the tissue


@dataclass
class FrameDeformation:
    """The deformation at one instant: breathing (optional) and an indentation (optional)."""

    t: float
    breathing: Optional[Breathing] = None
    indentation: Optional[Indentation] = None

    @property
    def active(self) -> bool:
        return self.breathing is not None or self.indentation is not None

    def displacement(self, x, y, hx, hy, A):
        """``(ux, uy, uz)`` float32 arrays at rest coordinates ``x, y`` given the rest height
        gradient ``hx, hy`` and the breathing amplitude ``A`` sampled there."""
        ux = np.zeros_like(x)
        uy = np.zeros_like(x)
        uz = np.zeros_like(x)
        if self.breathing is not None:
            br = self.breathing
            b = 0.5 - 0.5 * np.cos(br.theta(self.t, x, y))
            inv = 1.0 / np.sqrt(1.0 + hx * hx + hy * hy)
            ab = A * b
            ux += ab * (hx * inv + np.float32(br.lateral[0]))
            uy += ab * (hy * inv + np.float32(br.lateral[1]))
            uz += ab * (-inv + np.float32(br.lateral[2]))
        if self.indentation is not None:
            ind = self.indentation
            g = self._gauss(x, y)
            dvec = ind.direction.astype(np.float32)
            ux += g * dvec[0]
            uy += g * dvec[1]
            uz += g * dvec[2]
        return ux, uy, uz

    def _gauss(self, x, y):
        ind = self.indentation
        dx = x - np.float32(ind.center[0])
        dy = y - np.float32(ind.center[1])
        return np.float32(ind.depth) * np.exp(-(dx * dx + dy * dy) * np.float32(0.5 / ind.sigma ** 2))

    def height_gradient(self, x, y, hx, hy, A, Ax, Ay):
        """Approximate x/y derivatives of ``uz`` (for the normals of the deformed surface)."""
        gx = np.zeros_like(x)
        gy = np.zeros_like(x)
        if self.breathing is not None:
            br = self.breathing
            th = br.theta(self.t, x, y)
            b = 0.5 - 0.5 * np.cos(th)
            db = 0.5 * np.sin(th)
            nz = -1.0 / np.sqrt(1.0 + hx * hx + hy * hy) + np.float32(br.lateral[2])
            gx += nz * (b * Ax - A * db * np.float32(br.k[0]))
            gy += nz * (b * Ay - A * db * np.float32(br.k[1]))
        if self.indentation is not None:
            ind = self.indentation
            g = self._gauss(x, y) * np.float32(ind.direction[2] / ind.sigma ** 2)
            gx -= g * (x - np.float32(ind.center[0]))
            gy -= g * (y - np.float32(ind.center[1]))
        return gx, gy

    def displacement_at(self, scene: TissueScene, x: float, y: float) -> np.ndarray:
        """``u`` at one rest point (used to place the instrument tip)."""
        gx, gy = scene.geo.sample(scene.grad, x, y)
        A = scene.geo.sample(self.breathing.amp, x, y) if self.breathing is not None else 0.0
        arr = lambda v: np.array([v], np.float32)  # noqa: E731
        u = self.displacement(arr(x), arr(y), arr(gx), arr(gy), arr(A))
        return np.array([float(c[0]) for c in u])
