"""VO core: Lie maps, residual Jacobians, the pose solver, depth from parallax."""
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vo.config import DepthConfig, SolverConfig
from vo.depth import depth_from_parallax, flow_consistency, parallax_from_depth
from vo.geometry import backproject, project, sample_by_flow
from vo.lie import se3_exp, se3_log
from vo.residuals import PoseProblem, jacobians, objective_se3, residuals
from vo.solver import Tolerance, solve_pose

DMAX = 250.0


def make_problem(p_gt: torch.Tensor, H=48, W=64, seed=0, dtype=torch.float64):
    """Exact depth and flow for a smooth surface seen from a known relative pose."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[55.0, 0, W / 2 - 0.5], [0, 55.0, H / 2 - 0.5], [0, 0, 1]], dtype=dtype)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    depth = 80 + 8 * torch.sin(xs / 9) * torch.cos(ys / 7) + 2 * torch.rand(H, W, generator=g, dtype=dtype)
    P = backproject(depth[None, None], K) / DMAX
    T = se3_exp(p_gt)
    Y = T[:, :3, :3] @ P.flatten(2) + T[:, :3, 3:]
    target = project(Y, K)
    s2, s3 = PoseProblem.scales(H, W)
    ones = torch.ones(1, H * W, dtype=dtype)
    return PoseProblem(P.flatten(2), target, Y.clone(), ones, ones.clone(), K[None], s2, s3)


def p_from_mm_rad(t_mm, r_rad):
    return torch.tensor([[*(np.asarray(t_mm) / DMAX), *r_rad]], dtype=torch.float64)


def pose_errors(p_est, p_gt):
    """(rotation error rad, translation error mm) between two tangent vectors."""
    T1, T2 = se3_exp(p_est.double()), se3_exp(p_gt.double())
    E = torch.linalg.inv(T2) @ T1
    rot = Rotation.from_matrix(E[0, :3, :3].numpy()).magnitude()
    return rot, float(E[0, :3, 3].norm()) * DMAX


def test_exp_log_round_trip():
    torch.manual_seed(0)
    p = torch.randn(64, 6, dtype=torch.float64) * torch.tensor([0.05] * 3 + [0.3] * 3, dtype=torch.float64)
    p[0] = 0  # identity
    p[1, 3:] = torch.tensor([1e-9, 0, 0])  # tiny rotation
    T = se3_exp(p)
    assert torch.allclose(se3_log(T), p, atol=1e-10)
    R = T[:, :3, :3].numpy()
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    # rotation part agrees with scipy's rotation vector
    assert np.allclose(Rotation.from_matrix(R).as_rotvec(), p[:, 3:].numpy(), atol=1e-10)
    T2 = se3_exp(se3_log(T))
    assert torch.allclose(T2, T, atol=1e-12)


def test_analytic_jacobians_match_autograd():
    p_gt = p_from_mm_rad([0.4, -0.2, 0.7], [0.01, -0.02, 0.005])
    prob = make_problem(p_gt, H=12, W=16)
    T = se3_exp(torch.randn(1, 6, dtype=torch.float64) * 0.01)
    _, _, Y = residuals(T, prob)
    J2, J3 = jacobians(Y, prob)

    def stacked(d):
        e2, e3, _ = residuals(se3_exp(d[None]) @ T, prob)
        return torch.cat([e2[0].T.reshape(-1), e3[0].T.reshape(-1)])

    J = torch.autograd.functional.jacobian(stacked, torch.zeros(6, dtype=torch.float64))
    J_analytic = torch.cat([J2[0].reshape(-1, 6), J3[0].reshape(-1, 6)])
    assert torch.allclose(J, J_analytic, rtol=1e-9, atol=1e-12)


def test_closed_form_normal_equations_match_the_jacobians():
    from vo.solver import normal_equations

    prob = make_problem(p_from_mm_rad([0.4, -0.2, 0.7], [0.01, -0.02, 0.005]), H=20, W=24)
    g = torch.Generator().manual_seed(1)
    prob = prob.with_weights(torch.rand(prob.w2d.shape, generator=g, dtype=torch.float64),
                             torch.rand(prob.w3d.shape, generator=g, dtype=torch.float64))
    T = se3_exp(torch.randn(1, 6, dtype=torch.float64, generator=g) * 0.01)
    e2, e3, Y = residuals(T, prob)
    J2, J3 = jacobians(Y, prob)
    w2, w3 = prob.w2d[0], prob.w3d[0]
    H_ref = torch.einsum("n,nri,nrj->ij", w2, J2[0], J2[0]) + torch.einsum("n,nri,nrj->ij", w3, J3[0], J3[0])
    g_ref = torch.einsum("n,nri,rn->i", w2, J2[0], e2[0]) + torch.einsum("n,nri,rn->i", w3, J3[0], e3[0])
    H, gv, _ = normal_equations(T, prob)
    assert torch.allclose(H[0], H_ref, rtol=1e-10, atol=1e-12)
    assert torch.allclose(gv[0], g_ref, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("method", ["lm", "lbfgs"])
def test_solver_recovers_known_pose(method):
    p_gt = p_from_mm_rad([0.8, -0.5, 1.2], [0.02, -0.015, 0.01])
    prob = make_problem(p_gt)
    res = solve_pose(prob, SolverConfig(method=method))
    rot_err, trans_err = pose_errors(res.p, p_gt)
    assert rot_err < 1e-5 and trans_err < 1e-5, (rot_err, trans_err)


@pytest.mark.parametrize("mode", ["2d", "3d"])
def test_each_residual_alone_recovers_the_pose(mode):
    p_gt = p_from_mm_rad([-0.6, 0.3, 0.4], [-0.01, 0.02, 0.0])
    prob = make_problem(p_gt, seed=1)
    zero = torch.zeros_like(prob.w2d)
    prob = prob.with_weights(prob.w2d if mode == "2d" else zero, prob.w3d if mode == "3d" else zero)
    res = solve_pose(prob, SolverConfig())
    rot_err, trans_err = pose_errors(res.p, p_gt)
    assert rot_err < 1e-5 and trans_err < 1e-5


def test_zero_weight_outliers_do_not_move_the_solution():
    p_gt = p_from_mm_rad([0.5, 0.5, -0.3], [0.01, 0.01, -0.02])
    prob = make_problem(p_gt, seed=2)
    g = torch.Generator().manual_seed(3)
    outliers = torch.rand(prob.w2d.shape, generator=g) < 0.3
    target = prob.target_px.clone()
    target[:, :, outliers[0]] += 25.0 * torch.randn(2, int(outliers.sum()), generator=g, dtype=torch.float64)
    ref = prob.points_ref.clone()
    ref[:, :, outliers[0]] += 0.05 * torch.randn(3, int(outliers.sum()), generator=g, dtype=torch.float64)
    w = (~outliers).double()
    corrupted = PoseProblem(prob.points_cur, target, ref, w, w.clone(), prob.K, prob.s2, prob.s3)
    res = solve_pose(corrupted, SolverConfig())
    rot_err, trans_err = pose_errors(res.p, p_gt)
    assert rot_err < 1e-5 and trans_err < 1e-5
    # with weight 1 the same outliers do move it: the test can fail
    spoiled = corrupted.with_weights(torch.ones_like(w), torch.ones_like(w))
    rot_bad, trans_bad = pose_errors(solve_pose(spoiled, SolverConfig()).p, p_gt)
    assert trans_bad > 1e-2 or rot_bad > 1e-3


def test_solver_batched_matches_single():
    ps = [p_from_mm_rad([0.3, 0.1, 0.2], [0.01, 0, 0]), p_from_mm_rad([-0.2, 0.4, -0.6], [0, -0.01, 0.02])]
    probs = [make_problem(p, seed=i) for i, p in enumerate(ps)]
    batch = PoseProblem(*(torch.cat([getattr(q, f) for q in probs]) for f in
                          ("points_cur", "target_px", "points_ref", "w2d", "w3d", "K")), probs[0].s2, probs[0].s3)
    res = solve_pose(batch, SolverConfig())
    for i, p in enumerate(ps):
        rot_err, trans_err = pose_errors(res.p[i:i + 1], p)
        assert rot_err < 1e-5 and trans_err < 1e-5


def test_float32_solver_is_accurate_enough_for_tracking():
    p_gt = p_from_mm_rad([0.8, -0.5, 1.2], [0.02, -0.015, 0.01])
    prob = make_problem(p_gt).to(torch.float32)
    res = solve_pose(prob, SolverConfig())
    rot_err, trans_err = pose_errors(res.p, p_gt)
    assert rot_err < 1e-4 and trans_err < 1e-3


def test_depth_from_parallax_and_validity():
    fxb = 500.0 * 4.5
    depth_true = torch.tensor([[[[50.0, 100.0, 300.0, 80.0]]]])
    parallax = parallax_from_depth(depth_true, fxb)
    parallax[..., 3] = 0.3  # negative disparity
    mask = torch.tensor([[[[True, False, True, True]]]])
    depth, valid = depth_from_parallax(parallax, fxb, DepthConfig(max_depth_mm=250.0), mask)
    assert valid.tolist() == [[[[True, False, False, False]]]]
    assert depth[0, 0, 0, 0].item() == pytest.approx(50.0)
    assert (depth[~valid] == 0).all()


def test_flow_consistency_flags_occlusions():
    H, W = 20, 30
    fwd = torch.zeros(1, 2, H, W)
    fwd[:, 0] = 2.0
    bwd = torch.zeros(1, 2, H, W)
    bwd[:, 0] = -2.0
    bwd[:, 0, :, 20:] = 3.0  # inconsistent region in the second view
    ok = flow_consistency(fwd, bwd, 0.5)
    assert ok[0, 0, :, :15].all() and not ok[0, 0, :, 19:27].any()


def test_sample_by_flow_is_exact_on_integer_shifts():
    img = torch.arange(60.0).reshape(1, 1, 6, 10)
    flow = torch.zeros(1, 2, 6, 10)
    flow[:, 0] = 1.0
    flow[:, 1] = 2.0
    out = sample_by_flow(img, flow)
    assert torch.allclose(out[0, 0, :4, :9], img[0, 0, 2:, 1:])


def test_robust_3d_step_ignores_a_non_rigid_patch(synth_dir):
    """Exact flow, a plane seen from two poses, and a patch of the reference pushed 2 mm towards
    the camera (tissue that moved non-rigidly): the 3D residuals there pull the plain solution off
    the true motion; one Cauchy-reweighted step (``solver.robust_3d_mm``) recovers it."""
    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from vo.odometry import Correspondences, StereoOdometry, View, cauchy_weights_3d
    from vo.geometry import backproject, pixel_grid
    from vo.lie import se3_exp

    ds = open_dataset(synth_dir("rigid", 3, (160, 128)))
    H, W = 128, 160
    # the true motion current -> reference camera
    T = se3_exp(torch.tensor([[0.4, -0.3, 0.2, 0.004, -0.003, 0.002]], dtype=torch.float64))[0]
    K = torch.as_tensor(ds.camera.K, dtype=torch.float64)
    # plane n . X = d in the reference frame: depth along each reference ray
    n, d = torch.tensor([0.1, -0.05, 1.0], dtype=torch.float64), 60.0
    grid = pixel_grid(H, W, dtype=torch.float64)[0]
    rays = torch.stack([(grid[0] - K[0, 2]) / K[0, 0], (grid[1] - K[1, 2]) / K[1, 1], torch.ones(H, W, dtype=torch.float64)])
    depth_ref = d / torch.einsum("c,chw->hw", n, rays)
    # the same plane in the current frame: n_c . X_c = d_c with X_ref = R X_c + t
    R, t = T[:3, :3], T[:3, 3]
    n_c, d_c = R.T @ n, d - float(n @ t)
    depth_cur = d_c / torch.einsum("c,chw->hw", n_c, rays)
    X_ref = R @ (rays * depth_cur).reshape(3, -1) + t[:, None]
    uv = (K @ X_ref)[:2] / X_ref[2:]
    flow = (uv.reshape(2, H, W) - grid)[None].float()
    bump = torch.zeros(H, W, dtype=torch.bool)
    bump[30:80, 40:110] = True
    depth_ref = torch.where(bump, depth_ref - 2.0, depth_ref)

    def view(depth, from_model=False):
        depth = depth.float()[None, None]
        return View(image=torch.full((1, 3, H, W), 0.5), gray=np.full((H, W), 128, np.uint8), depth=depth,
                    valid=torch.ones(1, 1, H, W, dtype=torch.bool), parallax=torch.zeros(1, 2, H, W),
                    from_model=from_model)

    errors = {}
    for scale, model_reference in ((0.0, False), (0.5, False), (0.5, True)):
        cfg = load_config(None, ["weights.mode=constant", "weights.w3d=1.0", f"solver.robust_3d_mm={scale}", "depth.temporal_gain=1"])
        odo = StereoOdometry(ds.camera, cfg.vo())
        odo.correspondences = lambda cur, against, **_: Correspondences(flow, None)     # exact flow
        res = odo.track(view(depth_cur), view(depth_ref, from_model=model_reference))
        assert not res.failed
        # a rotation to float64 rounding (the float32 solve's is off by ~1e-8; chained over thousands
        # of frames it stops being one)
        rot = res.relative[:3, :3]
        assert np.abs(rot @ rot.T - np.eye(3)).max() < 1e-12 and np.linalg.det(rot) == pytest.approx(1.0, abs=1e-12)
        errors[scale, model_reference] = float(np.linalg.norm(res.relative[:3, 3] - T[:3, 3].numpy()))
    plain = errors[0.0, False]
    assert plain > 0.05, errors             # the patch biases the plain solution
    assert errors[0.5, False] < 0.2 * plain, errors
    # against a model view the step does not run
    assert errors[0.5, True] == pytest.approx(plain, rel=1e-6), errors
    defaults = load_config(None, []).vo().solver
    assert defaults.robust_3d_mm == 0.5
    # the weights: 1 at zero residual, 1/2 at the scale
    from vo.residuals import PoseProblem
    pts = torch.rand(1, 3, 4)
    prob = PoseProblem(points_cur=pts, target_px=torch.zeros(1, 2, 4), points_ref=pts + torch.tensor(
        [0.0, 0.5, 1.0, 2.0])[None, None] / 200.0 * torch.tensor([[[1.0], [0.0], [0.0]]]),
        w2d=torch.ones(1, 4), w3d=torch.ones(1, 4), K=K.float()[None], s2=1.0, s3=1.0)
    w = cauchy_weights_3d(prob, torch.eye(4)[None], 200.0, 0.5)
    assert torch.allclose(w, torch.tensor([[1.0, 0.5, 0.2, 1 / 17]]), atol=1e-5)


def test_closed_form_exponential_matches_kornia():
    """``se3_exp_fast`` (the compiled solver's step) equals kornia's exponential to float64
    rounding, on both sides of its series switch (1e-3 rad), at the identity and at large angles."""
    from vo.lie import se3_exp_fast

    g = torch.Generator().manual_seed(7)
    for angle in (0.0, 1e-9, 1e-5, 9.9e-4, 1.01e-3, 0.05, 1.0, 3.0):
        p = torch.randn(5, 6, dtype=torch.float64, generator=g)
        p[:, 3:] *= angle / p[:, 3:].norm(dim=1, keepdim=True)
        p[:, :3] *= 0.1
        got, ref = se3_exp_fast(p), se3_exp(p)
        assert got.dtype == torch.float64 and got.shape == (5, 4, 4)
        assert torch.allclose(got, ref, rtol=0, atol=1e-13), (angle, (got - ref).abs().max())
    assert se3_exp_fast(p.float()).dtype == torch.float32


def test_compiled_normal_equations_match_torch():
    """The compiled solver kernel (one numba loop) builds the same Gauss-Newton system as the
    torch code: to float64 rounding on float64 data, to float32 rounding on float32 data; the
    solver then lands on the same pose, batched too, and refuses to run where gradients flow."""
    from vo.solver import normal_equations
    from vo.solver_kernels import normal_equations_compiled

    ps = [p_from_mm_rad([0.4, -0.2, 0.7], [0.01, -0.02, 0.005]), p_from_mm_rad([-0.3, 0.5, -0.2], [0.0, 0.01, -0.02])]
    probs = [make_problem(p, H=20, W=24, seed=i) for i, p in enumerate(ps)]
    prob = PoseProblem(*(torch.cat([getattr(q, f) for q in probs]) for f in
                         ("points_cur", "target_px", "points_ref", "w2d", "w3d", "K")), probs[0].s2, probs[0].s3)
    g = torch.Generator().manual_seed(4)
    w2, w3 = (torch.rand(prob.w2d.shape, generator=g, dtype=torch.float64) for _ in range(2))
    w2[:, ::7] = 0.0                                 # pixels without a 2D residual
    w3[:, ::5] = 0.0
    prob = prob.with_weights(w2, w3)
    prob = PoseProblem(prob.points_cur, prob.target_px + 0.3 * torch.randn(prob.target_px.shape, generator=g,
                       dtype=torch.float64), prob.points_ref, prob.w2d, prob.w3d, prob.K, prob.s2, prob.s3)
    T = se3_exp(torch.randn(2, 6, dtype=torch.float64, generator=g) * 0.01)
    for data, rtol in ((prob, 1e-10), (prob.to(torch.float32), 1e-5)):
        ref = normal_equations(T.to(data.points_cur.dtype), data)
        got = normal_equations_compiled(T.to(data.points_cur.dtype), data)
        for a, b in zip(ref, got):
            assert b.dtype == torch.float64
            assert torch.allclose(b, a.double(), rtol=rtol, atol=rtol * float(a.abs().max())), (a, b)
    p_gt = p_from_mm_rad([0.8, -0.5, 1.2], [0.02, -0.015, 0.01])
    exact = make_problem(p_gt)
    res = solve_pose(exact, SolverConfig(method="lm"), tol=Tolerance(kernel="compiled"))
    rot_err, trans_err = pose_errors(res.p, p_gt)
    assert rot_err < 1e-5 and trans_err < 1e-5, (rot_err, trans_err)
    noisy32 = prob.to(torch.float32)
    a = solve_pose(noisy32, SolverConfig(), tol=Tolerance(kernel="torch")).T
    b = solve_pose(noisy32, SolverConfig(), tol=Tolerance(kernel="compiled")).T
    assert torch.equal(solve_pose(noisy32, SolverConfig()).T, b)           # auto, the default
    assert torch.allclose(a, b, atol=1e-5)
    with_grad = exact.with_weights(exact.w2d.clone().requires_grad_(True), exact.w3d)
    with pytest.raises(ValueError, match="compiled"):
        solve_pose(with_grad, SolverConfig(), tol=Tolerance(kernel="compiled"))
    auto = solve_pose(with_grad, SolverConfig(), tol=Tolerance(kernel="auto"))           # falls back to torch
    assert torch.equal(auto.T, solve_pose(with_grad, SolverConfig(), tol=Tolerance(kernel="torch")).T)
