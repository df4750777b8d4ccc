"""Frame2model's pose graph on GTSAM: graph keyframes, odometry and loop edges, optimised with
graduated non-convexity so that a false loop is dropped before it bends the graph.

Conventions. Poses are ``(4, 4)`` ``T_wc`` in mm. The tracker's covariances are of a relative
pose ``T`` as a *left* perturbation ``exp(xi) T`` with the translation first (mm, rad); GTSAM's
``Pose3`` takes a *right* perturbation ``T exp(xi')`` with the rotation first. To first order
``exp(xi) T = T exp(Ad(T^-1) xi)``, so the covariance becomes ``Ad(T^-1) Sigma Ad(T^-1)^T`` in
the translation-first order and is then re-ordered (:func:`to_gtsam_covariance`). Composing
``T = A B`` (right perturbations): ``Sigma_T = Ad(B^-1) Sigma_A Ad(B^-1)^T + Sigma_B``
(:func:`compose`).

A loop edge is accepted in two steps:

1. a gate: the squared Mahalanobis distance of the loop's measurement from the graph's
   prediction of it, under the loop's covariance plus the odometry chain's between the two
   keyframes, within the 99.9 % chi-square bound of 6 dof (:data:`LOOP_GATE_D2`). The chain's,
   not the graph's marginal: once a wrong loop were in, the marginal would be tight around it
   and the gate would turn the true loops away (measured in ``tests/test_pose_graph.py``);
2. GTSAM's graduated non-convexity optimiser (truncated least squares, the odometry edges known
   inliers) over every loop edge: a loop whose weight ends below one half is an outlier and is
   taken out of the graph, the new one (which then leaves the poses as they were) or an earlier
   one that the loops since contradict.
"""
from __future__ import annotations

from dataclasses import dataclass
import gtsam
import numpy as np

# the gate on a loop's measurement against the graph's prediction: the 99.9 % chi-square bound of
# 6 dof (a calibrated covariance puts 1 in 1000 true loops outside it)
LOOP_GATE_D2 = 22.46
# GNC's inlier threshold, as the probability of the chi-square bound of a factor's dimension
GNC_INLIER_PROBABILITY = 0.999
# a loop whose GNC weight ends below this is an outlier
GNC_MIN_WEIGHT = 0.5
# the first keyframe's prior (mm, rad): fixes the gauge, far tighter than any edge
PRIOR_SIGMA = 1e-6
# the translation-first tangent order's re-ordering into GTSAM's rotation-first one
_ROT_FIRST = np.array([3, 4, 5, 0, 1, 2])


def adjoint(T: np.ndarray) -> np.ndarray:
    """``(6, 6)`` adjoint of the ``(4, 4)`` rigid transform ``T`` in the translation-first order:
    ``[[R, [t]x R], [0, R]]``."""
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[:3, 3:] = tx @ R
    A[3:, 3:] = R
    return A


def to_gtsam_covariance(T: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """The ``(6, 6)`` covariance of the relative pose ``T`` (left perturbation, translation first,
    mm and rad) in GTSAM's ``Pose3`` convention (right perturbation, rotation first)."""
    A = adjoint(np.linalg.inv(T))
    right = A @ covariance @ A.T
    return symmetric(right[np.ix_(_ROT_FIRST, _ROT_FIRST)])


def symmetric(C: np.ndarray) -> np.ndarray:
    """``C`` made exactly symmetric (GTSAM's Gaussian model factorises it)."""
    return 0.5 * (C + C.T)


def compose(A: np.ndarray, cov_A: np.ndarray, B: np.ndarray, cov_B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``A @ B`` and its covariance from ``A``'s and ``B``'s (independent; GTSAM's convention)."""
    Ad = gtsam.Pose3(np.linalg.inv(B)).AdjointMap()
    return A @ B, symmetric(Ad @ cov_A @ Ad.T + cov_B)


def log_error(measured: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """``(6,)`` GTSAM tangent (rotation first) of ``predicted^-1 measured``."""
    return np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(np.linalg.inv(predicted) @ measured))).ravel()


@dataclass
class LoopOutcome:
    """What the graph made of a proposed loop edge.

    Attributes:
        accepted: the edge stands in the graph and the poses were optimised with it.
        d2: squared Mahalanobis distance of the measurement from the graph's prediction.
        weight: GNC's final weight of the edge (nan where the gate rejected it first).
        reason: why it was rejected ('' when accepted).
    """

    accepted: bool
    d2: float
    weight: float = float("nan")
    reason: str = ""


class PoseGraph:
    """Keyframe poses joined by odometry edges (consecutive keyframes) and loop edges.

    Args:
        first_pose: ``(4, 4)`` ``T_wc`` of keyframe 0 (held by a tight prior: the gauge).
    """

    def __init__(self, first_pose: np.ndarray):
        self.poses: list[np.ndarray] = [np.asarray(first_pose, dtype=np.float64).copy()]
        # odometry edge k joins keyframes k and k + 1: its measurement and covariance (GTSAM's)
        self.odometry: list[tuple[np.ndarray, np.ndarray]] = []
        # the accepted loop edges: (i, j, measurement, covariance)
        self.loops: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        self.dropped = 0        # accepted loops a later one showed to be outliers

    def __len__(self) -> int:
        return len(self.poses)

    def add_keyframe(self, pose: np.ndarray, relative: np.ndarray, covariance: np.ndarray) -> int:
        """Add a keyframe at ``pose`` (``T_wc``) joined to the last one by the odometry edge
        ``relative`` (last keyframe -> new one) with its ``(6, 6)`` GTSAM-convention covariance;
        returns its id."""
        self.odometry.append((np.asarray(relative, dtype=np.float64).copy(), symmetric(covariance)))
        self.poses.append(np.asarray(pose, dtype=np.float64).copy())
        return len(self.poses) - 1

    def remove_last_keyframe(self) -> tuple[np.ndarray, np.ndarray]:
        """Take the newest keyframe out of the graph (it must have no loop edge); returns its
        odometry edge ``(relative, covariance)`` from the keyframe before it."""
        k = len(self.poses) - 1
        if k == 0 or any(k in (i, j) for i, j, _, _ in self.loops):
            raise ValueError(f"keyframe {k} is the first one or has a loop edge: it stays")
        self.poses.pop()
        return self.odometry.pop()

    def chain_covariance(self, i: int, j: int) -> np.ndarray:
        """The covariance of keyframe ``j`` relative to ``i < j`` along the odometry chain alone
        (GTSAM's convention): the drift the loop may have to undo."""
        T, C = np.eye(4), np.zeros((6, 6))
        for k in range(i, j):
            T, C = compose(T, C, *self.odometry[k])
        return C

    def propose_loop(self, i: int, j: int, measured: np.ndarray, covariance: np.ndarray) -> LoopOutcome:
        """Propose the loop edge ``measured`` = pose of keyframe ``j`` relative to keyframe
        ``i < j`` with its GTSAM-convention ``covariance``; the gate, then GNC (see the module's
        docstring). An accepted edge stays and the poses are re-optimised; a rejected one leaves
        the graph and the poses as they were."""
        if not 0 <= i < j < len(self.poses):
            raise ValueError(f"loop edge {i} -> {j} outside the graph's {len(self.poses)} keyframes")
        predicted = np.linalg.inv(self.poses[i]) @ self.poses[j]
        e = log_error(measured, predicted)
        S = symmetric(covariance + self.chain_covariance(i, j))
        d2 = float(e @ np.linalg.solve(S, e))
        if not np.isfinite(d2) or d2 > LOOP_GATE_D2:
            return LoopOutcome(False, d2, reason=f"inconsistent with the odometry (d2 {d2:.1f} > {LOOP_GATE_D2:.1f})")
        self.loops.append((i, j, np.asarray(measured, dtype=np.float64).copy(), symmetric(covariance)))
        weights, poses = self._optimise()
        loop_weights = weights[len(weights) - len(self.loops):]
        weight = float(loop_weights[-1])
        if weight < GNC_MIN_WEIGHT:
            self.loops.pop()
            return LoopOutcome(False, d2, weight, reason=f"an outlier to the graph (GNC weight {weight:.2f})")
        if (loop_weights < GNC_MIN_WEIGHT).any():     # earlier loops the new one contradicts: out, and again
            self.loops = [edge for edge, w in zip(self.loops, loop_weights) if w >= GNC_MIN_WEIGHT]
            self.dropped += int((loop_weights < GNC_MIN_WEIGHT).sum())
            _, poses = self._optimise()
        self.poses = poses
        return LoopOutcome(True, d2, weight)

    def _graph(self) -> gtsam.NonlinearFactorGraph:
        """The factor graph: the prior on keyframe 0, the odometry edges, then the loop edges."""
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(self.poses[0]), gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)))
        for k, (Z, C) in enumerate(self.odometry):
            graph.add(gtsam.BetweenFactorPose3(k, k + 1, gtsam.Pose3(Z), gtsam.noiseModel.Gaussian.Covariance(C)))
        for i, j, Z, C in self.loops:
            graph.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(Z), gtsam.noiseModel.Gaussian.Covariance(C)))
        return graph

    def _optimise(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """GNC over the whole graph from the current poses: the factors' final weights (in the
        order of :meth:`_graph`) and the optimised poses."""
        values = gtsam.Values()
        for k, T in enumerate(self.poses):
            values.insert(k, gtsam.Pose3(T))
        params = gtsam.GncLMParams()
        params.setKnownInliers(list(range(1 + len(self.odometry))))
        optimiser = gtsam.GncLMOptimizer(self._graph(), values, params)
        optimiser.setInlierCostThresholdsAtProbability(GNC_INLIER_PROBABILITY)
        result = optimiser.optimize()
        weights = np.asarray(optimiser.getWeights()).ravel()
        return weights, [result.atPose3(k).matrix() for k in range(len(self.poses))]

    def loop_edges(self) -> list[tuple[int, int]]:
        """The ``(i, j)`` keyframe pairs of the accepted loop edges."""
        return [(i, j) for i, j, _, _ in self.loops]

