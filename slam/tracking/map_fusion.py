"""What a tracked frame adds to the map: its depth and colour fused at its pose.

A variant chosen once per run: :class:`NoFusion` (frame2frame without an exported map) or
:class:`SurfelFusion` (frame2model, ``--export-map``, mapping at known poses), which weighs each
pixel by the learned 3D weight where there is one (:class:`LearnedWeight`) or counts every valid
pixel fully (:class:`EveryPixel`: constant weights, 2D-only networks) and brings the colour to
the map's exposure (:class:`FusionExposure`).
"""
from __future__ import annotations

import time
from typing import Optional

import torch

from vo.odometry import View


def normalised_fusion_weight(w3d: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The per-pixel fusion weight of a frame from its learned 3D weight.

    Where the tracker weighed the pixel (``w3d > 0``): ``w3d`` divided by its median over those
    pixels, clamped to [0, 1]. The optimum does not fix the weights' scale, so a typical pixel
    counts as one observation (the map's confidence keeps ElasticFusion's meaning and a surface
    becomes stable after a few frames) and a pixel the network trusts k times less than typical
    counts 1/k. Valid pixels the tracker could not weigh (no reference depth there: tissue coming
    into view, outside the model view) count fully: leaving them out would keep new tissue out of
    the map until the tracker next falls back to the previous frame.
    Invalid pixels (no stereo depth, instruments, highlights) are 0.

    Args:
        w3d: ``(H, W)`` learned 3D weight, 0 where the tracker did not weigh the pixel;
        valid: ``(H, W)`` bool valid pixels of the frame.
    """
    weighed = valid & (w3d > 0)
    vals = w3d[weighed]
    if vals.numel() == 0:
        return valid.to(w3d.dtype)
    ref = vals.float()[:: max(1, vals.numel() // 20000)].median().clamp(min=1e-12)   # (quantile: 8x slower)
    return torch.where(weighed, (w3d / ref).clamp(0, 1), valid.to(w3d.dtype))


class LearnedWeight:
    """Fusion weighed by the tracker's learned w3D (:func:`normalised_fusion_weight`); a frame
    fused without one (the first, known poses without a pair) counts every valid pixel fully."""

    def __call__(self, w3d: Optional[torch.Tensor], valid: torch.Tensor) -> Optional[torch.Tensor]:
        return None if w3d is None else normalised_fusion_weight(w3d[0, 0], valid)


class EveryPixel:
    """Every valid pixel counts fully (constant weights: a w3D that says nothing per pixel)."""

    def __call__(self, w3d: Optional[torch.Tensor], valid: torch.Tensor) -> None:
        return None


def mean_brightness(view: View) -> float:
    """Mean grey level (0-255) of ``view``'s valid pixels (of all pixels when under 1 % are valid:
    a dark frame may have no stereo depth at all)."""
    gray = torch.from_numpy(view.gray)
    valid = view.valid[0, 0].cpu()
    if valid.shape == gray.shape and int(valid.sum()) >= 0.01 * valid.numel():
        gray = gray[valid]
    return float(gray.float().mean()) if gray.numel() else 0.0


def exposure_gain(brightness: float, level: float, lo: float = 0.25, hi: float = 8.0) -> float:
    """The gain that brings a frame of mean ``brightness`` to the map's exposure ``level`` (both
    0-255 grey), clamped to ``[lo, hi]``: exposure is a global factor on the image (the light's
    intensity, the exposure time), so the fused colour is ``image x gain``."""
    return float(min(max(level / max(brightness, 0.5), lo), hi))


class FusionExposure:
    """The colour each view is fused with: brought to the map's exposure, the mean brightness of
    the first fused frame that is not black (:func:`exposure_gain`). The map's colour then stays
    one exposure through exposure jumps (fused as captured, a few frames at a quarter of the
    brightness left dark patches the flow against the render could not match: twice the ATE on
    the synthetic scanning sequence of ``tests/test_exposure.py``), and the render is relit to the
    current frame's shading anyway."""

    def __init__(self):
        self.level: Optional[float] = None

    def colour(self, view: View) -> torch.Tensor:
        """``view``'s ``(3, H, W)`` colour to fuse."""
        colour = view.image[0]
        brightness = mean_brightness(view)
        if self.level is None and brightness >= 8.0:     # (not a black frame)
            self.level = brightness
        gain = exposure_gain(brightness, self.level) if self.level else 1.0
        return (colour * gain).clamp_(0.0, 1.0) if gain != 1.0 else colour


class NoFusion:
    """A run without a map: nothing is fused."""

    map = None

    def fuse(self, view: View, w3d, pose, position: int, active_from: Optional[int], scale: float = 1.0) -> list:
        return []


class SurfelFusion:
    """Frames fused into a :class:`mapping.SurfelMap`.

    Args:
        surfel_map: the map.
        K: ``(3, 3)`` rectified intrinsics (torch).
        weight: :class:`LearnedWeight` or :class:`EveryPixel`.
    """

    def __init__(self, surfel_map, K: torch.Tensor, weight):
        self.map = surfel_map
        self.K = K
        self.weight = weight
        self.exposure = FusionExposure()

    def fuse(self, view: View, w3d: Optional[torch.Tensor], pose, position: int,
             active_from: Optional[int], scale: float = 1.0) -> list:
        """Fuse ``view`` at ``pose`` (rectified ``T_wc``, mm) as frame ``position``, weighted by its
        ``(1, 1, H, W)`` learned ``w3d`` where the weight policy takes one; only into the surfels
        fused from ``active_from`` on (None: all). Returns the ``(stage, ms)`` it took."""
        t0 = time.perf_counter()
        valid = view.valid[0, 0]
        weight = self.weight(w3d, valid)
        if scale != 1.0:
            weight = (valid.to(view.depth.dtype) if weight is None else weight) * scale
        self.map.fuse(view.depth[0, 0], self.exposure.colour(view), self.K, torch.as_tensor(pose, dtype=torch.float32),
                      frame_index=position, weight=weight, valid=valid, active_from=active_from)
        return [("fusion", (time.perf_counter() - t0) * 1000.0)]
