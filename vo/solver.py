"""Weighted se(3) pose optimisation (paper eq. 4).

``solve_pose`` minimises ``f(T) = sum w2 |e2|^2 + w3 |e3|^2`` over the relative pose. The default is
Levenberg-Marquardt on the analytic Jacobians (``vo.residuals.jacobians``) with left updates
``T <- exp(d) T``; ``lbfgs`` follows the paper
(quasi-Newton on the tangent vector with autograd gradients). Normal equations are accumulated and
solved in float64 whatever the data type.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from vo.config import SolverConfig
from vo.lie import se3_exp, se3_exp_fast, se3_log, skew
from vo.residuals import PoseProblem, objective, objective_se3, residuals


@dataclass(frozen=True)
class Tolerance:
    """When an iterative solve stops, and how its normal equations are computed.

    Attributes:
        step: stop when the update's norm (normalised units / radians) falls below this.
        cost_rtol: stop when an accepted step lowers the cost by less than this fraction.
        lbfgs_iters: iteration cap of L-BFGS.
        kernel: ``torch`` (vectorised, any device, differentiable; kornia's exponential),
            ``compiled`` (one numba loop over the pixels and the closed-form exponential
            :func:`vo.lie.se3_exp_fast`, CPU without gradients: 4x faster per evaluation at 16k
            pixels, float64 sums, equal to ``torch`` to float32 rounding; :mod:`vo.solver_kernels`)
            or ``auto`` (compiled where it can run, torch elsewhere).
    """

    step: float = 1e-6
    cost_rtol: float = 1e-6
    lbfgs_iters: int = 100
    kernel: str = "auto"


# Tracking: a step of 1e-6 is 0.0002 mm at a maximum depth of 200 mm and 0.00006 deg, two orders
# below the per-frame error (tighter values cost iterations, not accuracy).
TRACKING = Tolerance()
# The declarative layer needs a true minimum: no early stop on a flat cost, a tight step, and
# torch's normal equations (differentiable; the shipped checkpoints were trained with them).
DECLARATIVE = Tolerance(step=1e-12, cost_rtol=0.0, kernel="torch")


@dataclass
class SolverResult:
    """The optimum of a batch of pose problems.

    Attributes:
        T: ``(B, 4, 4)`` optimal transforms (current camera -> reference camera, normalised units).
        p: ``(B, 6)`` their tangent vectors (the logarithm is taken when first asked for: the
            declarative layer needs it, tracking does not).
        cost: ``(B,)`` final objective.
        iterations: iterations run.
        converged: ``(B,)`` bool, the step fell below the tolerance.
        grad_norm: ``(B,)`` norm of the objective's gradient at the optimum (left perturbation).
    """

    T: torch.Tensor
    cost: torch.Tensor
    iterations: int
    converged: torch.Tensor
    grad_norm: torch.Tensor
    tangent: torch.Tensor | None = field(default=None, repr=False)

    @property
    def p(self) -> torch.Tensor:
        if self.tangent is None:
            self.tangent = se3_log(self.T.double()).to(self.T.dtype)
        return self.tangent


def _jacobian_2d_rows(Y: torch.Tensor, prob: PoseProblem) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows of the 2D residual's Jacobian (left perturbation), ``(B, N, 6)`` each for u and v."""
    x, y = Y[:, 0], Y[:, 1]
    iz = 1.0 / Y[:, 2].clamp(min=1e-6)
    xz, yz = x * iz, y * iz
    B = Y.shape[0]
    fx = prob.K[:, 0, 0].view(B, 1) * prob.s2
    fy = prob.K[:, 1, 1].view(B, 1) * prob.s2
    zero = torch.zeros_like(iz)
    ju = torch.stack([fx * iz, zero, -fx * xz * iz, -fx * xz * yz, fx * (1 + xz * xz), -fx * yz], -1)
    jv = torch.stack([zero, fy * iz, -fy * yz * iz, -fy * (1 + yz * yz), fy * xz * yz, fy * xz], -1)
    return ju, jv


def normal_equations(T: torch.Tensor, prob: PoseProblem) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gauss-Newton system at ``T`` (the same as ``J^T W J`` and ``J^T W e`` of
    ``vo.residuals.jacobians``, with the 3D block in closed form from weighted moments of ``Y``).

    Returns:
        ``H`` ``(B, 6, 6)`` float64, ``g`` ``(B, 6)`` float64 (gradient / 2) and the cost ``(B,)``.
    """
    e2, e3, Y = residuals(T, prob)
    B = Y.shape[0]
    w2, w3 = prob.w2d, prob.w3d
    cost = (w2 * e2.pow(2).sum(1)).sum(1) + (w3 * e3.pow(2).sum(1)).sum(1)
    # 2D block: H2 = sum w (ju ju^T + jv jv^T), g2 = sum w (ju e_u + jv e_v)
    ju, jv = _jacobian_2d_rows(Y, prob)
    wu, wv = ju * w2[..., None], jv * w2[..., None]
    H = (wu.transpose(1, 2) @ ju + wv.transpose(1, 2) @ jv).double()
    g = ((wu * e2[:, 0, :, None]).sum(1) + (wv * e2[:, 1, :, None]).sum(1)).double()
    # 3D block: J3 = s3 [I | -[Y]x]; H3 = s3^2 sum w [[I, -[Y]x], [[Y]x, |Y|^2 I - Y Y^T]]
    s3 = prob.s3
    Yd, e3d, w3d = Y.double(), e3.double(), w3.double()
    sw = w3d.sum(1)
    swY = (Yd * w3d[:, None]).sum(2)  # (B, 3)
    swYY = (Yd * w3d[:, None]) @ Yd.transpose(1, 2)  # (B, 3, 3)
    eye = torch.eye(3, dtype=torch.float64, device=Y.device).expand(B, 3, 3)
    Sk = skew(swY)
    H3 = torch.zeros(B, 6, 6, dtype=torch.float64, device=Y.device)
    H3[:, :3, :3] = sw[:, None, None] * eye
    H3[:, :3, 3:] = -Sk
    H3[:, 3:, :3] = Sk
    H3[:, 3:, 3:] = torch.diagonal(swYY, dim1=1, dim2=2).sum(-1)[:, None, None] * eye - swYY
    g3 = torch.cat([(e3d * w3d[:, None]).sum(2), (torch.cross(Yd, e3d, dim=1) * w3d[:, None]).sum(2)], 1)
    return H + s3 * s3 * H3, g + s3 * g3, cost.double()


def _solve_damped(H: torch.Tensor, g: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """``(H + lam diag(H) + eps I) d = -g`` per batch element, float64."""
    diag = torch.diagonal(H, dim1=-2, dim2=-1)
    eps = 1e-12 * diag.abs().amax(-1, keepdim=True).clamp(min=1e-30)
    A = H + torch.diag_embed(lam[:, None] * diag + eps)
    return torch.linalg.solve(A, -g)


def kernels_for(prob: PoseProblem, kernel: str):
    """The normal equations and the step's exponential: torch's (and kornia's), or with
    ``kernel`` compiled/auto for a CPU problem without gradients the compiled loop of
    ``vo.solver_kernels`` and the closed-form :func:`vo.lie.se3_exp_fast`."""
    if kernel == "torch":
        return normal_equations, se3_exp
    if kernel not in ("compiled", "auto"):
        raise ValueError(f"unknown solver kernel '{kernel}' (torch, compiled, auto)")
    from vo import solver_kernels

    tensors = (prob.points_cur, prob.target_px, prob.points_ref, prob.w2d, prob.w3d)
    usable = (solver_kernels.AVAILABLE and prob.points_cur.device.type == "cpu"
              and not any(t.requires_grad for t in tensors))
    if kernel == "compiled" and not usable:
        raise ValueError("the compiled solver kernel needs numba and a CPU problem without gradients")
    return (solver_kernels.normal_equations_compiled, se3_exp_fast) if usable else (normal_equations, se3_exp)


def solve_pose_lm(prob: PoseProblem, config: SolverConfig, T_init: torch.Tensor | None = None,
                  tol: Tolerance = TRACKING) -> SolverResult:
    """Levenberg-Marquardt on the analytic Jacobians.

    Args:
        prob: the problem (batch of ``B``).
        config: the iteration cap.
        T_init: ``(B, 4, 4)`` start; identity when None.
        tol: when to stop, and which normal equations.
    """
    B = prob.points_cur.shape[0]
    dtype, device = prob.points_cur.dtype, prob.points_cur.device
    T = torch.eye(4, dtype=dtype, device=device).repeat(B, 1, 1) if T_init is None else T_init.to(dtype).clone()
    lam = torch.full((B,), 1e-4, dtype=torch.float64, device=device)
    converged = torch.zeros(B, dtype=torch.bool, device=device)
    normal_equations, exp = kernels_for(prob, tol.kernel)
    H, g, cost = normal_equations(T, prob)
    cost_prev = cost
    accepted_before = torch.ones(B, dtype=torch.bool, device=device)
    it = 0
    for it in range(1, config.max_iters + 1):
        d = _solve_damped(H, g, lam)
        d = torch.where(converged[:, None], torch.zeros_like(d), d)
        T_new = exp(d.to(dtype)) @ T
        H_new, g_new, cost_new = normal_equations(T_new, prob)
        accept = (cost_new <= cost) & ~converged
        T = torch.where(accept[:, None, None], T_new, T)
        H = torch.where(accept[:, None, None], H_new, H)
        g = torch.where(accept[:, None], g_new, g)
        cost = torch.where(accept, cost_new, cost)
        lam = torch.where(accept, (lam * 0.3).clamp(min=1e-7), (lam * 10.0).clamp(max=1e6))
        small = d.norm(dim=-1) < tol.step
        # the cost no longer decreases measurably (the noise floor of float32 data)
        flat = accept & ((cost_prev - cost) <= tol.cost_rtol * cost_prev)
        rejected_twice = ~accept & ~accepted_before
        converged = converged | small | flat | rejected_twice
        accepted_before = accept
        cost_prev = cost
        if bool(converged.all()):
            break
    return SolverResult(T=T, cost=cost, iterations=it, converged=converged, grad_norm=(2.0 * g).norm(dim=-1))


def solve_pose_lbfgs(prob: PoseProblem, config: SolverConfig, T_init: torch.Tensor | None = None,
                     tol: Tolerance = TRACKING) -> SolverResult:
    """L-BFGS with strong-Wolfe line search on the tangent vector (the paper's choice), float64."""
    prob64 = prob.to(torch.float64)
    B = prob.points_cur.shape[0]
    p0 = torch.zeros(B, 6, dtype=torch.float64) if T_init is None else se3_log(T_init.double())
    p = p0.clone().requires_grad_(True)
    opt = torch.optim.LBFGS([p], lr=1.0, max_iter=tol.lbfgs_iters, tolerance_grad=1e-12,
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
    return SolverResult(T=T.to(prob.points_cur.dtype), cost=cost, iterations=int(state.get("n_iter", 0)),
                        converged=torch.ones(B, dtype=torch.bool), grad_norm=(2.0 * g).norm(dim=-1),
                        tangent=p.to(prob.points_cur.dtype))


def solve_pose(prob: PoseProblem, config: SolverConfig, T_init: torch.Tensor | None = None,
               tol: Tolerance = TRACKING) -> SolverResult:
    """Minimise the weighted objective with the method of ``config`` (eq. 4), stopping at ``tol``."""
    if config.method == "lm":
        return solve_pose_lm(prob, config, T_init, tol=tol)
    if config.method == "lbfgs":
        return solve_pose_lbfgs(prob, config, T_init, tol=tol)
    raise ValueError(f"unknown solver.method '{config.method}' (lm, lbfgs)")


__all__ = ["Tolerance", "TRACKING", "DECLARATIVE", "SolverResult", "solve_pose", "solve_pose_lm", "solve_pose_lbfgs", "normal_equations", "objective"]
