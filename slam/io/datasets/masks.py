"""Validity masks: specular highlights, dark pixels and instrument masks.

A frame's ``mask`` (True = valid tissue) is ``instrument_mask AND NOT specular_mask AND NOT
dark_mask AND valid``, all at the output size: the instrument mask comes from the dataset's mask
files (non-zero = tissue, 0 = instrument) when present and enabled, the specular and dark masks
are detected on the rectified, resized left image, and ``valid`` marks rectified pixels that map
inside the raw image.
"""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np


def _peak(rgb: np.ndarray) -> np.ndarray:
    """``(H, W)`` maximum channel intensity of an ``(H, W, 3)`` (or grey ``(H, W)``) image.

    (The channels' element-wise maximum: numpy's ``max(axis=2)`` over three interleaved channels
    took 7.8 ms at 640x512, this 0.4.)"""
    if rgb.ndim == 3:
        return np.maximum.reduce([rgb[..., c] for c in range(rgb.shape[2])])
    if rgb.ndim == 2:
        return rgb
    raise ValueError(f"expected an (H, W, 3) image, got shape {rgb.shape}")


def specular_mask(rgb: np.ndarray, threshold: float, dilate_px: int) -> np.ndarray:
    """Specular highlights by maximum-intensity detection.

    A pixel is specular when its maximum channel intensity, scaled to 0-1 (``/ 255``), reaches
    ``threshold``; the detection is then dilated with an elliptical kernel of radius ``dilate_px``
    (diameter ``2 * dilate_px + 1``) to cover the highlight's blurry rim.

    Args:
        rgb: ``(H, W, 3)`` uint8 image (channel order irrelevant).
        threshold: in (0, 1]; values > 1 disable the detection.
        dilate_px: dilation radius in pixels, 0 = none.

    Returns:
        ``(H, W)`` bool, True = specular.
    """
    rgb = np.asarray(rgb)
    peak = _peak(rgb)
    if rgb.dtype == np.uint8:
        cut = int(np.ceil(threshold * 255.0 - 1e-9))
        spec = peak >= cut if cut <= 255 else np.zeros(peak.shape, dtype=bool)
    else:
        spec = peak.astype(np.float64) / 255.0 >= threshold
    r = int(dilate_px)
    if r > 0 and spec.any():
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        spec = cv2.dilate(spec.astype(np.uint8), kernel) > 0
    return spec


def dark_mask(rgb: np.ndarray, threshold: float) -> np.ndarray:
    """``(H, W)`` bool, True where the maximum channel intensity (scaled to 0-1, ``/ 255``) is below
    ``threshold`` (0 = none): too little light for stereo or flow to match."""
    return _peak(np.asarray(rgb)).astype(np.float32) < np.float32(threshold * 255.0)


def combine_masks(
    left_rgb: np.ndarray,
    instrument: Optional[np.ndarray],
    threshold: float,
    dilate_px: int,
    valid: Optional[np.ndarray] = None,
    dark_threshold: float = 0.0,
    specular: Optional[np.ndarray] = None,
) -> np.ndarray:
    """The frame mask: ``instrument AND NOT specular(left_rgb) AND NOT dark(left_rgb) AND valid``
    (True = valid tissue).

    ``instrument`` (True = tissue) and ``valid`` may be None (all True); all at the image's size.
    ``specular``: the left view's :func:`specular_mask` if already computed.
    """
    if specular is None:
        specular = specular_mask(left_rgb, threshold, dilate_px)
    mask = ~specular
    if dark_threshold > 0:
        mask &= ~dark_mask(left_rgb, dark_threshold)
    if instrument is not None:
        mask &= np.asarray(instrument, dtype=bool)
    if valid is not None:
        mask &= np.asarray(valid, dtype=bool)
    return mask
