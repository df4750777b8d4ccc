"""Depth from stereo parallax flow, and the correspondence checks that mark pixels invalid."""
from __future__ import annotations

import torch

from vo.config import DepthConfig
from vo.geometry import flow_grid, sample_by_flow, sample_valid_by_flow

# Smaller disparities are invalid: at the depths an endoscope sees (20-250 mm) disparities are tens
# of pixels, so this only drops the stereo matcher's zero and negative matches.
MIN_DISPARITY_PX = 0.5


def depth_from_parallax(parallax: torch.Tensor, fx_baseline: float, config: DepthConfig,
                        mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth of the left view from the stereo parallax flow (left -> right).

    Args:
        parallax: ``(B, 2, H, W)`` flow from the left to the right rectified view; disparity ``d = -F'_x``.
        fx_baseline: ``fx * baseline`` (pixel * mm): ``depth = fx_baseline / d``.
        config: validity range.
        mask: ``(B, 1, H, W)`` bool valid pixels (instrument/specular excluded) or None.

    Returns:
        depth ``(B, 1, H, W)`` mm (0 where invalid) and valid ``(B, 1, H, W)`` bool. Invalid:
        disparity below ``MIN_DISPARITY_PX``, depth outside ``[min_depth_mm, max_depth_mm]``, masked.
    """
    disparity = -parallax[:, 0:1]
    valid = disparity > MIN_DISPARITY_PX
    depth = fx_baseline / disparity.clamp(min=1e-6)
    valid = valid & (depth >= config.min_depth_mm) & (depth <= config.max_depth_mm)
    if mask is not None:
        valid = valid & mask
    return torch.where(valid, depth, torch.zeros_like(depth)), valid


def parallax_from_depth(depth: torch.Tensor, fx_baseline: float) -> torch.Tensor:
    """Synthesise the stereo parallax flow of a view from its depth (rendered model views).

    Args:
        depth: ``(B, 1, H, W)`` mm, 0 where unknown.

    Returns:
        ``(B, 2, H, W)`` with ``x = -fx_baseline / depth`` (0 where unknown) and ``y = 0``.
    """
    px = torch.where(depth > 0, -fx_baseline / depth.clamp(min=1e-6), torch.zeros_like(depth))
    return torch.cat([px, torch.zeros_like(px)], 1)


def flow_consistency(forward: torch.Tensor, backward: torch.Tensor, threshold_px: float) -> torch.Tensor:
    """Forward-backward (or left-right) consistency check.

    Args:
        forward: ``(B, 2, H, W)`` flow from view a to view b.
        backward: ``(B, 2, H, W)`` flow from view b to view a.
        threshold_px: largest tolerated round-trip error.

    Returns:
        ``(B, 1, H, W)`` bool: ``|F_ab(x) + F_ba(x + F_ab(x))| < threshold``.
    """
    return round_trip_error(forward, backward) < threshold_px


def round_trip_error(forward: torch.Tensor, backward: torch.Tensor) -> torch.Tensor:
    """``(B, 1, H, W)`` ``|F_ab(x) + F_ba(x + F_ab(x))|`` (pixels) of ``(B, 2, H, W)`` flows
    ``forward`` (a -> b) and ``backward`` (b -> a)."""
    round_trip = forward + sample_by_flow(backward, forward)
    return round_trip.norm(dim=1, keepdim=True)


def vertical_parallax_ok(parallax: torch.Tensor, max_px: float) -> torch.Tensor:
    """``(B, 1, H, W)`` bool: the vertical stereo parallax is at most ``max_px`` (rectified views have none)."""
    return parallax[:, 1:2].abs() <= max_px


def filter_depth_along_flow(depth: torch.Tensor, valid: torch.Tensor, ref_depth: torch.Tensor,
                            ref_valid: torch.Tensor, flow: torch.Tensor, flow_ok: torch.Tensor | None,
                            gain: float, gate_mm: float) -> torch.Tensor:
    """A frame's stereo depth filtered along the temporal flow against its reference's depth.

    Per pixel, ``d = p + gain (d_stereo - p)`` with ``p = d_ref(x + F(x))`` the reference's
    (filtered) depth where the flow lands: an exponential filter that follows the tissue along
    the flow, needs no pose, and keeps the stereo matcher's error, which is new in every frame,
    out of the difference between two frames' depths.

    Args:
        depth: ``(B, 1, H, W)`` the frame's stereo depth, mm (0 where invalid).
        valid: ``(B, 1, H, W)`` bool, the frame's valid depth.
        ref_depth, ref_valid: the same of the reference frame.
        flow: ``(B, 2, H, W)`` temporal flow frame -> reference (pixels).
        flow_ok: ``(B, 1, H, W)`` bool flows that passed the forward-backward check, or None.
        gain: weight of the new stereo depth in (0, 1]; 1 returns ``depth``.
        gate_mm: where ``|d_stereo - p|`` exceeds this the pixel keeps its stereo depth.

    Returns:
        ``(B, 1, H, W)`` filtered depth, mm; 0 where ``valid`` is False (validity is unchanged).
    """
    if gain >= 1.0:
        return depth
    grid = flow_grid(flow)
    carried = sample_by_flow(ref_depth, flow, grid=grid)
    # every bilinear neighbour must be valid: a mix with an invalid (0) depth is no prediction
    use = valid & sample_valid_by_flow(ref_valid, flow, grid) & (carried > 0)
    if flow_ok is not None:
        use = use & flow_ok
    innovation = depth - carried
    use = use & (innovation.abs() <= gate_mm)
    return torch.where(use, carried + gain * innovation, depth)
