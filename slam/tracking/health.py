"""Tracking health: per-frame figures of how well each pose is supported, the calibrated pose
covariance, and the normalised estimation error squared (NEES) where the ground truth is known.

The correspondences are fixed before the solve, so where the image gives little the flow is
wrong with confidence, not the normal equations singular: the figures compare each frame with the
sequence's own recent history (residual medians against their running medians), besides the
share of supported pixels and the covariance ``Sigma = s * sigma^2 * H^-1`` (:mod:`vo.health`).
"""
from __future__ import annotations

from collections import deque
from typing import Optional

import numpy as np
import torch

from slam.config import HealthConfig
from vo.lie import se3_log
from vo.odometry import TrackResult

# good frames whose residual medians make the running medians (about a second of video at 25 fps)
RUNNING_FRAMES = 25

# the figures of tracking.csv, in order (nan where a frame has none)
FIGURES = ("valid_pixels", "support", "iterations", "cost", "round_trip_px", "residual_2d_px", "residual_3d_mm",
           "residual_2d_ratio", "residual_3d_ratio", "model_coverage", "plane_residual_mm",
           "plane_cost_share", "cross_check_d2", "cross_check_mm", "chain_correction_mm", "sigma_t_mm", "sigma_r_deg", "nees")


class HealthMonitor:
    """One sequence's health bookkeeping: the running medians of its good frames' residuals."""

    def __init__(self, config: HealthConfig):
        self.config = config
        self._r2: deque = deque(maxlen=RUNNING_FRAMES)
        self._r3: deque = deque(maxlen=RUNNING_FRAMES)

    def assess(self, track: Optional[TrackResult], against_model: bool) -> tuple[dict, Optional[np.ndarray]]:
        """The health figures of a frame tracked as ``track`` (None: not tracked) against a
        model view or a camera frame, and its ``(6, 6)`` pose covariance (mm and rad,
        translation first; None without a fit)."""
        if track is None:
            return {}, None
        figures = {"valid_pixels": track.valid_pixels, "iterations": track.iterations, "cost": track.cost,
                   "support": track.support, "round_trip_px": track.round_trip_px}
        fit = track.fit
        if fit is None:
            return figures, None
        cfg = self.config
        cov = fit.covariance(cfg.covariance_scale_model if against_model else cfg.covariance_scale_frame)
        figures.update(residual_2d_px=fit.residual_2d_px, residual_3d_mm=fit.residual_3d_mm,
                       residual_2d_ratio=_ratio(fit.residual_2d_px, self._r2),
                       residual_3d_ratio=_ratio(fit.residual_3d_mm, self._r3),
                       sigma_t_mm=float(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))),
                       sigma_r_deg=float(np.degrees(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0)))))
        if not track.failed:
            for history, value in ((self._r2, fit.residual_2d_px), (self._r3, fit.residual_3d_mm)):
                if np.isfinite(value):
                    history.append(value)
        return figures, cov


def _ratio(value: float, history: deque) -> float:
    """``value`` over the median of ``history`` (nan before there is one)."""
    if not history or not np.isfinite(value):
        return float("nan")
    ref = float(np.median(history))
    return value / ref if ref > 0 else float("nan")


def relative_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The ``(6,)`` error ``log(estimate @ truth^-1)`` of a ``(4, 4)`` mm relative pose, in mm
    and rad, translation first: the left perturbation the covariance is expressed in."""
    delta = torch.from_numpy(np.asarray(estimate @ np.linalg.inv(truth), np.float64))[None]
    return se3_log(delta)[0].numpy()


def nees(error: np.ndarray, covariance: np.ndarray) -> float:
    """``e^T Sigma^-1 e`` of a ``(6,)`` error under its ``(6, 6)`` covariance."""
    try:
        return float(error @ np.linalg.solve(covariance, error))
    except np.linalg.LinAlgError:
        return float("nan")


def health_summary(rows: list[dict]) -> dict:
    """``metrics.json``'s summary of per-frame figures: the median of each over the frames that
    have it, and the mean NEES (6 for a calibrated covariance) with the frames it is over."""
    out = {}
    for name in FIGURES:
        values = np.array([r.get(name, np.nan) for r in rows], float)
        values = values[np.isfinite(values)]
        if name == "nees":
            out["nees_mean"] = float(values.mean()) if values.size else None
            out["nees_frames"] = int(values.size)
        elif values.size:
            out[f"{name}_median"] = float(np.median(values))
    return out
