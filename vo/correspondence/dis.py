"""OpenCV DIS optical flow (Kroeger et al. 2016) as the default correspondence backend."""
from __future__ import annotations

import cv2
import numpy as np
import torch

_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def to_gray_u8(image: torch.Tensor) -> np.ndarray:
    """``(3, H, W)`` float RGB in [0, 1] -> ``(H, W)`` uint8 grey."""
    rgb = (image.detach().clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)


class DisFlow:
    """Dense Inverse Search flow on grey images; implements ``FlowEstimator``.

    Args:
        preset: ``ultrafast`` | ``fast`` | ``medium``.
        variational_refinement: keep DIS's variational refinement (False sets its iterations to 0).
    """

    name = "dis"

    def __init__(self, preset: str = "medium", variational_refinement: bool = True):
        if preset not in _PRESETS:
            raise ValueError(f"unknown DIS preset '{preset}' (choose from {', '.join(_PRESETS)})")
        self.preset = preset
        self._dis = cv2.DISOpticalFlow_create(_PRESETS[preset])
        if not variational_refinement:
            self._dis.setVariationalRefinementIterations(0)

    def flow_gray(self, gray1: np.ndarray, gray2: np.ndarray) -> np.ndarray:
        """``(H, W)`` uint8 grey images -> ``(H, W, 2)`` float32 flow from ``gray1`` to ``gray2``."""
        return self._dis.calc(gray1, gray2, None)

    def flow(self, image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
        """``(B, 3, H, W)`` float RGB in [0, 1] -> ``(B, 2, H, W)`` flow from ``image1`` to ``image2``."""
        flows = [
            torch.from_numpy(self.flow_gray(to_gray_u8(a), to_gray_u8(b))).permute(2, 0, 1)
            for a, b in zip(image1, image2)
        ]
        return torch.stack(flows).to(image1.device)
