"""Which frames frame2model registers against the map (*model frames*), chosen once per run.

- :class:`EveryFrame`: every frame (``tracking.model_every: 1``, the paper's frame2model).
- :class:`ModelFrameSchedule`: a frame keeps the cross-check's estimate against the last frame (its
  flow computed ahead) as its pose, and is a model frame, registered against the map's view and
  fused, when the chain needs the map's word: the last model frame is ``model_every`` frames back,
  the chain is unconfirmed (a flag, a relocalisation, a fallback), the frame's own estimate failed,
  or the chain's spread since the last model frame (the filter's ``P``) would exceed half of
  ``health.flag_mm``. A model frame's registration confirms the chain and corrects the frames
  since the last one (:mod:`slam.tracking.chain_repair`).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from slam.tracking.acceptance import sigma_t_mm


class EveryFrame:
    """Every frame is a model frame."""

    def between(self, position: int, estimate, acceptance) -> bool:
        return False

    def model_frame(self, position: int) -> None:
        """(Nothing to remember.)"""


class ModelFrameSchedule:
    """Model frames where the chain needs them (see the module docstring).

    Args:
        every: ``tracking.model_every``.
        flag_mm: ``health.flag_mm``.
    """

    def __init__(self, every: int, flag_mm: float):
        self.every = every
        self.flag_mm = flag_mm
        self.last: Optional[int] = None

    def between(self, position: int, estimate, acceptance) -> bool:
        """Whether the frame at ``position`` is tracked along the chain only (its independent
        ``estimate`` against the last frame, None where it failed)."""
        if estimate is None or self.last is None or position - self.last >= self.every:
            return False
        if not acceptance.chain_confirmed:
            return False
        spread = sigma_t_mm(acceptance.cross_check.P + np.asarray(estimate.estimate.covariance))
        return spread <= self.flag_mm / 2

    def model_frame(self, position: int) -> None:
        self.last = position
