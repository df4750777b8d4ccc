"""What every dataset reader yields, and the interface readers implement."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator, Optional

import numpy as np

from vo.camera import StereoCamera


@dataclass
class StereoFrame:
    """One rectified, resized stereo frame.

    Attributes:
        index: position of the frame in the sequence (before frame selection).
        timestamp: the sequence's own timestamp (seconds or whatever the dataset uses).
        left, right: ``(H, W, 3)`` uint8 RGB, rectified to the reader's ``camera``.
        mask: ``(H, W)`` bool, True = valid tissue pixel (instrument mask AND specularity mask).
        gt_pose: ``(4, 4)`` float64 ground-truth ``T_wc`` of the *original* left camera, in mm,
            or None.
        gt_depth: ``(H, W)`` float32 ground-truth depth of the rectified left view in mm
            (synthetic data only), or None.
        extras: reader-specific per-frame data (e.g. synthetic non-rigid motion maps).
        specular: ``(2, H, W)`` bool specular highlights of the left and right views (True =
            highlight, dilated as in ``mask``), or None. A highlight is the light's mirror image,
            so the two views show it on different tissue: stereo matching must not see it.
    """

    index: int
    timestamp: float
    left: np.ndarray
    right: np.ndarray
    mask: np.ndarray
    gt_pose: Optional[np.ndarray] = None
    gt_depth: Optional[np.ndarray] = None
    extras: dict = field(default_factory=dict)
    specular: Optional[np.ndarray] = None
