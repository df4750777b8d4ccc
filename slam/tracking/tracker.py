"""The tracker: a sequence's state and its decisions, one frame at a time.

``Tracker.track`` is called once per frame and reads like the algorithm: start the graph at the
first frame; relocalise after frames that could not be read; estimate it against the last frame
where the cross-check wants an independent estimate (this needs no map: it runs while the mapping
thread fuses the last frame); take the map as of the last frame; choose the reference; predict the
solver's start; register the frame; accept it (or fail it); recover it where tracking lost it;
settle its trust along the chain (confirmed by the map, tracked, unconfirmed or flagged; the map
rebuilt or re-anchored where that lasts); hand it to the mapping stage where it is trusted (or
re-anchors the map); advance; add it to the graph. What varies between runs are objects chosen once, in the
constructor:

- the reference policy (:mod:`slam.tracking.references`): previous frame, still-camera keyframes,
  or the model view;
- the acceptance policy (:mod:`slam.tracking.acceptance`): plain, or the cross-check;
- the fusion (:mod:`slam.tracking.map_fusion`): none, or into the surfel map, in the mapping
  thread (:mod:`slam.tracking.mapping_stage`);
- the graph (:mod:`slam.tracking.graph`): none, or loop closure with relocalisation;
- the recovery after a failed frame or frames that could not be read: relocalisation against the
  recent good frames (:mod:`slam.tracking.recovery`), or the graph's;
- the solver's start: identity, or the last motion continued.

:class:`KnownPoseMapper` maps at known poses instead (``analysis.poses: groundtruth``). The VO
core (``vo.StereoOdometry``) does the per-pair work; the pipeline (``slam.app.pipeline``) reads
frames, logs and writes results. Poses are those of the rectified left camera (``T_wc``, mm).
"""
from __future__ import annotations

import os

import time
from typing import Optional

import numpy as np
import torch

from slam.config import SlamConfig
from slam.tracking.acceptance import CrossCheckAcceptance, PlainAcceptance
from slam.tracking.chain_repair import ChainRepair
from slam.tracking.cross_check import CrossCheck
from slam.tracking.graph import LoopClosureGraph, NoGraph
from slam.tracking.health import HealthMonitor
from slam.tracking.model_frames import EveryFrame, ModelFrameSchedule
from slam.tracking.map_fusion import EveryPixel, LearnedWeight, NoFusion, SurfelFusion
from slam.tracking.mapping_stage import BackgroundMapping, InlineMapping
from slam.tracking.poses import relative
from slam.tracking.recovery import FrameRelocaliser
from slam.tracking.references import (DepthFilter, ModelViewReference, NoDepthFilter, PreviousFrame,
                                      StillCameraKeyframes)
from slam.tracking.state import FrameResult, TrackState
from vo.camera import StereoCamera
from vo.odometry import AheadFlow, StereoOdometry, TrackResult, View


class IdentityStart:
    """The solver starts each frame at the identity (``solver.init: identity``)."""

    def __call__(self, state: TrackState, ref=None) -> None:
        return None


class LastMotionStart:
    """The solver starts from the last tracked motion continued by one frame (from the keyframe:
    the motion since it, continued; ``ref`` None: from the last frame)."""

    def __call__(self, state: TrackState, ref=None) -> np.ndarray:
        if ref is not None and ref.keyframe is not None:
            return relative(ref.pose, state.pose) @ state.velocity
        return state.velocity


def make_fusion(config: SlamConfig, odometry: StereoOdometry, fuses: bool):
    """:class:`SurfelFusion` into a new map where the run ``fuses``, else :class:`NoFusion`."""
    if not fuses:
        return NoFusion()
    from mapping import SurfelMap

    surfel_map = SurfelMap(config.map, device=config.device)
    surfel_map.warm_up()      # compiled kernels loaded now, not in the first frame's time
    # the learned w3D weighs fusion where there is one (not with constant weights or 2D only)
    learned = odometry.networks is not None and config.weights.residuals != "2d"
    return SurfelFusion(surfel_map, odometry.K, LearnedWeight() if learned else EveryPixel())


def make_mapping(fusion):
    """The mapping stage: a map's fusion in the mapping thread, else nothing to hand over."""
    return InlineMapping(fusion) if fusion.map is None else BackgroundMapping(fusion)


class SequenceMapping:
    """What a run reports of its tracker or mapper: the map, the last pose, the graph's poses.
    Subclasses hold ``mapping`` (:mod:`slam.tracking.mapping_stage`), ``state`` and ``graph``."""

    graph = NoGraph()

    @property
    def map(self):
        """The surfel map (None when the run fuses none); its every use waits for the fusion in
        flight."""
        return self.mapping.map

    def hand_over(self, result: FrameResult) -> None:
        """Add the fusions the mapping stage finished since the last frame to ``result``'s
        timings and the mapping thread's CPU time to its ``thread_cpu``."""
        timings, cpu_ms = self.mapping.finished()
        result.timings += timings
        if cpu_ms:
            result.thread_cpu["mapping"] = result.thread_cpu.get("mapping", 0.0) + cpu_ms

    def close(self) -> FrameResult:
        """Finish the fusion in flight and stop the mapping thread; returns what it reports (the
        last fusion's time) in an otherwise empty result."""
        result = FrameResult(self.state.pose)
        self.mapping.close()
        self.hand_over(result)
        return result

    @property
    def pose(self) -> np.ndarray:
        """The last tracked frame's rectified ``T_wc`` (mm)."""
        return self.state.pose

    @property
    def loops(self):
        """The loop closure's graph and its events (None without ``graph.loop_closure``)."""
        return self.graph.loops

    @property
    def repaired_frames(self) -> int:
        """Frames of unconfirmed stretches whose poses the map corrected (:mod:`slam.tracking.chain_repair`)."""
        return len(self.repair.corrections)

    def optimised_poses(self, tracked: np.ndarray) -> Optional[np.ndarray]:
        """``(N, 4, 4)`` rectified ``T_wc`` of the ``tracked`` ones (every processed frame's, as
        tracked) after the repairs of unconfirmed stretches and the graph's optimisations (None
        where neither changed a pose)."""
        optimised = self.graph.optimised_poses(range(len(tracked)))
        if optimised is not None:
            return optimised
        return self.repair.corrected(tracked)


class Tracker(SequenceMapping):
    """One sequence's tracking.

    Args:
        config: the resolved configuration (at the frames' rate: ``slam.config.at_frame_rate``).
        camera: the rectified stereo camera.
        initial_pose: ``(4, 4)`` ``T_wc`` of the first frame's rectified left camera, mm.
    """

    def __init__(self, config: SlamConfig, camera: StereoCamera, initial_pose: np.ndarray):
        self.config = config
        self.camera = camera
        self.odometry = StereoOdometry(camera, config.vo(), device=config.device)
        self.state = TrackState(np.asarray(initial_pose, dtype=np.float64))
        frame2model = config.tracking.mode == "frame2model"
        self.mapping = make_mapping(make_fusion(config, self.odometry, frame2model or config.logging.export_map))
        self.graph = (LoopClosureGraph(config.graph, config.health.covariance_scale_model)
                      if frame2model and config.graph.loop_closure else NoGraph())
        self.recovery = self.graph if isinstance(self.graph, LoopClosureGraph) else FrameRelocaliser(
            self.odometry, config.health.covariance_scale_frame, camera.width)
        self.references = self._reference_policy(frame2model)
        self.acceptance = self._acceptance_policy(frame2model)
        self.model_frames = (ModelFrameSchedule(config.tracking.model_every, config.health.flag_mm)
                             if frame2model and config.health.cross_check > 0 and config.tracking.model_every > 1
                             else EveryFrame())
        self.start = LastMotionStart() if config.solver.init == "constant_velocity" else IdentityStart()
        self.repair = ChainRepair()

    def _reference_policy(self, frame2model: bool):
        cfg = self.config
        depth_filter = DepthFilter(cfg.depth.temporal_still_mm) if self.odometry.filters_depth() else NoDepthFilter()
        if frame2model:
            return ModelViewReference(depth_filter, self._render, self.odometry, self.recovery.active_from,
                                      cfg.tracking.refine_passes, float(os.environ.get("EXP_COVERAGE", cfg.tracking.min_model_coverage)),
                                      lambda: self.acceptance.chain_checked)
        if cfg.tracking.keyframe_gap > 1:
            return StillCameraKeyframes(depth_filter, cfg.tracking.keyframe_gap, cfg.tracking.keyframe_still_mm)
        return PreviousFrame(depth_filter)

    def _acceptance_policy(self, frame2model: bool):
        hc = self.config.health
        health = HealthMonitor(hc)
        if not (frame2model and hc.cross_check > 0):
            return PlainAcceptance(health, hc.flag_mm)
        return CrossCheckAcceptance(health, hc.flag_mm, CrossCheck(hc.cross_check, hc.flag_mm), self.odometry,
                                    hc.covariance_scale_frame, self._forget_view, self.recovery.set_aside)

    # ------------------------------------------------------------------ what the run reports
    @property
    def fallbacks(self) -> int:
        """Frame2model steps tracked against the previous frame for lack of model coverage."""
        return self.references.fallbacks

    @property
    def rebuilds(self) -> int:
        """Times the model around the view was rebuilt (the cross-check)."""
        return self.acceptance.rebuilds

    @property
    def reanchors(self) -> int:
        """Times the map re-anchored after an unconfirmed stretch (the cross-check)."""
        return self.acceptance.reanchors

    def flows_against_previous_frame(self) -> bool:
        """Whether each frame's temporal flow goes against the frame before it (frame2frame; the
        cross-check), so that it can be computed ahead (:meth:`StereoOdometry.flow_ahead`)."""
        return self.references.flows_to_previous_frame or self.acceptance.flows_to_previous_frame

    # ------------------------------------------------------------------ one frame
    def track(self, position: int, view: View, ahead: Optional[AheadFlow] = None) -> FrameResult:
        """Track the frame at ``position`` of the frames processed (0, 1, 2, ... whatever frames
        were selected: the map's time window counts them) given its ``view`` and, where the
        read-ahead thread made it, its flow ``ahead`` against the view it read before. A frame
        that cannot be tracked keeps the last good pose and reference."""
        state = self.state
        if state.last_view is None:
            return self.first_frame(position, view)
        result = FrameResult(state.pose)
        if self.recovery.relocalised_after_gap(self, position, view, result):
            return self.finish_early(position, result)
        estimate = self.acceptance.independent_estimate(view, self.start(state), ahead, result, state)
        if self.model_frames.between(position, estimate, self.acceptance):
            return self.track_between(position, estimate, result)
        self.model_frames.model_frame(position)
        self.mapping.settle()
        ref = self.references.choose(state, result)
        result.reference, result.reference_position, result.keyframe = ref.kind, ref.position, ref.keyframe
        init = self.start(state, ref)
        track = self.register(view, ref, init, ahead, result)
        if not self.acceptance.accept(track.view, ref, track, estimate, result, state):
            self.references.forget_keyframe()
            self.recovery.after_failure(self, position, view, result)
            return self.finish_early(position, result)
        pose = result.pose
        state.velocity = relative(state.pose, pose)
        if self.recovery.recovered(self, position, view, result):
            return self.finish_early(position, result)
        self.acceptance.after_flags(position, pose, result, state)
        self.repair_stretch(position, pose, result)
        if result.fuses:
            self.mapping.fuse(track.view, result.track.w3d, pose, position, self.recovery.active_from(position))
        self.advance(position, track.view, pose, result)
        self.recovery.remember(position, track.view, pose, result)
        self.graph.add(self, position, track.view, pose, result)
        self.hand_over(result)
        return result

    def track_between(self, position: int, estimate, result: FrameResult) -> FrameResult:
        """A frame between model frames: the last frame's estimate is its pose
        (:mod:`slam.tracking.model_frames`); not fused, no graph keyframe."""
        state = self.state
        track = estimate.track
        result.reference, result.reference_position = "previous_frame", state.position
        result.track, result.view = track, track.view
        self.acceptance.chain_step(position, estimate, result, state)
        pose = result.pose
        state.velocity = relative(state.pose, pose)
        self.repair_stretch(position, pose, result)
        if result.fuses and not os.environ.get("EXP_NOFUSE"):
            self.mapping.fuse(track.view, track.w3d, pose, position, self.recovery.active_from(position),
                              float(os.environ.get("EXP_BETWEEN_WEIGHT", "0.2")))
        self.advance(position, track.view, pose, result)
        self.recovery.remember(position, track.view, pose, result)
        self.hand_over(result)
        return result

    def first_frame(self, position: int, view: View) -> FrameResult:
        """The first frame: fused at the initial pose; the graph starts at it."""
        result = FrameResult(self.state.pose, reference="first")
        self.acceptance.first(result)
        self.mapping.fuse(view, None, self.state.pose, position, self.recovery.active_from(position))
        self.advance(position, view, self.state.pose, result)
        self.recovery.remember(position, view, self.state.pose, result)
        self.graph.start(self, position, view)
        self.hand_over(result)
        return result

    def register(self, view: View, ref, init: Optional[np.ndarray], ahead: Optional[AheadFlow],
                 result: FrameResult) -> TrackResult:
        """The VO core's estimate of ``view`` against ``ref`` (its depth filtered against the
        frame the reference says)."""
        track = self.odometry.track(view, ref.view, init, ref.filter_against, ahead)
        result.timings += list(track.timings_ms.items())
        result.track, result.view = track, track.view
        return track

    def finish_early(self, position: int, result: FrameResult) -> FrameResult:
        """A frame relocalised (or failed): its pose is not fused; the stretch follows it."""
        self.repair_stretch(position, result.pose, result)
        self.hand_over(result)
        return result

    def repair_stretch(self, position: int, pose: np.ndarray, result: FrameResult) -> None:
        """Follow the chain's stretch the map has not confirmed; where the map ends it, correct its
        poses (:mod:`slam.tracking.chain_repair`), in the graph's frames too."""
        for k in self.repair.follow(position, pose, result):
            self.graph.correct(k, self.repair.corrections[k])

    def advance(self, position: int, view: View, pose: np.ndarray, result: FrameResult) -> None:
        """Make a tracked frame the last good one (and, by the reference policy, the keyframe)."""
        self.references.advance(position, view, pose, result, self.state)
        self.state.pose, self.state.last_view, self.state.position = pose, view, position

    # ------------------------------------------------------------------ the map
    def _render(self, pose: np.ndarray, colour: bool, seen_from: Optional[int]):
        """The model (from frame ``seen_from`` on; None: all) rendered at ``pose``."""
        return self.map.render(self.odometry.K, torch.as_tensor(pose, dtype=torch.float32), self.camera.height,
                               self.camera.width, colour=colour, seen_from=seen_from)

    def _forget_view(self, pose: np.ndarray) -> int:
        """Remove the active surfels the view sees from ``pose`` (the cross-check's rebuild)."""
        return self.map.forget_view(self.odometry.K, torch.as_tensor(pose, dtype=torch.float32), self.camera.height,
                                    self.camera.width, seen_from=self.recovery.active_from(self.state.position))


class KnownPoseMapper(SequenceMapping):
    """``analysis.poses: groundtruth``: no tracking; each frame is fused at its known pose. The
    learned w3D is what keeps badly matched depth, moving tissue and instruments out of the map,
    so each frame is still matched to the previous one for it (no pose is solved for).

    Args: as :class:`Tracker`, and ``poses``: ``(N, 4, 4)`` the frames' rectified ``T_wc`` (mm).
    """

    fallbacks = rebuilds = reanchors = 0

    def __init__(self, config: SlamConfig, camera: StereoCamera, initial_pose: np.ndarray, poses: np.ndarray):
        self.config = config
        self.poses = poses
        self.odometry = StereoOdometry(camera, config.vo(), device=config.device)
        fusion = make_fusion(config, self.odometry, True)
        self.mapping = make_mapping(fusion)
        self.learned = isinstance(fusion.weight, LearnedWeight)
        self.state = TrackState(np.asarray(initial_pose, dtype=np.float64))
        self.repair = ChainRepair()     # (nothing to repair: the poses are known)

    def flows_against_previous_frame(self) -> bool:
        """Whether the frames are matched to the previous one (for the learned w3D)."""
        return self.learned

    def track(self, position: int, view: View, ahead: Optional[AheadFlow] = None) -> FrameResult:
        """Fuse ``view`` at its known pose."""
        pose = self.poses[position]
        result = FrameResult(pose, reference="groundtruth", trust="known")
        w3d = None
        last = self.state.last_view
        if last is not None and self.learned:
            t0 = time.perf_counter()
            corr = self.odometry.correspondences(view, last, round_trip=False, ahead=ahead)
            t1 = time.perf_counter()
            problem = self.odometry.residual_problem(view, last, corr)
            _, w3d = self.odometry.weight_maps(view, last, corr, problem)
            result.timings += [("flow", (t1 - t0) * 1000.0), ("weights", (time.perf_counter() - t1) * 1000.0)]
        self.mapping.fuse(view, w3d, pose, position, None)
        self.state.pose, self.state.last_view, self.state.position = pose, view, position
        self.hand_over(result)
        return result
