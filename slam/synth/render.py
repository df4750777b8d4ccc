"""Ray casting of the (deformed) tissue height field and the instrument, and one view's images.

Tissue: for every pixel ray ``o + s d`` (``d`` has camera-z 1, so ``s`` is the depth) solve for the
rest coordinates ``(x, y)`` whose deformed surface point lies on the ray, by fixed-point
iteration: sample the height and deformation at the current rest estimate, move along the ray to
that height, subtract the lateral displacement. This contracts for the smooth, near-frontal
surfaces used here. All maps are sampled with cv2.remap (bilinear).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from slam.synth.appearance import Appearance
from slam.synth.cameras import ViewCamera
from slam.synth.deformation import Breathing, FrameDeformation
from slam.synth.instrument import Capsule, capsule_normal, intersect_capsule, intersect_instrument
from slam.synth.scene import TEX_LEVELS, TissueScene
from slam.synth.shading import SRGB_TO_LINEAR, Sensor, blinn_phong

MAX_ITERATIONS = 40
TOLERANCE_MM = 1e-4  # stop when no depth changes by more than this
TISSUE_KS, TISSUE_SHININESS = 2.5, 400.0
# Appearance.highlights = 1: a wet film everywhere whose lobe is this broad (a fifth of a frontal
# 640x512 view saturates, tests/test_synth.py)
FILM_SHININESS = 60.0
SMOKE_RGB = np.array([0.62, 0.60, 0.58], np.float32)  # radiance of the veil scattered by smoke
SMOKE_FEATURE_PX = 0.25  # the smoke's blobs, as a share of the image width
SMOKE_DRIFT = 0.02  # share of the image width the smoke drifts per frame
METAL = [  # albedo, ks, shininess per capsule material (head, shaft)
    (np.array([0.55, 0.56, 0.58], np.float32), 1.6, 60.0),
    (np.array([0.30, 0.31, 0.33], np.float32), 1.2, 40.0),
]


@dataclass
class ViewImages:
    """One rendered view: ``rgb`` uint8 ``(H, W, 3)``; ``depth`` float32 mm (camera z);
    ``nonrigid`` float32 mm (|displacement| of the tissue point seen, 0 on the instrument);
    ``tissue`` bool (False on instrument pixels)."""

    rgb: np.ndarray
    depth: np.ndarray
    nonrigid: np.ndarray
    tissue: np.ndarray


def _remap(img, mx, my, border=cv2.BORDER_REPLICATE):
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=border)


def _shade_instrument(P: np.ndarray, idx: np.ndarray, capsules: list[Capsule], light: np.ndarray, eye: np.ndarray,
                      intensity: float) -> np.ndarray:
    """Linear radiance ``(N, 3)`` of instrument surface points ``P`` on capsules ``idx``."""
    n = np.zeros_like(P)
    along = np.zeros(len(P), np.float32)
    for k, cap in enumerate(capsules):
        sel = idx == k
        if np.any(sel):
            n[sel], along[sel] = capsule_normal(P[sel], cap)
    out = np.zeros_like(P)
    for k, cap in enumerate(capsules):
        sel = idx == k
        if not np.any(sel):
            continue
        albedo, ks, shininess = METAL[cap.material]
        alb = np.broadcast_to(albedo, (int(sel.sum()), 3)).astype(np.float32)
        if cap.material == 0:  # a dark insulation ring on the head
            ring = (along[sel] > 6.5) & (along[sel] < 8.0)
            alb = alb * np.where(ring, np.float32(0.25), np.float32(1.0))[:, None]
        out[sel] = blinn_phong(alb, P[sel], n[sel], light, eye, intensity, ks, shininess)
    v = eye.astype(np.float32) - P
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    rim = (1 - np.abs(np.sum(n * v, -1))) ** 3  # grazing reflection of the reddish surroundings
    return out + (0.06 * rim)[:, None] * np.array([1.0, 0.55, 0.5], np.float32)


class Renderer:
    """Renders views of one scene (tissue, optional breathing) with a fixed texture level."""

    def __init__(self, scene: TissueScene, breathing: Optional[Breathing], mm_per_px: float, exposure: float = 1.0,
                 appearance: Appearance = Appearance(), seed: int = 0):
        self.scene = scene
        self.appearance = appearance
        self.seed = int(seed)
        G = scene.geo.size
        zeros = np.zeros((G, G), np.float32)
        amp = breathing.amp if breathing is not None else zeros
        self.geo = np.ascontiguousarray(np.dstack([scene.height, scene.grad[..., 0], scene.grad[..., 1], amp]))
        if breathing is not None:
            extra = [breathing.amp_grad[..., 0], breathing.amp_grad[..., 1], scene.wet]
        else:
            extra = [zeros, zeros, scene.wet]
        self.extra = np.ascontiguousarray(np.dstack(extra))
        # texture level whose texel best matches the pixel footprint (no aliasing, little blur)
        self.level = int(np.clip(np.round(np.log2(max(mm_per_px / scene.tex.res, 1.0))), 0, TEX_LEVELS - 1))
        self.tex_grid = scene.tex_grid(self.level)
        self.albedo = scene.albedo[self.level]
        self.exposure = exposure
        self._sensors: dict[int, Sensor] = {}
        self._smoke: Optional[np.ndarray] = None
        a = appearance
        self.tint = (None if a.tint == 1.0 else
                     np.array([a.tint ** 0.5, a.tint ** -0.5, a.tint ** -0.5], np.float32))
        if a.highlights > 0:
            h = np.float32(a.highlights)
            self.shininess = float(TISSUE_SHININESS ** (1 - h) * FILM_SHININESS ** h)
        else:
            self.shininess = TISSUE_SHININESS

    def specular(self, wet: np.ndarray) -> np.ndarray:
        """Per-pixel specular strength from the surface's wetness (0-1)."""
        ks = TISSUE_KS * wet * wet
        h = self.appearance.highlights
        if h > 0:
            ks = ks + np.float32(h * TISSUE_KS) * (1 - wet * wet)
        return ks

    def smoke(self, shape: tuple[int, int], frame: int) -> np.ndarray:
        """The smoke's density ``(H, W)`` in [0, 1] at ``frame`` (a smooth field drifting across
        the view; the same for both views of a frame)."""
        H, W = shape
        if self._smoke is None or self._smoke.shape[1] < W:
            rng = np.random.default_rng([self.seed, 9])
            size = 4 * max(H, W)
            field = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0),
                                     SMOKE_FEATURE_PX * W / 2.5, borderType=cv2.BORDER_REFLECT_101)
            field = (field - field.mean()) / max(float(field.std()), 1e-9)
            self._smoke = np.clip(0.6 + 0.2 * field, 0.0, 1.0).astype(np.float32)
        size = self._smoke.shape[0]
        shift = int(round(frame * SMOKE_DRIFT * W))
        rows = (np.arange(H) + shift // 3) % size
        cols = (np.arange(W) + shift) % size
        return self.appearance.haze * self._smoke[np.ix_(rows, cols)]

    # -- tissue ---------------------------------------------------------------------------
    def cast_tissue(self, o: np.ndarray, d: np.ndarray, deform: FrameDeformation, iterations: int = MAX_ITERATIONS,
                    tol: float = TOLERANCE_MM):
        """Depth ``s``, rest coordinates ``x, y``, samples ``[h, hx, hy, A]`` and displacement
        ``(ux, uy, uz)`` of the tissue seen along every ray."""
        D0 = np.float32(self.scene.rest_depth_mm)
        ox, oy, oz = (np.float32(v) for v in o)
        dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
        inv_dz = 1.0 / dz
        s = (D0 - oz) * inv_dz
        x = ox + s * dx
        y = oy + s * dy
        zero = np.zeros_like(x)
        u = (zero, zero, zero)
        ds_last = None
        for k in range(iterations):
            s_prev = s
            mx, my = self.scene.geo.to_map(x, y)
            smp = _remap(self.geo, mx, my)
            h, hx, hy, A = smp[..., 0], smp[..., 1], smp[..., 2], smp[..., 3]
            if deform.active:
                u = deform.displacement(x, y, hx, hy, A)
            s = (D0 + h + u[2] - oz) * inv_dz
            x_new = ox + s * dx - u[0]
            y_new = oy + s * dy - u[1]
            x_prev, y_prev = x, y
            if k == 0:
                x, y = x_new, y_new
                continue
            # where the iteration oscillates (steep slopes facing the ray, the instrument's dent),
            # take half steps: that turns a slowly alternating sequence into a fast one
            ds = s - s_prev
            if ds_last is not None:
                w = np.where(ds * ds_last < 0, np.float32(0.5), np.float32(1.0))
                x = x + w * (x_new - x)
                y = y + w * (y_new - y)
            else:
                x, y = x_new, y_new
            ds_last = ds
            if k >= 3 and float(np.max(np.abs(ds))) < tol:
                break
        # report the rest point the last depth was computed from (consistent with ``u``)
        return s, x_prev, y_prev, (h, hx, hy, A), u

    def _tissue_normals(self, x, y, smp, deform: FrameDeformation):
        h, hx, hy, A = smp
        mx, my = self.scene.geo.to_map(x, y)
        ext = _remap(self.extra, mx, my)
        gx, gy = hx, hy
        if deform.active:
            dgx, dgy = deform.height_gradient(x, y, hx, hy, A, ext[..., 0], ext[..., 1])
            gx, gy = hx + dgx, hy + dgy
        n = np.stack([gx, gy, -np.ones_like(gx)], -1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        return n, ext[..., 2]

    def albedo_at(self, x, y) -> np.ndarray:
        mx, my = self.tex_grid.to_map(x, y)
        srgb = cv2.remap(self.albedo, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
        linear = SRGB_TO_LINEAR[srgb]
        return linear if self.tint is None else np.clip(linear * self.tint, 0.0, 1.0)

    # -- one view -------------------------------------------------------------------------
    def render(self, cam: ViewCamera, T_wl: np.ndarray, light: np.ndarray, deform: FrameDeformation,
               capsules: Optional[list[Capsule]], rng: np.random.Generator, frame: int = 0,
               gain: float = 1.0) -> ViewImages:
        """Render ``cam`` of the rig whose left camera is at ``T_wl``; light at ``light`` (world);
        ``frame`` places the smoke, ``gain`` is the automatic exposure's factor on this frame."""
        o, d = cam.world_rays(T_wl)
        s, x, y, smp, u = self.cast_tissue(o, d, deform)
        P = o.astype(np.float32) + s[..., None] * d
        n, wet = self._tissue_normals(x, y, smp, deform)
        albedo = self.albedo_at(x, y)
        I0 = self.scene.rest_depth_mm ** 2

        shadow = None
        inst_t = None
        if capsules:
            dnorm = np.linalg.norm(d, axis=-1)
            dn = d / dnorm[..., None]
            inst_t, inst_idx = intersect_instrument(o, dn, capsules)
            inst_depth = inst_t / dnorm
            on_inst = inst_depth < s
            # shadows of the instrument on the tissue (visible from the right camera)
            Lv = light.astype(np.float32) - P
            dist = np.linalg.norm(Lv, axis=-1)
            Ld = Lv / dist[..., None]
            blocked = np.zeros(s.shape, bool)
            for cap in capsules:
                blocked |= intersect_capsule(P + 0.05 * Ld, Ld, cap) < dist
            shadow = np.where(blocked, np.float32(0.12), np.float32(1.0))

        rad = blinn_phong(albedo, P, n, light, o, I0, self.specular(wet), self.shininess, wrap=0.2, shadow=shadow)
        rad += albedo * np.float32(0.02)  # a little ambient (inter-reflections)
        depth = s.copy()
        tissue = np.ones(s.shape, bool)
        if capsules:
            tissue = ~on_inst
            if np.any(on_inst):
                Pi = o.astype(np.float32) + inst_t[on_inst][:, None] * dn[on_inst]
                rad[on_inst] = _shade_instrument(Pi, inst_idx[on_inst], capsules, light, o, I0)
                depth[on_inst] = inst_depth[on_inst]
        nonrigid = np.sqrt(u[0] ** 2 + u[1] ** 2 + u[2] ** 2) if deform.active else np.zeros_like(s)
        nonrigid = np.where(tissue, nonrigid, np.float32(0))
        if self.appearance.haze > 0:
            a = self.smoke(s.shape, frame)[..., None]
            rad = rad * (1 - a) + a * SMOKE_RGB
        sensor = self._sensors.get(id(cam))
        if sensor is None:
            sensor = self._sensors[id(cam)] = Sensor(cam.rays, self.exposure, vignetting=self.appearance.vignetting)
        rgb = sensor.capture(rad, rng, gain)
        return ViewImages(rgb=rgb, depth=depth.astype(np.float32), nonrigid=nonrigid.astype(np.float32), tissue=tissue)
