"""How well a pose is supported by its residual problem: the residuals left at the optimum and
the objective's curvature (the Gauss-Newton Hessian), for the tracker's health figures and the
pose covariance ``Sigma = s * sigma^2 * H^-1``."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from vo.residuals import PoseProblem, residuals
from vo.solver import kernels_for


class PoseFit(NamedTuple):
    """The fit of one pose to its residual problem.

    Attributes:
        residual_2d_px: w2D-weighted median of ``|e2D|`` (pixels, eq. 1 without its scale).
        residual_3d_mm: w3D-weighted median of ``|e3D|`` (mm, eq. 2 without its scale); nan
            without 3D residuals.
        hessian: ``(6, 6)`` Gauss-Newton Hessian ``J^T W J`` of the objective (eq. 3) in mm and
            rad, translation first (``vo/lie.py``'s tangent order, left perturbation).
        sigma2: the objective's value per degree of freedom, ``cost / (m - 6)`` with ``m`` the
            weighted scalar residuals: the residual variance the covariance scales with.
    """

    residual_2d_px: float
    residual_3d_mm: float
    hessian: np.ndarray
    sigma2: float

    def covariance(self, scale: float) -> np.ndarray:
        """``(6, 6)`` pose covariance ``scale * sigma2 * H^-1`` (mm^2, rad^2; translation first)."""
        return scale * self.sigma2 * np.linalg.pinv(self.hessian)


# weighted_median sorts at most this many values: above it, a weighted histogram narrows the
# values down to the bin that holds the half weight (each pass O(n), the result the same element)
MEDIAN_SORT_MAX = 4096
MEDIAN_BINS = 1024


def weighted_median(values: torch.Tensor, weights: torch.Tensor) -> float:
    """The median of ``values`` ``(N,)`` under non-negative ``weights`` ``(N,)`` (nan when they sum
    to 0): the smallest value whose cumulative weight in ascending order reaches half the total.
    Linear in ``N`` (a full sort of a 640x512 frame's values cost 12 ms a figure)."""
    v = values.detach().cpu().numpy().astype(np.float32, copy=False)
    w = weights.detach().cpu().numpy()
    keep = w > 0
    if not keep.any():
        return float("nan")
    v, w = v[keep], w[keep]
    half = 0.5 * float(w.sum(dtype=np.float64))
    if np.isfinite(v).all():
        while v.size > MEDIAN_SORT_MAX:
            lo, hi = float(v.min()), float(v.max())
            if lo == hi:
                return lo
            bins = np.minimum(((v - np.float32(lo)) * np.float32(MEDIAN_BINS / (hi - lo))).astype(np.intp), MEDIAN_BINS - 1)
            cw = np.cumsum(np.bincount(bins, w, MEDIAN_BINS))
            b = min(int(np.searchsorted(cw, half)), MEDIAN_BINS - 1)
            if b > 0:
                half -= float(cw[b - 1])
            inside = bins == b
            v, w = v[inside], w[inside]
    order = np.argsort(v, kind="stable")
    cw = np.cumsum(w[order], dtype=np.float64)
    i = int(np.searchsorted(cw, half))
    return float(v[order][min(i, v.size - 1)])


def pose_fit(prob: PoseProblem, T: torch.Tensor, max_depth_mm: float) -> PoseFit:
    """The :class:`PoseFit` of the ``(1, 4, 4)`` pose ``T`` (normalised units) to ``prob``
    (batch of 1, depths divided by ``max_depth_mm``)."""
    e2, e3, _ = residuals(T, prob)
    w2, w3 = prob.w2d[0], prob.w3d[0]
    r2 = (e2[0, 0] ** 2 + e2[0, 1] ** 2).sqrt() / prob.s2
    r3 = (e3[0, 0] ** 2 + e3[0, 1] ** 2 + e3[0, 2] ** 2).sqrt() * (max_depth_mm / prob.s3)
    normal_equations, _ = kernels_for(prob, "auto")     # the compiled kernel where it applies
    H, _, cost = normal_equations(T, prob)
    scale = torch.tensor([1.0 / max_depth_mm] * 3 + [1.0] * 3, dtype=torch.float64, device=H.device)
    H_mm = (H[0] * scale[:, None] * scale[None, :]).cpu().numpy()
    m = 2 * int((w2 > 0).sum()) + 3 * int((w3 > 0).sum())
    sigma2 = float(cost[0]) / max(m - 6, 1)
    return PoseFit(residual_2d_px=weighted_median(r2, w2), residual_3d_mm=weighted_median(r3, w3),
                   hessian=H_mm, sigma2=sigma2)
