"""The declarative layer's implicit gradient against finite differences and unrolled autograd, on
problems whose residuals are not zero at the optimum (noisy depth, a non-rigid patch)."""
import torch

from vo.config import SolverConfig
from vo.ddn import declarative_pose, exact_hessian
from vo.lie import se3_exp
from vo.residuals import PoseProblem, objective_se3
from vo.solver import TRACKING, Tolerance, solve_pose
from tests.test_vo_core import make_problem, p_from_mm_rad


def noisy_nonrigid_problem(seed=0, B=2):
    probs = []
    for b in range(B):
        g = torch.Generator().manual_seed(seed + b)
        p_gt = p_from_mm_rad([0.5 - b, 0.3, 0.6], [0.01, -0.01 * b, 0.004])
        prob = make_problem(p_gt, H=24, W=32, seed=seed + b)
        # noisy flow and depth, and a patch of tissue that moved on its own (non-rigid)
        target = prob.target_px + 0.3 * torch.randn(prob.target_px.shape, generator=g, dtype=torch.float64)
        ref = prob.points_ref + 0.002 * torch.randn(prob.points_ref.shape, generator=g, dtype=torch.float64)
        patch = torch.zeros(24, 32, dtype=torch.bool)
        patch[4:12, 6:16] = True
        patch = patch.flatten()
        target[:, :, patch] += torch.tensor([[2.0], [-1.5]], dtype=torch.float64)
        ref[:, :, patch] += torch.tensor([[0.01], [0.0], [-0.008]], dtype=torch.float64)
        probs.append(PoseProblem(prob.points_cur, target, ref, prob.w2d, prob.w3d, prob.K, prob.s2, prob.s3))
    return PoseProblem(*(torch.cat([getattr(q, f) for q in probs]) for f in
                         ("points_cur", "target_px", "points_ref", "w2d", "w3d", "K")), probs[0].s2, probs[0].s3)


def random_weights(prob, seed):
    g = torch.Generator().manual_seed(seed)
    w2 = (0.2 + torch.rand(prob.w2d.shape, generator=g, dtype=torch.float64)).requires_grad_(True)
    w3 = (0.2 + torch.rand(prob.w3d.shape, generator=g, dtype=torch.float64)).requires_grad_(True)
    return w2, w3


TIGHT = SolverConfig(method="lm", max_iters=100)
TIGHT_TOL = Tolerance(step=1e-14, cost_rtol=0.0)


def loss_of(p):
    c = torch.linspace(0.5, 1.5, 6, dtype=torch.float64)
    return (p * c).sum() + (p ** 2).sum()


def test_residuals_are_not_zero_at_the_optimum():
    prob = noisy_nonrigid_problem()
    w2, w3 = random_weights(prob, 1)
    res = solve_pose(prob.with_weights(w2.detach(), w3.detach()), TIGHT, tol=TIGHT_TOL)
    assert (res.cost > 1e-3).all()
    g, H = exact_hessian(res.p, prob.with_weights(w2.detach(), w3.detach()))
    assert (g.norm(dim=1) / res.cost < 1e-6).all()  # a true minimum


def test_implicit_gradient_matches_finite_differences():
    prob = noisy_nonrigid_problem()
    w2, w3 = random_weights(prob, 2)
    p, ok = declarative_pose(w2, w3, prob, TIGHT, tol=TIGHT_TOL)
    assert ok.all()
    loss_of(p).backward()
    g = torch.Generator().manual_seed(5)
    for w, grad, name in ((w2, w2.grad, "w2"), (w3, w3.grad, "w3")):
        direction = torch.randn(w.shape, generator=g, dtype=torch.float64)
        eps = 1e-3
        def L(delta):
            a = w2 + delta * direction if name == "w2" else w2
            b = w3 + delta * direction if name == "w3" else w3
            with torch.no_grad():
                return loss_of(declarative_pose(a.detach(), b.detach(), prob, TIGHT, tol=TIGHT_TOL)[0]).item()
        fd = (L(eps) - L(-eps)) / (2 * eps)
        analytic = float((grad * direction).sum())
        assert abs(fd - analytic) <= 1e-3 * abs(fd), (name, fd, analytic)


def test_implicit_gradient_matches_unrolled_autograd():
    """Differentiate through many unrolled Gauss-Newton iterations (exact solution of the
    linearised problem at each step) and compare with the implicit gradient."""
    prob = noisy_nonrigid_problem(seed=3)
    w2, w3 = random_weights(prob, 4)
    p_ddn, ok = declarative_pose(w2, w3, prob, TIGHT, tol=TIGHT_TOL)
    g2, g3 = torch.autograd.grad(loss_of(p_ddn), (w2, w3))

    w2u, w3u = w2.detach().clone().requires_grad_(True), w3.detach().clone().requires_grad_(True)
    probu = prob.with_weights(w2u, w3u)
    p = torch.zeros(prob.w2d.shape[0], 6, dtype=torch.float64, requires_grad=True)
    for _ in range(40):  # Newton steps on the tangent vector, differentiable
        f = objective_se3(p, probu).sum()
        g = torch.autograd.grad(f, p, create_graph=True)[0]
        H = torch.stack([torch.autograd.grad(g[:, i].sum(), p, create_graph=True)[0] for i in range(6)], 1)
        p = p - torch.linalg.solve(H, g.unsqueeze(-1)).squeeze(-1)
    assert torch.allclose(p, p_ddn, atol=1e-10)
    u2, u3 = torch.autograd.grad(loss_of(p), (w2u, w3u))
    for a, b in ((g2, u2), (g3, u3)):
        assert (a - b).norm() <= 1e-3 * b.norm()


def test_failed_sample_contributes_no_gradient():
    prob = noisy_nonrigid_problem()
    w2, w3 = random_weights(prob, 6)
    one_iter = SolverConfig(method="lm", max_iters=1)
    p, ok = declarative_pose(w2, w3, prob, one_iter, grad_tol=1e-12, tol=TRACKING)
    assert not ok.any()
    loss_of(p).backward()
    assert (w2.grad == 0).all() and (w3.grad == 0).all()
