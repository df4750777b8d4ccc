"""The photometric residual (``weights.residuals: 2d3dphoto``): its Jacobian against autograd and
a pose recovered from brightness alone where brightness is constant."""
import dataclasses
import math

import torch

from vo.config import SolverConfig
from vo.geometry import backproject
from vo.lie import se3_exp
from vo.residuals import PoseProblem, Shading, objective_se3
from vo.solver import TRACKING, normal_equations, solve_pose

H, W = 96, 128
K = torch.tensor([[110.0, 0.0, 63.5], [0.0, 110.0, 47.5], [0.0, 0.0, 1.0]])


def pattern(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """A smooth texture in grey levels and its derivatives along u and v."""
    a, b = 2 * math.pi / 23.0, 2 * math.pi / 17.0
    f = 128 + 40 * torch.sin(a * u) * torch.cos(b * v) + 25 * torch.sin(0.7 * a * u + 1.3 * b * v)
    fu = 40 * a * torch.cos(a * u) * torch.cos(b * v) + 25 * 0.7 * a * torch.cos(0.7 * a * u + 1.3 * b * v)
    fv = -40 * b * torch.sin(a * u) * torch.sin(b * v) + 25 * 1.3 * b * torch.cos(0.7 * a * u + 1.3 * b * v)
    return f, fu, fv


def problem(T_true: torch.Tensor) -> PoseProblem:
    """A curved surface seen by the current camera; the reference image is the pattern, the
    current image what the reference shows at each current point moved by ``T_true``."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    f, fu, fv = pattern(u, v)
    usable = torch.ones(H, W)
    usable[:3], usable[-3:], usable[:, :3], usable[:, -3:] = 0, 0, 0, 0
    maps = torch.stack([f, fu, fv, usable])[None]
    depth = 0.4 + 0.05 * torch.sin(u / 40.0) + 0.03 * torch.cos(v / 30.0)       # normalised depth units
    points = backproject(depth[None, None], K).flatten(2)
    Y = T_true[:3, :3] @ points[0] + T_true[:3, 3:4]
    uv = (K @ (Y / Y[2:3]))[:2]
    cur, _, _ = pattern(uv[0], uv[1])
    n = H * W
    s2, s3 = PoseProblem.scales(H, W)
    zero = torch.zeros(1, n)
    return PoseProblem(points_cur=points, target_px=torch.zeros(1, 2, n), points_ref=torch.zeros(1, 3, n),
                       w2d=zero, w3d=zero, K=K[None], s2=s2, s3=s3, wph=torch.ones(1, n),
                       shading=Shading(maps=maps, cur=cur[None]))


def true_pose() -> torch.Tensor:
    return se3_exp(torch.tensor([[0.004, -0.003, 0.002, 0.004, -0.006, 0.003]]))[0]


def test_jacobian_matches_autograd():
    """The Gauss-Newton gradient (Sobel-free here: the exact derivatives of the pattern) equals
    half the autograd gradient of the objective under a left perturbation, away from the optimum."""
    prob = problem(true_pose()).to(torch.float64)
    T = se3_exp(torch.tensor([[0.001, 0.002, -0.001, -0.002, 0.001, 0.002]], dtype=torch.float64)) @ true_pose().double()[None]
    _, g, cost = normal_equations(T, prob)
    d = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    from vo.residuals import objective
    f = objective(se3_exp(d) @ T, prob)
    (grad,) = torch.autograd.grad(f.sum(), d)
    assert float(cost[0]) > 0
    # the sampled derivative maps are exact at the pixels and interpolated between them
    assert torch.allclose(2 * g, grad, rtol=0.05, atol=1e-3 * float(grad.abs().max()))


def test_pose_recovered_from_brightness_alone():
    """With no flow term, the photometric residual alone brings a start 0.5 px-scale off back to
    the true pose."""
    T_true = true_pose()
    prob = problem(T_true)
    T0 = se3_exp(torch.tensor([[0.002, -0.002, 0.001, -0.002, 0.003, 0.001]])) @ T_true[None]
    result = solve_pose(prob, SolverConfig(max_iters=50), T0, tol=dataclasses.replace(TRACKING, kernel="torch"))
    err = (result.T[0] @ torch.linalg.inv(T_true))
    assert float((err[:3, 3]).norm()) < 1e-4        # normalised units: 0.02 mm at 200 mm
    assert float(torch.linalg.matrix_norm(err[:3, :3] - torch.eye(3))) < 3e-4   # (bilinear sampling of the reference)
    start = float((T0[0] @ torch.linalg.inv(T_true))[:3, 3].norm())
    assert start > 20 * 1e-4 and float(torch.linalg.matrix_norm((T0[0] @ torch.linalg.inv(T_true))[:3, :3] - torch.eye(3))) > 10 * 3e-4
