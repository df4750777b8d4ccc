"""Whether a frame's estimate is accepted, with what covariance and flags: the acceptance policy,
chosen once per run.

- :class:`PlainAcceptance`: a registration that passes the VO core's check is the frame's pose;
  its health figures and covariance come with it; an uncertain pose (``sigma_t`` above
  ``health.flag_mm``) is flagged and not fused.
- :class:`CrossCheckAcceptance`: frame2model with ``health.cross_check``: each frame tracked
  against the model view is also tracked against the last frame with its own flow, and the two
  estimates are combined by their covariances (:class:`slam.tracking.cross_check.CrossCheck`);
  where they disagree the frame is flagged, reports the better-supported one and is not fused;
  after ``REBUILD_AFTER`` such frames in a row the model around the view is rebuilt.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from slam.tracking.cross_check import CrossCheck, Estimate
from slam.tracking.health import HealthMonitor
from slam.tracking.poses import relative
from slam.tracking.state import FrameResult, TrackState
from vo.odometry import AheadFlow, StereoOdometry, TrackResult, View

log = logging.getLogger("slam")

# frame2model: frames flagged in a row after which the model around the view is rebuilt (at 25 fps
# 0.4 s: a short disagreement is a frame's flow, a lasting one the model's own error)
REBUILD_AFTER = 10


@dataclass
class FrameEstimate:
    """Frame2model's independent estimate of a frame: its tracking against the last frame and
    the relative pose with its covariance (:class:`slam.tracking.cross_check.Estimate`)."""

    track: TrackResult
    estimate: Estimate


class PlainAcceptance:
    """The registration's estimate, checked by the VO core, assessed, flagged when uncertain.

    Args:
        health: the sequence's health monitor (running medians of the residuals).
        flag_mm: ``health.flag_mm``.
    """

    rebuilds = 0
    flows_to_previous_frame = False

    def __init__(self, health: HealthMonitor, flag_mm: float):
        self.health = health
        self.flag_mm = flag_mm

    def independent_estimate(self, view: View, init: Optional[np.ndarray], ahead: Optional[AheadFlow],
                             result: FrameResult, state: TrackState) -> None:
        """(No second estimate.)"""
        return None

    def accept(self, view: View, ref, track: TrackResult, estimate, result: FrameResult, state: TrackState) -> bool:
        """Set ``result``'s pose, health figures, covariance and flags from ``track`` (the
        registration against ``ref``); False when the frame failed."""
        if track.failed:
            self.fail(result, track)
            return False
        self.take(view, ref, track, result)
        self.flag_uncertain(result)
        return True

    def fail(self, result: FrameResult, track: TrackResult) -> None:
        result.failed, result.reason = True, track.reason
        self.assess(result, track)

    def take(self, view: View, ref, track: TrackResult, result: FrameResult) -> None:
        """The registration's pose (refined against the model where the reference is one),
        assessed and verified."""
        pose, track = ref.refine(view, ref.pose @ track.relative, track, result)
        result.pose, result.track = pose, track
        self.assess(result, track)
        ref.verify(view, pose, result)

    def assess(self, result: FrameResult, track: TrackResult) -> None:
        """The frame's health figures and pose covariance (:class:`slam.tracking.health.HealthMonitor`)."""
        figures, result.covariance = self.health.assess(track, against_model=result.reference == "model")
        result.health.update(figures)

    def flag_uncertain(self, result: FrameResult) -> None:
        """Health figures ``sigma_t_mm``, ``sigma_r_deg`` of the covariance of the pose reported,
        and a flag where ``sigma_t`` exceeds ``health.flag_mm``."""
        if result.covariance is None:
            return
        sigma_t = float(np.sqrt(max(np.trace(result.covariance[:3, :3]), 0.0)))
        sigma_r = float(np.degrees(np.sqrt(max(np.trace(result.covariance[3:, 3:]), 0.0))))
        result.health.update(sigma_t_mm=sigma_t, sigma_r_deg=sigma_r)
        if not result.flagged and sigma_t > self.flag_mm:
            self.flag(result, f"uncertain pose (sigma_t {sigma_t:.2f} mm)", model_disagrees=False)

    def flag(self, result: FrameResult, reason: str, model_disagrees: bool = True) -> None:
        result.flagged, result.reason = True, reason

    def after_flags(self, pose: np.ndarray, result: FrameResult, state: TrackState) -> None:
        """(No model to rebuild.)"""

    def reset(self) -> None:
        """(Nothing is carried from frame to frame.)"""


class CrossCheckAcceptance(PlainAcceptance):
    """The model view's estimate cross-checked against the last frame's (see the module docstring).

    Args:
        health, flag_mm: as :class:`PlainAcceptance`.
        cross_check: the sequence's :class:`CrossCheck` (``health.cross_check``, ``flag_mm``).
        odometry: the VO core (the estimate against the last frame).
        covariance_scale_frame: ``health.covariance_scale_frame``.
        forget_view: ``forget_view(pose)`` removes the surfels the view sees from ``pose`` and
            returns how many (the rebuild).

    Attributes:
        flagged_in_row: frames flagged since the model view last agreed.
        rebuilds: times the model around the view was rebuilt.
    """

    flows_to_previous_frame = True       # (the independent estimate's flow can be computed ahead)

    def __init__(self, health: HealthMonitor, flag_mm: float, cross_check: CrossCheck, odometry: StereoOdometry,
                 covariance_scale_frame: float, forget_view: Callable[[np.ndarray], int]):
        super().__init__(health, flag_mm)
        self.cross_check = cross_check
        self.odometry = odometry
        self.covariance_scale_frame = covariance_scale_frame
        self.forget_view = forget_view
        self.flagged_in_row = 0
        self.rebuilds = 0

    def independent_estimate(self, view: View, init: Optional[np.ndarray], ahead: Optional[AheadFlow],
                             result: FrameResult, state: TrackState) -> Optional[FrameEstimate]:
        """The frame tracked against the last frame with its own flow (``ahead`` where it was
        computed ahead), independent of the map: it is made before the reference is chosen,
        while the mapping thread fuses the last frame, and used only where the reference is the
        model view (:meth:`accept`). None where it failed or has no covariance. Timed as
        ``cross_check`` (its flow, weights and solve)."""
        t0 = time.perf_counter()
        if ahead is None or not ahead.serves(state.last_view):
            ahead = AheadFlow(state.last_view, self.odometry.correspondences(view, state.last_view))
        track = self.odometry.track(view, state.last_view, init, ahead=ahead)
        result.time("cross_check", t0)
        if track.failed or track.fit is None:
            return None
        covariance = track.fit.covariance(self.covariance_scale_frame)
        return FrameEstimate(track, Estimate(track.relative, covariance))

    def accept(self, view: View, ref, track: TrackResult, estimate: Optional[FrameEstimate], result: FrameResult,
               state: TrackState) -> bool:
        if not ref.against_model:       # (tracked against a frame: nothing independent to check)
            estimate = None
        if track.failed and estimate is None:
            self.fail(result, track)
            return False
        if track.failed:            # the model view's estimate failed, the last frame's did not
            self.assess(result, estimate.track)
            result.pose = self.keep_frame_estimate(estimate, result, state,
                                                   f"the model view's estimate failed ({track.reason})")
        else:
            self.take(view, ref, track, result)
            if estimate is not None:
                result.pose = self.combine(estimate, result, state)
        self.flag_uncertain(result)
        if estimate is None and result.covariance is not None:
            if ref.against_model:
                self.cross_check.tracked_against_model(result.covariance)
            else:
                self.cross_check.tracked_against_frame(result.covariance)
        return True

    def combine(self, estimate: FrameEstimate, result: FrameResult, state: TrackState) -> np.ndarray:
        """Combine the model view's estimate of the frame (``result``, tracked and assessed) with
        the last frame's (:class:`slam.tracking.cross_check.CrossCheck`; health figures
        ``cross_check_d2`` and ``cross_check_mm``). Where they disagree the frame is flagged and
        reports the better-supported one. Returns the frame's pose."""
        if result.covariance is None:       # (no fit of the model view's estimate: as if it failed)
            return self.keep_frame_estimate(estimate, result, state, "the model view's estimate has no fit")
        model = Estimate(relative(state.pose, result.pose), result.covariance)
        result.other_estimates += [model.relative, estimate.estimate.relative]
        check = self.cross_check.check(model, estimate.estimate)
        result.health.update(cross_check_d2=check.d2, cross_check_mm=check.distance_mm)
        result.covariance = check.covariance
        if not check.agree:
            kept = "the last frame's" if check.kept == "frame" else "the model view's"
            self.flag(result, f"the model view and the last frame disagree by {check.distance_mm:.2f} mm "
                              f"(d2 {check.d2:.0f}): {kept} estimate kept")
            if check.kept == "frame":
                result.track = estimate.track
        return state.pose @ check.relative

    def keep_frame_estimate(self, estimate: FrameEstimate, result: FrameResult, state: TrackState,
                            reason: str) -> np.ndarray:
        """Flag the frame and report the last frame's estimate alone; returns its pose."""
        self.cross_check.tracked_against_frame(estimate.estimate.covariance)
        result.track, result.covariance = estimate.track, self.cross_check.P.copy()
        self.flag(result, reason + ": the last frame's estimate kept")
        return state.pose @ estimate.estimate.relative

    def flag(self, result: FrameResult, reason: str, model_disagrees: bool = True) -> None:
        """Flag ``result``; ``model_disagrees``: against the model view (counts towards the rebuild)."""
        result.flagged, result.reason = True, reason
        self.flagged_in_row += int(model_disagrees)

    def after_flags(self, pose: np.ndarray, result: FrameResult, state: TrackState) -> None:
        """After ``REBUILD_AFTER`` frames flagged without the model view agreeing in between
        (frames tracked against the previous frame, where the unfused frames leave the model
        short of the view, do not count either way) the model around the view is taken as
        wrong: the surfels the view sees from ``pose`` are removed and the frame is fused (not
        flagged), so the model agrees with the last frames again."""
        if not result.flagged:
            if result.reference == "model":
                self.flagged_in_row = 0
            return
        if self.flagged_in_row < REBUILD_AFTER:     # (reached only on a disagreement: it rebuilds at once)
            return
        removed = self.forget_view(pose)
        log.warning("%d frames flagged in a row: the model around the view is rebuilt (%d surfels removed)",
                    self.flagged_in_row, removed)
        result.flagged = False
        result.reason += f"; the model around this view rebuilt ({removed} surfels removed)"
        self.flagged_in_row = 0
        self.rebuilds += 1
        self.cross_check.reset()

    def reset(self) -> None:
        """The pose is the map's own again (a loop closed, a frame relocalised)."""
        self.cross_check.reset()
