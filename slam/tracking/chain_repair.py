"""The stretch of poses the map did not confirm, corrected when the map speaks again.

Frames tracked along the chain while the map did not confirm it (a relocalisation, frames tracked
against the previous frame, frames whose estimate disagreed with the map) carry whatever error the
chain picked up. When a registration against the map ends the stretch (it confirms the chain, or
the map's estimate is kept over it: the snap back), the map's pose of that frame against the
chain's says how far the chain was off there: ``D = T_map T_chain^-1`` (world frame, mm). The
stretch is corrected linearly in time, each frame ``i`` by ``exp(alpha_i log D)``, ``alpha_i``
rising from 0 at the last pose the map held (confirmed, or snapped back) to 1 at the frame that
ended it: drift grows along the chain. A stretch that begins with a relocalisation is corrected
by ``D`` whole: its error is the relocalisation's, which every frame after it carries. The corrected poses are the run's result (``trajectory.txt``), the ones tracked what was
known at the time (``trajectory_online.txt``).

A stretch that ends in a re-anchoring of the map is not corrected (the new map was built from the
chain: it cannot tell how far the chain was off), nor is one longer than ``MAX_STRETCH`` frames
(the memory is bounded: its oldest frames keep their poses).
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from slam.tracking.state import FrameResult
from vo.lie import se3_exp, se3_log

MAX_STRETCH = 500


def fraction_of(correction: np.ndarray, alpha: float) -> np.ndarray:
    """``exp(alpha log correction)`` of a ``(4, 4)`` rigid transform (mm)."""
    xi = se3_log(torch.from_numpy(np.asarray(correction, np.float64))[None])[0]
    return se3_exp((alpha * xi)[None])[0].numpy()


class ChainRepair:
    """One run's corrections of unconfirmed stretches (see the module docstring).

    Attributes:
        corrections: position -> corrected rectified ``T_wc`` (mm) of every repaired frame.
        repairs: stretches corrected.
    """

    def __init__(self):
        self.corrections: dict[int, np.ndarray] = {}
        self.repairs = 0
        self._stretch: dict[int, np.ndarray] = {}     # the current stretch: position -> tracked pose
        self._held: Optional[int] = None               # the last frame whose pose the map held
        self._jump = False                             # the stretch began with a relocalisation

    def follow(self, position: int, pose: np.ndarray, result: FrameResult) -> list[int]:
        """Take the frame's outcome: extend the stretch, or end it (corrected where the map gave
        the correction, ``result.map_correction``); returns the positions corrected now."""
        if result.failed:
            return []
        if result.anchors_map and not (result.trusted or result.agrees_with_map):
            self._stretch.clear()               # (re-anchored or rebuilt from the chain: no correction known)
            self._held = position
            return []
        if (result.trusted and not result.between) or result.snapped_to_map:
            repaired = self._correct(position, result.map_correction)
            self._held = position
            return repaired
        if not self._stretch:
            self._jump = result.reference == "relocalised"
        self._stretch[position] = np.asarray(pose, np.float64).copy()
        if len(self._stretch) > MAX_STRETCH:
            self._stretch.pop(min(self._stretch))
        return []

    def _correct(self, end: int, correction: Optional[np.ndarray]) -> list[int]:
        stretch, self._stretch = self._stretch, {}
        if not stretch or correction is None or self._held is None:
            return []
        start = self._held
        for k, pose in stretch.items():
            alpha = 1.0 if self._jump else (k - start) / (end - start)
            self.corrections[k] = fraction_of(correction, alpha) @ pose
        self.repairs += 1
        return sorted(stretch)

    def corrected(self, tracked: np.ndarray) -> Optional[np.ndarray]:
        """``(N, 4, 4)`` the tracked rectified poses with the corrections applied (None where
        nothing was corrected)."""
        if not self.corrections:
            return None
        out = np.array(tracked, dtype=np.float64, copy=True)
        for k, pose in self.corrections.items():
            if k < len(out):
                out[k] = pose
        return out
