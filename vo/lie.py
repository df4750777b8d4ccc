"""se(3) <-> SE(3) through kornia's Lie groups (twice differentiable at the identity, which the
declarative layer's exact Hessian needs).

Tangent vectors are ``(..., 6)`` with the translation part first: ``p = (v_x, v_y, v_z, w_x, w_y, w_z)``.
"""
from __future__ import annotations

import numpy as np
import torch
from kornia.geometry.liegroup import Se3


def se3_exp(p: torch.Tensor) -> torch.Tensor:
    """Matrix exponential.

    Args:
        p: ``(B, 6)`` tangent vectors (translation first).

    Returns:
        ``(B, 4, 4)`` rigid transforms.
    """
    if p.requires_grad:
        return Se3.exp(p).matrix()
    with torch.no_grad():  # kornia wraps the translation in a Parameter: keep constants constant
        return Se3.exp(p).matrix()


def se3_exp_fast(p: torch.Tensor) -> torch.Tensor:
    """:func:`se3_exp` in closed form (Rodrigues' formula and the left Jacobian, Taylor series
    below 1e-3 rad) on the CPU in float64, without gradients: the solver's step, where kornia's
    version costs 1-2 ms a call in its checks and wrappers (``solver.kernel`` compiled, auto).

    Args:
        p: ``(B, 6)`` tangent vectors (translation first), no gradient.

    Returns:
        ``(B, 4, 4)`` rigid transforms, ``p``'s dtype; equal to :func:`se3_exp` to float64
        rounding.
    """
    v = p.detach().cpu().double().numpy()
    B = v.shape[0]
    out = np.zeros((B, 4, 4))
    for b in range(B):
        u, w = v[b, :3], v[b, 3:]
        t2 = float(w @ w)
        th = np.sqrt(t2)
        if th < 1e-3:   # series: the closed forms lose digits to cancellation near 0
            a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
            c = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
            d = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
        else:
            a = np.sin(th) / th
            c = (1.0 - np.cos(th)) / t2
            d = (th - np.sin(th)) / (t2 * th)
        W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        W2 = W @ W
        out[b, :3, :3] = np.eye(3) + a * W + c * W2
        out[b, :3, 3] = (np.eye(3) + c * W + d * W2) @ u
        out[b, 3, 3] = 1.0
    return torch.from_numpy(out).to(device=p.device, dtype=p.dtype)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """Matrix logarithm.

    Args:
        T: ``(B, 4, 4)`` rigid transforms.

    Returns:
        ``(B, 6)`` tangent vectors (translation first).
    """
    if T.requires_grad:
        return Se3.from_matrix(T).log()
    with torch.no_grad():
        return Se3.from_matrix(T).log()


def skew(w: torch.Tensor) -> torch.Tensor:
    """``(..., 3)`` vectors -> ``(..., 3, 3)`` cross-product matrices ``[w]_x``."""
    zero = torch.zeros_like(w[..., 0])
    return torch.stack(
        [
            torch.stack([zero, -w[..., 2], w[..., 1]], -1),
            torch.stack([w[..., 2], zero, -w[..., 0]], -1),
            torch.stack([-w[..., 1], w[..., 0], zero], -1),
        ],
        -2,
    )


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply rigid transforms to point maps.

    Args:
        T: ``(B, 4, 4)``.
        points: ``(B, 3, H, W)`` or ``(B, 3, N)``.

    Returns:
        Transformed points, same shape as ``points``.
    """
    shape = points.shape
    flat = points.reshape(shape[0], 3, -1)
    out = T[:, :3, :3] @ flat + T[:, :3, 3:4]
    return out.reshape(shape)


def rotation_angle_deg(T: torch.Tensor) -> torch.Tensor:
    """``(B, 4, 4)`` -> ``(B,)`` rotation angle in degrees."""
    trace = T[:, 0, 0] + T[:, 1, 1] + T[:, 2, 2]
    cos = ((trace - 1.0) / 2.0).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cos))
