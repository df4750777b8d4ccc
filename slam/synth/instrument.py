"""A surgical instrument: two capsules (metal head + darker shaft) entering the view from an
image border, whose tip slides over the tissue and pushes it in (an :class:`Indentation`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.synth.deformation import Breathing, FrameDeformation, Indentation
from slam.synth.scene import TissueScene

HEAD_RADIUS, HEAD_LENGTH = 2.3, 10.0
SHAFT_RADIUS, SHAFT_LENGTH = 2.8, 160.0


@dataclass
class Capsule:
    """Segment ``a``-``b`` (world mm) swept by a sphere of ``radius``; ``material`` 0 = polished
    head, 1 = shaft."""

    a: np.ndarray
    b: np.ndarray
    radius: float
    material: int


class InstrumentMotion:
    """Seeded smooth motion of the instrument in front of a static camera ``T_wc``."""

    def __init__(self, scene: TissueScene, seed: int, T_wc: np.ndarray, breathing: Breathing | None):
        rng = np.random.default_rng([seed, 5])
        self.scene = scene
        self.breathing = breathing
        R, o = T_wc[:3, :3], T_wc[:3, 3]
        # where the optical axis meets the rest plane
        zc = R[:, 2]
        centre = o + zc * (scene.rest_depth_mm - o[2]) / zc[2]
        phi = rng.uniform(0, 2 * np.pi)  # image direction the shaft comes from
        lat_cam = np.array([np.cos(phi), np.sin(phi), 0.0])
        lat = R @ lat_cam
        beta = np.deg2rad(rng.uniform(40, 55))
        self.axis = -np.sin(beta) * lat + np.cos(beta) * zc  # from the back towards the tip
        self.axis /= np.linalg.norm(self.axis)
        perp = R @ np.array([-np.sin(phi), np.cos(phi), 0.0])
        c0 = centre - lat * rng.uniform(0, 8) + perp * rng.uniform(-8, 8)
        self.c0 = c0[:2]
        self.radius_xy = rng.uniform(4, 8, 2)
        self.w = 2 * np.pi / rng.uniform(5, 9, 2)
        self.p = rng.uniform(0, 2 * np.pi, 2)
        self.depth_range = (rng.uniform(1.5, 2.5), rng.uniform(4.5, 6.0))
        self.push_period = rng.uniform(3.0, 5.0)
        self.push_phase = rng.uniform(0, 2 * np.pi)
        self.sigma = rng.uniform(6.0, 9.0)

    def at(self, t: float) -> tuple[FrameDeformation, list[Capsule]]:
        """The deformation of the tissue and the instrument's capsules at time ``t`` (s)."""
        c = self.c0 + self.radius_xy * np.sin(self.w * t + self.p)
        d0, d1 = self.depth_range
        depth = d0 + (d1 - d0) * (0.5 - 0.5 * np.cos(2 * np.pi * t / self.push_period + self.push_phase))
        n = self.scene.rest_normal(c[0], c[1])  # towards the camera
        push = 0.4 * self.axis - 0.6 * n
        push /= np.linalg.norm(push)
        deform = FrameDeformation(t=t, breathing=self.breathing,
                                  indentation=Indentation(center=c, depth=float(depth), sigma=self.sigma, direction=push))
        contact = self.scene.rest_point(c[0], c[1]) + deform.displacement_at(self.scene, c[0], c[1])
        tip = contact + HEAD_RADIUS * n
        head = Capsule(tip, tip - HEAD_LENGTH * self.axis, HEAD_RADIUS, 0)
        start = tip - (HEAD_LENGTH + 1.0) * self.axis
        shaft = Capsule(start, start - SHAFT_LENGTH * self.axis, SHAFT_RADIUS, 1)
        return deform, [head, shaft]


def _dot(u, v):
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]


def intersect_capsule(o: np.ndarray, d: np.ndarray, cap: Capsule) -> np.ndarray:
    """Ray parameter of the first hit of rays ``o + t d`` (``d`` unit, ``o`` ``(3,)`` or per-ray)
    with a capsule; ``inf`` where the ray misses (or the hit is behind the origin)."""
    a = cap.a.astype(np.float32)
    ba = (cap.b - cap.a).astype(np.float32)
    oa = o.astype(np.float32) - a
    baba = np.float32(ba @ ba)
    bard = _dot(d, ba)
    baoa = _dot(np.broadcast_to(oa, d.shape), ba)
    rdoa = _dot(d, oa)
    oaoa = _dot(np.broadcast_to(oa, d.shape), oa)
    r2 = np.float32(cap.radius ** 2)
    A = baba - bard * bard
    B = baba * rdoa - baoa * bard
    C = baba * oaoa - baoa * baoa - r2 * baba
    h = B * B - A * C
    hit = h >= 0
    sq = np.sqrt(np.maximum(h, 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_body = (-B - sq) / np.where(np.abs(A) > 1e-12, A, np.float32(1e-12))
    y = baoa + t_body * bard
    body = hit & (y > 0) & (y < baba)
    # caps: the sphere at the nearer end
    oc = np.where((y <= 0)[..., None], oa, o.astype(np.float32) - cap.b.astype(np.float32))
    b2 = _dot(d, oc)
    c2 = _dot(oc, oc) - r2
    h2 = b2 * b2 - c2
    t_cap = -b2 - np.sqrt(np.maximum(h2, 0))
    capped = hit & ~body & (h2 > 0)
    t = np.where(body, t_body, np.where(capped, t_cap, np.inf)).astype(np.float32)
    t[t <= 1e-3] = np.inf
    return t


def capsule_normal(p: np.ndarray, cap: Capsule) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals at surface points ``p`` ``(..., 3)`` and the distance from the tip
    end ``a`` along the axis (mm)."""
    a = cap.a.astype(np.float32)
    ba = (cap.b - cap.a).astype(np.float32)
    L = float(np.linalg.norm(ba))
    s = np.clip(_dot(p - a, ba) / np.float32(L * L), 0.0, 1.0)
    n = (p - a - s[..., None] * ba) / np.float32(cap.radius)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-9
    return n, s * np.float32(L)


def intersect_instrument(o: np.ndarray, d: np.ndarray, caps: list[Capsule]):
    """Nearest hit over the capsules: ``(t, capsule index)`` (``t = inf``, index -1 on a miss)."""
    best = np.full(d.shape[:-1], np.inf, np.float32)
    idx = np.full(d.shape[:-1], -1, np.int8)
    for i, cap in enumerate(caps):
        t = intersect_capsule(o, d, cap)
        closer = t < best
        best = np.where(closer, t, best)
        idx[closer] = i
    return best, idx
