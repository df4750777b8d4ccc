"""A cue that needs no texture: how well the frame's depth, placed by the tracked pose, lies on the
model view's surface (the point-to-plane distance KinectFusion and ElasticFusion track by).

The frame's points are moved into the reference camera by the tracked relative pose and associated
projectively with the reference's points and normals. Two figures come out: the median
point-to-plane distance (mm), and the share of the point-to-plane cost that one Gauss-Newton step
of a rigid correction would remove: near 0 when the geometry agrees with the pose (the residuals
are noise), towards 1 when the surface's shape asks for another pose. Smooth tissue leaves the
in-plane directions unconstrained; the cost share is blind to them instead of sliding along them
as a full ICP does.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

import torch.nn.functional as F

from vo.geometry import backproject, project

MAX_GAP_MM = 3.0            # an association farther apart along the view ray is an occlusion
DAMPING = 1e-6              # of the 6x6 normal equations, relative to their trace
STRIDE = 2                  # the frame's points used: one pixel in STRIDE x STRIDE


class PlaneCheck(NamedTuple):
    """Figures of the point-to-plane check of one pose.

    Attributes:
        residual_mm: the median ``|n . (T p - q)|`` over the associated points (mm).
        cost_share: the share of ``sum r^2`` that one Gauss-Newton step on ``T`` removes, in [0, 1].
        points: the associated points.
    """

    residual_mm: float
    cost_share: float
    points: int


def normals_of(points: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit normals ``(1, 3, H, W)`` of an organised point map ``(1, 3, H, W)`` from central
    differences, facing the camera, and where they exist (``(1, 1, H, W)`` bool: the four
    neighbours valid)."""
    du = points[..., 1:-1, 2:] - points[..., 1:-1, :-2]
    dv = points[..., 2:, 1:-1] - points[..., :-2, 1:-1]
    n = torch.cross(du, dv, dim=1)
    n = n / (n[:, 0:1] ** 2 + n[:, 1:2] ** 2 + n[:, 2:3] ** 2).sqrt().clamp(min=1e-12)
    n = torch.where((n * points[..., 1:-1, 1:-1]).sum(1, keepdim=True) > 0, -n, n)
    ok = valid[..., 1:-1, 2:] & valid[..., 1:-1, :-2] & valid[..., 2:, 1:-1] & valid[..., :-2, 1:-1]
    normals = torch.zeros_like(points)
    normals[..., 1:-1, 1:-1] = n
    has = torch.zeros_like(valid)
    has[..., 1:-1, 1:-1] = ok & valid[..., 1:-1, 1:-1]
    return normals, has


def point_to_plane_check(cur_depth: torch.Tensor, cur_valid: torch.Tensor, ref_depth: torch.Tensor,
                         ref_valid: torch.Tensor, K: torch.Tensor, relative: np.ndarray) -> PlaneCheck | None:
    """The :class:`PlaneCheck` of the ``(4, 4)`` mm pose ``relative`` (current camera ->
    reference camera) for ``(1, 1, H, W)`` depth maps (mm) and validity of both views; None when
    fewer than 100 points associate."""
    T = torch.as_tensor(relative, dtype=torch.float32, device=cur_depth.device)
    H, W = ref_depth.shape[-2:]
    # the frame's points on every STRIDE-th pixel of every STRIDE-th row, in the reference camera
    Ks = K.clone()
    Ks[:2] /= STRIDE            # pixel (STRIDE i, STRIDE j) of the full view is (i, j) here
    d = cur_depth[..., ::STRIDE, ::STRIDE]
    P = backproject(d, Ks)
    Y = (T[:3, :3] @ P.flatten(2) + T[:3, 3:4]).view_as(P)
    uv = project(Y, K)
    grid = torch.stack([2.0 * uv[:, 0] / (W - 1) - 1.0, 2.0 * uv[:, 1] / (H - 1) - 1.0], -1)
    Q = backproject(ref_depth, K)
    normals, has_normal = normals_of(Q, ref_valid)
    both = F.grid_sample(torch.cat([Q, normals, has_normal.to(Q.dtype)], 1), grid, mode="nearest",
                         padding_mode="zeros", align_corners=True)
    q, n, has = both[:, :3], both[:, 3:6], both[:, 6:7] > 0.5
    ok = cur_valid[..., ::STRIDE, ::STRIDE] & (d > 0) & has & (Y[:, 2:3] > 0)
    ok &= (Y[:, 2:3] - q[:, 2:3]).abs() < MAX_GAP_MM
    m = ok[0, 0]
    if int(m.sum()) < 100:
        return None
    y, q, n = Y[0][:, m].double(), q[0][:, m].double(), n[0][:, m].double()      # (3, N)
    r = (n * (y - q)).sum(0)
    J = torch.cat([n, torch.cross(y, n, dim=0)], 0)                                 # (6, N), left perturbation
    Hm = J @ J.T
    g = J @ r
    Hm = Hm + DAMPING * torch.trace(Hm) * torch.eye(6, dtype=Hm.dtype)
    drop = float(g @ torch.linalg.solve(Hm, g))
    total = float((r * r).sum())
    return PlaneCheck(residual_mm=float(r.abs().median()), cost_share=drop / total if total > 0 else 0.0,
                      points=int(m.sum()))
