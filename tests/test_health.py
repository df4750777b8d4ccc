"""Tracking health: the pose fit's covariance, the running residual figures, tracking.csv."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from slam.config import HealthConfig
from slam.tracking.health import HealthMonitor, health_summary, nees, relative_error
from vo.config import SolverConfig
from vo.health import PoseFit, pose_fit, weighted_median
from vo.lie import se3_exp, se3_log
from vo.odometry import TrackResult
from vo.residuals import PoseProblem
from vo.solver import solve_pose

DMAX = 200.0


def _problem(rng: np.random.Generator, T_true: torch.Tensor, sigma_mm: float, n: int = 3000) -> PoseProblem:
    """3D residuals only: reference points = T_true X + Gaussian noise of sigma_mm per axis."""
    X = np.stack([rng.uniform(-30, 30, n), rng.uniform(-25, 25, n), rng.uniform(50, 90, n)], 0) / DMAX
    X = torch.from_numpy(X).float()[None]
    Y = T_true[:, :3, :3] @ X + T_true[:, :3, 3:4]
    ref = Y + torch.from_numpy(rng.normal(0, sigma_mm / DMAX, Y.shape)).float()
    K = torch.tensor([[[300.0, 0, 160], [0, 300.0, 128], [0, 0, 1]]])
    s2, s3 = PoseProblem.scales(256, 320)
    target = torch.zeros(1, 2, n)
    return PoseProblem(points_cur=X, target_px=target, points_ref=ref, w2d=torch.zeros(1, n), w3d=torch.ones(1, n),
                       K=K, s2=s2, s3=s3)


def test_the_textbook_covariance_matches_the_spread_of_solved_poses():
    """Independent noise of known sigma: s = 1 must predict the poses' scatter (mm and rad)."""
    rng = np.random.default_rng(0)
    p_true = torch.tensor([[0.5 / DMAX, -0.3 / DMAX, 0.2 / DMAX, 0.01, -0.02, 0.005]], dtype=torch.float64)
    T_true = se3_exp(p_true).float()
    errors, covs = [], []
    for _ in range(150):
        prob = _problem(rng, T_true, sigma_mm=0.5)
        result = solve_pose(prob, SolverConfig())
        fit = pose_fit(prob, result.T, DMAX)
        T_est_mm, T_true_mm = result.T[0].double().clone(), T_true[0].double().clone()
        T_est_mm[:3, 3] *= DMAX
        T_true_mm[:3, 3] *= DMAX
        errors.append(relative_error(T_est_mm.numpy(), T_true_mm.numpy()))
        covs.append(fit.covariance(1.0))
    errors = np.array(errors)
    predicted = np.mean(covs, axis=0)
    ratio = errors.var(axis=0) / np.diag(predicted)
    assert np.all((ratio > 0.6) & (ratio < 1.6)), ratio
    mean_nees = np.mean([nees(e, c) for e, c in zip(errors, covs)])
    assert 4.5 < mean_nees < 7.5


def test_the_fit_reports_residuals_in_pixels_and_mm():
    rng = np.random.default_rng(1)
    T = torch.eye(4)[None]
    prob = _problem(rng, T, sigma_mm=0.3)
    fit = pose_fit(prob, T, DMAX)
    # |N(0, 0.3^2 I_3)| has median 0.3 * sqrt(chi2_3 median = 2.366)
    assert fit.residual_3d_mm == pytest.approx(0.3 * math.sqrt(2.366), rel=0.06)
    assert math.isnan(fit.residual_2d_px)          # no 2D weights
    assert fit.sigma2 > 0 and fit.hessian.shape == (6, 6)
    assert np.allclose(fit.hessian, fit.hessian.T)


def test_weighted_median():
    v = torch.tensor([1.0, 2.0, 3.0, 100.0])
    assert weighted_median(v, torch.tensor([1.0, 1.0, 1.0, 0.0])) == 2.0
    assert weighted_median(v, torch.tensor([0.0, 0.0, 1.0, 5.0])) == 100.0
    assert math.isnan(weighted_median(v, torch.zeros(4)))


def test_weighted_median_of_many_values_is_the_sorted_one():
    # above MEDIAN_SORT_MAX values the median is narrowed down by histogram passes: the same element
    rng = np.random.default_rng(3)
    for n, draw in [(50_000, lambda n: rng.exponential(size=n)), (300_000, lambda n: rng.standard_cauchy(n)),
                    (100_000, lambda n: rng.integers(0, 4, n))]:
        v = torch.tensor(np.asarray(draw(n), dtype=np.float32))
        w = torch.tensor((rng.random(n) * (rng.random(n) > 0.3)).astype(np.float32))
        keep = w.numpy() > 0
        vs, ws = v.numpy()[keep], w.numpy()[keep]
        order = np.argsort(vs, kind="stable")
        cw = np.cumsum(ws[order], dtype=np.float64)
        assert weighted_median(v, w) == vs[order][np.searchsorted(cw, 0.5 * cw[-1])]


def _track(r2: float, r3: float, failed: bool = False) -> TrackResult:
    fit = PoseFit(residual_2d_px=r2, residual_3d_mm=r3, hessian=np.eye(6) * 4.0, sigma2=2.0)
    z = torch.zeros(1, 1, 2, 2)
    return TrackResult(relative=np.eye(4), failed=failed, reason="x" if failed else "", iterations=3, cost=1.0,
                       valid_pixels=900, flow=z, w2d=z, w3d=z, timings_ms={}, fit=fit, support=0.9)


def test_residuals_are_compared_with_the_running_median_of_good_frames():
    monitor = HealthMonitor(HealthConfig(covariance_scale_frame=3.0, covariance_scale_model=5.0))
    first, cov = monitor.assess(_track(0.1, 0.2), against_model=False)
    assert math.isnan(first["residual_2d_ratio"])
    np.testing.assert_allclose(cov, np.eye(6) * 3.0 * 2.0 / 4.0)
    for _ in range(5):
        monitor.assess(_track(0.1, 0.2), against_model=False)
    figures, cov = monitor.assess(_track(0.4, 0.2, failed=True), against_model=True)
    assert figures["residual_2d_ratio"] == pytest.approx(4.0) and figures["residual_3d_ratio"] == pytest.approx(1.0)
    np.testing.assert_allclose(cov, np.eye(6) * 5.0 * 2.0 / 4.0)
    assert figures["sigma_t_mm"] == pytest.approx(math.sqrt(3 * 2.5))
    # a failed frame does not enter the history
    again, _ = monitor.assess(_track(0.1, 0.2), against_model=False)
    assert again["residual_2d_ratio"] == pytest.approx(1.0)


def test_relative_error_and_nees():
    T = se3_exp(torch.tensor([[1.0, 0.0, 0.0, 0.0, 0.0, 0.1]], dtype=torch.float64))[0].numpy()
    np.testing.assert_allclose(relative_error(T, T), 0.0, atol=1e-12)
    e = relative_error(T, np.eye(4))
    np.testing.assert_allclose(e, se3_log(torch.from_numpy(T)[None])[0].numpy())
    assert nees(np.ones(6), np.eye(6) * 2.0) == pytest.approx(3.0)
    summary = health_summary([{"nees": 4.0, "support": 0.5}, {"nees": 8.0, "support": 0.7}, {}])
    assert summary["nees_mean"] == 6.0 and summary["nees_frames"] == 2 and summary["support_median"] == 0.6


def metrics_timing(run, stage: str) -> float:
    return json.loads((run / "metrics.json").read_text())["timings_ms"][stage]


def test_a_run_writes_tracking_csv_and_its_summary(tmp_path):
    from slam.config import load_config
    from slam.app.runner import run_from_config
    from slam.synth import generate
    from slam.app.tracking_csv import COLUMNS, read_tracking_csv

    data = generate(tmp_path / "seq", "rigid", frames=8, size=(96, 80), seed=9601)
    cfg = load_config(None, ["tracking.mode=frame2model", "threads=1",
                             "analysis.round_trip=true"])
    res = run_from_config(data, cfg, tmp_path / "run", print_summary=False)
    rows = read_tracking_csv(tmp_path / "run" / "tracking.csv")
    assert list(rows) == list(COLUMNS) and len(rows["frame"]) == 8
    assert rows["reference"][0] == "first" and set(rows["reference"][1:]) <= {"model", "previous_frame"}
    np.testing.assert_array_equal(rows["reference_frame"][1:], np.arange(7))
    tracked = rows["failed"][1:] == 0
    assert np.all(np.isfinite(rows["nees"][1:][tracked])) and np.all(rows["sigma_t_mm"][1:][tracked] > 0)
    assert np.all((rows["support"][1:] > 0.5) & (rows["support"][1:] <= 1.0))
    assert np.all((rows["round_trip_px"][1:] >= 0) & (rows["round_trip_px"][1:] < 1.0))    # rich texture, small motion
    assert metrics_timing(tmp_path / "run", "flow_back") > 0
    on_model = rows["reference"] == "model"
    assert on_model.any() and np.all(np.isfinite(rows["plane_residual_mm"][on_model]))
    assert np.all((rows["plane_cost_share"][on_model] >= 0) & (rows["plane_cost_share"][on_model] <= 1))
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["health"]["nees_frames"] == int(tracked.sum())
    assert metrics["health"] == res.metrics["health"]


def _bowl(H: int = 96, W: int = 128, f: float = 120.0):
    """Depth of a curved surface (a bowl 60 mm away) seen by a pinhole camera, and its K."""
    K = torch.tensor([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    x, y = (u - W / 2) / f, (v - H / 2) / f
    depth = 60.0 + 40.0 * (x ** 2 + y ** 2)
    return depth[None, None], torch.ones(1, 1, H, W, dtype=torch.bool), K


def test_the_point_to_plane_check_sees_a_pose_off_the_surface():
    from vo.geometric_check import point_to_plane_check

    depth, valid, K = _bowl()
    exact = point_to_plane_check(depth, valid, depth, valid, K, np.eye(4))
    assert exact.residual_mm < 1e-3 and exact.cost_share < 1e-3
    off = np.eye(4)
    off[2, 3] = 0.5                      # 0.5 mm along the view: the surface's normal direction
    moved = point_to_plane_check(depth, valid, depth, valid, K, off)
    assert 0.3 < moved.residual_mm < 0.55
    assert moved.cost_share > 0.9        # one rigid correction explains it
    noise = torch.from_numpy(np.random.default_rng(0).normal(0, 0.2, depth.shape)).float()
    noisy = point_to_plane_check(depth + noise, valid, depth, valid, K, np.eye(4))
    assert noisy.cost_share < 0.05       # noise is not a pose error
    assert point_to_plane_check(depth, valid & False, depth, valid, K, np.eye(4)) is None
