"""What the tracker knows of the sequence between two frames (:class:`TrackState`) and what it
made of one frame (:class:`FrameResult`).

Poses are those of the rectified left camera (``T_wc``, mm; :mod:`slam.tracking.poses`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from slam.tracking.loop_closure import LoopEvent
from vo.odometry import TrackResult, View


#: what a pose rests on (:attr:`FrameResult.trust`), the trusted ones first
TRUST = ("confirmed", "tracked", "known", "unconfirmed", "flagged", "failed")
TRUSTED = ("confirmed", "tracked", "known")


@dataclass
class TrackState:
    """The last tracked frame: its pose, view and sequence position, and the motion that led to
    it (``velocity``: the relative pose from the frame before, the still-camera rules' input).
    ``last_view`` is None before the first frame."""

    pose: np.ndarray
    last_view: Optional[View] = None
    position: int = -1
    velocity: np.ndarray = field(default_factory=lambda: np.eye(4))


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
        view: the frame's view as tracked (its depth filtered where it was), None where it was
            not tracked.
        thread_cpu: CPU ms of the pipeline's other threads handed over with the frame (``mapping``:
            the fusions that finished while it was tracked).
        other_estimates: ``(4, 4)`` estimates of the frame's motion from the last frame (mm) that
            were not reported (the cross-check's other one): starts for a recovery.
        trust: what the pose rests on (:data:`TRUST`): ``confirmed`` (frame2model: registered against
            the map in agreement with the chain of poses before it), ``tracked`` (tracked against a
            camera frame where no map confirms: frame2frame), ``known`` (mapped at a known pose,
            ``analysis.poses: groundtruth``), ``unconfirmed`` (frame2model: carried
            along the chain since a frame the map did not confirm, reported flagged), ``flagged``
            or ``failed``.
        anchors_map: the frame is fused although it is not trusted: the map is rebuilt or
            re-anchored from it (``reason`` says which).
        agrees_with_map: registered against the map in agreement with the chain (fused), even
            where the map's own anchor makes the pose uncertain in the world (then flagged).
        snapped_to_map: the model view's estimate was kept where it refuted a chain the map had
            not confirmed (inconsistent beyond the cross-check's bound; flagged: the track jumped
            back onto the map, which is not a lost match to relocalise).
        map_correction: ``(4, 4)`` where the map ended an unconfirmed stretch at this frame (it
            confirmed the chain, or snapped it back): its pose against the chain's, ``T_map
            T_chain^-1`` (world frame, mm; :mod:`slam.tracking.chain_repair`); else None.
        between: a frame between model frames (``tracking.model_every``): its pose the chain's
            from the last frame, not registered against the map and not fused; corrected with the
            next model frame.
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
    view: Optional[View] = None
    thread_cpu: dict = field(default_factory=dict)
    other_estimates: list = field(default_factory=list)
    trust: str = ""
    anchors_map: bool = False
    agrees_with_map: bool = False
    snapped_to_map: bool = False
    map_correction: Optional[np.ndarray] = None
    between: bool = False

    @property
    def trusted(self) -> bool:
        """A pose a user may take as it is (confirmed or tracked, not flagged)."""
        return self.trust in TRUSTED

    @property
    def fuses(self) -> bool:
        """Whether the frame is fused into the map: a trusted pose, one that agrees with the map,
        or one the map is rebuilt or re-anchored from."""
        return self.trusted or self.agrees_with_map or self.anchors_map

    def time(self, stage: str, since: float) -> None:
        """Record ``stage`` as the time elapsed since ``since`` (``time.perf_counter()``)."""
        self.timings.append((stage, (time.perf_counter() - since) * 1000.0))


