"""The interface every correspondence backend implements."""
from __future__ import annotations

from typing import Protocol

import torch


class FlowEstimator(Protocol):
    """Dense optical flow between two images.

    ``flow(image1, image2)`` takes ``(B, 3, H, W)`` float32 RGB in [0, 1] and returns ``(B, 2, H, W)``
    float32 pixel displacements (x, y) such that pixel ``p`` of ``image1`` corresponds to
    ``p + flow[:, :, p]`` in ``image2``. ``start``: a ``(B, 2, H, W)`` flow the search starts from
    (a prediction: the motion field of a predicted pose), None: from scratch.

    Stereo parallax flow is ``flow(left, right)``: on a rectified pair its horizontal part is minus
    the disparity (``d = -F'_x > 0``) and its vertical part is ideally zero.
    """

    name: str

    def flow(self, image1: torch.Tensor, image2: torch.Tensor,
             start: torch.Tensor | None = None) -> torch.Tensor:  # pragma: no cover - protocol
        ...
