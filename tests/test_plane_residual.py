"""The point-to-plane residual: projective association, its analytic Jacobian against autograd, the
compiled kernel against torch's, a pose recovered from the surface alone, and surface normals of a
depth map against the surface's own."""
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from vo.config import SolverConfig
from vo.geometry import backproject
from vo.lie import se3_exp
from vo.normals import angular_error_deg, box_mean, integral_box_mean, surface_normals
from vo.residuals import PoseProblem, Surface, objective, plane_jacobian, plane_residuals
from vo.solver import Tolerance, normal_equations, solve_pose

DMAX = 250.0
H, W = 48, 64


def _scene(dtype=torch.float64):
    """A curved surface (a bump on a tilted sheet, mm) and the intrinsics."""
    K = torch.tensor([[55.0, 0, W / 2 - 0.5], [0, 55.0, H / 2 - 0.5], [0, 0, 1]], dtype=dtype)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    depth = 80 + 0.15 * xs + 10 * torch.exp(-((xs - 30) ** 2 + (ys - 22) ** 2) / 300.0)
    return K, depth[None, None]


def _plane_problem(p_true: torch.Tensor, dtype=torch.float64) -> PoseProblem:
    """The reference sees the surface; the current camera sees it from ``exp(p_true)``'s inverse:
    its points, moved by ``exp(p_true)``, lie on the reference's surface. Only the point-to-plane
    term is weighted."""
    K, depth = _scene(dtype)
    valid = depth > 0
    normals, _ = surface_normals(depth, valid, K, window=3)
    ref_points = backproject(depth / DMAX, K).flatten(2)
    # the current view: the reference's points moved into the current camera, re-rendered at its pixels
    T = se3_exp(p_true)
    Tinv = torch.linalg.inv(T)
    P = Tinv[:, :3, :3] @ ref_points + Tinv[:, :3, 3:]                       # the reference's points in the current camera
    n = P.shape[-1]
    s2, s3 = PoseProblem.scales(H, W)
    zeros = torch.zeros(1, n, dtype=dtype)
    surface = Surface(points=ref_points, normals=normals.flatten(2).to(dtype), height=H, width=W, max_gap=3.0 / DMAX)
    return PoseProblem(points_cur=P, target_px=torch.zeros(1, 2, n, dtype=dtype), points_ref=P.clone(),
                       w2d=zeros, w3d=zeros.clone(), K=K[None], s2=s2, s3=s3,
                       wp=torch.ones(1, n, dtype=dtype), surface=surface)


P_TRUE = torch.tensor([[0.4 / DMAX, -0.3 / DMAX, 0.5 / DMAX, 0.004, -0.006, 0.003]], dtype=torch.float64)


def test_plane_residual_is_zero_at_the_true_pose_and_its_jacobian_matches_autograd():
    prob = _plane_problem(P_TRUE)
    T = se3_exp(P_TRUE)
    Y = T[:, :3, :3] @ prob.points_cur + T[:, :3, 3:]
    ep, wp, _ = plane_residuals(Y, prob)
    assert int((wp > 0).sum()) > 0.8 * H * W                         # most points associate
    assert float(ep[wp > 0].abs().max()) < 1e-9
    # away from the truth: the analytic Jacobian (association frozen) against autograd
    T0 = se3_exp(torch.tensor([[0.3 / DMAX, 0.2 / DMAX, -0.2 / DMAX, 0.002, 0.001, -0.002]], dtype=torch.float64)) @ T
    d = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    Y0 = T0[:, :3, :3] @ prob.points_cur + T0[:, :3, 3:]
    _, wp0, n0 = plane_residuals(Y0, prob)

    def frozen(dv):
        Td = se3_exp(dv) @ T0
        Yd = Td[:, :3, :3] @ prob.points_cur + Td[:, :3, 3:]
        q = prob.surface.points.gather(2, _nearest(Y0, prob)[:, None].expand(-1, 3, -1))
        return ((n0 * (Yd - q)).sum(1) * prob.s3)[wp0 > 0]

    J_auto = torch.autograd.functional.jacobian(frozen, d)[:, 0]          # (M, 6)
    J = plane_jacobian(Y0, n0, prob.s3)[0][wp0[0] > 0]
    assert torch.allclose(J, J_auto, atol=1e-9, rtol=1e-7)


def _nearest(Y, prob):
    from vo.geometry import project

    uv = (project(Y, prob.K) + 0.5).floor()
    return (uv[:, 1].clamp(0, H - 1) * W + uv[:, 0].clamp(0, W - 1)).long()


def test_normal_equations_match_the_objective_and_the_compiled_kernel():
    from vo import solver_kernels

    prob = _plane_problem(P_TRUE)
    g = torch.Generator().manual_seed(3)
    prob = prob.with_weights(torch.rand(prob.w2d.shape, generator=g, dtype=torch.float64),
                             torch.rand(prob.w3d.shape, generator=g, dtype=torch.float64))
    prob.target_px = prob.target_px + torch.tensor([[[W / 2], [H / 2]]], dtype=torch.float64)
    T = se3_exp(torch.tensor([[0.1 / DMAX, 0.0, 0.2 / DMAX, 0.001, 0.0, -0.001]], dtype=torch.float64)) @ se3_exp(P_TRUE)
    Hm, gv, cost = normal_equations(T, prob)
    assert float(cost[0]) == pytest.approx(float(objective(T, prob)[0]), rel=1e-10)
    # the gradient of the objective (association frozen at T) is 2 g
    d = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    f = objective(se3_exp(d) @ T, prob).sum()
    (grad,) = torch.autograd.grad(f, d)
    assert torch.allclose(grad, 2 * gv, rtol=1e-6, atol=1e-12)
    if not solver_kernels.AVAILABLE:
        pytest.skip("numba is not installed")
    Hc, gc, cc = solver_kernels.normal_equations_compiled(T, prob)
    assert torch.allclose(Hc, Hm, rtol=1e-9, atol=1e-12)
    assert torch.allclose(gc, gv, rtol=1e-9, atol=1e-15)
    assert float(cc[0]) == pytest.approx(float(cost[0]), rel=1e-9)


@pytest.mark.parametrize("kernel", ["torch", "compiled"])
def test_the_surface_alone_recovers_the_pose_on_curved_tissue(kernel):
    """No flow at all: the point-to-plane term on a curved surface brings the pose from 1 mm and
    1 degree off back to within 0.02 mm and 0.02 degrees."""
    from vo import solver_kernels

    if kernel == "compiled" and not solver_kernels.AVAILABLE:
        pytest.skip("numba is not installed")
    prob = _plane_problem(P_TRUE)
    off = torch.tensor([[0.7 / DMAX, -0.5 / DMAX, 0.5 / DMAX, 0.01, -0.012, 0.008]], dtype=torch.float64)
    T0 = se3_exp(off) @ se3_exp(P_TRUE)
    res = solve_pose(prob, SolverConfig(max_iters=50), T0, tol=Tolerance(kernel=kernel))
    E = torch.linalg.inv(se3_exp(P_TRUE)) @ res.T
    assert float(E[0, :3, 3].norm()) * DMAX < 0.02
    angle = math.degrees(math.acos(min(1.0, (float(torch.trace(E[0, :3, :3])) - 1) / 2)))
    assert angle < 0.02


def test_windowed_normals_of_a_noisy_depth_are_closer_than_central_differences():
    """On a curved sheet with 0.5 mm depth noise, the 7-pixel window's normals are within a few
    degrees where the 3-pixel ones are not; around a hole in the depth there is no normal."""
    K, depth = _scene(torch.float32)
    truth, _ = surface_normals(depth, depth > 0, K, window=3)
    g = torch.Generator().manual_seed(0)
    noisy = depth + 0.5 * torch.randn(depth.shape, generator=g)
    n3, _ = surface_normals(noisy, noisy > 0, K, window=3)
    n7, _ = surface_normals(noisy, noisy > 0, K, window=7)
    inner = torch.zeros_like(depth, dtype=torch.bool)
    inner[..., 4:-4, 4:-4] = True
    e3 = float(angular_error_deg(n3, truth, inner).median())
    e7 = float(angular_error_deg(n7, truth, inner).median())
    assert e7 < 0.5 * e3 and e7 < 8.0
    # a hole of depth: the windows over it have too few points and get no normal
    holed = depth.clone()
    holed[..., 10:30, 10:30] = 0
    nh, has = surface_normals(holed, holed > 0, K, window=7)
    assert not bool(has[0, 0, 20, 20]) and float(nh[0, :, 20, 20].abs().sum()) == 0.0
    assert not bool(has[0, 0, 20, 32])                    # (at the hole's edge: too few points)
    assert bool(has[0, 0, 40, 50]) and np.isfinite(nh.numpy()).all()


@pytest.mark.parametrize("mean, rel", [(box_mean, 1e-6), (integral_box_mean, 1e-12)])
def test_box_mean_is_the_window_average(mean, rel):
    """OpenCV's box filter (the CPU path, float32) and the integral image (any device) alike."""
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 2, 9, 11, generator=g, dtype=torch.float64)
    out = mean(x, 3)
    assert out.dtype == x.dtype and out.shape == x.shape
    assert float(out[0, 1, 4, 5]) == pytest.approx(float(x[0, 1, 3:6, 4:7].mean()), rel=rel)
    assert float(out[0, 0, 0, 0]) == pytest.approx(float(x[0, 0, 0:2, 0:2].sum()) / 9, rel=rel)


def _tissue(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Depth ``z`` (mm) of a tilted sheet with two bumps at ``(x, y)`` (mm, reference camera)."""
    return (80 + 0.1 * x + 8 * torch.exp(-((x - 5) ** 2 + (y + 3) ** 2) / 200.0)
            + 5 * torch.exp(-((x + 12) ** 2 + (y - 8) ** 2) / 120.0))


def _tissue_depth(K: torch.Tensor, T: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """``(H, W)`` depth (mm) of :func:`_tissue` seen by a camera at ``T`` (camera -> reference):
    Newton's method along each ray on ``o_z + s d_z - z(o_xy + s d_xy)``."""
    from vo.geometry import pixel_grid

    grid = pixel_grid(H, W, dtype=torch.float64)[0]
    rays = torch.stack([(grid[0] - K[0, 2]) / K[0, 0], (grid[1] - K[1, 2]) / K[1, 1], torch.ones(H, W, dtype=torch.float64)])
    d = torch.einsum("ij,jhw->ihw", T[:3, :3], rays)
    o = T[:3, 3][:, None, None]
    s = torch.full((H, W), 80.0, dtype=torch.float64)
    for _ in range(30):
        s = s.detach().requires_grad_(True)
        p = o + s * d
        g = p[2] - _tissue(p[0], p[1])
        dg, = torch.autograd.grad(g.sum(), s)
        s = s - g / dg
    return s.detach()                                     # rays have z = 1: s is the depth


def test_the_plane_term_holds_the_pose_where_the_flow_slides(synth_dir):
    """A curved sheet seen from two poses, exact depth; the flow slides 1 px along x everywhere (DIS on
    smooth tissue): the paper's 2D and 3D residuals follow the slide, the point-to-plane term
    (``weights.residuals: 2d3dplane``) holds the pose against the surface. With the exact flow
    both recover the motion."""
    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from vo.geometry import pixel_grid
    from vo.odometry import Correspondences, StereoOdometry, View

    ds = open_dataset(synth_dir("rigid", 3, (160, 128)))
    Hs, Ws = 128, 160
    K = torch.as_tensor(ds.camera.K, dtype=torch.float64)
    T = se3_exp(torch.tensor([[0.6, -0.4, 0.3, 0.006, -0.004, 0.003]], dtype=torch.float64))[0]   # current -> reference
    depth_ref = _tissue_depth(K, torch.eye(4, dtype=torch.float64), Hs, Ws)
    depth_cur = _tissue_depth(K, T, Hs, Ws)
    grid = pixel_grid(Hs, Ws, dtype=torch.float64)[0]
    X = backproject(depth_cur[None, None], K)[0].reshape(3, -1)
    X_ref = T[:3, :3] @ X + T[:3, 3:]
    uv = (K @ X_ref)[:2] / X_ref[2:]
    exact = (uv.reshape(2, Hs, Ws) - grid)[None].float()

    def view(depth):
        return View(image=torch.full((1, 3, Hs, Ws), 0.5), gray=np.full((Hs, Ws), 128, np.uint8),
                    depth=depth.float()[None, None], valid=torch.ones(1, 1, Hs, Ws, dtype=torch.bool),
                    parallax=torch.zeros(1, 2, Hs, Ws))

    def track(residuals: str, w2d: float, w3d: float, flow: torch.Tensor) -> float | None:
        cfg = load_config(None, ["weights.mode=constant", f"weights.w2d={w2d}", f"weights.w3d={w3d}",
                                 f"weights.residuals={residuals}", "depth.temporal_gain=1"])
        odo = StereoOdometry(ds.camera, cfg.vo())
        odo.correspondences = lambda cur, against, **_: Correspondences(flow, None)
        res = odo.track(view(depth_cur), view(depth_ref))
        return None if res.failed else float(np.linalg.norm(res.relative[:3, 3] - T[:3, 3].numpy()))

    # the surface alone (no weight on the flow's residuals) recovers the motion, normals fitted to the depth
    assert track("2d3d", 0.0, 0.0, exact) is None
    assert track("2d3dplane", 0.0, 0.0, exact) < 0.02
    # with the flow's residuals at the learned maps' means on weak texture (w2D ~0.1, w3D ~0.005)
    assert track("2d3d", 0.1, 0.005, exact) < 0.01 and track("2d3dplane", 0.1, 0.005, exact) < 0.01
    slid = exact + torch.tensor([1.0, 0.0])[None, :, None, None]
    paper, plane = track("2d3d", 0.1, 0.005, slid), track("2d3dplane", 0.1, 0.005, slid)
    assert paper > 0.3 and plane < 0.95 * paper, (paper, plane)   # the slide moves the paper's pose, less with the plane


def test_declarative_gradient_with_the_plane_term_matches_finite_differences():
    """The declarative layer differentiates the joint objective (2D, 3D and point-to-plane, the
    association frozen at the optimum): its gradient w.r.t. w2D and w3D against central
    differences of the re-solved pose, with noisy flow and depth so that no residual is zero."""
    from vo.ddn import declarative_pose
    from vo.geometry import project

    base = _plane_problem(P_TRUE)
    g = torch.Generator().manual_seed(3)
    ref = base.surface.points
    target = project(ref, base.K) + 0.3 * torch.randn(base.target_px.shape, generator=g, dtype=torch.float64)
    points_ref = ref + 0.002 * torch.randn(ref.shape, generator=g, dtype=torch.float64)
    prob = replace(base, target_px=target, points_ref=points_ref, wp=0.5 * base.wp)
    w2 = (0.2 + torch.rand(base.w2d.shape, generator=g, dtype=torch.float64)).requires_grad_(True)
    w3 = (0.2 + torch.rand(base.w3d.shape, generator=g, dtype=torch.float64)).requires_grad_(True)
    tight, tol = SolverConfig(method="lm", max_iters=100), Tolerance(step=1e-14, cost_rtol=0.0)
    c = torch.linspace(0.5, 1.5, 6, dtype=torch.float64)

    def loss(p):
        return (p * c).sum() + (p ** 2).sum()

    p, ok = declarative_pose(w2, w3, prob, tight, tol=tol)
    assert ok.all()
    loss(p).backward()
    for w, name in ((w2, "w2"), (w3, "w3")):
        direction = torch.randn(w.shape, generator=g, dtype=torch.float64)
        eps = 1e-2                     # (smaller steps drown in the solver's rounding on the small w2 gradient)

        def L(delta):
            a = w2 + delta * direction if name == "w2" else w2
            b = w3 + delta * direction if name == "w3" else w3
            with torch.no_grad():
                return loss(declarative_pose(a.detach(), b.detach(), prob, tight, tol=tol)[0]).item()

        fd = (L(eps) - L(-eps)) / (2 * eps)
        analytic = float((w.grad * direction).sum())
        assert abs(fd - analytic) <= 1e-3 * abs(fd), (name, fd, analytic)
