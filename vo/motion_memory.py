"""Where the tissue has been moving: a per-pixel memory of the 3D residual left at the solved pose,
carried along the temporal flow from frame to frame (the input of layout-5 weight networks).

Between two frames the tissue moves non-rigidly by a few hundredths of a millimetre, about the
noise of even a filtered depth, so one pair hardly shows *where* it moves. Breathing and an
instrument move the same regions for seconds: the residual of the rigid fit, averaged over the
last second along the tissue it belongs to, stands out of the noise where one pair's does not
(the paper's "regions more affected by breathing"). The memory is causal: the weights of the pair
``(cur, ref)`` see the memory of ``ref``, built from the frames up to ``ref``.

The memory of a view is ``(B, 4, H, W)`` on its own pixel grid: an exponential moving average of
the relative residual vector ``(R X_cur + t - X_ref) / Z_cur`` over the frames (channels 0-2, the
weighted sum) and of the pixels' validity (channel 3, the weight): their ratio is the mean over
the frames where the pixel had a residual, the weight says how much history there is. The mean
is signed: tissue keeps moving the same way for a good part of a breath, so its residuals add
up, while the depth's noise, new in every frame, averages out (the noise of a one-second mean is
about a seventh of one frame's).
"""
from __future__ import annotations

import torch

from vo.geometry import sample_by_flow

MEMORY_RATE = 0.04  # weight of the newest frame: a time constant of 25 frames, one second at 25 fps
MEMORY_SCALE_REL = 1e-4  # relative scale of the features: 0.007 mm per frame at 70 mm


def relative_residual(points_cur: torch.Tensor, points_ref: torch.Tensor, T: torch.Tensor,
                      valid: torch.Tensor) -> torch.Tensor:
    """The 3D residual of every pixel at the pose ``T``, relative to its depth.

    Args:
        points_cur: ``(B, 3, H, W)`` current points (any unit).
        points_ref: ``(B, 3, H, W)`` the reference's points where the flow lands (same unit).
        T: ``(B, 4, 4)`` current -> reference camera, translation in that unit.
        valid: ``(B, 1, H, W)`` bool pixels with both points.

    Returns:
        ``(B, 3, H, W)`` ``(R X_cur + t - X_ref) / Z_cur`` (reference camera axes), 0 where not ``valid``.
    """
    B = points_cur.shape[0]
    T = T.to(points_cur.dtype)
    moved = torch.einsum("bij,bjhw->bihw", T[:, :3, :3], points_cur) + T[:, :3, 3].view(B, 3, 1, 1)
    r = (moved - points_ref) / points_cur[:, 2:3].clamp(min=1e-12)
    ok = valid & (points_cur[:, 2:3] > 0)
    return torch.where(ok, r, torch.zeros_like(r))


def update_memory(memory_ref: torch.Tensor | None, flow: torch.Tensor, residual: torch.Tensor,
                  valid: torch.Tensor, rate: float = MEMORY_RATE) -> torch.Tensor:
    """The current view's memory: the reference's carried along the flow, plus this pair's residual.

    Args:
        memory_ref: ``(B, 4, H, W)`` the reference's memory on its grid, or None (no history).
        flow: ``(B, 2, H, W)`` temporal flow current -> reference (pixels).
        residual: ``(B, 3, H, W)`` :func:`relative_residual` of the pair.
        valid: ``(B, 1, H, W)`` bool pixels whose residual counts.
        rate: weight of this pair in (0, 1].

    Returns:
        ``(B, 4, H, W)`` the weighted sum of the residuals (3) and the weight (1) on the current grid.
    """
    if not 0.0 < rate <= 1.0:
        raise ValueError(f"memory rate must be in (0, 1], got {rate}")
    v = valid.to(residual.dtype)
    new = torch.cat([v * residual, v], 1)
    if memory_ref is None:
        return rate * new
    carried = sample_by_flow(memory_ref.to(residual.dtype), flow)
    return (1.0 - rate) * carried + rate * new


def memory_features(memory: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """``(B, 2, H, W)`` network features of a memory: ``asinh(|mean| / MEMORY_SCALE_REL)`` with
    ``mean = sum / weight`` the residual averaged over the remembered frames (0 where the weight
    is below 1e-3), and the weight itself. ``like`` ``(B, 1, H, W)`` gives the shape where
    ``memory`` is None (all zero: no history)."""
    if memory is None:
        B, _, H, W = like.shape
        return torch.zeros(B, 2, H, W, dtype=like.dtype, device=like.device)
    s, w = memory[:, :3].to(like.dtype), memory[:, 3:4].to(like.dtype)
    has = w > 1e-3
    speed = torch.where(has, s.norm(dim=1, keepdim=True) / w.clamp(min=1e-3), torch.zeros_like(w))
    return torch.cat([torch.asinh(speed / MEMORY_SCALE_REL), w], 1)
