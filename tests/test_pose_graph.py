"""The pose graph (slam.tracking.pose_graph): GTSAM's conventions, loop edges, false loops rejected."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from slam.tracking.pose_graph import PoseGraph, compose, log_error, to_gtsam_covariance
from vo.lie import se3_exp


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _sample_covariance(T: np.ndarray, cov_left: np.ndarray, n: int, rng) -> np.ndarray:
    """Empirical GTSAM-convention covariance of ``exp(xi) T`` with ``xi ~ N(0, cov_left)``."""
    xi = rng.multivariate_normal(np.zeros(6), cov_left, size=n)
    samples = se3_exp(torch.from_numpy(xi)).numpy() @ T
    return np.cov(np.stack([log_error(S, T) for S in samples]).T)


def test_covariance_conversion_matches_sampling():
    rng = np.random.default_rng(0)
    T = _pose([0.1, -0.2, 0.3], [5.0, -3.0, 2.0])
    L = rng.normal(size=(6, 6))
    cov = L @ L.T * 1e-3
    expected = to_gtsam_covariance(T, cov)
    got = _sample_covariance(T, cov, 20000, rng)
    assert np.abs(got - expected).max() < 0.03 * np.abs(expected).max()
    # rotation first: GTSAM's rotation block is our rotation block rotated into the body frame
    R = T[:3, :3]
    assert np.allclose(expected[:3, :3], R.T @ cov[3:, 3:] @ R)


def test_composition_matches_sampling():
    rng = np.random.default_rng(1)
    A, B = _pose([0.2, 0.0, 0.1], [3.0, 1.0, 0.0]), _pose([0.0, -0.3, 0.2], [-2.0, 4.0, 1.0])
    cA, cB = np.diag([1e-2, 2e-2, 1e-2, 1e-3, 2e-3, 1e-3]), np.diag([3e-2, 1e-2, 1e-2, 2e-3, 1e-3, 1e-3])
    AB, cAB = compose(A, to_gtsam_covariance(A, cA), B, to_gtsam_covariance(B, cB))
    xa = se3_exp(torch.from_numpy(rng.multivariate_normal(np.zeros(6), cA, 20000))).numpy()
    xb = se3_exp(torch.from_numpy(rng.multivariate_normal(np.zeros(6), cB, 20000))).numpy()
    got = np.cov(np.stack([log_error((a @ A) @ (b @ B), AB) for a, b in zip(xa, xb)]).T)
    assert np.allclose(AB, A @ B)
    assert np.abs(got - cAB).max() < 0.05 * np.abs(cAB).max()


def _drifting_chain(rng, n=40, sigma_mm=0.1):
    """A circle of ``n`` steps tracked with noisy steps: (graph, true poses)."""
    step = _pose([0.0, 0.0, 2 * np.pi / n], [2.0, 0.0, 0.0])
    cov = np.diag([1e-4] * 3 + [sigma_mm ** 2] * 3)       # GTSAM's order: rotation first
    graph, truth, est = PoseGraph(np.eye(4)), [np.eye(4)], np.eye(4)
    for _ in range(n):
        truth.append(truth[-1] @ step)
        noisy = step.copy()
        noisy[:3, 3] += rng.normal(0.0, sigma_mm, 3)
        noisy[:3, :3] = noisy[:3, :3] @ Rotation.from_rotvec(rng.normal(0.0, 0.01, 3)).as_matrix()
        est = est @ noisy
        graph.add_keyframe(est, noisy, cov)
    return graph, truth


def _errors(graph, truth) -> np.ndarray:
    return np.array([np.linalg.norm(P[:3, 3] - T[:3, 3]) for P, T in zip(graph.poses, truth)])


def test_a_true_loop_undoes_the_drift():
    graph, truth = _drifting_chain(np.random.default_rng(2))
    drift = _errors(graph, truth)
    assert drift[-1] > 0.5
    tight = np.diag([1e-6] * 3 + [1e-4] * 3)
    outcome = graph.propose_loop(0, 40, np.linalg.inv(truth[0]) @ truth[40], tight)
    assert outcome.accepted and outcome.d2 < 22.5 and outcome.weight > 0.9
    after = _errors(graph, truth)
    assert after[-1] < 0.05 * drift[-1]
    assert after.mean() < 0.5 * drift.mean()
    assert graph.loop_edges() == [(0, 40)]


def test_a_false_loop_with_a_confident_covariance_is_rejected():
    graph, truth = _drifting_chain(np.random.default_rng(3))
    before = [P.copy() for P in graph.poses]
    wrong = np.linalg.inv(truth[10]) @ truth[40]
    wrong[:3, 3] += [8.0, -5.0, 0.0]                            # a different place
    outcome = graph.propose_loop(10, 40, wrong, np.diag([1e-6] * 3 + [1e-4] * 3))
    assert not outcome.accepted and "odometry" in outcome.reason
    assert all(np.array_equal(P, Q) for P, Q in zip(before, graph.poses))
    assert graph.loop_edges() == []


def test_gnc_drops_a_loop_the_loops_after_it_contradict():
    """A wrong loop the odometry's wide drift cannot rule out passes the gate; once true loops
    tie the graph, GNC finds it an outlier, takes it out and the poses follow the true loops."""
    clean, truth = _drifting_chain(np.random.default_rng(4), sigma_mm=0.3)
    graph, _ = _drifting_chain(np.random.default_rng(4), sigma_mm=0.3)
    tight = np.diag([1e-6] * 3 + [1e-4] * 3)
    chain = graph.chain_covariance(0, 20)
    wrong = np.linalg.inv(graph.poses[0]) @ graph.poses[20]     # where the odometry puts it ...
    wrong[:3, 3] += 2.0 * np.sqrt(np.diag(chain)[3:])          # ... moved 2 sigma of its drift per axis
    first = graph.propose_loop(0, 20, wrong, tight)
    assert first.accepted and first.d2 < 22.5
    for i, j in ((0, 40), (10, 30), (20, 40)):
        true_loop = np.linalg.inv(truth[i]) @ truth[j]
        assert graph.propose_loop(i, j, true_loop, tight).accepted
        assert clean.propose_loop(i, j, true_loop, tight).accepted
    assert graph.dropped == 1 and (0, 20) not in graph.loop_edges()
    # the trajectory is the one the true loops alone give
    assert max(np.linalg.norm(P[:3, 3] - Q[:3, 3]) for P, Q in zip(graph.poses, clean.poses)) < 1e-3


def test_loop_outside_the_graph_is_an_error():
    graph = PoseGraph(np.eye(4))
    with pytest.raises(ValueError, match="outside"):
        graph.propose_loop(0, 1, np.eye(4), np.eye(6))


def _circle_pose(s: float) -> np.ndarray:
    """A camera on a 20 mm circle at arc length ``s`` mm, looking along -z with a small wobble."""
    a = s / 20.0
    return _pose([0.05 * np.sin(a), 0.05 * np.cos(a), 0.0], [20.0 * np.cos(a), 20.0 * np.sin(a), 0.0])


def test_keyframes_culled_on_a_camera_circling_the_same_place():
    from slam.config import GraphConfig
    from slam.tracking.loop_closure import LoopClosure

    per_lap = 2 * np.pi * 20.0
    steps = np.arange(0.0, 3 * per_lap, 0.5)        # three laps, 0.5 mm per frame
    poses = [_circle_pose(s) for s in steps]
    lc = LoopClosure(GraphConfig(loop_closure=True, keyframe_mm=5.0, keyframe_deg=5.0), poses[0], 0)
    cov = np.diag([0.01] * 3 + [1e-5] * 3)
    lap_end = int(per_lap / 0.5)
    for p in range(1, len(poses)):
        if lc.add_frame(p, poses[p], cov):
            lc.cull(p)
        if p == lap_end:
            after_one_lap = len(lc.graph)
    # the second and third laps add (almost) no keyframe: their views are held by the first's
    assert after_one_lap >= 20
    assert len(lc.graph) <= after_one_lap + 2
    assert lc.culled >= 2 * (after_one_lap - 2)
    # no pose changes without a loop: every frame keeps its tracked pose through the culling
    got = lc.optimised_poses(range(len(poses)))
    assert np.abs(got - np.stack(poses)).max() < 1e-9
    # the odometry chain still composes to the kept keyframes' poses
    T = lc.graph.poses[0]
    for (Z, _), expected in zip(lc.graph.odometry, lc.graph.poses[1:]):
        T = T @ Z
        assert np.abs(T - expected).max() < 1e-8
