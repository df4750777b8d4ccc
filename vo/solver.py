"""Weighted se(3) pose optimisation (paper eq. 6).

``solve_pose`` minimises ``f(T) = sum w2 |e2|^2 + w3 |e3|^2`` over the relative pose. The default is
Levenberg-Marquardt on the analytic Jacobians (``vo.residuals.jacobians``) with left updates
``T <- exp(d) T``; ``gauss_newton`` is the same without damping; ``lbfgs`` follows the paper
(quasi-Newton on the tangent vector with autograd gradients). Normal equations are accumulated and
solved in float64 whatever the data type.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from vo.config import SolverConfig
from vo.lie import se3_exp, se3_log
from vo.residuals import PoseProblem, jacobians, objective, objective_se3, residuals


@dataclass
class SolverResult:
    """The optimum of a batch of pose problems.

    Attributes:
        T: ``(B, 4, 4)`` optimal transforms (current camera -> reference camera, normalised units).
        p: ``(B, 6)`` their tangent vectors.
        cost: ``(B,)`` final objective.
        iterations: iterations run.
        converged: ``(B,)`` bool, the step fell below the tolerance.
        grad_norm: ``(B,)`` norm of the objective's gradient at the optimum (left perturbation).
    """

    T: torch.Tensor
    p: torch.Tensor
    cost: torch.Tensor
    iterations: int
    converged: torch.Tensor
    grad_norm: torch.Tensor


def normal_equations(T: torch.Tensor, prob: PoseProblem) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gauss-Newton system at ``T``.

    Returns:
        ``H`` ``(B, 6, 6)`` float64, ``g`` ``(B, 6)`` float64 (gradient / 2) and the cost ``(B,)``.
    """
    e2, e3, Y = residuals(T, prob)
    J2, J3 = jacobians(Y, prob)
    B = Y.shape[0]
    w2 = prob.w2d[..., None, None]
    w3 = prob.w3d[..., None, None]
    A2 = (J2 * w2).reshape(B, -1, 6)
    A3 = (J3 * w3).reshape(B, -1, 6)
    H = A2.transpose(1, 2) @ J2.reshape(B, -1, 6) + A3.transpose(1, 2) @ J3.reshape(B, -1, 6)
    g = (A2.transpose(1, 2) @ e2.transpose(1, 2).reshape(B, -1, 1)).squeeze(-1) + (
        A3.transpose(1, 2) @ e3.transpose(1, 2).reshape(B, -1, 1)
    ).squeeze(-1)
    cost = (prob.w2d * e2.pow(2).sum(1)).sum(1) + (prob.w3d * e3.pow(2).sum(1)).sum(1)
    return H.double(), g.double(), cost.double()


def _solve_damped(H: torch.Tensor, g: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """``(H + lam diag(H) + eps I) d = -g`` per batch element, float64."""
    diag = torch.diagonal(H, dim1=-2, dim2=-1)
    eps = 1e-12 * diag.abs().amax(-1, keepdim=True).clamp(min=1e-30)
    A = H + torch.diag_embed(lam[:, None] * diag + eps)
    return torch.linalg.solve(A, -g)


def solve_pose_lm(prob: PoseProblem, config: SolverConfig, T_init: torch.Tensor | None = None,
                  damping: bool = True) -> SolverResult:
    """Levenberg-Marquardt (``damping=True``) or Gauss-Newton on the analytic Jacobians.

    Args:
        prob: the problem (batch of ``B``).
        config: iteration cap and tolerance.
        T_init: ``(B, 4, 4)`` start; identity when None.
    """
    B = prob.points_cur.shape[0]
    dtype, device = prob.points_cur.dtype, prob.points_cur.device
    T = torch.eye(4, dtype=dtype, device=device).repeat(B, 1, 1) if T_init is None else T_init.to(dtype).clone()
    lam = torch.full((B,), 1e-4 if damping else 0.0, dtype=torch.float64, device=device)
    converged = torch.zeros(B, dtype=torch.bool, device=device)
    H, g, cost = normal_equations(T, prob)
    it = 0
    for it in range(1, config.max_iters + 1):
        d = _solve_damped(H, g, lam)
        d = torch.where(converged[:, None], torch.zeros_like(d), d)
        T_new = se3_exp(d.to(dtype)) @ T
        H_new, g_new, cost_new = normal_equations(T_new, prob)
        accept = (cost_new <= cost) | (not damping)
        accept = accept & ~converged
        T = torch.where(accept[:, None, None], T_new, T)
        H = torch.where(accept[:, None, None], H_new, H)
        g = torch.where(accept[:, None], g_new, g)
        cost = torch.where(accept, cost_new, cost)
        if damping:
            lam = torch.where(accept, (lam * 0.3).clamp(min=1e-7), (lam * 10.0).clamp(max=1e6))
        small = d.norm(dim=-1) < config.step_tol
        stalled = damping & ~accept & (lam >= 1e6)
        converged = converged | (accept & small) | small | stalled
        if bool(converged.all()):
            break
    return SolverResult(T=T, p=se3_log(T.double()).to(dtype), cost=cost, iterations=it,
                        converged=converged, grad_norm=(2.0 * g).norm(dim=-1))


def solve_pose_lbfgs(prob: PoseProblem, config: SolverConfig, T_init: torch.Tensor | None = None) -> SolverResult:
    """L-BFGS with strong-Wolfe line search on the tangent vector (the paper's choice), float64."""
    prob64 = prob.to(torch.float64)
    B = prob.points_cur.shape[0]
    p0 = torch.zeros(B, 6, dtype=torch.float64) if T_init is None else se3_log(T_init.double())
    p = p0.clone().requires_grad_(True)
    opt = torch.optim.LBFGS([p], lr=1.0, max_iter=config.lbfgs_max_iters, tolerance_grad=1e-12,
                            tolerance_change=1e-16, history_size=20, line_search_fn="strong_wolfe")
    scale = 1.0 / objective_se3(p0, prob64).sum().clamp(min=1e-30).item()

    def closure():
        opt.zero_grad()
        loss = objective_se3(p, prob64).sum() * scale
        loss.backward()
        return loss

    opt.step(closure)
    state = opt.state[opt._params[0]]
    p = p.detach()
    T = se3_exp(p)
    _, g, cost = normal_equations(T, prob64)
    return SolverResult(T=T.to(prob.points_cur.dtype), p=p.to(prob.points_cur.dtype), cost=cost,
                        iterations=int(state.get("n_iter", 0)),
                        converged=torch.ones(B, dtype=torch.bool), grad_norm=(2.0 * g).norm(dim=-1))


def solve_pose(prob: PoseProblem, config: SolverConfig, T_init: torch.Tensor | None = None) -> SolverResult:
    """Minimise the weighted objective with the method of ``config``."""
    if config.method == "lm":
        return solve_pose_lm(prob, config, T_init, damping=True)
    if config.method == "gauss_newton":
        return solve_pose_lm(prob, config, T_init, damping=False)
    if config.method == "lbfgs":
        return solve_pose_lbfgs(prob, config, T_init)
    raise ValueError(f"unknown solver.method '{config.method}' (lm, gauss_newton, lbfgs)")


__all__ = ["SolverResult", "solve_pose", "solve_pose_lm", "solve_pose_lbfgs", "normal_equations", "objective"]
