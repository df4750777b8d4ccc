"""What each frame is tracked against: the reference policy, chosen once per run.

- :class:`PreviousFrame`: every frame against the one before it (the paper; ``keyframe_gap: 1``).
- :class:`StillCameraKeyframes`: frame2frame's default: while the camera is still, a keyframe
  stays the reference for ``tracking.keyframe_gap`` frames; a moving camera's frames go against
  the previous one.
- :class:`ModelViewReference`: frame2model: the map rendered at the last pose, its colour relit to
  the last frame's shading; the previous frame where the map covers too little of the view.

A policy's :meth:`choose` gives a :class:`FrameReference` or a :class:`ModelReference`, which
carry what differs between the two: the frame whose depth a still camera's depth is filtered
against, the refinement against the model re-rendered at the estimate, and the geometric check
of the estimate against the model's surface.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from slam.tracking.poses import moved_less_than, relative
from slam.tracking.state import FrameResult, TrackState
from vo.geometric_check import point_to_plane_check
from vo.odometry import StereoOdometry, TrackResult, View

log = logging.getLogger("slam")


def model_coverage(model_valid: torch.Tensor, frame_valid: torch.Tensor) -> float:
    """The fraction of a frame's valid pixels ``(H, W)`` bool that the model view ``(H, W)`` bool
    rendered at its pose covers (the whole image's fraction when the frame has none).

    Measured on what the camera saw, not on the whole image: pixels without stereo depth (the
    border the right view does not see) or masked out (instruments, highlights) are left out.
    """
    n = int(frame_valid.sum())
    if n == 0:
        return float(model_valid.float().mean())
    return int((model_valid & frame_valid).sum()) / n


class DepthFilter:
    """A still camera's depth is filtered along the flow against the previous frame's
    (``depth.temporal_gain`` < 1): while the last motion moved it less than ``still_mm``."""

    def __init__(self, still_mm: float):
        self.still_mm = still_mm

    def against(self, state: TrackState) -> Optional[View]:
        return state.last_view if moved_less_than(state.velocity, self.still_mm) else None


class NoDepthFilter:
    """Each frame keeps its own stereo depth (the paper; ``depth.temporal_gain: 1``)."""

    def against(self, state: TrackState) -> None:
        return None


@dataclass
class FrameReference:
    """A camera frame as the reference.

    Attributes:
        view, pose: the frame's view and rectified ``T_wc`` (mm).
        kind: ``previous_frame`` or ``keyframe``.
        position: the sequence position of the frame at whose pose the reference sits.
        keyframe: that position for a keyframe, else None.
        filter_against: the real frame the current frame's depth is filtered against, or None.
    """

    view: View
    pose: np.ndarray
    kind: str
    position: int
    keyframe: Optional[int] = None
    filter_against: Optional[View] = None

    against_model = False

    def refine(self, view: View, pose: np.ndarray, track: TrackResult, result: FrameResult
               ) -> tuple[np.ndarray, TrackResult]:
        return pose, track

    def verify(self, view: View, pose: np.ndarray, result: FrameResult) -> None:
        """(Nothing to check against besides the frame itself.)"""


@dataclass
class ModelReference:
    """The map's view rendered at the last pose as the reference (see :class:`ModelViewReference`)."""

    view: View
    pose: np.ndarray
    position: int
    policy: "ModelViewReference"
    seen_from: Optional[int]

    kind = "model"
    keyframe = None
    filter_against = None
    against_model = True

    def refine(self, view: View, pose: np.ndarray, track: TrackResult, result: FrameResult
               ) -> tuple[np.ndarray, TrackResult]:
        """``tracking.refine_passes`` x: track ``view`` against the model rendered at its
        estimated ``pose`` and compose the correction. Returns the pose and the last
        successful tracking result (its weight maps weigh the fusion)."""
        policy = self.policy
        for _ in range(policy.refine_passes):
            t0 = time.perf_counter()
            # depth first, as in choose: the colour's blending pass only for a view that is used
            mv = policy.render(pose, False, self.seen_from)
            if model_coverage(mv.valid, view.valid[0, 0]) < policy.min_coverage:
                result.time("render", t0)
                break
            mv.with_colour()
            result.time("render", t0)
            # the current frame fills the few uncovered pixels (no residual there: it sits at the
            # true pose, the render at the estimate) and gives the render its shading
            ref = policy.odometry.view_from_render(mv.color, mv.depth, mv.valid, background=view,
                                                   background_matchable=False)
            refined = policy.odometry.track(view, ref)
            result.timings += list(refined.timings_ms.items())
            if refined.failed:
                break
            pose, track = pose @ refined.relative, refined
        return pose, track

    def verify(self, view: View, pose: np.ndarray, result: FrameResult) -> None:
        """How well the frame's depth at ``pose`` lies on the model view's surface
        (:func:`vo.geometric_check.point_to_plane_check`): health figures
        ``plane_residual_mm`` and ``plane_cost_share``."""
        t0 = time.perf_counter()
        check = point_to_plane_check(view.depth, view.valid, self.view.depth, self.view.valid, self.policy.odometry.K,
                                     relative(self.pose, pose))
        result.time("verify", t0)
        if check is not None:
            result.health.update(plane_residual_mm=check.residual_mm, plane_cost_share=check.cost_share)


class PreviousFrame:
    """Every frame against the frame before it."""

    fallbacks = 0
    flows_to_previous_frame = True      # (its flow can be computed ahead)

    def __init__(self, depth_filter):
        self.depth_filter = depth_filter

    def choose(self, state: TrackState, result: FrameResult) -> FrameReference:
        return FrameReference(state.last_view, state.pose, "previous_frame", state.position,
                              filter_against=self.depth_filter.against(state))

    def advance(self, position: int, view: View, pose: np.ndarray, result: FrameResult, state: TrackState) -> None:
        """(No keyframe to keep.)"""

    def forget_keyframe(self) -> None:
        """(No keyframe to forget.)"""


@dataclass
class Keyframe:
    """Frame2frame's reference while the camera is still: its sequence position, view and pose."""

    position: int
    view: View
    pose: np.ndarray


class StillCameraKeyframes(PreviousFrame):
    """While the camera is still, a keyframe is the reference of the ``gap`` frames after it; a
    frame becomes the keyframe when the keyframe is ``gap`` frames old, the camera moves
    (``still_mm`` per frame), or tracking failed before it (``tracking.keyframe_gap``)."""

    def __init__(self, depth_filter, gap: int, still_mm: float):
        super().__init__(depth_filter)
        self.gap = gap
        self.still_mm = still_mm
        self.keyframe: Optional[Keyframe] = None

    def choose(self, state: TrackState, result: FrameResult) -> FrameReference:
        kf = self.keyframe
        if kf is None or kf.view is state.last_view:
            return super().choose(state, result)
        return FrameReference(kf.view, kf.pose, "keyframe", kf.position, keyframe=kf.position,
                              filter_against=self.depth_filter.against(state))

    def advance(self, position: int, view: View, pose: np.ndarray, result: FrameResult, state: TrackState) -> None:
        """Make the tracked frame the keyframe when the keyframe is ``gap`` frames old or the
        camera moves (``state.velocity``: its motion into this frame)."""
        if (self.keyframe is None or position - self.keyframe.position >= self.gap or result.reference == "first"
                or not moved_less_than(state.velocity, self.still_mm)):
            self.keyframe = Keyframe(position, view, pose)   # (a moving camera: the next frame goes against this one)

    def forget_keyframe(self) -> None:
        """After a failed frame: the next goes against the last tracked frame and becomes the keyframe."""
        self.keyframe = None


# the model view's coverage of what the last frame saw from which it is the reference of a frame
# whose chain holds a relocalisation the map has not confirmed: only the map can confirm or
# correct such a pose, and a pose a few mm off sees the map shifted out of part of the view
UNCONFIRMED_MIN_COVERAGE = 0.5


class ModelViewReference(PreviousFrame):
    """The model view rendered at the last pose (frame2model), where it covers at least
    ``min_coverage`` of what the last frame saw (``UNCONFIRMED_MIN_COVERAGE`` where the chain holds a
    relocalisation the map never checked: it needs the map's word); else the previous frame for that
    step.

    Args:
        depth_filter: for the steps against the previous frame.
        render: ``render(pose, colour, seen_from)`` of the map (``mapping.SurfelMap.render`` at
            the camera's intrinsics and size).
        odometry: the VO core (views from renders, the refinement's tracking).
        active_from: the graph's ``active_from(position)``: the first frame whose surfels the
            model at a position holds (None: all).
        refine_passes: ``tracking.refine_passes``.
        min_coverage: ``slam.config.MIN_MODEL_COVERAGE``.
        chain_checked: ``chain_checked()``: whether the chain since the last pose the map confirmed
            holds no relocalisation (the acceptance policy's).

    Attributes:
        fallbacks: steps tracked against the previous frame for lack of coverage.
    """

    flows_to_previous_frame = False      # (against the model's colour)

    def __init__(self, depth_filter, render: Callable, odometry: StereoOdometry, active_from: Callable,
                 refine_passes: int, min_coverage: float, chain_checked: Callable[[], bool] = lambda: True):
        super().__init__(depth_filter)
        self.chain_checked = chain_checked
        self.render = render
        self.odometry = odometry
        self.active_from = active_from
        self.refine_passes = refine_passes
        self.min_coverage = min_coverage
        self.fallbacks = 0

    def choose(self, state: TrackState, result: FrameResult):
        t0 = time.perf_counter()
        seen_from = self.active_from(state.position + 1)
        mv = self.render(state.pose, False, seen_from)    # depth first: the colour's pass only for a view used
        coverage = model_coverage(mv.valid, state.last_view.valid[0, 0])
        result.health["model_coverage"] = coverage
        if coverage < (self.min_coverage if self.chain_checked() else UNCONFIRMED_MIN_COVERAGE):
            result.time("render", t0)
            self.fallbacks += 1
            log.info("the model view covers %.0f%% of what the last frame saw: tracking against the previous frame",
                     100 * coverage)
            return super().choose(state, result)
        mv.with_colour()
        result.time("render", t0)
        ref = self.odometry.view_from_render(mv.color, mv.depth, mv.valid, background=state.last_view)
        return ModelReference(ref, state.pose, state.position, self, seen_from)
