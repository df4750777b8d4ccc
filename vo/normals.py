"""Surface normals of a depth map, and where there is one.

Central differences of neighbouring pixels of stereo depth are noise (a 0.1 mm depth error across
one pixel, 0.1-0.2 mm wide at 60-100 mm, tilts the normal by tens of degrees). Each normal here is
the cross product of central differences of the *window-averaged* point map, ``r = k // 2`` pixels
apart: the tangents span a ``2k``-pixel patch, the noise is averaged over ``k x k`` points at each
end. Box averages are OpenCV's box filter on the CPU (an integral image elsewhere), so the cost
does not grow with the window: 10-15 ms at 640x512 (a per-pixel eigen-decomposition of the
window's covariance, the textbook plane fit, took 600 ms). A pixel has a normal where at least ``MIN_VALID`` of the ``(2k + 1)``-pixel window around
it has depth (not across an edge or a hole) and the window's mean depth lies within ``MAX_STEP`` of
its own (not across a depth step).
"""
from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from vo.geometry import backproject

MIN_VALID = 0.75          # share of the window's pixels that must have depth
MAX_STEP = 0.03           # largest |mean depth - depth| / depth of a pixel with a normal


def window_for(width: int) -> int:
    """The averaging window's side (odd, pixels) for images ``width`` px wide: 7 at 640 px, 5
    below (a millimetre or so of tissue at working distance either way)."""
    return 7 if width >= 480 else 5


def box_mean(x: torch.Tensor, k: int) -> torch.Tensor:
    """The mean of ``x`` ``(B, C, H, W)`` over the ``k x k`` window centred at each pixel (``k``
    odd; the image is zero outside), in ``x``'s dtype: OpenCV's box filter on the CPU, else an
    integral image in float64."""
    if x.device.type == "cpu":
        planes = x.detach().float().reshape(-1, *x.shape[-2:]).numpy()
        out = np.stack([cv2.boxFilter(p, -1, (k, k), borderType=cv2.BORDER_CONSTANT) for p in planes])
        return torch.from_numpy(out).reshape(x.shape).to(x.dtype)
    return integral_box_mean(x, k)


def integral_box_mean(x: torch.Tensor, k: int) -> torch.Tensor:
    """:func:`box_mean` on any device, from an integral image in float64."""
    r = k // 2
    xp = F.pad(x.double(), (r + 1, r, r + 1, r))
    s = xp.cumsum(2).cumsum(3)
    H, W = x.shape[-2:]
    out = s[..., k:k + H, k:k + W] - s[..., 0:H, k:k + W] - s[..., k:k + H, 0:W] + s[..., 0:H, 0:W]
    return (out / float(k * k)).to(x.dtype)


def surface_normals(depth: torch.Tensor, valid: torch.Tensor, K: torch.Tensor,
                    window: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit normals facing the camera, and where there is one.

    Args:
        depth: ``(B, 1, H, W)`` depth (mm), 0 where invalid.
        valid: ``(B, 1, H, W)`` bool pixels with depth.
        K: ``(3, 3)`` or ``(B, 3, 3)`` intrinsics (pixels).
        window: the averaging window's odd side in pixels (default :func:`window_for`).

    Returns:
        ``normals`` ``(B, 3, H, W)`` in ``depth``'s dtype (zero where there is none) and ``has``
        ``(B, 1, H, W)`` bool.
    """
    k = window or window_for(depth.shape[-1])
    r = k // 2
    m = valid.float()
    P = backproject(depth.float(), K.float()) * m
    sums = box_mean(torch.cat([m, P], 1), k)
    mean = sums[:, 1:] / sums[:, :1].clamp(min=1e-12)                      # (B, 3, H, W) window-averaged points
    pad = F.pad(mean, (r, r, r, r), mode="replicate")
    H, W = depth.shape[-2:]
    tx = pad[..., r:r + H, 2 * r:2 * r + W] - pad[..., r:r + H, 0:W]
    ty = pad[..., 2 * r:2 * r + H, r:r + W] - pad[..., 0:H, r:r + W]
    (ax, ay, az), (bx, by, bz) = tx.unbind(1), ty.unbind(1)  # the cross product by channels:
    n = torch.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], 1)  # (fast on NCHW)
    length = (n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2]).sqrt().clamp(min=1e-12)
    facing = n[:, 0] * mean[:, 0] + n[:, 1] * mean[:, 1] + n[:, 2] * mean[:, 2] > 0
    n = n * torch.where(facing, -1.0 / length, 1.0 / length)[:, None]
    share = box_mean(m, 2 * k + 1)
    step = (mean[:, 2:3] - depth.float()).abs() / depth.float().clamp(min=1e-6)
    has = valid & (share >= MIN_VALID) & (step <= MAX_STEP)
    return (n * has).to(depth.dtype), has


def angular_error_deg(normals: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The angle (degrees) between ``normals`` and ``truth`` (``(B, 3, H, W)`` unit vectors) on
    the ``(B, 1, H, W)`` bool ``mask``, as a flat tensor."""
    cos = (normals * truth).sum(1, keepdim=True).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(cos))[mask]
