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

**Trust along the chain** (frame2model with the cross-check). The cross-check's ``P``, the
uncertainty of the last pose against the map, is the trust a pose carries: a registration against
the map that agrees with the chain confirms the pose (``P`` shrinks to the combined estimate's);
a frame tracked against the previous frame (the model view covers too little of it) adds its
step's covariance to ``P``; a relocalisation sets ``P`` to its registration's covariance, never to
zero. A pose that no registration against the map confirmed since the chain left it is
*unconfirmed*: reported flagged ("unconfirmed since frame N"), not fused, no keyframe, and its
``sigma_t`` is ``P``'s. The model's rebuild does not confirm either (the rebuilt frame stays
flagged), and unconfirmed frames do not count toward it. Where the chain stays unconfirmed for
``REANCHOR_AFTER`` confident steps in a row (the camera explores tissue the map does not hold, and
unfused frames would never let it), the map re-anchors at the frame as after a gap: the map before
it is set aside and the frame is fused, which the reason says. The new map is only as sure of the
world as the chain was there: its *anchor* uncertainty (``P`` at the re-anchoring, summed over
re-anchorings) is added to the covariance every later pose reports, so that poses confirmed by a
map re-anchored after an unrecovered gap stay flagged as uncertain (they are fused all the same:
they agree with the map); a loop closed back onto the old map clears it.
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
# frame2model: confident unconfirmed steps in a row after which the map re-anchors (set aside
# before the frame, the frame fused): unfused frames cannot grow the map into tissue it lacks
REANCHOR_AFTER = 2


def sigma_t_mm(covariance: np.ndarray) -> float:
    """The translation spread ``sqrt(trace)`` (mm) of a ``(6, 6)`` pose covariance."""
    return float(np.sqrt(max(np.trace(covariance[:3, :3]), 0.0)))


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

    rebuilds = reanchors = 0
    flows_to_previous_frame = False
    TRUSTED = "tracked"      # (what an unflagged pose is called where no map confirms it)

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
        result.failed, result.reason, result.trust = True, track.reason, "failed"
        self.assess(result, track)

    def first(self, result: FrameResult) -> None:
        """The first frame: the world's anchor (the map starts from it where there is one)."""
        result.trust = self.TRUSTED

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

    def report_spread(self, result: FrameResult) -> float:
        """Health figures ``sigma_t_mm``, ``sigma_r_deg`` of the covariance of the pose reported;
        returns ``sigma_t`` (nan without a covariance)."""
        if result.covariance is None:
            return float("nan")
        sigma_t = sigma_t_mm(result.covariance)
        sigma_r = float(np.degrees(np.sqrt(max(np.trace(result.covariance[3:, 3:]), 0.0))))
        result.health.update(sigma_t_mm=sigma_t, sigma_r_deg=sigma_r)
        return sigma_t

    def flag_uncertain(self, result: FrameResult, why: str = "") -> None:
        """:meth:`report_spread`, and a flag where ``sigma_t`` exceeds ``health.flag_mm``."""
        sigma_t = self.report_spread(result)
        if not result.flagged and sigma_t > self.flag_mm:
            self.flag(result, f"uncertain pose (sigma_t {sigma_t:.2f} mm{why})", model_disagrees=False)

    def flag(self, result: FrameResult, reason: str, model_disagrees: bool = True) -> None:
        result.flagged, result.reason = True, reason

    def after_flags(self, position: int, pose: np.ndarray, result: FrameResult, state: TrackState) -> None:
        """The frame's trust: flagged, else tracked (against the model view: confirmed)."""
        result.trust = "flagged" if result.flagged else ("confirmed" if result.reference == "model" else "tracked")

    def relocalised(self, position: int, result: FrameResult) -> None:
        """A relocalised frame (flagged): nothing is carried from frame to frame."""
        result.trust = "flagged"

    chain_confirmed = chain_checked = True      # (no chain: every pose stands on its own)

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

        set_aside: ``set_aside(position)`` sets the map before ``position`` aside (the re-anchoring).

    Attributes:
        flagged_in_row: frames flagged since the model view last agreed.
        rebuilds: times the model around the view was rebuilt.
        reanchors: times the map re-anchored after an unconfirmed stretch.
        unconfirmed_since: the first frame of the stretch the map has not confirmed (None: the last
            pose is confirmed).
        unchecked_since: the relocalisation in that stretch, a long-baseline registration the map
            never checked (None: every link is a step from the frame before, compared with the map
            or not).
        confident_steps: unconfirmed frames in a row tracked confidently against the previous frame.
        anchor: ``(6, 6)`` the map's uncertainty against the world frame (``P`` summed over the
            re-anchorings; zero for the map the run started).
    """

    flows_to_previous_frame = True       # (the independent estimate's flow can be computed ahead)
    TRUSTED = "confirmed"

    def __init__(self, health: HealthMonitor, flag_mm: float, cross_check: CrossCheck, odometry: StereoOdometry,
                 covariance_scale_frame: float, forget_view: Callable[[np.ndarray], int],
                 set_aside: Callable[[int], None]):
        super().__init__(health, flag_mm)
        self.cross_check = cross_check
        self.odometry = odometry
        self.covariance_scale_frame = covariance_scale_frame
        self.forget_view = forget_view
        self.set_aside = set_aside
        self.flagged_in_row = 0
        self.rebuilds = 0
        self.reanchors = 0
        self.unconfirmed_since: Optional[int] = None
        self.unchecked_since: Optional[int] = None
        self.confident_steps = 0
        self.anchor = np.zeros((6, 6))       # the map's own uncertainty against the world (re-anchorings)
        self.anchored_at: Optional[int] = None
        self.chained = False          # frames between model frames since the map last confirmed
        self._confirms = False        # the frame being accepted was confirmed by the map
        self._step_sigma = np.inf     # its own step's spread (a frame tracked against the previous one)

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
        self._confirms, self._step_sigma = False, np.inf
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
            elif result.covariance is not None and ref.against_model:
                # (the last frame's estimate failed: the model view's alone, which confirms a pose
                # only where the chain before it was confirmed)
                self.cross_check.tracked_against_model(result.covariance)
                self._confirms = self.unconfirmed_since is None
            elif result.covariance is not None:
                # against the previous frame: the step's uncertainty adds up along the chain (the
                # frame is unconfirmed, :meth:`after_flags`, whatever its spread)
                self._step_sigma = sigma_t_mm(result.covariance)
                self.cross_check.tracked_against_frame(result.covariance)
                result.covariance = self.cross_check.P.copy()
                self.report_spread(result)
                return True
        self.flag_uncertain(result)
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
        check = self.cross_check.check(model, estimate.estimate, chain_checked=self.chain_checked)
        result.health.update(cross_check_d2=check.d2, cross_check_mm=check.distance_mm)
        result.covariance = check.covariance
        self._confirms = check.agree
        if (not self.chain_confirmed or self.chained) and check.kept != "frame":   # (the map ends a stretch)
            chain = state.pose @ estimate.estimate.relative
            result.map_correction = (state.pose @ check.relative) @ np.linalg.inv(chain)
        if not check.agree:
            kept = "the last frame's" if check.kept == "frame" else "the model view's"
            self.flag(result, f"the model view and the last frame disagree by {check.distance_mm:.2f} mm "
                              f"(d2 {check.d2:.0f}): {kept} estimate kept")
            if check.kept == "frame":
                result.track = estimate.track
            result.snapped_to_map = (check.kept == "model" and not self.chain_checked
                                     and not check.d2 <= self.cross_check.limit_d2)
        return state.pose @ check.relative

    def keep_frame_estimate(self, estimate: FrameEstimate, result: FrameResult, state: TrackState,
                            reason: str) -> np.ndarray:
        """Flag the frame and report the last frame's estimate alone; returns its pose."""
        self.cross_check.tracked_against_frame(estimate.estimate.covariance)
        result.track, result.covariance = estimate.track, self.cross_check.P.copy()
        self.flag(result, reason + ": the last frame's estimate kept")
        return state.pose @ estimate.estimate.relative

    def flag(self, result: FrameResult, reason: str, model_disagrees: bool = True) -> None:
        """Flag ``result``; ``model_disagrees``: against the model view (counts towards the rebuild
        unless the chain holds a relocalisation the map never checked: no evidence against it)."""
        result.flagged, result.reason = True, reason
        self.flagged_in_row += int(model_disagrees and self.chain_checked)

    def after_flags(self, position: int, pose: np.ndarray, result: FrameResult, state: TrackState) -> None:
        """The frame's trust along the chain (see the module docstring): confirmed by the map,
        flagged, or unconfirmed (then flagged); the model's rebuild after ``REBUILD_AFTER`` frames
        the model view disagreed with, and the map's re-anchoring after ``REANCHOR_AFTER``
        confident unconfirmed steps."""
        if self._confirms and not result.flagged:
            result.trust, result.agrees_with_map = "confirmed", True
            self.unconfirmed_since, self.unchecked_since, self.confident_steps = None, None, 0
            self.chained = False
            if result.reference == "model":
                self.flagged_in_row = 0
            self.add_anchor(result)
            return
        self.leave_chain(position)
        if result.flagged:
            result.trust = "flagged"
            self.confident_steps = 0
            self.rebuild_if_lasting(pose, result)
            return
        result.trust = "unconfirmed"
        self.add_anchor(result)
        sigma = result.health.get("sigma_t_mm", float("nan"))
        self.flag(result, f"unconfirmed since frame {self.unconfirmed_since} (sigma_t {sigma:.2f} mm)",
                  model_disagrees=False)
        self.confident_steps = self.confident_steps + 1 if self._step_sigma <= self.flag_mm else 0
        if self.confident_steps >= REANCHOR_AFTER:
            self.reanchor(position, result)

    def chain_step(self, position: int, estimate: FrameEstimate, result: FrameResult, state: TrackState) -> None:
        """A frame between model frames: the last frame's ``estimate`` is its pose, the filter's
        ``P`` with the step's covariance added its spread (flagged where uncertain); trusted as
        ``tracked`` until the next model frame confirms or corrects it."""
        self.assess(result, estimate.track)
        self.cross_check.tracked_against_frame(estimate.estimate.covariance)
        result.pose = state.pose @ estimate.estimate.relative
        result.covariance = self.cross_check.P.copy()
        result.between = True
        self.chained = True
        self.flag_uncertain(result)
        if result.flagged:
            result.trust = "flagged"
            self.leave_chain(position)
        else:
            result.trust = "tracked"
        self.add_anchor(result)

    def add_anchor(self, result: FrameResult) -> None:
        """The map's anchor uncertainty added to the pose's covariance (a pose confirmed by a map
        re-anchored after an uncertain stretch is no surer than the map); flagged where the sum is
        uncertain."""
        if self.anchored_at is None or result.covariance is None:
            return
        result.covariance = result.covariance + self.anchor
        self.flag_uncertain(result, f": the map re-anchored at frame {self.anchored_at}")
        if result.flagged and result.trust in ("confirmed", "tracked"):
            result.trust = "flagged"

    def reanchor(self, position: int, result: FrameResult) -> None:
        """The map re-anchors at the frame: the map before it set aside, the frame fused; its
        chain's uncertainty becomes the new map's anchor, and the pose is the new map's own."""
        self.set_aside(position)
        result.anchors_map = True
        result.reason += (f"; the map re-anchored here after {self.confident_steps} unconfirmed frames "
                          "(the map before set aside)")
        log.warning("frame %d: the map re-anchored after %d unconfirmed frames since frame %d", position,
                    self.confident_steps, self.unconfirmed_since)
        self.anchor = self.anchor + self.cross_check.P
        self.anchored_at = position
        self.cross_check.reset()
        self.confident_steps = 0
        self.reanchors += 1

    @property
    def chain_confirmed(self) -> bool:
        """Whether the last pose is confirmed by the map."""
        return self.unconfirmed_since is None

    @property
    def chain_checked(self) -> bool:
        """Whether the chain since the last confirmed pose holds no relocalisation (a registration
        across a gap or a long baseline, which the map never checked)."""
        return self.unchecked_since is None

    def leave_chain(self, position: int) -> None:
        """The chain is unconfirmed from ``position`` on, unless it already was."""
        if self.unconfirmed_since is None:
            self.unconfirmed_since = position

    def rebuild_if_lasting(self, pose: np.ndarray, result: FrameResult) -> None:
        """After ``REBUILD_AFTER`` frames flagged without the model view agreeing in between
        (unconfirmed frames, which the map does not see, do not count either way) the model
        around the view is taken as wrong: the surfels the view sees from ``pose`` are removed and
        the frame is fused (it stays flagged: a map rebuilt from it does not confirm it), so the
        model agrees with the last frames again."""
        if self.flagged_in_row < REBUILD_AFTER:     # (reached only on a disagreement: it rebuilds at once)
            return
        removed = self.forget_view(pose)
        log.warning("%d frames flagged in a row: the model around the view is rebuilt (%d surfels removed)",
                    self.flagged_in_row, removed)
        result.anchors_map = True
        result.reason += f"; the model around this view rebuilt from it ({removed} surfels removed)"
        self.flagged_in_row = 0
        self.rebuilds += 1

    def relocalised(self, position: int, result: FrameResult) -> None:
        """A relocalised frame (flagged): ``P`` is its registration's covariance, and the chain is
        unconfirmed from it until the map agrees."""
        super().relocalised(position, result)
        if result.covariance is not None:
            self.cross_check.P = np.array(result.covariance, dtype=np.float64)
        self.confident_steps = 0
        self.leave_chain(position)
        if self.unchecked_since is None:
            self.unchecked_since = position

    def reset(self) -> None:
        """The pose is the map's own again (a loop closed: the graph moved it onto the old map)."""
        self.cross_check.reset()
        self.unconfirmed_since, self.unchecked_since, self.confident_steps = None, None, 0
        self.chained = False
        self.anchor, self.anchored_at = np.zeros((6, 6)), None
