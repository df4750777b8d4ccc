"""The declarative pose layer: ``p* = argmin_p f(p; w2D, w3D)`` with gradients by implicit
differentiation (Gould et al. 2021, Deep Declarative Networks).

At a minimum ``g(p*, w) = df/dp (p*, w) = 0``; differentiating gives
``dp*/dw = -H^{-1} d^2f/(dp dw)`` with ``H = d^2f/dp^2`` the *exact* Hessian at ``p*`` (not J^T J:
the residuals are not zero on non-rigid scenes). The backward pass therefore solves
``H u = dL/dp*`` and returns ``dL/dw = -(d g / d w)^T u``, one vector-Jacobian product through the
gradient of the objective. Everything in float64. ``H`` is damped when it is ill-conditioned.
A sample whose forward pass did not reach a minimum (solver failure, large gradient norm,
non-finite values) contributes no gradient.
"""
from __future__ import annotations

from dataclasses import replace

import torch

from vo.config import SolverConfig
from vo.residuals import PoseProblem, objective_se3
from vo.solver import DECLARATIVE, Tolerance, solve_pose


def exact_hessian(p: torch.Tensor, prob: PoseProblem) -> tuple[torch.Tensor, torch.Tensor]:
    """Gradient ``(B, 6)`` and exact Hessian ``(B, 6, 6)`` of the objective w.r.t. ``p`` (float64).

    ``prob``'s weights may require grad; the returned gradient keeps its graph (create_graph).
    """
    p = p.detach().double().requires_grad_(True)
    f = objective_se3(p, prob).sum()
    g = torch.autograd.grad(f, p, create_graph=True)[0]
    rows = [torch.autograd.grad(g[:, i].sum(), p, retain_graph=True)[0] for i in range(6)]
    H = torch.stack(rows, 1)
    return g, 0.5 * (H + H.transpose(1, 2))


def damp(H: torch.Tensor, rel: float = 1e-8) -> torch.Tensor:
    """Shift the spectrum of ``(B, 6, 6)`` symmetric ``H`` so its smallest eigenvalue is at least
    ``rel`` times its largest (a no-op for a well-conditioned minimum)."""
    evals = torch.linalg.eigvalsh(H)
    floor = rel * evals[:, -1:].abs().clamp(min=1e-300)
    shift = (floor - evals[:, :1]).clamp(min=0.0)
    return H + shift[..., None] * torch.eye(6, dtype=H.dtype, device=H.device)


class DeclarativePose(torch.autograd.Function):
    """``p* (B, 6) = DeclarativePose.apply(w2d (B, N), w3d (B, N), prob, config, grad_tol, tol)``."""

    @staticmethod
    def forward(ctx, w2d, w3d, prob: PoseProblem, config: SolverConfig, grad_tol: float, tol: Tolerance):
        prob64 = replace(prob.to(torch.float64), w2d=w2d.detach().double(), w3d=w3d.detach().double())
        with torch.no_grad():
            res = solve_pose(prob64, config, tol=tol)
        p = res.p.double()
        cost_scale = res.cost.abs().clamp(min=1e-30)
        ok = torch.isfinite(p).all(1) & torch.isfinite(res.cost)
        # the minimum is checked relative to the objective's scale: |grad f| / f
        ok &= (res.grad_norm / cost_scale) < grad_tol
        ctx.save_for_backward(w2d, w3d, p, ok)
        ctx.prob = prob64
        ctx.mark_non_differentiable(ok)
        p_out = torch.where(ok[:, None], p, torch.zeros_like(p)).to(w2d.dtype)
        return p_out, ok

    @staticmethod
    def backward(ctx, grad_p, _grad_ok):
        w2d, w3d, p, ok = ctx.saved_tensors
        if not bool(ok.any()):
            return torch.zeros_like(w2d), torch.zeros_like(w3d), None, None, None, None
        with torch.enable_grad():
            w2 = w2d.detach().double().requires_grad_(True)
            w3 = w3d.detach().double().requires_grad_(True)
            prob = replace(ctx.prob, w2d=w2, w3d=w3)
            g, H = exact_hessian(p, prob)
            H = damp(H.detach())
            u = torch.linalg.solve(H, grad_p.double().unsqueeze(-1)).squeeze(-1)
            u = torch.where(ok[:, None], u, torch.zeros_like(u))
            gw2, gw3 = torch.autograd.grad(g, (w2, w3), grad_outputs=-u, allow_unused=True)
        gw2 = torch.zeros_like(w2d) if gw2 is None else gw2.to(w2d.dtype)
        gw3 = torch.zeros_like(w3d) if gw3 is None else gw3.to(w3d.dtype)
        return gw2, gw3, None, None, None, None


def declarative_pose(w2d: torch.Tensor, w3d: torch.Tensor, prob: PoseProblem, config: SolverConfig,
                     grad_tol: float = 1e-4, tol: Tolerance = DECLARATIVE) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve the weighted pose problem and make the optimum differentiable w.r.t. the weights.

    Args:
        w2d, w3d: ``(B, N)`` weights (they may require grad).
        prob: the fixed data (its own weights are ignored).
        config: solver settings of the forward pass.
        grad_tol: a sample is a minimum when ``|grad f| / f`` is below this.
        tol: the forward solve's stopping rule (default: a true minimum, torch's normal equations).

    Returns:
        ``p*`` ``(B, 6)`` (zeros for failed samples) and ``ok`` ``(B,)`` bool.
    """
    return DeclarativePose.apply(w2d, w3d, prob, config, grad_tol, tol)
