"""The paper's geometric residuals (eqs. 1-2), a flow-free point-to-plane residual, and the
weighted objective (eqs. 3 and 4).

All quantities live in *normalised* units: depth and points are divided by the maximum expected
depth (paper, Sec. 2.1), so the translation of the pose is in units of that depth and rotation and
translation contribute on the same order. Pixel data are flattened to ``N = H * W`` columns.

The objective is ``f(T) = sum_x w2D(x) |e2D(x)|^2 + w3D(x) |e3D(x)|^2`` with
``e2D = s2 * (pi(T P_t(x)) - (x + F_t(x)))`` and ``e3D = s3 * (T P_t(x) - P_ref(x + F_t(x)))``.
``s2 = 1 / sqrt(X Y)`` (paper, eq. 1). ``s3 = sqrt(REFERENCE_PIXELS / (X Y))`` leaves eq. 2 as the
paper states it at the paper's 640x512 and keeps the 2D/3D balance independent of the pixel count
at other sizes. Squaring eq. 3 literally adds a cross term that is not differentiable at zero
residual, so the two squared terms are summed, as in the authors' implementation.

The point-to-plane term (optional, ``PoseProblem.surface``) needs no flow: each current point,
moved by ``T``, is projected into the reference view and associated with the reference's point
``q`` and normal ``n`` at the nearest pixel (projective association, re-done at every evaluation
of ``T``, as KinectFusion and Open3D's hybrid odometry), ``ep = s3 * n . (T P_t(x) - q)``, weighed
by ``wp(x)``. An association lands inside the reference, on a pixel with a normal, and within
``Surface.max_gap`` along the view axis (farther: an occlusion). The association is piecewise
constant in ``T``: derivatives are taken with it frozen (the Gauss-Newton step, the declarative
layer's Hessian at the optimum).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from vo.geometry import project
from vo.lie import se3_exp, skew

REFERENCE_PIXELS = 640 * 512
# the point-to-plane residual's weight on every current pixel with depth (``weights.residuals:
# 2d3dplane``), against the learned w3D's mean of ~0.005 (docs/experiments.md, "A flow-free term")
PLANE_WEIGHT = 0.1


@dataclass
class Surface:
    """The reference's surface for the point-to-plane residual.

    Attributes:
        points: ``(B, 3, H * W)`` the reference's points per pixel (normalised depth units).
        normals: ``(B, 3, H * W)`` their unit normals facing the camera, zero where there is none
            (the association then gives no residual).
        height, width: the reference image's size (pixels).
        max_gap: the largest ``|z(T P) - z(q)|`` of an association (normalised units).
    """

    points: torch.Tensor
    normals: torch.Tensor
    height: int
    width: int
    max_gap: float

    def to(self, dtype: torch.dtype) -> "Surface":
        return replace(self, points=self.points.to(dtype), normals=self.normals.to(dtype))


def associate(Y: torch.Tensor, K: torch.Tensor, surface: Surface) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Projective association of the points ``Y`` ``(B, 3, N)`` (in the reference camera) with the
    reference's surface: ``q`` ``(B, 3, N)``, ``n`` ``(B, 3, N)`` at the nearest pixel of each
    projection, and ``ok`` ``(B, N)`` bool (inside, with a normal, within ``max_gap``)."""
    with torch.no_grad():
        uv = (project(Y, K) + 0.5).floor()          # (the nearest pixel, halves up as the compiled kernel)
        H, W = surface.height, surface.width
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1) & (Y[:, 2] > 0)
        at = torch.where(inside, uv[:, 1] * W + uv[:, 0], torch.zeros_like(uv[:, 0])).long()   # (B, N)
        index = at[:, None].expand(-1, 3, -1)
    q = surface.points.gather(2, index)
    n = surface.normals.gather(2, index)
    with torch.no_grad():
        ok = inside & (n.abs().sum(1) > 0) & ((Y[:, 2] - q[:, 2]).abs() < surface.max_gap)
    return q, n, ok


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
        s2, s3: residual scales (see module docstring); the point-to-plane residual takes ``s3``.
        wp: ``(B, N)`` point-to-plane weights, or None (no such term).
        surface: the reference's surface the point-to-plane term associates with, or None.
    """

    points_cur: torch.Tensor
    target_px: torch.Tensor
    points_ref: torch.Tensor
    w2d: torch.Tensor
    w3d: torch.Tensor
    K: torch.Tensor
    s2: float
    s3: float
    wp: torch.Tensor | None = None
    surface: Surface | None = None

    @property
    def has_surface(self) -> bool:
        """Whether the point-to-plane term is in the objective."""
        return self.surface is not None and self.wp is not None

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
        weighted = (self.w2d > 0) | (self.w3d > 0)
        if self.has_surface:
            weighted |= self.wp > 0
        idx = weighted.any(0).nonzero().squeeze(1)
        n = int(idx.numel())
        scale = 1.0
        if 0 < max_pixels < n:
            idx = idx[torch.linspace(0, n - 1, max_pixels, device=idx.device).round().long()]
            scale = n / float(max_pixels)
        w2d, w3d = self.w2d[:, idx] * scale, self.w3d[:, idx] * scale
        wp = self.wp[:, idx] * scale if self.wp is not None else None
        return replace(self, points_cur=self.points_cur[:, :, idx], target_px=self.target_px[:, :, idx],
                       points_ref=self.points_ref[:, :, idx], w2d=w2d, w3d=w3d, wp=wp), n

    def to(self, dtype: torch.dtype) -> "PoseProblem":
        return replace(
            self,
            points_cur=self.points_cur.to(dtype),
            target_px=self.target_px.to(dtype),
            points_ref=self.points_ref.to(dtype),
            w2d=self.w2d.to(dtype),
            w3d=self.w3d.to(dtype),
            K=self.K.to(dtype),
            wp=None if self.wp is None else self.wp.to(dtype),
            surface=None if self.surface is None else self.surface.to(dtype),
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


def plane_residuals(Y: torch.Tensor, prob: PoseProblem) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The point-to-plane residual of the moved points ``Y`` ``(B, 3, N)``: ``ep`` ``(B, N)``
    (zero where not associated), the weights of the associated points ``(B, N)`` and their
    normals ``n`` ``(B, 3, N)`` (see the module docstring)."""
    q, n, ok = associate(Y, prob.K, prob.surface)
    ep = (n * (Y - q)).sum(1) * prob.s3
    return torch.where(ok, ep, torch.zeros_like(ep)), prob.wp * ok, n


def objective(T: torch.Tensor, prob: PoseProblem) -> torch.Tensor:
    """``(B,)`` weighted objective ``sum w2 |e2|^2 + w3 |e3|^2 (+ wp ep^2)`` at ``T`` ``(B, 4, 4)``."""
    e2, e3, Y = residuals(T, prob)
    f = (prob.w2d * e2.pow(2).sum(1)).sum(1) + (prob.w3d * e3.pow(2).sum(1)).sum(1)
    if prob.has_surface:
        ep, wp, _ = plane_residuals(Y, prob)
        f = f + (wp * ep.pow(2)).sum(1)
    return f


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


def plane_jacobian(Y: torch.Tensor, n: torch.Tensor, s3: float) -> torch.Tensor:
    """Analytic Jacobian ``(B, N, 6)`` of the point-to-plane residual w.r.t. a left perturbation,
    the association frozen: ``s3 [n, Y x n]`` for points ``Y`` and normals ``n`` ``(B, 3, N)``."""
    return s3 * torch.cat([n, torch.cross(Y, n, dim=1)], 1).transpose(1, 2)
