"""The pose graph beside the tracker, chosen once per run: :class:`NoGraph`, or
:class:`LoopClosureGraph` (frame2model with ``graph.loop_closure``): ElasticFusion's active and
inactive model, graph keyframes, loops closed against the inactive model (or, where the drift took
the view off it, against the pose an ORB match to an old keyframe gives), and relocalisation after
a failed frame or frames that could not be read (:class:`slam.tracking.loop_closure.LoopClosure`,
:class:`slam.tracking.place_recognition.PlaceRecognition`).

The graph works on the tracker it belongs to (``tracker``: its state, map, odometry and
acceptance policy): an accepted loop moves the surfels and the tracker's pose, a relocalised
frame becomes the tracker's last frame.
"""
from __future__ import annotations

import logging
import time
from typing import Optional

import numpy as np
import torch

from slam.tracking.loop_closure import LOOP_MIN_COVERAGE, LoopClosure
from slam.tracking.place_recognition import PlaceRecognition
from slam.tracking.references import model_coverage
from slam.tracking.state import FrameResult
from vo.geometric_check import point_to_plane_check
from vo.odometry import TrackResult, View

log = logging.getLogger("slam")

# frames that could not be read, after which a frame is relocalised before it is tracked (the
# camera may have moved further than the flow bridges: 20 mm over 40 frames of a synthetic loop
# left frame2model 11 mm off; 8 mm over 16 frames it bridged)
RELOCALISE_AFTER_MISSED = 5


class NoGraph:
    """No pose graph: the poses are those tracked."""

    loops = None

    def start(self, tracker, position: int, view: View) -> None:
        """(Nothing to start.)"""

    def active_from(self, position: int) -> None:
        return None

    def add(self, tracker, position: int, view: View, pose: np.ndarray, result: FrameResult) -> None:
        """(No graph to add to.)"""

    def optimised_poses(self, positions: range) -> None:
        return None

    def correct(self, position: int, pose: np.ndarray) -> None:
        """(No graph to hold the corrected pose.)"""


class LoopClosureGraph(NoGraph):
    """Loop closure and relocalisation on a pose graph of keyframes (see the module docstring).

    Args:
        config: ``graph`` (``slam.config.GraphConfig``).
        covariance_scale_model: ``health.covariance_scale_model`` (a registration's covariance).
    """

    def __init__(self, config, covariance_scale_model: float):
        self.config = config
        self.covariance_scale_model = covariance_scale_model
        self.loops: Optional[LoopClosure] = None       # made at the first frame
        self.places: Optional[PlaceRecognition] = None
        self.model_from: Optional[int] = None          # the map re-anchored here: nothing before it is active

    def start(self, tracker, position: int, view: View) -> None:
        self.loops = LoopClosure(self.config, tracker.state.pose, position)
        self.places = PlaceRecognition(tracker.odometry.K.cpu().numpy(), tracker.camera.width)
        self.remember_place(position, view)

    def active_from(self, position: int) -> Optional[int]:
        """The first frame whose surfels are in the active model at ``position`` (None: all): the
        time window's, or the frame where the map last re-anchored, whichever is later."""
        window = self.loops.active_from(position) if self.loops is not None else None
        starts = [p for p in (window, self.model_from) if p is not None]
        return max(starts) if starts else None

    def set_aside(self, position: int) -> None:
        """The active map before ``position`` set aside (the map re-anchors there); the inactive
        model keeps it for loops."""
        self.model_from = position

    def relocalised_after_gap(self, tracker, position: int, view: View, result: FrameResult) -> bool:
        """After ``RELOCALISE_AFTER_MISSED`` frames that could not be read, relocalise the frame
        before tracking it; True where it was."""
        missed = position - tracker.state.position - 1
        if missed < RELOCALISE_AFTER_MISSED or not self.relocalise(tracker, position, view, result):
            return False
        result.reference = "relocalised"
        result.reason = f"relocalised after {missed} frames that could not be read; " + result.reason
        self.loops.add_frame(position, result.pose, None, may_be_keyframe=False)
        return True

    def after_failure(self, tracker, position: int, view: View, result: FrameResult) -> None:
        """A frame that could not be tracked: relocalised where it can be; its motion enters the
        graph as unknown."""
        reason = result.reason
        if self.relocalise(tracker, position, view, result):
            result.reason = f"{reason}; " + result.reason
        self.loops.add_frame(position, tracker.state.pose, None, may_be_keyframe=False)

    def recovered(self, tracker, position: int, view: View, result: FrameResult) -> bool:
        """(A frame keeps its estimate: the graph relocalises failed frames only.)"""
        return False

    def remember(self, position: int, view: View, pose: np.ndarray, result: FrameResult) -> None:
        """(Its relocalisation's candidates are the graph's keyframes, :meth:`add`.)"""

    def add(self, tracker, position: int, view: View, pose: np.ndarray, result: FrameResult) -> None:
        """A tracked frame: a new graph keyframe (only a trusted frame becomes one) closes loops and
        is remembered by its looks."""
        if self.loops.add_frame(position, pose, result.covariance, may_be_keyframe=result.trusted):
            self.close_loop(tracker, position, view, result)
            if not self.loops.cull(position):
                self.remember_place(position, view)

    def correct(self, position: int, pose: np.ndarray) -> None:
        """The corrected pose of a frame of a repaired stretch, before the graph's corrections
        (:meth:`slam.tracking.loop_closure.LoopClosure.correct`)."""
        self.loops.correct(position, pose)

    def optimised_poses(self, positions: range) -> Optional[np.ndarray]:
        """``(N, 4, 4)`` rectified ``T_wc`` of ``positions`` after the graph's optimisations."""
        return self.loops.optimised_poses(positions) if self.loops is not None else None

    # ------------------------------------------------------------------ loops
    def close_loop(self, tracker, position: int, view: View, result: FrameResult) -> None:
        """At a new graph keyframe: render the inactive model at the frame's pose and, where it
        covers enough of the frame, register the frame against it, verify and propose the loop
        (:class:`slam.tracking.loop_closure.LoopClosure`). An accepted loop moves the surfels with their
        frames, corrects the tracker's pose and revives the inactive surfels in view. Timed as
        ``loop``."""
        t0 = time.perf_counter()
        active_from = self.loops.active_from(position)
        if active_from is None:
            return
        smap = tracker.map
        K, H, W = tracker.odometry.K, tracker.camera.height, tracker.camera.width
        rendered_at = None      # the tracked pose; else the pose an appearance match gives
        T = torch.as_tensor(tracker.state.pose, dtype=torch.float32)
        mv = smap.render(K, T, H, W, colour=False, seen_before=active_from)
        coverage = model_coverage(mv.valid, view.valid[0, 0])
        if coverage < LOOP_MIN_COVERAGE:
            match = self.look_up_place(view, [p for p in self.loops.keyframe_positions if p < active_from])
            if match is not None:
                rendered_at = self.loops.pose(match.position) @ match.relative
                T = torch.as_tensor(rendered_at, dtype=torch.float32)
                mv = smap.render(K, T, H, W, colour=False, seen_before=active_from)
                coverage = model_coverage(mv.valid, view.valid[0, 0])
        if coverage < LOOP_MIN_COVERAGE:
            result.time("loop", t0)
            return
        anchor = int(smap.last_seen_in_view(K, T, H, W, active_from).median())
        mv.with_colour()
        reg, covariance, reason = self.register_to_model(tracker, view, mv)
        old = list(self.loops.graph.poses)
        result.loop = self.loops.propose(position, anchor, reg.relative, covariance, reason, coverage, rendered_at)
        if result.loop.accepted:
            smap.move_surfels(torch.as_tensor(self.loops.corrections(old), dtype=torch.float32))
            tracker.state.pose = self.loops.adopt_optimised(position)
            revived, merged = smap.reactivate_view(K, torch.as_tensor(tracker.state.pose, dtype=torch.float32), H, W,
                                                   position, active_from)
            log.info("loop closed at frame %d: the pose moved %.2f mm; %d surfels revived, %d merged",
                     position, result.loop.moved_mm, revived, merged)
            tracker.acceptance.reset()
        result.time("loop", t0)

    def relocalise(self, tracker, position: int, view: View, result: FrameResult) -> bool:
        """Relocalise the frame at ``position`` (after a frame that could not be tracked, or
        frames that could not be read): find the graph keyframe it looks like (ORB,
        :class:`slam.tracking.place_recognition.PlaceRecognition`), render the whole model at the pose
        that gives and register the frame against it. Where the registration passes the loop's
        verification the frame takes that pose (``result.pose``, its ``reason`` says so) and
        becomes the last frame, the one the next is tracked from; it is not fused, and its
        motion enters the pose graph as unknown. Returns whether it was relocalised. Timed as
        ``relocalise``."""
        t0 = time.perf_counter()
        match = self.look_up_place(view, self.loops.keyframe_positions)
        if match is None:
            result.time("relocalise", t0)
            return False
        K, H, W = tracker.odometry.K, tracker.camera.height, tracker.camera.width
        guess = self.loops.pose(match.position) @ match.relative
        mv = tracker.map.render(K, torch.as_tensor(guess, dtype=torch.float32), H, W, colour=True)
        if model_coverage(mv.valid, view.valid[0, 0]) < LOOP_MIN_COVERAGE:
            result.time("relocalise", t0)
            return False
        reg, covariance, reason = self.register_to_model(tracker, view, mv)
        if reason:
            result.time("relocalise", t0)
            return False
        moved = float(np.linalg.norm((guess @ reg.relative)[:3, 3] - tracker.state.pose[:3, 3]))
        result.pose = guess @ reg.relative
        result.reason = f"relocalised against the keyframe at frame {match.position} ({moved:.1f} mm from the last pose)"
        tracker.state.velocity = np.eye(4)
        result.reference, result.covariance, result.flagged = "relocalised", covariance, True
        tracker.advance(position, view, result.pose, result)
        tracker.acceptance.relocalised(position, result)
        log.info("frame %d relocalised against the keyframe at frame %d: %.2f mm from the last pose",
                 position, match.position, moved)
        result.time("relocalise", t0)
        return True

    def register_to_model(self, tracker, view: View, mv) -> tuple[TrackResult, Optional[np.ndarray], str]:
        """Register ``view`` against the model view ``mv`` (rendered with colour) by the dense
        tracker and verify it as a loop: the registration, its calibrated covariance (None where
        it failed) and why it is not a loop ('' where it is one, :meth:`LoopClosure.verify`)."""
        odometry = tracker.odometry
        ref = odometry.view_from_render(mv.color, mv.depth, mv.valid, background=view, background_matchable=False)
        reg = odometry.track(view, ref)
        covariance = None
        if not reg.failed and reg.fit is not None:
            covariance = reg.fit.covariance(self.covariance_scale_model)
        plane = point_to_plane_check(view.depth, view.valid, ref.depth, ref.valid, odometry.K, reg.relative)
        reason = LoopClosure.verify(reg.failed, reg.support, covariance,
                                    plane.residual_mm if plane is not None else float("nan"))
        return reg, covariance, reason

    def look_up_place(self, view: View, candidates: list[int]):
        """The keyframe among ``candidates`` that ``view`` looks like, by ORB (an
        :class:`slam.tracking.place_recognition.AppearanceMatch`, None where none is)."""
        return self.places.query(view.gray, None if view.masked is None else ~view.masked, candidates)

    def remember_place(self, position: int, view: View) -> None:
        """Keep the ORB features of the new graph keyframe at ``position`` (appearance candidates)."""
        valid = view.valid[0, 0].cpu().numpy()
        self.places.add(position, view.gray, view.depth[0, 0].cpu().numpy(), valid)
