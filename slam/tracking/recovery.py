"""Recovery: re-acquiring the pose where tracking lost it, in both modes, without a map or a
pose graph.

After a frame failed, after five or more frames that could not be read (after fewer the flow
bridges the gap: the frame is tracked, and recovered as any other where it fails or is flagged),
where a frame's flow moved further than DIS from scratch reliably finds (``LARGE_FLOW``: such a
frame is flagged), or where a frame was flagged while it moved at least half as far, it is
registered again from a predicted pose, with its temporal flow started from that pose's motion
field (predict, then match what is left; :meth:`vo.odometry.StereoOdometry.track` with ``seed``).
The starts: the frame's own estimates (a flagged frame: the one reported and the cross-check's
other) and the last motion continued, against the last frame; and the pose PnP gives against the
recent frame whose ORB features it matches best
(:class:`slam.tracking.place_recognition.PlaceRecognition`: ratio test, RANSAC PnP on the frame's
stereo depth; the last frame and :class:`RecentFrames`, a few good frames before it). Each
registration is verified as a loop is, with a wider spread allowed
(:meth:`slam.tracking.loop_closure.LoopClosure.verify`: support, the covariance's spread, and how
far the frame's depth lies off the candidate's surface); of those that pass, the one whose depth lies
closest to the candidate's surface is kept, and for a flagged frame only where it lies closer than
the frame's own estimate. The frame takes that pose, is flagged (reference ``relocalised``: a
registration across a gap or a long baseline; not fused, nor are the frames before it that were
not tracked) and becomes the last frame, from which the next is tracked. A frame that cannot be
recovered stays failed (or flagged) and says why.

With ``graph.loop_closure`` the graph's relocalisation (against its keyframes and the whole
model, :class:`slam.tracking.graph.LoopClosureGraph`) plays this part instead.
"""
from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass
from typing import Optional

import numpy as np

from slam.tracking.graph import RELOCALISE_AFTER_MISSED
from slam.tracking.loop_closure import LoopClosure
from slam.tracking.place_recognition import PlaceRecognition
from slam.tracking.state import FrameResult
from vo.geometric_check import point_to_plane_check
from vo.geometry import motion_field
from vo.odometry import StereoOdometry, TrackResult, View

log = logging.getLogger("slam")

# the good frames kept as candidates: the last one, and one every KEEP_EVERY frames among the
# KEPT before it (at 25 fps a second of video; a gap longer than that needs the graph's keyframes)
KEPT = 4
KEEP_EVERY = 6
# a frame whose flow's median is beyond what DIS from scratch reliably finds, as a share of the
# image width, is flagged and relocalised (measured at 640x512: as good as a flow started from the
# true motion up to 40-46 px median, one pair in three lost at 77-92 px on weak texture)
LARGE_FLOW = 1 / 10
# the gate's medians are taken on every GATE_STRIDE-th pixel in each direction (a full-resolution
# median of the flow's magnitude costs tens of ms at 640x512, on every frame)
GATE_STRIDE = 16
# a registration from a start is matched again from its result while that moves the start by this
# much, at most PASSES times (from a start 3-4 mm off, measured at 1.25 fps: 3.1 -> 0.54 -> 0.49 mm)
PASSES = 3
CONVERGED_MM = 0.25
# the largest spread of a relocalising registration (a loop's is 1.5 mm): across a long baseline
# the residuals grow with the change of view while the pose holds (from 12 mm away, measured
# 0.7 mm off with a spread of 4.2 mm); the surface (point to plane) is the sharper judge there
MAX_SIGMA_MM = 6.0


@dataclass
class Candidate:
    """A good frame to relocalise against: its sequence position, view and rectified ``T_wc`` (mm)."""

    position: int
    view: View
    pose: np.ndarray


class RecentFrames:
    """The last good frame and up to ``KEPT`` older ones, ``KEEP_EVERY`` frames apart; their ORB
    features are computed when a relocalisation first needs them."""

    def __init__(self, K: np.ndarray, width: int):
        self.places = PlaceRecognition(K, width)
        self.last: Optional[Candidate] = None
        self.kept: deque[Candidate] = deque(maxlen=KEPT)

    def add(self, position: int, view: View, pose: np.ndarray) -> None:
        """A tracked, unflagged frame (the newest)."""
        self.last = Candidate(position, view, pose)
        if not self.kept or position - self.kept[-1].position >= KEEP_EVERY:
            self.kept.append(self.last)

    def candidates(self) -> list[Candidate]:
        """The newest first, each once."""
        out = [] if self.last is None else [self.last]
        out += [c for c in reversed(self.kept) if self.last is None or c.position != self.last.position]
        return out

    def features_of(self, candidates: list[Candidate]) -> None:
        """Compute the ORB features of ``candidates`` not yet described; forget the others'."""
        keep = {c.position for c in candidates}
        for position in list(self.places.keyframes):
            if position not in keep:
                self.places.remove(position)
        for c in candidates:
            if c.position not in self.places.keyframes:
                self.places.add(c.position, c.view.gray, c.view.depth[0, 0].cpu().numpy(),
                                c.view.valid[0, 0].cpu().numpy())


class FrameRelocaliser:
    """Relocalisation against the recent good frames (see the module docstring).

    Args:
        odometry: the VO core (the dense registration).
        covariance_scale_frame: ``health.covariance_scale_frame`` (the registration's covariance).
        width: image width (pixels; the RANSAC threshold scales with it).
    """

    def __init__(self, odometry: StereoOdometry, covariance_scale_frame: float, width: int):
        self.odometry = odometry
        self.covariance_scale_frame = covariance_scale_frame
        self.recent = RecentFrames(odometry.K.cpu().numpy(), width)
        self.after_gap: Optional[int] = None      # the frame after a gap that was not relocalised
        self.model_from: Optional[int] = None     # the first frame whose surfels the model holds

    def active_from(self, position: int) -> Optional[int]:
        """The first frame whose surfels the model at ``position`` holds (None: all): after a gap
        that was not recovered, the map from before it is set aside (its poses and the new ones
        no longer agree)."""
        return self.model_from

    def set_aside(self, position: int) -> None:
        """The map before ``position`` set aside (:meth:`active_from`): the map re-anchors there."""
        self.model_from = position

    def remember(self, position: int, view: View, pose: np.ndarray, result: FrameResult) -> None:
        """Keep a trusted frame as a candidate (a relocalised frame is kept by :meth:`relocalise`)."""
        if result.trusted:
            self.recent.add(position, view, pose)

    def relocalised_after_gap(self, tracker, position: int, view: View, result: FrameResult) -> bool:
        """After ``RELOCALISE_AFTER_MISSED`` or more frames that could not be read (or failed),
        relocalise the frame before tracking it (the camera may have moved further than the flow
        finds); True where it was."""
        missed = position - tracker.state.position - 1
        if missed < RELOCALISE_AFTER_MISSED:       # (a few dropped frames: the flow bridges them)
            return False
        if not self.relocalise(tracker, position, view, result):
            log.info("frame %d after %d frames that could not be read: not relocalised (%s); tracked",
                     position, missed, result.reason)
            result.reason = ""
            self.after_gap = position
            return False
        result.reason = f"relocalised after {missed} frames that could not be read; " + result.reason
        return True

    def recovered(self, tracker, position: int, view: View, result: FrameResult) -> bool:
        """As :meth:`recover`; where the frame after a gap stays flagged, the map from before the
        gap is set aside (:meth:`active_from`): the model view would pull the new poses towards
        surfaces fused where the track was before the gap."""
        if self.recover(tracker, position, view, result):
            return True
        if result.flagged and position == self.after_gap:
            self.set_aside(position)
            result.reason += "; the map before the gap set aside"
            log.warning("frame %d after a gap was not recovered: the map before it is set aside", position)
        return False

    def recover(self, tracker, position: int, view: View, result: FrameResult) -> bool:
        """A frame tracked while its flow moved further than DIS from scratch reliably finds
        (median above ``LARGE_FLOW`` of the image width: flagged, its estimate may have lost the
        match unseen), or a flagged one whose flow or estimated motion moved at least half as far
        (a flow that lost the match need not be large; where the motion is small a flag has other
        causes and the frame keeps its estimate): relocalised where it can be, from its own
        estimates and the pose its features give; True where it was (its pose replaced, still
        flagged)."""
        track = result.track
        if track is None or result.snapped_to_map:      # (the map refuted an unconfirmed chain: not lost)
            return False
        width = view.depth.shape[-1]
        flow_px = float(track.flow[..., ::GATE_STRIDE, ::GATE_STRIDE].norm(dim=1).median())
        if not result.flagged and flow_px < LARGE_FLOW * width:
            return False
        if result.flagged:
            moved_px = max(flow_px, self.motion_px(view, tracker.state.pose, result.pose))
            if moved_px < LARGE_FLOW / 2 * width:
                return False
        if not result.flagged:
            tracker.acceptance.flag(result, f"motion beyond what the flow reliably finds ({flow_px:.0f} px median)",
                                    model_disagrees=False)
        reason = result.reason
        state = tracker.state
        starts = [np.linalg.inv(state.pose) @ result.pose, *result.other_estimates, state.velocity]
        if self.relocalise(tracker, position, view, result, distinct(starts)):
            result.reason = f"{reason}; " + result.reason
            return True
        result.reason = f"{reason}; not relocalised: {result.reason}"
        return False

    def after_failure(self, tracker, position: int, view: View, result: FrameResult) -> None:
        """A frame that could not be tracked: relocalised where it can be (then no longer failed),
        else it stays failed and its reason says why it was not recovered."""
        reason = result.reason
        state = tracker.state
        velocity = [state.velocity] if position == state.position + 1 else []    # (the last motion continued)
        if self.relocalise(tracker, position, view, result, distinct(velocity)):
            result.failed = False
            result.reason = f"{reason}; " + result.reason
        else:
            result.reason = f"{reason}; not relocalised: {result.reason}"

    def relocalise(self, tracker, position: int, view: View, result: FrameResult,
                   estimates: tuple = ()) -> bool:
        """Relocalise ``view``: registered against the last frame from each of ``estimates``
        (``(4, 4)`` mm, predictions of its motion from the last frame) and against
        the recent frame its features match best from the pose PnP gives, each with its flow
        started from that pose's motion field; of the registrations that pass the verification
        the one whose depth lies closest to its candidate's surface is kept (with ``estimates``,
        only where closer than the first estimate's). On success ``result`` holds the pose,
        ``reference`` ``relocalised`` (flagged: not fused) and the registration, and the frame is
        the tracker's last frame; else ``result.reason`` says why not. Timed as ``relocalise``."""
        t0 = time.perf_counter()
        state = tracker.state
        last = Candidate(state.position, state.last_view, state.pose)
        starts = [(last, estimate) for estimate in estimates]
        candidates = [last] + [c for c in self.recent.candidates() if c.position != last.position]
        self.recent.features_of(candidates)
        match = self.recent.places.query(view.gray, None if view.masked is None else ~view.masked,
                                         [c.position for c in candidates])
        if match is not None:
            starts.append((next(c for c in candidates if c.position == match.position), match.relative))
        best, why = None, "no recent frame matched its features"
        for cand, start in starts:
            reg, plane_mm, why_not = self.register(view, cand, start)
            if why_not:
                why = f"the registration against frame {cand.position} was not verified ({why_not})"
            elif best is None or plane_mm < best[2]:
                best = (cand, reg, plane_mm)
        if best is not None and estimates and not best[2] < self.plane_mm(view, last, estimates[0]):
            best, why = None, "no registration lies closer to the last frame's surface than the estimate"
        if best is None:
            result.reason = why
            result.time("relocalise", t0)
            return False
        cand, reg, _ = best
        pose = cand.pose @ reg.relative
        moved = float(np.linalg.norm(pose[:3, 3] - state.pose[:3, 3]))
        result.pose, result.track, result.view = pose, reg, reg.view
        result.reference, result.reference_position = "relocalised", cand.position
        result.snapped_to_map, result.map_correction = False, None      # (the pose is no longer the map's)
        tracker.acceptance.assess(result, reg)
        tracker.acceptance.flag_uncertain(result)
        result.flagged = True      # (a registration across the gap: not fused, the next frames go from it)
        result.reason = f"relocalised against frame {cand.position} ({moved:.1f} mm from the last pose)"
        state.velocity = np.linalg.inv(state.pose) @ pose if position == state.position + 1 else np.eye(4)
        tracker.references.forget_keyframe()
        tracker.advance(position, reg.view, pose, result)
        tracker.acceptance.relocalised(position, result)
        self.recent.add(position, reg.view, pose)
        log.info("frame %d relocalised against frame %d: %.2f mm from the last pose", position, cand.position, moved)
        result.time("relocalise", t0)
        return True

    def register(self, view: View, cand: Candidate, start: np.ndarray) -> tuple[TrackResult, float, str]:
        """The dense registration of ``view`` against ``cand`` from ``start`` (``(4, 4)`` mm, the
        flow started from its motion field; again from its result while that moves the start by
        ``CONVERGED_MM`` or more, at most ``PASSES`` times), how far the frame's depth lies off
        the candidate's surface at it (mm) and why it is not verified ('' where it is)."""
        for _ in range(PASSES):
            reg = self.odometry.track(view, cand.view, start, seed=True)
            if reg.failed or np.linalg.norm(reg.relative[:3, 3] - start[:3, 3]) < CONVERGED_MM:
                break
            start = reg.relative        # (what is left to find is smaller: match again from here)
        plane_mm = self.plane_mm(reg.view, cand, reg.relative)
        covariance = None if reg.failed or reg.fit is None else reg.fit.covariance(self.covariance_scale_frame)
        return reg, plane_mm, LoopClosure.verify(reg.failed, reg.support, covariance, plane_mm, MAX_SIGMA_MM)

    def motion_px(self, view: View, last_pose: np.ndarray, pose: np.ndarray) -> float:
        """The median (pixels) of the motion field that ``view`` moved through from ``last_pose``
        to ``pose`` (``T_wc``, mm) gives."""
        K = self.odometry.K.clone()
        K[:2] /= GATE_STRIDE            # (on every GATE_STRIDE-th pixel: a gate, not a measurement)
        step = (slice(None), slice(None), slice(None, None, GATE_STRIDE), slice(None, None, GATE_STRIDE))
        field = motion_field(view.depth[step], view.valid[step], K, np.linalg.inv(last_pose) @ pose)
        return float(field.norm(dim=1).median()) * GATE_STRIDE

    def plane_mm(self, view: View, cand: Candidate, relative: np.ndarray) -> float:
        """How far ``view``'s depth at ``relative`` (``(4, 4)`` mm, to ``cand``) lies off
        ``cand``'s surface (:func:`vo.geometric_check.point_to_plane_check`; nan without overlap)."""
        check = point_to_plane_check(view.depth, view.valid, cand.view.depth, cand.view.valid, self.odometry.K,
                                     relative)
        return check.residual_mm if check is not None else float("nan")


def distinct(motions: list, mm: float = 0.5) -> tuple:
    """``motions`` (``(4, 4)`` mm) without those within ``mm`` of one before them (the identity
    left out: no prediction)."""
    out: list = []
    for T in motions:
        if np.linalg.norm(T[:3, 3]) < mm and np.allclose(T[:3, :3], np.eye(3), atol=1e-3):
            continue
        if all(np.linalg.norm(T[:3, 3] - U[:3, 3]) >= mm for U in out):
            out.append(T)
    return tuple(out)
