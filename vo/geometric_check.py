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

from vo.geometry import backproject, project

MAX_GAP_MM = 3.0            # an association farther apart along the view ray is an occlusion
DAMPING = 1e-6              # of the 6x6 normal equations, relative to their trace
POINTS_ACROSS = 160          # the frame's points used: one pixel in s x s, s = max(2, W / POINTS_ACROSS)


def point_stride(width: int) -> int:
    """The stride ``s`` of the frame's points for images ``width`` px wide: about 160 x 128 points
    at 640x512 and above (the figures are medians and sums over them: 20,000 points settle
    them; at 640x512 stride 2 took 13 ms a frame), every second pixel below."""
    return max(2, round(width / POINTS_ACROSS))


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


def point_to_plane_check(cur_depth: torch.Tensor, cur_valid: torch.Tensor, ref_depth: torch.Tensor,
                         ref_valid: torch.Tensor, K: torch.Tensor, relative: np.ndarray) -> PlaneCheck | None:
    """The :class:`PlaneCheck` of the ``(4, 4)`` mm pose ``relative`` (current camera ->
    reference camera) for ``(1, 1, H, W)`` depth maps (mm) and validity of both views; None when
    fewer than 100 points associate."""
    T = torch.as_tensor(relative, dtype=torch.float32, device=cur_depth.device)
    H, W = ref_depth.shape[-2:]
    # the frame's valid points on every s-th pixel of every s-th row, in the reference camera
    s = point_stride(W)
    Ks = K.clone()
    Ks[:2] /= s                 # pixel (s i, s j) of the full view is (i, j) here
    d = cur_depth[..., ::s, ::s]
    keep = (cur_valid[..., ::s, ::s] & (d > 0)).flatten()
    P = backproject(d, Ks).flatten(2)[0][:, keep]                                   # (3, M)
    Y = T[:3, :3] @ P + T[:3, 3:4]
    uv = project(Y[None], K)[0]
    # the reference's point and normal (central differences, facing the camera, where the four
    # neighbours are valid) at each projection's nearest pixel, computed there only
    ix, iy = uv[0].round(), uv[1].round()
    inside = (ix >= 1) & (ix <= W - 2) & (iy >= 1) & (iy <= H - 2) & (Y[2] > 0)
    at = (iy[inside] * W + ix[inside]).long()
    Y = Y[:, inside]
    Q = backproject(ref_depth, K)[0].flatten(1)                                    # (3, H W)
    rv = ref_valid.flatten()

    def gather(offset: int) -> torch.Tensor:
        return Q.index_select(1, at + offset)

    q = gather(0)
    n = torch.cross(gather(1) - gather(-1), gather(W) - gather(-W), dim=0)
    n = n / (n[0:1] ** 2 + n[1:2] ** 2 + n[2:3] ** 2).sqrt().clamp(min=1e-12)
    n = torch.where((n * q).sum(0, keepdim=True) > 0, -n, n)
    m = rv[at] & rv[at + 1] & rv[at - 1] & rv[at + W] & rv[at - W] & ((Y[2] - q[2]).abs() < MAX_GAP_MM)
    if int(m.sum()) < 100:
        return None
    y, q, n = Y[:, m].double(), q[:, m].double(), n[:, m].double()                 # (3, N)
    r = (n * (y - q)).sum(0)
    J = torch.cat([n, torch.cross(y, n, dim=0)], 0)                                 # (6, N), left perturbation
    Hm = J @ J.T
    g = J @ r
    Hm = Hm + DAMPING * torch.trace(Hm) * torch.eye(6, dtype=Hm.dtype)
    drop = float(g @ torch.linalg.solve(Hm, g))
    total = float((r * r).sum())
    return PlaneCheck(residual_mm=float(r.abs().median()), cost_share=drop / total if total > 0 else 0.0,
                      points=int(m.sum()))
