"""The paper's geometric residuals (eqs. 1-2) and the weighted objective (eqs. 3 and 4).

All quantities live in *normalised* units: depth and points are divided by the maximum expected
depth (paper, Sec. 2.1), so the translation of the pose is in units of that depth and rotation and
translation contribute on the same order. Pixel data are flattened to ``N = H * W`` columns.

The objective is ``f(T) = sum_x w2D(x) |e2D(x)|^2 + w3D(x) |e3D(x)|^2`` with
``e2D = s2 * (pi(T P_t(x)) - (x + F_t(x)))`` and ``e3D = s3 * (T P_t(x) - P_ref(x + F_t(x)))``.
``s2 = 1 / sqrt(X Y)`` (paper, eq. 1). ``s3 = sqrt(REFERENCE_PIXELS / (X Y))`` leaves eq. 2 as the
paper states it at the paper's 640x512 and keeps the 2D/3D balance independent of the pixel count
at other sizes. Squaring eq. 3 literally adds a cross term that is not differentiable at zero
residual, so the two squared terms are summed, as in the authors' implementation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from vo.geometry import project
from vo.lie import se3_exp, skew

REFERENCE_PIXELS = 640 * 512


@dataclass
class PoseProblem:
    """The fixed data of one batch of pose problems.

    Attributes:
        points_cur: ``(B, 3, N)`` current points ``P_t(x)`` (normalised depth units).
        target_px: ``(B, 2, N)`` flow targets ``x + F_t(x)`` in the reference image (pixels).
        points_ref: ``(B, 3, N)`` reference points sampled at the flow targets (normalised).
        w2d: ``(B, N)`` 2D weights, zero on invalid pixels.
        w3d: ``(B, N)`` 3D weights, zero on invalid pixels.
        K: ``(B, 3, 3)`` intrinsics (pixels).
        s2, s3: residual scales (see module docstring).
    """

    points_cur: torch.Tensor
    target_px: torch.Tensor
    points_ref: torch.Tensor
    w2d: torch.Tensor
    w3d: torch.Tensor
    K: torch.Tensor
    s2: float
    s3: float

    @staticmethod
    def scales(height: int, width: int) -> tuple[float, float]:
        """``(s2, s3)`` for an image of ``height x width``."""
        n = float(height * width)
        return 1.0 / math.sqrt(n), math.sqrt(REFERENCE_PIXELS / n)

    def with_weights(self, w2d: torch.Tensor, w3d: torch.Tensor) -> "PoseProblem":
        return replace(self, w2d=w2d, w3d=w3d)

    def compact(self, max_pixels: int = 0) -> tuple["PoseProblem", int]:
        """Drop the columns whose weights are zero in every batch element (saves work at
        inference) and, with ``max_pixels`` > 0, keep at most that many of the rest, evenly
        spaced (deterministic), with the weights rescaled by ``N / kept`` so that the objective
        keeps its magnitude. One gather; returns the problem and ``N``, the weighted columns."""
        idx = ((self.w2d > 0) | (self.w3d > 0)).any(0).nonzero().squeeze(1)
        n = int(idx.numel())
        scale = 1.0
        if 0 < max_pixels < n:
            idx = idx[torch.linspace(0, n - 1, max_pixels, device=idx.device).round().long()]
            scale = n / float(max_pixels)
        w2d, w3d = self.w2d[:, idx], self.w3d[:, idx]
        if scale != 1.0:
            w2d, w3d = w2d * scale, w3d * scale
        return replace(self, points_cur=self.points_cur[:, :, idx], target_px=self.target_px[:, :, idx],
                       points_ref=self.points_ref[:, :, idx], w2d=w2d, w3d=w3d), n

    def to(self, dtype: torch.dtype) -> "PoseProblem":
        return replace(
            self,
            points_cur=self.points_cur.to(dtype),
            target_px=self.target_px.to(dtype),
            points_ref=self.points_ref.to(dtype),
            w2d=self.w2d.to(dtype),
            w3d=self.w3d.to(dtype),
            K=self.K.to(dtype),
        )


def residuals(T: torch.Tensor, prob: PoseProblem) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Residual vectors at the pose ``T``.

    Args:
        T: ``(B, 4, 4)`` transform taking current-camera points into the reference camera.
        prob: the problem data.

    Returns:
        ``e2`` ``(B, 2, N)``, ``e3`` ``(B, 3, N)`` and the transformed points ``Y`` ``(B, 3, N)``.
    """
    Y = T[:, :3, :3] @ prob.points_cur + T[:, :3, 3:4]
    e2 = (project(Y, prob.K) - prob.target_px) * prob.s2
    e3 = (Y - prob.points_ref) * prob.s3
    return e2, e3, Y


def objective(T: torch.Tensor, prob: PoseProblem) -> torch.Tensor:
    """``(B,)`` weighted objective ``sum w2 |e2|^2 + w3 |e3|^2`` at ``T`` ``(B, 4, 4)``."""
    e2, e3, _ = residuals(T, prob)
    return (prob.w2d * e2.pow(2).sum(1)).sum(1) + (prob.w3d * e3.pow(2).sum(1)).sum(1)


def objective_se3(p: torch.Tensor, prob: PoseProblem) -> torch.Tensor:
    """``(B,)`` objective as a function of the tangent vector ``p`` ``(B, 6)`` (``T = exp(p)``)."""
    return objective(se3_exp(p), prob)


def jacobians(Y: torch.Tensor, prob: PoseProblem) -> tuple[torch.Tensor, torch.Tensor]:
    """Analytic Jacobians of ``e2`` and ``e3`` w.r.t. a left perturbation ``T <- exp(d) T``.

    Args:
        Y: ``(B, 3, N)`` transformed points ``T P_t``.

    Returns:
        ``J2`` ``(B, N, 2, 6)`` and ``J3`` ``(B, N, 3, 6)``; ``d = (v, w)``, translation first.
    """
    B, _, N = Y.shape
    Yt = Y.transpose(1, 2)  # (B, N, 3)
    eye = torch.eye(3, dtype=Y.dtype, device=Y.device).expand(B, N, 3, 3)
    J3 = prob.s3 * torch.cat([eye, -skew(Yt)], -1)  # (B, N, 3, 6): dY/dd = [I | -[Y]x]
    x, y = Yt[..., 0], Yt[..., 1]
    iz = 1.0 / Yt[..., 2].clamp(min=1e-6)
    xz, yz = x * iz, y * iz
    fx = prob.K[:, 0, 0].view(B, 1) * prob.s2
    fy = prob.K[:, 1, 1].view(B, 1) * prob.s2
    zero = torch.zeros_like(iz)
    ju = torch.stack([fx * iz, zero, -fx * xz * iz, -fx * xz * yz, fx * (1 + xz * xz), -fx * yz], -1)
    jv = torch.stack([zero, fy * iz, -fy * yz * iz, -fy * (1 + yz * yz), fy * xz * yz, fy * xz], -1)
    J2 = torch.stack([ju, jv], -2)  # (B, N, 2, 6)
    return J2, J3
