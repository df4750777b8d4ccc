"""Frame2model's loop closure: graph keyframes, every frame's pose relative to its keyframe, the
loop candidates' verification and the corrections an accepted loop brings.

The algorithm, per tracked frame (:meth:`LoopClosure.add_frame`):

1. **Odometry.** The frame's motion from the last frame and its calibrated covariance (the
   tracker's, ``health.covariance_scale_*``) are composed into the edge since the last graph
   keyframe (:func:`slam.tracking.pose_graph.compose`, GTSAM's convention).
2. **Keyframe.** Once the camera has moved ``graph.keyframe_mm`` or turned ``graph.keyframe_deg``
   from the last keyframe candidate, the frame becomes one, joined to the last graph keyframe by
   that edge. Every frame keeps its pose relative to its keyframe, so an optimisation moves it
   with the keyframe.
3. **Detection** (the tracker, at a new keyframe): the *inactive* model (surfels not fused for
   ``graph.inactive_after`` frames, ElasticFusion's split) is rendered at the frame's pose; where
   it covers :data:`LOOP_MIN_COVERAGE` of the frame, the frame is registered against it by the
   same dense tracker (:meth:`verify` checks the result: support, positional spread, the depth's
   fit to the rendered surface). Where the inactive model covers less (the drift took the
   tracked pose away from the old tissue), an *appearance* candidate: the frame's ORB features
   matched to an inactive keyframe's (:mod:`slam.tracking.place_recognition`) give a pose by PnP, the
   inactive model is rendered there and the frame registered and verified the same way. The
   same match relocalises a lost camera (the tracker's ``_relocalise``).
4. **Loop edge.** The registration says where the camera is in the inactive model's frame; the
   edge joins the keyframe that last fused the surfels in view (the median frame) and this one
   (:meth:`propose`), and the pose graph gates and optimises it
   (:meth:`slam.tracking.pose_graph.PoseGraph.propose_loop`).
5. **Correction.** An accepted loop moves every keyframe; each frame's correction is its
   keyframe's (:meth:`corrections`). The tracker moves the surfels with the frame that last fused
   them, its own pose, and revives the inactive surfels in view.
6. **Culling** (:meth:`cull`). A new keyframe without a loop edge whose pose an older keyframe
   already holds (within ``graph.keyframe_mm`` and ``graph.keyframe_deg``) adds nothing: it
   leaves the graph, its frames go to the keyframe before it and its odometry edge goes on
   growing. A camera circling the same tissue adds keyframes only where it closes loops.

Poses are ``(4, 4)`` ``T_wc`` of the rectified left camera, mm.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional

import numpy as np

from slam.config import GraphConfig
from slam.tracking.pose_graph import PoseGraph, compose, to_gtsam_covariance

log = logging.getLogger("slam")

# the inactive model must cover this fraction of the frame's valid pixels for a loop candidate
# (a camera coming back sees old tissue beside tissue it saw recently, which is active: on the
# synthetic loops the inactive share of the view rises to 0.4-0.5 as the camera returns)
LOOP_MIN_COVERAGE = 0.3
# verification of a candidate's registration: the share of the frame's valid pixels that carry a
# weight (a registration on a sliver of the view is not a loop) ...
LOOP_MIN_SUPPORT = 0.2
# ... the positional spread of its calibrated covariance (mm; health.flag_mm's default: a pose
# that uncertain is flagged in tracking too) ...
LOOP_MAX_SIGMA_MM = 1.5
# ... and the frame's depth on the rendered surface at the registered pose: the weighted median
# point-to-plane distance (mm; the stereo noise at endoscopic depths is 0.1-0.5 mm)
LOOP_MAX_PLANE_MM = 1.0
# a loop candidate must reach back further than this many graph keyframes (neighbours are
# joined by odometry already)
LOOP_MIN_KEYFRAME_GAP = 2
# covariance of a frame's motion where the tracker gave none (a failed frame keeps the last pose:
# its motion is unknown): 5 mm and 5 deg, far above any tracked frame's
UNKNOWN_MOTION_COVARIANCE = np.diag([25.0] * 3 + [np.radians(5.0) ** 2] * 3)


@dataclass
class LoopEvent:
    """One loop candidate and what became of it.

    Attributes:
        position: the frame (sequence position) the candidate was found at.
        keyframe, anchor: the graph keyframes the loop edge joins (this frame's, the old one's).
        anchor_position: the frame the anchor keyframe sits at.
        accepted: verified and accepted by the graph.
        reason: why it was rejected ('' when accepted).
        coverage: the inactive model's coverage of the frame.
        correction_mm: how far the registration moved the frame from its tracked pose.
        d2: the graph's squared Mahalanobis distance of the edge (nan where not proposed).
        moved_mm: how far the optimisation moved this frame's pose (0 unless accepted).
        source: where the candidate came from: 'model' (the inactive model rendered at the
            tracked pose) or 'appearance' (rendered at the pose an ORB match to a keyframe gave).
    """

    position: int
    keyframe: int
    anchor: int
    anchor_position: int
    accepted: bool
    reason: str = ""
    coverage: float = float("nan")
    correction_mm: float = float("nan")
    d2: float = float("nan")
    moved_mm: float = 0.0
    source: str = "model"

    def as_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def rotation_deg(T: np.ndarray) -> float:
    """The rotation angle of the ``(4, 4)`` transform ``T``, degrees."""
    c = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


class LoopClosure:
    """The pose graph of one sequence and the frames tied to it.

    Args:
        config: the ``graph`` section.
        first_pose: ``(4, 4)`` ``T_wc`` of the first frame (graph keyframe 0).
        first_position: the first frame's sequence position.
    """

    def __init__(self, config: GraphConfig, first_pose: np.ndarray, first_position: int = 0):
        self.config = config
        self.graph = PoseGraph(first_pose)
        self.keyframe_positions = [int(first_position)]
        self.frames: dict[int, tuple[int, np.ndarray]] = {int(first_position): (0, np.eye(4))}
        self.last_pose = np.asarray(first_pose, dtype=np.float64).copy()
        self._edge = (np.eye(4), np.zeros((6, 6)))    # odometry since the last graph keyframe
        self._candidate = self.last_pose.copy()         # the pose of the last keyframe candidate
        self.events: list[LoopEvent] = []
        self.culled = 0

    # ------------------------------------------------------------------ steps 1-2
    def add_frame(self, position: int, pose: np.ndarray, covariance: Optional[np.ndarray],
                  may_be_keyframe: bool = True) -> bool:
        """Add the tracked frame at ``position`` with its ``pose`` and the ``(6, 6)`` covariance of
        its motion from the last frame (left perturbation, translation first; None: unknown);
        returns whether it became a graph keyframe (never where not ``may_be_keyframe``: a pose
        that is not trusted)."""
        pose = np.asarray(pose, dtype=np.float64)
        motion = np.linalg.inv(self.last_pose) @ pose
        cov = UNKNOWN_MOTION_COVARIANCE if covariance is None else covariance
        self._edge = compose(*self._edge, motion, to_gtsam_covariance(motion, cov))
        self.last_pose = pose.copy()
        k = len(self.graph) - 1
        if not (may_be_keyframe and self._apart(self._candidate, pose)):
            self.frames[int(position)] = (k, np.linalg.inv(self.graph.poses[k]) @ pose)
            return False
        self._candidate = pose.copy()
        k = self.graph.add_keyframe(pose, *self._edge)
        self._edge = (np.eye(4), np.zeros((6, 6)))
        self.keyframe_positions.append(int(position))
        self.frames[int(position)] = (k, np.eye(4))
        return True

    def _apart(self, A: np.ndarray, B: np.ndarray) -> bool:
        """Whether the poses ``A`` and ``B`` are ``graph.keyframe_mm`` or ``graph.keyframe_deg`` apart."""
        d = np.linalg.inv(A) @ B
        return bool(np.linalg.norm(d[:3, 3]) >= self.config.keyframe_mm or rotation_deg(d) >= self.config.keyframe_deg)

    def cull(self, position: int) -> bool:
        """Step 6, after the loop detection at the new keyframe at ``position``: take it out of
        the graph if it has no loop edge and an older keyframe (at least
        :data:`LOOP_MIN_KEYFRAME_GAP` before it) holds its pose; returns whether it was culled."""
        k = len(self.graph) - 1
        if k == 0 or self.keyframe_positions[k] != int(position):
            return False
        if any(k in edge for edge in self.graph.loop_edges()):
            return False
        pose = self.graph.poses[k]
        if all(self._apart(self.graph.poses[j], pose) for j in range(k - LOOP_MIN_KEYFRAME_GAP + 1)):
            return False
        self._edge = self.graph.remove_last_keyframe()
        self.keyframe_positions.pop()
        self.frames[int(position)] = (k - 1, np.linalg.inv(self.graph.poses[k - 1]) @ pose)
        self.culled += 1
        return True

    def active_from(self, position: int) -> Optional[int]:
        """The first frame whose surfels are active at ``position`` (None: all of them)."""
        start = position - self.config.inactive_after
        return start if start > 0 else None

    def keyframe_of(self, position: int) -> int:
        """The graph keyframe of the frame at ``position`` (of the nearest earlier frame known)."""
        known = [p for p in self.frames if p <= position]
        return self.frames[max(known)][0] if known else 0

    # ------------------------------------------------------------------ steps 3-4
    @staticmethod
    def verify(failed: bool, support: float, covariance: Optional[np.ndarray], plane_mm: float,
               max_sigma_mm: float = LOOP_MAX_SIGMA_MM) -> str:
        """Why a registration against the inactive model is not a loop ('' where it is one);
        ``max_sigma_mm``: the largest spread of the translation taken (a loop's by default)."""
        if failed:
            return "the registration failed"
        if covariance is None:
            return "the registration has no covariance"
        if not support >= LOOP_MIN_SUPPORT:
            return f"support {support:.2f} < {LOOP_MIN_SUPPORT}"
        sigma_t = float(np.sqrt(max(np.trace(covariance[:3, :3]), 0.0)))
        if sigma_t > max_sigma_mm:
            return f"uncertain (sigma_t {sigma_t:.2f} mm)"
        if not plane_mm <= LOOP_MAX_PLANE_MM:
            return f"the depth lies {plane_mm:.2f} mm off the reference's surface"
        return ""

    def propose(self, position: int, anchor_frame: int, relative: np.ndarray,
                covariance: Optional[np.ndarray], reason: str = "", coverage: float = float("nan"),
                rendered_at: Optional[np.ndarray] = None) -> LoopEvent:
        """A loop candidate at the keyframe frame ``position``: its registration ``relative``
        (current camera -> the inactive model's view rendered at ``rendered_at``, ``T_wc``; None:
        at the frame's tracked pose) with its covariance (left perturbation, translation first),
        against the surfels last fused at ``anchor_frame``; ``reason``: why verification rejected
        it ('' where it passed)."""
        i = self.frames[int(position)][0]
        j = self.keyframe_of(anchor_frame)
        seen_at = self.graph.poses[i] if rendered_at is None else np.asarray(rendered_at, dtype=np.float64)
        event = LoopEvent(int(position), i, j, self.keyframe_positions[j], False, reason, coverage,
                          float(np.linalg.norm((np.linalg.inv(self.graph.poses[i]) @ seen_at @ relative)[:3, 3])),
                          source="model" if rendered_at is None else "appearance")
        if not reason and i - j < LOOP_MIN_KEYFRAME_GAP:
            event.reason = f"the surfels in view are {i - j} keyframe(s) old"
        if not event.reason:
            pose = self.graph.poses[i]
            measured = np.linalg.inv(self.graph.poses[j]) @ seen_at @ relative
            outcome = self.graph.propose_loop(j, i, measured, to_gtsam_covariance(relative, covariance))
            event.d2, event.accepted, event.reason = outcome.d2, outcome.accepted, outcome.reason
            if outcome.accepted:
                event.moved_mm = float(np.linalg.norm(self.graph.poses[i][:3, 3] - pose[:3, 3]))
        self.events.append(event)
        (log.info if event.accepted else log.debug)(
            "loop candidate at frame %d (keyframe %d -> %d, frame %d): %s", position, j, i, event.anchor_position,
            "accepted" if event.accepted else f"rejected, {event.reason}")
        return event

    # ------------------------------------------------------------------ step 5
    def corrections(self, old_poses: list[np.ndarray]) -> np.ndarray:
        """``(F, 4, 4)`` per-frame corrections ``T_new T_old^-1`` (frames 0 .. the last known
        position) from the keyframe poses ``old_poses`` before the optimisation to the graph's
        now; a frame's correction is its keyframe's."""
        per_keyframe = np.stack([T @ np.linalg.inv(T_old) for T, T_old in zip(self.graph.poses, old_poses)])
        n = max(self.frames) + 1
        out = np.tile(np.eye(4), (n, 1, 1))
        for p, (k, _) in self.frames.items():
            out[p] = per_keyframe[k]
        # frames the tracker never saw (unreadable) move with the frame before them
        for p in range(1, n):
            if p not in self.frames:
                out[p] = out[p - 1]
        return out

    def adopt_optimised(self, position: int) -> np.ndarray:
        """After an accepted loop at the keyframe frame ``position``: its optimised pose, from
        which the next frames' motion is taken."""
        self.last_pose = self.pose(position)
        self._candidate = self.last_pose.copy()
        return self.last_pose.copy()

    def pose(self, position: int) -> np.ndarray:
        """The current (optimised) ``T_wc`` of the tracked frame at ``position``."""
        k, rel = self.frames[int(position)]
        return self.graph.poses[k] @ rel

    def correct(self, position: int, pose: np.ndarray) -> None:
        """A frame's pose corrected outside the graph (a repaired stretch): held against its
        graph keyframe, so that the graph's optimisations move it from there. (A keyframe's own
        pose is the graph's; a stretch holds none, its frames being untrusted.)"""
        k, rel = self.frames.get(int(position), (None, None))
        if k is not None and not np.allclose(rel, np.eye(4)):
            self.frames[int(position)] = (k, np.linalg.inv(self.graph.poses[k]) @ np.asarray(pose, np.float64))

    def optimised_poses(self, positions: range) -> np.ndarray:
        """``(N, 4, 4)`` optimised ``T_wc`` of ``positions``; a frame the tracker never saw takes
        the frame before it's (or the first frame's)."""
        out, last = [], self.graph.poses[0]
        for p in positions:
            if p in self.frames:
                last = self.pose(p)
            out.append(last)
        return np.stack(out) if out else np.zeros((0, 4, 4))

    def summary(self, frames: int, ms_total: float) -> dict:
        """The ``metrics.json`` section: keyframes, loop edges, candidates and the cost per frame."""
        return {"keyframes": len(self.graph), "culled": self.culled, "loop_edges": len(self.graph.loops),
                "candidates": len(self.events), "accepted": sum(e.accepted for e in self.events),
                "rejected": sum(not e.accepted for e in self.events),
                "ms_per_frame": ms_total / max(frames, 1),
                "events": [e.as_dict() for e in self.events]}
