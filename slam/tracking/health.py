"""Tracking health: per-frame figures of how well each pose is supported, the calibrated pose
covariance, and the normalised estimation error squared (NEES) where the ground truth is known.

The correspondences are fixed before the solve, so where the image gives little the flow is
wrong with confidence, not the normal equations singular: besides the share of supported pixels
and the covariance ``Sigma = s * sigma^2 * H^-1`` (:mod:`vo.health`), the figures compare each
frame with the sequence's own recent level (:class:`RunningLevel`: the cost, the residual medians,
the plane residual against the model and the support, each as a robust z-score of its logarithm
against its last ``RUNNING_FRAMES`` frames), so that a frame whose cost jumps thirtyfold is seen
whatever the scene's usual cost.
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

# the figures whose level a sequence keeps, and +1 where higher is worse (-1: lower)
LEVEL_FIGURES = {"cost": 1, "residual_2d_px": 1, "residual_3d_mm": 1, "plane_residual_mm": 1, "support": -1}
# frames a level needs before it scores one
LEVEL_MIN_FRAMES = 5
# the least spread (natural log) a level's z-score divides by: a sequence whose figure barely
# moves does not make a 10 % change an outlier
LEVEL_MIN_SPREAD = 0.1

# the figures of tracking.csv, in order (nan where a frame has none)
FIGURES = ("valid_pixels", "support", "iterations", "cost", "round_trip_px", "residual_2d_px", "residual_3d_mm",
           "model_coverage", "plane_residual_mm", "plane_cost_share", "level_z", "cross_check_d2",
           "cross_check_mm", "sigma_t_mm", "sigma_r_deg", "nees")


class RunningLevel:
    """A figure's level over a sequence's last ``RUNNING_FRAMES`` frames, and how far a new value
    lies from it: the robust z-score ``worse * (log v - median) / max(1.4826 * MAD, LEVEL_MIN_SPREAD)``
    of its logarithm (the figures are positive and vary by factors).

    Args:
        worse: +1 where a higher value is worse, -1 where a lower one is.
    """

    def __init__(self, worse: int = 1):
        self.worse = worse
        self._logs: deque = deque(maxlen=RUNNING_FRAMES)

    def z(self, value: float) -> float:
        """The z-score of ``value`` (nan before ``LEVEL_MIN_FRAMES`` values or for a value that is
        not positive and finite)."""
        if len(self._logs) < LEVEL_MIN_FRAMES or not (np.isfinite(value) and value > 0):
            return float("nan")
        logs = np.asarray(self._logs)
        median = float(np.median(logs))
        spread = max(1.4826 * float(np.median(np.abs(logs - median))), LEVEL_MIN_SPREAD)
        return self.worse * (float(np.log(value)) - median) / spread

    def add(self, value: float) -> None:
        """Take ``value`` into the level (ignored where it is not positive and finite)."""
        if np.isfinite(value) and value > 0:
            self._logs.append(float(np.log(value)))


class SequenceLevel:
    """The levels of a sequence's :data:`LEVEL_FIGURES`, kept apart for frames tracked against the
    model view and against a camera frame (their costs differ)."""

    def __init__(self):
        self._levels = {against: {name: RunningLevel(worse) for name, worse in LEVEL_FIGURES.items()}
                        for against in (True, False)}

    def score(self, figures: dict, against_model: bool) -> tuple[float, str]:
        """The largest z-score of a frame's ``figures`` against the level and the figure that
        gives it (nan and "" where none scores)."""
        best, name = float("nan"), ""
        for figure, level in self._levels[against_model].items():
            z = level.z(figures.get(figure, float("nan")))
            if np.isfinite(z) and not z <= best:
                best, name = z, figure
        return best, name

    def add(self, figures: dict, against_model: bool) -> None:
        """Take a tracked frame's ``figures`` into the level."""
        for figure, level in self._levels[against_model].items():
            level.add(figures.get(figure, float("nan")))


class HealthMonitor:
    """One sequence's health bookkeeping: its level (:class:`SequenceLevel`)."""

    def __init__(self, config: HealthConfig):
        self.config = config
        self.level = SequenceLevel()

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
                       sigma_t_mm=float(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))),
                       sigma_r_deg=float(np.degrees(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0)))))
        return figures, cov

    def against_level(self, figures: dict, against_model: bool) -> tuple[float, str]:
        """A tracked frame's largest z-score against the sequence's level (health figure
        ``level_z``) and the figure that gives it; the frame's figures then join the level."""
        z, figure = self.level.score(figures, against_model)
        figures["level_z"] = z
        self.level.add(figures, against_model)
        return z, figure


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
