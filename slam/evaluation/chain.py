"""Silent errors: poses that are wrong and not flagged, measured along the chain of trusted poses.

A frame is *trusted* when it was neither flagged nor failed: a user takes its pose as it is. Its
error along the chain is the translation error of its motion from the last trusted frame before it
against the true motion between the same two frames. A pose carried wrong from flagged frames (a
wrong relocalisation followed by frames tracked correctly against it) then counts at the first
trusted frame that carries it, and a pose that snaps back to the map counts at the frame that
jumps; a frame's motion from the frame just before it (RPE at delta 1) sees neither.

Poses are ``(N, 4, 4)`` ``T_wc`` in mm, the estimate and the truth of the same camera, in any world
frames (the errors are relative).
"""
from __future__ import annotations

import numpy as np

from slam.tracking.health import relative_error

#: an error above this (mm) on a trusted frame is a silent wrong pose
SILENT_MM = 1.0


def motion_error_mm(poses: np.ndarray, truth: np.ndarray, a: int, b: int) -> float:
    """The translation error (mm) of the estimated motion from frame ``a`` to ``b`` against the
    true one."""
    estimate = np.linalg.inv(poses[a]) @ poses[b]
    motion = np.linalg.inv(truth[a]) @ truth[b]
    return float(np.linalg.norm(relative_error(estimate, motion)[:3]))


def chain_errors(poses: np.ndarray, truth: np.ndarray, trusted: np.ndarray) -> np.ndarray:
    """``(N,)`` each trusted frame's error (mm) against the last trusted frame before it; nan for
    the frames that are not trusted and for the first trusted frame (it has nothing before it).

    Args:
        poses, truth: ``(N, 4, 4)`` estimated and true ``T_wc`` (mm).
        trusted: ``(N,)`` bool, neither flagged nor failed.
    """
    errors = np.full(len(poses), np.nan)
    last = None
    for k in np.flatnonzero(np.asarray(trusted, bool)):
        if last is not None:
            errors[k] = motion_error_mm(poses, truth, last, k)
        last = k
    return errors


def step_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``(N,)`` each frame's error (mm) of its motion from the frame just before it (nan for the
    first): evo's RPE translation at delta 1, per frame."""
    errors = np.full(len(poses), np.nan)
    for k in range(1, len(poses)):
        errors[k] = motion_error_mm(poses, truth, k - 1, k)
    return errors


def silent_summary(poses: np.ndarray, truth: np.ndarray, flagged: np.ndarray, failed: np.ndarray,
                   limit_mm: float = SILENT_MM) -> dict:
    """What a run's silent errors come to.

    Returns:
        ``silent_over``: trusted frames whose chain error exceeds ``limit_mm``; ``silent_frames``:
        their positions; ``silent_max_mm``: the largest chain error of a trusted frame;
        ``unflagged_step_max_mm``: the largest motion error from the frame before among trusted
        frames (0 where there is none).
    """
    flagged, failed = np.asarray(flagged, bool), np.asarray(failed, bool)
    trusted = ~flagged & ~failed
    chain = chain_errors(poses, truth, trusted)
    steps = step_errors(poses, truth)
    steps[~trusted] = np.nan
    over = np.flatnonzero(np.nan_to_num(chain, nan=0.0) > limit_mm)
    return {"silent_over": int(over.size), "silent_frames": over.tolist(),
            "silent_max_mm": float(np.nanmax(chain)) if np.isfinite(chain).any() else 0.0,
            "unflagged_step_max_mm": float(np.nanmax(steps)) if np.isfinite(steps).any() else 0.0}
