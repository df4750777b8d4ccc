"""The tracker: a sequence's state and its decisions, one frame at a time.

``Tracker.track`` is called once per frame. It owns what lives across frames: the pose, the last
good view, the keyframe of frame2frame, the last motion (the still-camera rule and the solver's
start), the surfel map and what gets fused into it. It decides each frame's reference (the
previous frame, a keyframe, or the model view rendered from the map), whether the frame's depth
is filtered, and whether the model view's estimate is refined. The VO core (``vo.StereoOdometry``)
does the per-pair work; the pipeline (``slam.app.pipeline``) reads frames, logs and writes results.

Poses here are those of the rectified left camera (``T_wc``, mm).
"""
from __future__ import annotations

import logging
import time
import weakref
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from slam.config import SlamConfig
from vo.geometric_check import point_to_plane_check
from slam.tracking.cross_check import CrossCheck, Estimate
from slam.tracking.health import HealthMonitor
from slam.tracking.loop_closure import LOOP_MIN_COVERAGE, LoopClosure, LoopEvent
from slam.tracking.place_recognition import PlaceRecognition
from vo.camera import StereoCamera
from vo.odometry import StereoOdometry, TrackResult, View, moved_less_than

log = logging.getLogger("slam")

# frames that could not be read, after which a frame is relocalised before it is tracked (the
# camera may have moved further than the flow bridges: 20 mm over 40 frames of a synthetic loop
# left frame2model 11 mm off; 8 mm over 16 frames it bridged)
RELOCALISE_AFTER_MISSED = 5

# frame2model: frames flagged in a row after which the model around the view is rebuilt (at 25 fps
# 0.4 s: a short disagreement is a frame's flow, a lasting one the model's own error)
REBUILD_AFTER = 10


@dataclass
class FrameResult:
    """What the tracker made of one frame.

    Attributes:
        pose: ``(4, 4)`` ``T_wc`` of the rectified left camera, mm (a failed frame keeps the
            last good pose).
        failed: the frame's pose could not be trusted (``reason`` says why).
        flagged: frame2model's cross-check (``health.cross_check``) found the model view's and
            the last frame's estimates in disagreement, or the model view's estimate failed (the
            frame reports the better-supported estimate), or the reported pose is uncertain
            (``health.flag_mm``); a flagged frame is not fused (``reason`` says why).
        reason: '' for a good frame.
        reference: what the frame was tracked against: ``first`` (the first frame),
            ``previous_frame``, ``keyframe`` (an earlier frame, ``tracking.keyframe_gap``),
            ``model`` (the map's view) or ``groundtruth`` (``tracking.poses: groundtruth``).
        track: the VO core's result (flow, weight maps, solver figures), None without a solve.
        keyframe: the sequence position of the keyframe the frame was tracked against, else None.
        reference_position: the sequence position of the frame at whose pose the reference sits
            (the keyframe, or the last tracked frame for the previous frame and the model view).
        health: per-frame figures of how well the frame was tracked (``slam.tracking.health.FIGURES``:
            supported pixels, residuals against their running medians, the covariance's
            spread; ``model_coverage`` against the map).
        covariance: ``(6, 6)`` covariance of the relative pose to the reference (mm and rad,
            translation first, left perturbation), where one is estimated; None otherwise.
        timings: ``(stage, ms)`` of the work done for the frame, in order (a stage may repeat).
        loop: the loop candidate found at the frame (``graph.loop_closure``), else None.
    """

    pose: np.ndarray
    failed: bool = False
    flagged: bool = False
    reason: str = ""
    reference: str = ""
    track: Optional[TrackResult] = None
    keyframe: Optional[int] = None
    reference_position: Optional[int] = None
    health: dict = field(default_factory=dict)
    covariance: Optional[np.ndarray] = None
    timings: list = field(default_factory=list)
    loop: Optional[LoopEvent] = None

    def time(self, stage: str, since: float) -> None:
        """Record ``stage`` as the time elapsed since ``since`` (``time.perf_counter()``)."""
        self.timings.append((stage, (time.perf_counter() - since) * 1000.0))


@dataclass
class FrameEstimate:
    """Frame2model's independent estimate of a frame: its tracking against the last frame and
    the relative pose with its covariance (:class:`slam.tracking.cross_check.Estimate`)."""

    track: TrackResult
    estimate: Estimate


@dataclass
class Keyframe:
    """Frame2frame's reference while the camera is still: its sequence position, view and pose."""

    position: int
    view: View
    pose: np.ndarray


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


def normalised_fusion_weight(w3d: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The per-pixel fusion weight of a frame from its learned 3D weight.

    Where the tracker weighed the pixel (``w3d > 0``): ``w3d`` divided by its median over those
    pixels, clamped to [0, 1]. The optimum does not fix the weights' scale, so a typical pixel
    counts as one observation (the map's confidence keeps ElasticFusion's meaning and a surface
    becomes stable after a few frames) and a pixel the network trusts k times less than typical
    counts 1/k. Valid pixels the tracker could not weigh (no reference depth there: tissue coming
    into view, outside the model view) count fully: leaving them out would keep new tissue out of
    the map until the tracker next falls back to the previous frame.
    Invalid pixels (no stereo depth, instruments, highlights) are 0.

    Args:
        w3d: ``(H, W)`` learned 3D weight, 0 where the tracker did not weigh the pixel;
        valid: ``(H, W)`` bool valid pixels of the frame.
    """
    weighed = valid & (w3d > 0)
    vals = w3d[weighed]
    if vals.numel() == 0:
        return valid.to(w3d.dtype)
    ref = vals.float()[:: max(1, vals.numel() // 20000)].median().clamp(min=1e-12)   # (quantile: 8x slower)
    return torch.where(weighed, (w3d / ref).clamp(0, 1), valid.to(w3d.dtype))


def mean_brightness(view: View) -> float:
    """Mean grey level (0-255) of ``view``'s valid pixels (of all pixels when under 1 % are valid:
    a dark frame may have no stereo depth at all)."""
    gray = torch.from_numpy(view.gray)
    valid = view.valid[0, 0].cpu()
    if valid.shape == gray.shape and int(valid.sum()) >= 0.01 * valid.numel():
        gray = gray[valid]
    return float(gray.float().mean()) if gray.numel() else 0.0


def exposure_gain(brightness: float, level: float, lo: float = 0.25, hi: float = 8.0) -> float:
    """The gain that brings a frame of mean ``brightness`` to the map's exposure ``level`` (both
    0-255 grey), clamped to ``[lo, hi]``: exposure is a global factor on the image (the light's
    intensity, the exposure time), so the fused colour is ``image x gain``."""
    return float(min(max(level / max(brightness, 0.5), lo), hi))


class FusionExposure:
    """The colour each view is fused with: brought to the map's exposure, the mean brightness of
    the first fused frame that is not black (:func:`exposure_gain`). The map's colour then stays
    one exposure through exposure jumps (fused as captured, a few frames at a quarter of the
    brightness left dark patches the flow against the render could not match: twice the ATE on
    the synthetic scanning sequence of ``tests/test_exposure.py``), and the render is relit to the
    current frame's shading anyway."""

    def __init__(self):
        self.level: Optional[float] = None

    def colour(self, view: View) -> torch.Tensor:
        """``view``'s ``(3, H, W)`` colour to fuse."""
        colour = view.image[0]
        brightness = mean_brightness(view)
        if self.level is None and brightness >= 8.0:     # (not a black frame)
            self.level = brightness
        gain = exposure_gain(brightness, self.level) if self.level else 1.0
        return (colour * gain).clamp_(0.0, 1.0) if gain != 1.0 else colour


class Tracker:
    """One sequence's tracking.

    Args:
        config: the resolved configuration.
        camera: the rectified stereo camera.
        initial_pose: ``(4, 4)`` ``T_wc`` of the first frame's rectified left camera, mm.
    """

    def __init__(self, config: SlamConfig, camera: StereoCamera, initial_pose: np.ndarray):
        self.config = config
        self.camera = camera
        self.odometry = StereoOdometry(camera, config.vo(), device=config.device)
        tc = config.tracking
        self.frame2model = tc.mode == "frame2model"
        self.known_poses = tc.poses == "groundtruth"
        self.map = None
        if self.frame2model or tc.export_map or self.known_poses:
            from mapping import SurfelMap

            self.map = SurfelMap(config.map, device=config.device)
            self.map.warm_up()      # compiled kernels loaded now, not in the first frame's time
        # the learned w3D weighs fusion where there is one (not with constant weights or 2D only)
        self.learned_fusion_weight = (tc.fuse_weight == "w3d" and self.odometry.networks is not None
                                      and config.weights.residuals != "2d")
        self.keyframe_gap = tc.keyframe_gap if not self.frame2model else 1
        self.exposure = FusionExposure()
        self.pose = np.asarray(initial_pose, dtype=np.float64)
        self.last_view: Optional[View] = None
        self.keyframe: Optional[Keyframe] = None
        self.position = -1          # the last tracked frame's sequence position
        self.health = HealthMonitor(config.health)
        self.velocity = np.eye(4)   # the last tracked relative motion: solver.init=constant_velocity's start
        self.fallbacks = 0          # frame2model frames tracked against the previous frame
        self.flagged_in_row = 0     # frames flagged since the model view last agreed (REBUILD_AFTER)
        self.rebuilds = 0           # times the model around the view was rebuilt (REBUILD_AFTER)
        hc = config.health
        self.cross_check = CrossCheck(hc.cross_check, hc.flag_mm) if self.frame2model and hc.cross_check > 0 else None
        self.closes_loops = self.frame2model and config.graph.loop_closure
        self.loops: Optional[LoopClosure] = None    # made at the first frame (graph.loop_closure)
        self.places: Optional[PlaceRecognition] = None   # the graph keyframes' ORB features (graph.loop_closure)

    # ------------------------------------------------------------------ what may run ahead
    def flows_against_previous_frame(self) -> bool:
        """Whether each frame's temporal flow goes against the frame before it (frame2frame;
        frame2model with ``flow_reference: last_frame`` or the cross-check; known poses with a
        learned w3D), so that
        it can be computed ahead (:meth:`vo.odometry.StereoOdometry.flow_ahead`)."""
        if self.known_poses:
            return self.learned_fusion_weight
        return (not self.frame2model or self.config.tracking.flow_reference == "last_frame"
                or self.cross_check is not None)

    # ------------------------------------------------------------------ one frame
    def track(self, position: int, view: View, gt_pose: Optional[np.ndarray] = None) -> FrameResult:
        """Track the frame at ``position`` of the frames processed (0, 1, 2, ... whatever frames
        were selected: the map's time window counts them) given its ``view``;
        with ``tracking.poses: groundtruth``, ``gt_pose`` (rectified ``T_wc``, mm) is its pose.

        A frame that cannot be tracked keeps the last good pose and reference."""
        if self.known_poses:
            return self._map_at_known_pose(position, view, gt_pose)
        if self.last_view is None:
            result = FrameResult(self.pose, reference="first")
            self._fuse(view, None, self.pose, position, result)
            self._advance(position, view, self.pose, result)
            if self.closes_loops:
                self.loops = LoopClosure(self.config.graph, self.pose, position)
                self.places = PlaceRecognition(self.odometry.K.cpu().numpy(), self.camera.width)
                self._remember_place(position, view)
            return result
        result = FrameResult(self.pose)
        missed = position - self.position - 1
        if self.places is not None and missed >= RELOCALISE_AFTER_MISSED and self._relocalise(position, view, result):
            result.reference = "relocalised"
            result.reason = f"relocalised after {missed} frames that could not be read; " + result.reason
            self.loops.add_frame(position, result.pose, None)
            return result
        # the reference: the keyframe, the model view, or the previous frame
        ref, ref_pose, result.reference = self._reference(result)
        result.reference_position = self.position
        init = self.velocity if self.config.solver.init == "constant_velocity" else None
        if result.reference == "keyframe":
            result.keyframe = result.reference_position = self.keyframe.position
            if init is not None:        # the motion since the keyframe, continued by one frame's
                init = np.linalg.inv(ref_pose) @ self.pose @ self.velocity
        # the depth is filtered between real frames while the camera is still
        filter_against = None
        if (result.reference != "model" and self.odometry.filters_depth()
                and moved_less_than(self.velocity, self.config.depth.temporal_still_mm)):
            filter_against = self.last_view
        estimate = None
        if result.reference == "model" and self.cross_check is not None:
            estimate = self._estimate_against_last_frame(view, init, result)   # (first: it takes the flow ahead)
        track = self.odometry.track(view, ref, init, filter_against)
        result.timings += list(track.timings_ms.items())
        result.track = track
        if track.failed and estimate is None:
            result.failed, result.reason = True, track.reason
            self._assess(result, track)
            self.keyframe = None    # the next frame goes against the last tracked one, and becomes the keyframe
            if self.places is not None and self._relocalise(position, view, result):
                result.reason = f"{track.reason}; " + result.reason
            if self.loops is not None:
                self.loops.add_frame(position, self.pose, None)
            return result
        if track.failed:            # the model view's estimate failed, the last frame's did not
            self._assess(result, estimate.track)
            pose = result.pose = self._keep_frame_estimate(estimate, result,
                                                           f"the model view's estimate failed ({track.reason})")
        else:
            pose = ref_pose @ track.relative
            if result.reference == "model":
                pose, track = self._refine(view, pose, track, result)
                result.track = track
            result.pose = pose
            self._assess(result, track)
            if result.reference == "model":
                self._verify_geometry(view, ref, np.linalg.inv(ref_pose) @ pose, result)
            if estimate is not None:
                pose = result.pose = self._cross_check(estimate, result)
        self._flag_uncertain(result)
        if estimate is None and result.covariance is not None and self.cross_check is not None:
            if result.reference == "model":
                self.cross_check.tracked_against_model(result.covariance)
            else:
                self.cross_check.tracked_against_frame(result.covariance)
        self.velocity = np.linalg.inv(self.pose) @ pose
        self._after_flags(view, pose, result)
        if not result.flagged:
            self._fuse(view, result.track.w3d, pose, position, result)
        self._advance(position, view, pose, result)
        if self.loops is not None and self.loops.add_frame(position, pose, result.covariance):
            self._close_loop(position, view, result)
            if not self.loops.cull(position):
                self._remember_place(position, view)
        return result

    # ------------------------------------------------------------------ loop closure (graph.loop_closure)
    def _active_from(self, position: int) -> Optional[int]:
        """The first frame whose surfels are in the active model at ``position`` (None: all)."""
        return self.loops.active_from(position) if self.loops is not None else None

    def _close_loop(self, position: int, view: View, result: FrameResult) -> None:
        """At a new graph keyframe: render the inactive model at the frame's pose and, where it
        covers enough of the frame, register the frame against it, verify and propose the loop
        (:class:`slam.tracking.loop_closure.LoopClosure`). An accepted loop moves the surfels with their
        frames, corrects the tracker's pose and revives the inactive surfels in view. Timed as
        ``loop``."""
        t0 = time.perf_counter()
        active_from = self.loops.active_from(position)
        if active_from is None:
            return
        K, H, W = self.odometry.K, self.camera.height, self.camera.width
        rendered_at = None      # the tracked pose; else the pose an appearance match gives
        T = torch.as_tensor(self.pose, dtype=torch.float32)
        mv = self.map.render(K, T, H, W, colour=False, seen_before=active_from)
        coverage = model_coverage(mv.valid, view.valid[0, 0])
        if coverage < LOOP_MIN_COVERAGE:
            match = self._look_up_place(view, [p for p in self.loops.keyframe_positions if p < active_from])
            if match is not None:
                rendered_at = self.loops.pose(match.position) @ match.relative
                T = torch.as_tensor(rendered_at, dtype=torch.float32)
                mv = self.map.render(K, T, H, W, colour=False, seen_before=active_from)
                coverage = model_coverage(mv.valid, view.valid[0, 0])
        if coverage < LOOP_MIN_COVERAGE:
            result.time("loop", t0)
            return
        anchor = int(self.map.last_seen_in_view(K, T, H, W, active_from).median())
        mv.with_colour()
        reg, covariance, reason = self._register_to_model(view, mv)
        old = list(self.loops.graph.poses)
        result.loop = self.loops.propose(position, anchor, reg.relative, covariance, reason, coverage, rendered_at)
        if result.loop.accepted:
            self.map.move_surfels(torch.as_tensor(self.loops.corrections(old), dtype=torch.float32))
            self.pose = self.loops.adopt_optimised(position)
            revived, merged = self.map.reactivate_view(K, torch.as_tensor(self.pose, dtype=torch.float32), H, W,
                                                       position, active_from)
            log.info("loop closed at frame %d: the pose moved %.2f mm; %d surfels revived, %d merged",
                     position, result.loop.moved_mm, revived, merged)
            if self.cross_check is not None:
                self.cross_check.reset()
        result.time("loop", t0)

    def _relocalise(self, position: int, view: View, result: FrameResult) -> bool:
        """Relocalise the frame at ``position`` (after a frame that could not be tracked, or
        frames that could not be read): find the graph keyframe it looks like (ORB,
        :class:`slam.tracking.place_recognition.PlaceRecognition`), render the whole model at the pose
        that gives and register the frame against it. Where the registration passes the loop's
        verification the frame takes that pose (``result.pose``, its ``reason`` says so) and
        becomes the last frame, the one the next is tracked from; it is not fused, and its
        motion enters the pose graph as unknown. Returns whether it was relocalised. Timed as
        ``relocalise``."""
        t0 = time.perf_counter()
        match = self._look_up_place(view, self.loops.keyframe_positions)
        if match is None:
            result.time("relocalise", t0)
            return False
        K, H, W = self.odometry.K, self.camera.height, self.camera.width
        guess = self.loops.pose(match.position) @ match.relative
        mv = self.map.render(K, torch.as_tensor(guess, dtype=torch.float32), H, W, colour=True)
        if model_coverage(mv.valid, view.valid[0, 0]) < LOOP_MIN_COVERAGE:
            result.time("relocalise", t0)
            return False
        reg, _, reason = self._register_to_model(view, mv)
        if reason:
            result.time("relocalise", t0)
            return False
        moved = float(np.linalg.norm((guess @ reg.relative)[:3, 3] - self.pose[:3, 3]))
        result.pose = guess @ reg.relative
        result.reason = f"relocalised against the keyframe at frame {match.position} ({moved:.1f} mm from the last pose)"
        self.velocity = np.eye(4)
        self._advance(position, view, result.pose, result)
        if self.cross_check is not None:
            self.cross_check.reset()
        log.info("frame %d relocalised against the keyframe at frame %d: %.2f mm from the last pose",
                 position, match.position, moved)
        result.time("relocalise", t0)
        return True

    def _register_to_model(self, view: View, mv) -> tuple[TrackResult, Optional[np.ndarray], str]:
        """Register ``view`` against the model view ``mv`` (rendered with colour) by the dense
        tracker and verify it as a loop: the registration, its calibrated covariance (None where
        it failed) and why it is not a loop ('' where it is one, :meth:`LoopClosure.verify`)."""
        ref = self.odometry.view_from_render(mv.color, mv.depth, mv.valid, background=view,
                                             background_matchable=False)
        reg = self.odometry.track(view, ref)
        covariance = None
        if not reg.failed and reg.fit is not None:
            covariance = reg.fit.covariance(self.config.health.covariance_scale_model)
        plane = point_to_plane_check(view.depth, view.valid, ref.depth, ref.valid, self.odometry.K, reg.relative)
        reason = LoopClosure.verify(reg.failed, reg.support, covariance,
                                    plane.residual_mm if plane is not None else float("nan"))
        return reg, covariance, reason

    def _look_up_place(self, view: View, candidates: list[int]):
        """The keyframe among ``candidates`` that ``view`` looks like, by ORB (an
        :class:`slam.tracking.place_recognition.AppearanceMatch`, None where none is)."""
        return self.places.query(view.gray, None if view.masked is None else ~view.masked, candidates)

    def _remember_place(self, position: int, view: View) -> None:
        """Keep the ORB features of the new graph keyframe at ``position`` (appearance candidates)."""
        valid = view.valid[0, 0].cpu().numpy()
        self.places.add(position, view.gray, view.depth[0, 0].cpu().numpy(), valid)

    def optimised_poses(self, positions: range) -> Optional[np.ndarray]:
        """``(N, 4, 4)`` rectified ``T_wc`` of ``positions`` after the pose graph's optimisations
        (None without ``graph.loop_closure``)."""
        return self.loops.optimised_poses(positions) if self.loops is not None else None

    # ------------------------------------------------------------------ frame2model's cross-check
    def _estimate_against_last_frame(self, view: View, init: Optional[np.ndarray],
                                     result: FrameResult) -> Optional[FrameEstimate]:
        """The frame tracked against the last frame with its own flow (computed ahead where it
        can be), independent of the map; None where it failed or has no covariance. Timed as
        ``cross_check`` (its flow, weights and solve)."""
        t0 = time.perf_counter()
        ahead = view.flow_ahead
        if ahead is None or ahead[0]() is not self.last_view:   # (not computed ahead: now, and kept the same way)
            ahead = (weakref.ref(self.last_view), self.odometry.correspondences(view, self.last_view))
        view.flow_ahead = ahead
        track = self.odometry.track(view, self.last_view, init)
        view.flow_ahead = ahead     # the model view's tracking takes it too where it flows against the last frame
        result.time("cross_check", t0)
        if track.failed or track.fit is None:
            return None
        covariance = track.fit.covariance(self.config.health.covariance_scale_frame)
        return FrameEstimate(track, Estimate(track.relative, covariance))

    def _cross_check(self, estimate: FrameEstimate, result: FrameResult) -> np.ndarray:
        """Combine the model view's estimate of the frame (``result``, tracked and assessed) with
        the last frame's (:class:`slam.tracking.cross_check.CrossCheck`; health figures ``cross_check_d2``
        and ``cross_check_mm``). Where they disagree the frame is flagged and reports the
        better-supported one. Returns the frame's pose."""
        if result.covariance is None:       # (no fit of the model view's estimate: as if it failed)
            return self._keep_frame_estimate(estimate, result, "the model view's estimate has no fit")
        model = Estimate(np.linalg.inv(self.pose) @ result.pose, result.covariance)
        check = self.cross_check.check(model, estimate.estimate)
        result.health.update(cross_check_d2=check.d2, cross_check_mm=check.distance_mm)
        result.covariance = check.covariance
        if not check.agree:
            kept = "the last frame's" if check.kept == "frame" else "the model view's"
            self._flag(result, f"the model view and the last frame disagree by {check.distance_mm:.2f} mm "
                               f"(d2 {check.d2:.0f}): {kept} estimate kept")
            if check.kept == "frame":
                result.track = estimate.track
        return self.pose @ check.relative

    def _keep_frame_estimate(self, estimate: FrameEstimate, result: FrameResult, reason: str) -> np.ndarray:
        """Flag the frame and report the last frame's estimate alone; returns its pose."""
        self.cross_check.tracked_against_frame(estimate.estimate.covariance)
        result.track, result.covariance = estimate.track, self.cross_check.P.copy()
        self._flag(result, reason + ": the last frame's estimate kept")
        return self.pose @ estimate.estimate.relative

    def _flag_uncertain(self, result: FrameResult) -> None:
        """Health figures ``sigma_t_mm``, ``sigma_r_deg`` of the covariance of the pose reported,
        and a flag where ``sigma_t`` exceeds ``health.flag_mm``."""
        if result.covariance is None:
            return
        sigma_t = float(np.sqrt(max(np.trace(result.covariance[:3, :3]), 0.0)))
        sigma_r = float(np.degrees(np.sqrt(max(np.trace(result.covariance[3:, 3:]), 0.0))))
        result.health.update(sigma_t_mm=sigma_t, sigma_r_deg=sigma_r)
        if not result.flagged and sigma_t > self.config.health.flag_mm:
            self._flag(result, f"uncertain pose (sigma_t {sigma_t:.2f} mm)", model_disagrees=False)

    def _flag(self, result: FrameResult, reason: str, model_disagrees: bool = True) -> None:
        """Flag ``result``; ``model_disagrees``: against the model view (counts towards the rebuild)."""
        result.flagged, result.reason = True, reason
        self.flagged_in_row += int(model_disagrees)

    def _after_flags(self, view: View, pose: np.ndarray, result: FrameResult) -> None:
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
        removed = self.map.forget_view(self.odometry.K, torch.as_tensor(pose, dtype=torch.float32),
                                       self.camera.height, self.camera.width, seen_from=self._active_from(self.position))
        log.warning("%d frames flagged in a row: the model around the view is rebuilt (%d surfels removed)",
                    self.flagged_in_row, removed)
        result.flagged = False
        result.reason += f"; the model around this view rebuilt ({removed} surfels removed)"
        self.flagged_in_row = 0
        self.rebuilds += 1
        self.cross_check.reset()

    def _advance(self, position: int, view: View, pose: np.ndarray, result: FrameResult) -> None:
        """Make a tracked frame the last good one and, in frame2frame, the keyframe when the
        keyframe is ``tracking.keyframe_gap`` frames old or the camera moves."""
        if self.keyframe_gap > 1 and (self.keyframe is None or position - self.keyframe.position >= self.keyframe_gap
                                      or result.reference == "first" or not self._still_for_keyframe()):
            self.keyframe = Keyframe(position, view, pose)   # (a moving camera: the next frame goes against this one)
        self.pose, self.last_view, self.position = pose, view, position

    def _still_for_keyframe(self) -> bool:
        """Whether the last tracked motion leaves the camera still enough to keep the keyframe
        (``tracking.keyframe_still_mm``; always with 0)."""
        return moved_less_than(self.velocity, self.config.tracking.keyframe_still_mm)

    def _verify_geometry(self, view: View, ref: View, relative: np.ndarray, result: FrameResult) -> None:
        """How well the frame's depth at the tracked ``relative`` pose lies on the model view's
        surface (:func:`vo.geometric_check.point_to_plane_check`): health figures
        ``plane_residual_mm`` and ``plane_cost_share``."""
        t0 = time.perf_counter()
        check = point_to_plane_check(view.depth, view.valid, ref.depth, ref.valid, self.odometry.K, relative)
        result.time("verify", t0)
        if check is not None:
            result.health.update(plane_residual_mm=check.residual_mm, plane_cost_share=check.cost_share)

    def _assess(self, result: FrameResult, track: TrackResult) -> None:
        """The frame's health figures and pose covariance (:class:`slam.tracking.health.HealthMonitor`)."""
        figures, result.covariance = self.health.assess(track, against_model=result.reference == "model")
        result.health.update(figures)

    def _reference(self, result: FrameResult) -> tuple[View, np.ndarray, str]:
        """The reference view of the next frame, the pose it sits at and its kind: the keyframe
        (frame2frame, an earlier frame), the model view rendered at the last pose (frame2model,
        where the map covers enough of what the last frame saw), else the previous frame."""
        if self.keyframe is not None and self.keyframe.view is not self.last_view:
            return self.keyframe.view, self.keyframe.pose, "keyframe"
        if not self.frame2model:
            return self.last_view, self.pose, "previous_frame"
        t0 = time.perf_counter()
        # depth first: the colour's blending pass is only run when the view is used
        mv = self._render(self.pose, colour=False)
        coverage = model_coverage(mv.valid, self.last_view.valid[0, 0])
        result.health["model_coverage"] = coverage
        if coverage < self.config.tracking.min_model_coverage:
            result.time("render", t0)
            self.fallbacks += 1
            log.info("the model view covers %.0f%% of what the last frame saw: tracking against the previous frame",
                     100 * coverage)
            return self.last_view, self.pose, "previous_frame"
        rendered = self.config.tracking.flow_reference == "rendered"
        if rendered:
            mv.with_colour()
        result.time("render", t0)
        ref = self.odometry.view_from_render(mv.color if rendered else None, mv.depth, mv.valid,
                                             background=self.last_view)
        return ref, self.pose, "model"

    def _refine(self, view: View, pose: np.ndarray, track: TrackResult,
                result: FrameResult) -> tuple[np.ndarray, TrackResult]:
        """``tracking.refine_passes`` x: track ``view`` against the model rendered at its
        estimated ``pose`` and compose the correction. Returns the pose and the last
        successful tracking result (its weight maps weigh the fusion)."""
        for _ in range(self.config.tracking.refine_passes):
            t0 = time.perf_counter()
            # depth first, as in _reference: the colour's blending pass only for a view that is used
            mv = self._render(pose, colour=False)
            if model_coverage(mv.valid, view.valid[0, 0]) < self.config.tracking.min_model_coverage:
                result.time("render", t0)
                break
            mv.with_colour()
            result.time("render", t0)
            # the current frame fills the few uncovered pixels (no residual there: it sits at the
            # true pose, the render at the estimate) and gives the render its shading
            ref = self.odometry.view_from_render(mv.color, mv.depth, mv.valid, background=view,
                                                 background_matchable=False)
            refined = self.odometry.track(view, ref)
            result.timings += list(refined.timings_ms.items())
            if refined.failed:
                break
            pose, track = pose @ refined.relative, refined
        return pose, track

    def _render(self, pose: np.ndarray, colour: bool):
        """The active model (all of it without loop closure) rendered at ``pose``."""
        return self.map.render(self.odometry.K, torch.as_tensor(pose, dtype=torch.float32), self.camera.height,
                               self.camera.width, colour=colour, seen_from=self._active_from(self.position + 1))

    def _fuse(self, view: View, w3d: Optional[torch.Tensor], pose: np.ndarray, position: int,
              result: FrameResult) -> None:
        """Fuse ``view`` at ``pose``, weighted by its ``(1, 1, H, W)`` learned ``w3d`` if given."""
        if self.map is None:
            return
        t0 = time.perf_counter()
        valid = view.valid[0, 0]
        weight = None
        if w3d is not None and self.learned_fusion_weight:
            weight = normalised_fusion_weight(w3d[0, 0], valid)
        self.map.fuse(view.depth[0, 0], self.exposure.colour(view), self.odometry.K,
                      torch.as_tensor(pose, dtype=torch.float32), frame_index=position, weight=weight, valid=valid,
                      active_from=self._active_from(position))
        result.time("fusion", t0)

    def _map_at_known_pose(self, position: int, view: View, pose: np.ndarray) -> FrameResult:
        """``tracking.poses: groundtruth``: fuse ``view`` at its known ``pose``. The learned w3D
        is what keeps badly matched depth, moving tissue and instruments out of the map, so each
        frame is still matched to the previous one for it (no pose is solved for)."""
        result = FrameResult(pose, reference="groundtruth")
        w3d = None
        if self.last_view is not None and self.learned_fusion_weight:
            t0 = time.perf_counter()
            corr = self.odometry.correspondences(view, self.last_view, round_trip=False)
            view.flow_ahead = None
            t1 = time.perf_counter()
            problem = self.odometry.residual_problem(view, self.last_view, corr)
            _, w3d = self.odometry.weight_maps(view, self.last_view, corr, problem)
            result.timings += [("flow", (t1 - t0) * 1000.0), ("weights", (time.perf_counter() - t1) * 1000.0)]
        self._fuse(view, w3d, pose, position, result)
        self.pose, self.last_view, self.position = pose, view, position
        return result
