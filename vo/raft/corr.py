"""All-pairs correlation pyramid and its windowed lookup (RAFT, Sec. 3.2).

For feature maps ``f1, f2`` of shape ``(B, D, H, W)`` (1/8 resolution) the correlation volume is

    C[b, i, j, k, l] = <f1[b, :, i, j], f2[b, :, k, l]> / sqrt(D)

kept as ``(B*H*W, 1, H, W)``: one "image" over the second frame's pixels per first-frame pixel.
Level ``k`` of the pyramid average-pools the last two dims by ``2**k`` (``F.avg_pool2d`` with kernel
and stride 2, applied ``k`` times, so odd sizes floor; a dimension of size 1 stays 1, see
:func:`pool_level`).

The lookup samples every level bilinearly on a ``(2r+1) x (2r+1)`` window of integer offsets around
``coords / 2**k`` (pixel coordinates in the second frame) and concatenates the levels into
``num_levels * (2r+1)**2`` channels. Within a level, channel ``a * (2r+1) + b`` holds the
offset ``dx = a - r, dy = b - r`` (x-major): this is the order the published weights were trained
with, so it is kept here.

Pure torch: no CUDA-only ``alt_cuda_corr`` variant.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def coords_grid(batch: int, ht: int, wd: int, device: torch.device | str | None = None) -> torch.Tensor:
    """Pixel coordinates ``(batch, 2, ht, wd)`` float32, channel 0 = x (column), channel 1 = y (row)."""
    ys, xs = torch.meshgrid(
        torch.arange(ht, device=device, dtype=torch.float32),
        torch.arange(wd, device=device, dtype=torch.float32),
        indexing="ij",
    )
    return torch.stack([xs, ys], dim=0)[None].repeat(batch, 1, 1, 1)


def bilinear_sampler(img: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Sample ``img`` ``(N, C, H, W)`` at pixel coordinates ``coords`` ``(N, h, w, 2)`` (x, y).

    Bilinear with zeros outside the image: ``F.grid_sample(..., align_corners=True)`` after mapping
    pixel ``x`` to ``2 x / (W - 1) - 1``, as the original. A dimension of size 1 (the coarsest level of
    a small image) would make that mapping divide by zero, so such a dimension is first padded with
    one zero row/column, which leaves the zero-padded bilinear interpolant unchanged.

    Returns ``(N, C, h, w)``.
    """
    H, W = img.shape[-2:]
    if H == 1 or W == 1:
        img = F.pad(img, (0, 1 if W == 1 else 0, 0, 1 if H == 1 else 0))
        H, W = img.shape[-2:]
    x, y = coords.unbind(dim=-1)
    grid = torch.stack([2.0 * x / (W - 1) - 1.0, 2.0 * y / (H - 1) - 1.0], dim=-1)
    return F.grid_sample(img, grid, mode="bilinear", padding_mode="zeros", align_corners=True)


def all_pairs_correlation(fmap1: torch.Tensor, fmap2: torch.Tensor) -> torch.Tensor:
    """Dot products of every feature pair, scaled by ``1/sqrt(D)``.

    ``fmap1, fmap2``: ``(B, D, H, W)``. Returns ``(B, H, W, 1, H, W)``: entry ``[b, i, j, 0, k, l]``
    correlates pixel ``(i, j)`` of the first map with pixel ``(k, l)`` of the second.
    """
    batch, dim, ht, wd = fmap1.shape
    f1 = fmap1.reshape(batch, dim, ht * wd)
    f2 = fmap2.reshape(batch, dim, ht * wd)
    corr = torch.matmul(f1.transpose(1, 2), f2)  # (B, HW, HW)
    return corr.view(batch, ht, wd, 1, ht, wd) / math.sqrt(dim)


def window_offsets(radius: int, device: torch.device | str | None = None) -> torch.Tensor:
    """Integer lookup offsets ``(2r+1, 2r+1, 2)``; entry ``[a, b]`` is ``(dx, dy) = (a - r, b - r)``."""
    d = torch.arange(-radius, radius + 1, device=device, dtype=torch.float32)
    da, db = torch.meshgrid(d, d, indexing="ij")
    return torch.stack([da, db], dim=-1)


def pool_level(corr: torch.Tensor) -> torch.Tensor:
    """The next pyramid level: ``(N, 1, H, W) -> (N, 1, H // 2, W // 2)`` by 2x2 average pooling.

    As the original on any input it handles (every level at least 1 x 1). A dimension already of
    size 1, where the original would fail (images under 64 px), is left at 1 instead of pooled.
    """
    kh = 2 if corr.shape[-2] >= 2 else 1
    kw = 2 if corr.shape[-1] >= 2 else 1
    if kh == kw == 2:
        return F.avg_pool2d(corr, 2, stride=2)
    return F.avg_pool2d(corr, (kh, kw), stride=(kh, kw))


class CorrBlock:
    """The correlation pyramid of two feature maps, indexed by :meth:`__call__`.

    Args:
        fmap1, fmap2: ``(B, D, H, W)`` features of the first and second image.
        num_levels: pyramid levels (4 in RAFT and RAFT-S).
        radius: lookup radius ``r`` (4 in RAFT, 3 in RAFT-S).

    Attributes:
        corr_pyramid: list of ``num_levels`` tensors ``(B*H*W, 1, H_k, W_k)``, ``H_k = max(H // 2**k, 1)``.
    """

    def __init__(self, fmap1: torch.Tensor, fmap2: torch.Tensor, num_levels: int = 4, radius: int = 4):
        self.num_levels = num_levels
        self.radius = radius
        corr = all_pairs_correlation(fmap1.float(), fmap2.float())
        batch, h1, w1, dim, h2, w2 = corr.shape
        corr = corr.reshape(batch * h1 * w1, dim, h2, w2)
        self.corr_pyramid = [corr]
        for _ in range(num_levels - 1):
            corr = pool_level(corr)
            self.corr_pyramid.append(corr)

    @property
    def out_channels(self) -> int:
        """``num_levels * (2r+1)**2``: channels of a lookup."""
        return self.num_levels * (2 * self.radius + 1) ** 2

    def __call__(self, coords: torch.Tensor) -> torch.Tensor:
        """Look the pyramid up around ``coords`` ``(B, 2, H, W)`` (x, y pixel positions in image 2 at 1/8).

        Returns ``(B, num_levels * (2r+1)**2, H, W)`` float32: levels in order, each level's window
        x-major (see the module docstring).
        """
        r = self.radius
        batch, _, h1, w1 = coords.shape
        centres = coords.permute(0, 2, 3, 1).reshape(batch * h1 * w1, 1, 1, 2)
        delta = window_offsets(r, device=coords.device).view(1, 2 * r + 1, 2 * r + 1, 2)
        out = []
        for level, corr in enumerate(self.corr_pyramid):
            sampled = bilinear_sampler(corr, centres / 2**level + delta)  # (BHW, 1, 2r+1, 2r+1)
            out.append(sampled.view(batch, h1, w1, -1))
        return torch.cat(out, dim=-1).permute(0, 3, 1, 2).contiguous().float()
