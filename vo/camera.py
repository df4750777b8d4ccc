"""The rectified stereo camera the VO core works with."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class StereoCamera:
    """A rectified stereo pair: both views share ``K``; the right camera sits ``baseline_mm`` along +x.

    Attributes:
        K: ``(3, 3)`` float64 intrinsics of the rectified left view, pixels.
        baseline_mm: distance between the optical centres, millimetres (> 0).
        width, height: image size in pixels.
    """

    K: np.ndarray
    baseline_mm: float
    width: int
    height: int

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def scaled(self, width: int, height: int) -> "StereoCamera":
        """The same camera resampled to ``width x height`` (intrinsics scaled, pixel-centre convention)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return StereoCamera(K=K, baseline_mm=self.baseline_mm, width=width, height=height)

    def K_tensor(self, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """``(3, 3)`` intrinsics as a tensor."""
        return torch.as_tensor(self.K, dtype=dtype, device=device)

    def depth_from_disparity_scale(self) -> float:
        """``fx * baseline_mm``: depth (mm) = this / disparity (px)."""
        return self.fx * self.baseline_mm
