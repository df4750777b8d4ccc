"""Frame2model's cross-check: the model view's estimate of a frame against an independent one,
tracked against the last frame with its own flow.

The two are combined as a filter on the pose relative to the map (an error-state Kalman step,
first order, relative poses as left perturbations in mm and rad, translation first):

- prediction: the last frame's estimate ``F`` (``Sigma_F``) from the last pose, whose uncertainty
  against the map is ``P``: ``P_pred = P + Sigma_F``;
- measurement: the model view's estimate ``M`` (``Sigma_M``), tied to the map;
- innovation ``delta = log(M F^-1)`` with ``S = P_pred + Sigma_M`` and its squared Mahalanobis
  distance ``d2 = delta^T S^-1 delta`` (chi-square, 6 dof, for calibrated covariances);
- where they agree (``d2`` and the positional distance within their limits): the pose
  ``exp(K delta) F`` with the gain ``K = P_pred S^-1``, and ``P = (I - K) P_pred``;
- where they disagree: the better-supported estimate alone (the smaller positional spread); the
  frame is flagged. Keeping the last frame's estimate lets ``P`` grow with each such frame, so
  the gate widens as frame-to-frame drift accumulates and the model agrees again.

Where the last frame's flow is the better one (weak texture: a tenth of the model view's
per-frame error on the sequences of ``tools/cross_check.py``) the map still pulls the pose back
within a few frames; where the model view is the better one (rich texture: its covariance is
several times smaller) ``K`` is near the identity and the model view's estimate stands.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from slam.tracking.health import nees, relative_error
from vo.lie import se3_exp


class CrossCheckResult(NamedTuple):
    """The outcome of one cross-check.

    Attributes:
        relative: ``(4, 4)`` mm transform current camera -> last camera to report.
        covariance: ``(6, 6)`` its uncertainty against the map (mm and rad, translation first).
        d2: the innovation's squared Mahalanobis distance.
        distance_mm: the distance of the two estimates' positions.
        kept: ``combined`` (they agree), ``frame`` or ``model`` (they disagree: the one kept).
    """

    relative: np.ndarray
    covariance: np.ndarray
    d2: float
    distance_mm: float
    kept: str

    @property
    def agree(self) -> bool:
        return self.kept == "combined"


class Estimate(NamedTuple):
    """A relative pose ``(4, 4)`` mm (current -> last camera) and its ``(6, 6)`` covariance."""

    relative: np.ndarray
    covariance: np.ndarray


class CrossCheck:
    """One sequence's cross-check state: ``P``, the uncertainty of the last pose against the map.

    Args:
        limit_d2: the largest ``d2`` at which the two estimates agree.
        limit_mm: the largest distance of their positions at which they agree (mm).
    """

    def __init__(self, limit_d2: float, limit_mm: float):
        self.limit_d2, self.limit_mm = float(limit_d2), float(limit_mm)
        self.P = np.zeros((6, 6))

    def reset(self) -> None:
        """The pose is the map's own (the first frame, a map rebuilt around the view)."""
        self.P = np.zeros((6, 6))

    def tracked_against_model(self, covariance: np.ndarray) -> None:
        """A frame tracked against the model view alone (no independent estimate)."""
        self.P = np.array(covariance, dtype=np.float64)

    def tracked_against_frame(self, covariance: np.ndarray) -> None:
        """A frame tracked against the previous frame alone: its uncertainty adds up."""
        self.P = self.P + covariance

    def check(self, model: Estimate, frame: Estimate, chain_checked: bool = True) -> CrossCheckResult:
        """Combine or choose between the model view's and the last frame's estimates. Where they
        disagree the better-supported is kept: the smaller positional spread of the two. Where the
        chain holds a relocalisation the map never checked, the chain's spread includes its ``P``,
        and where
        the two are inconsistent beyond ``limit_d2`` the model view's is kept whatever the spreads:
        the map, the evidence of every frame fused, outranks a chain it never confirmed that claims
        to be surer than they are, and the track snaps back to it (flagged)."""
        P_pred = self.P + frame.covariance
        S = P_pred + model.covariance
        delta = relative_error(model.relative, frame.relative)         # M = exp(delta) F
        d2 = nees(delta, S)
        distance = float(np.linalg.norm(delta[:3]))
        if np.isfinite(d2) and d2 <= self.limit_d2 and distance <= self.limit_mm:
            K = P_pred @ np.linalg.inv(S)
            P = (np.eye(6) - K) @ P_pred
            self.P = 0.5 * (P + P.T)
            step = se3_exp(torch.from_numpy(K @ delta)[None])[0].numpy()
            return CrossCheckResult(step @ frame.relative, self.P.copy(), d2, distance, "combined")
        frame_spread = frame.covariance if chain_checked else P_pred
        chain_refuted = not chain_checked and not d2 <= self.limit_d2
        if not chain_refuted and np.trace(frame_spread[:3, :3]) <= np.trace(model.covariance[:3, :3]):
            self.P = P_pred
            return CrossCheckResult(frame.relative, P_pred.copy(), d2, distance, "frame")
        self.P = np.array(model.covariance, dtype=np.float64)
        return CrossCheckResult(model.relative, self.P.copy(), d2, distance, "model")
