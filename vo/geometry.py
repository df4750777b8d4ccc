"""Pinhole geometry on dense maps: back-projection, projection, bilinear sampling by flow."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def pixel_grid(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """``(1, 2, H, W)`` pixel coordinates (x, y) of every pixel centre."""
    ys, xs = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype),
        torch.arange(width, device=device, dtype=dtype),
        indexing="ij",
    )
    return torch.stack([xs, ys], 0)[None]


def backproject(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Depth map to a point map in the camera frame.

    Args:
        depth: ``(B, 1, H, W)`` depth (z), any unit.
        K: ``(B, 3, 3)`` or ``(3, 3)`` intrinsics (pixels).

    Returns:
        ``(B, 3, H, W)`` points (x, y, z) in the unit of ``depth``.
    """
    B, _, H, W = depth.shape
    K = K.expand(B, 3, 3) if K.dim() == 3 else K[None].expand(B, 3, 3)
    grid = pixel_grid(H, W, depth.device, depth.dtype)
    fx, fy = K[:, 0, 0].view(B, 1, 1, 1), K[:, 1, 1].view(B, 1, 1, 1)
    cx, cy = K[:, 0, 2].view(B, 1, 1, 1), K[:, 1, 2].view(B, 1, 1, 1)
    x = (grid[:, 0:1] - cx) / fx * depth
    y = (grid[:, 1:2] - cy) / fy * depth
    return torch.cat([x, y, depth], 1)


def project(points: torch.Tensor, K: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Point map to pixel coordinates.

    Args:
        points: ``(B, 3, ...)`` points in the camera frame.
        K: ``(B, 3, 3)`` or ``(3, 3)``.

    Returns:
        ``(B, 2, ...)`` pixel coordinates (x, y).
    """
    B = points.shape[0]
    K = K.expand(B, 3, 3) if K.dim() == 3 else K[None].expand(B, 3, 3)
    view = (B,) + (1,) * (points.dim() - 1)
    z = points[:, 2:3].clamp(min=eps)
    u = K[:, 0, 0].view(view) * points[:, 0:1] / z + K[:, 0, 2].view(view)
    v = K[:, 1, 1].view(view) * points[:, 1:2] / z + K[:, 1, 2].view(view)
    return torch.cat([u, v], 1)


def flow_grid(flow: torch.Tensor, target: torch.Tensor | None = None) -> torch.Tensor:
    """The ``grid_sample`` grid (``align_corners=True``) of the points ``x + flow(x)``.

    Args:
        flow: ``(B, 2, H, W)`` displacements (pixels).
        target: ``pixel_grid + flow`` if already computed.

    Returns:
        ``(B, H, W, 2)`` normalised coordinates; compute it once for several maps sampled by
        the same flow (:func:`sample_by_flow`, :func:`sample_valid_by_flow` take it).
    """
    B, _, H, W = flow.shape
    coords = pixel_grid(H, W, flow.device, flow.dtype) + flow if target is None else target
    gx = 2.0 * coords[:, 0] / max(W - 1, 1) - 1.0
    gy = 2.0 * coords[:, 1] / max(H - 1, 1) - 1.0
    return torch.stack([gx, gy], -1)


def sample_by_flow(image: torch.Tensor, flow: torch.Tensor, mode: str = "bilinear",
                   grid: torch.Tensor | None = None) -> torch.Tensor:
    """Sample ``image`` at ``x + flow(x)`` (bilinear, zero outside).

    Args:
        image: ``(B, C, H, W)`` map in the target view.
        flow: ``(B, 2, H, W)`` displacements (pixels) from the source grid into ``image``.
        grid: ``flow_grid(flow)`` if already computed.

    Returns:
        ``(B, C, H, W)`` sampled values on the source grid.
    """
    grid = flow_grid(flow) if grid is None else grid
    return F.grid_sample(image, grid, mode=mode, padding_mode="zeros", align_corners=True)


def change_along_flow(cur: torch.Tensor, ref: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """``|cur(x) - ref(x + F(x))|``: how much a per-pixel quantity changed between two views along
    the flow ``F`` (current -> reference), e.g. the synthetic tissue's non-rigid displacement (mm):
    how far the tissue seen at ``x`` moved between the frames. ``cur``, ``ref``: ``(B, C, H, W)``;
    ``flow``: ``(B, 2, H, W)``; zero is sampled outside the reference."""
    return (cur - sample_by_flow(ref, flow)).abs()


def lands_inside(flow: torch.Tensor, target: torch.Tensor | None = None) -> torch.Tensor:
    """``(B, 1, H, W)`` bool: where ``x + flow(x)`` lies inside the ``H x W`` image (pixel centres);
    ``target``: ``pixel_grid + flow`` if already computed."""
    _, _, H, W = flow.shape
    if target is None:
        target = pixel_grid(H, W, flow.device, flow.dtype) + flow
    return ((target[:, 0:1] >= 0) & (target[:, 0:1] <= W - 1)
            & (target[:, 1:2] >= 0) & (target[:, 1:2] <= H - 1))


def sample_valid_by_flow(valid: torch.Tensor, flow: torch.Tensor, grid: torch.Tensor | None = None) -> torch.Tensor:
    """Where bilinear sampling by ``flow`` draws only on valid pixels inside the image.

    Args:
        valid: ``(B, 1, H, W)`` bool validity of the target view.
        flow: ``(B, 2, H, W)``.
        grid: ``flow_grid(flow)`` if already computed.

    Returns:
        ``(B, 1, H, W)`` bool.
    """
    return sample_by_flow(valid.to(flow.dtype), flow, grid=grid) > 0.999


def motion_field(depth: torch.Tensor, valid: torch.Tensor, K: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """The flow a rigid motion gives: each pixel ``x`` of a view to ``pi(T pi^-1(x, D(x)))``.

    Pixels without depth (``valid`` False, or no depth) take the median depth of those with: their
    flow's rotational part is exact, the translational part a guess at the scene's depth. A view
    without any depth gives the flow at a depth of 50 mm.

    Args:
        depth: ``(1, 1, H, W)`` the view's depth (mm).
        valid: ``(1, 1, H, W)`` bool.
        K: ``(3, 3)`` intrinsics (pixels).
        T: ``(4, 4)`` the motion, the view's camera -> the other view's camera (mm).

    Returns:
        ``(1, 2, H, W)`` float32 pixels.
    """
    d = depth.float()
    has = valid & (d > 0)
    fill = d[has].median() if bool(has.any()) else d.new_tensor(50.0)
    d = torch.where(has, d, fill)
    T = torch.as_tensor(T, dtype=torch.float32, device=d.device)
    points = backproject(d, K.to(d))
    moved = torch.einsum("ij,bjhw->bihw", T[:3, :3], points) + T[:3, 3].view(1, 3, 1, 1)
    return project(moved, K.to(d)) - pixel_grid(*d.shape[-2:], device=d.device)
