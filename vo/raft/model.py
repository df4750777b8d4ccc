"""RAFT: Recurrent All-Pairs Field Transforms for optical flow (Teed and Deng, ECCV 2020).

Pipeline for two images ``(B, 3, H, W)`` in [0, 255], ``H`` and ``W`` multiples of 8:

1. ``fnet`` encodes both images to ``(B, Df, H/8, W/8)`` features; their all-pairs correlation
   pyramid is built once (:class:`~vo.raft.corr.CorrBlock`).
2. ``cnet`` encodes the first image to ``(B, hidden + context, H/8, W/8)``: ``tanh`` of the first
   ``hidden`` channels initialises the GRU state, ``relu`` of the rest is the context input.
3. Starting from ``flow_init`` (or zero), ``iters`` update steps look the pyramid up at the current
   correspondences and add the update block's ``delta_flow``.
4. Each estimate is upsampled to full resolution: convex combination of 3x3 coarse neighbours with
   learned weights (full model) or bilinear x8 (RAFT-S).

Configurations (as published):

=========  ==========  ======  =======  ======  ======  ====================
model      encoder     Df      hidden   context  radius  GRU
=========  ==========  ======  =======  ======  ======  ====================
RAFT       Basic       256     128      128      4       SepConvGRU (1x5, 5x1)
RAFT-S     Small       128     96       64       3       ConvGRU (3x3)
=========  ==========  ======  =======  ======  ======  ====================

``RAFT().state_dict()`` has the names and shapes of ``raft-things.pth`` (and ``RAFT(small=True)`` of
``raft-small.pth``) once DataParallel's ``module.`` prefix is stripped.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .corr import CorrBlock, coords_grid
from .extractor import BasicEncoder, SmallEncoder
from .update import BasicUpdateBlock, SmallUpdateBlock


def upflow8(flow: torch.Tensor) -> torch.Tensor:
    """Bilinear x8 upsampling of a 1/8-resolution flow ``(B, 2, h, w) -> (B, 2, 8h, 8w)`` (values x8)."""
    h, w = flow.shape[-2:]
    return 8 * F.interpolate(flow, size=(8 * h, 8 * w), mode="bilinear", align_corners=True)


def convex_upsample(flow: torch.Tensor, mask: torch.Tensor, factor: int = 8) -> torch.Tensor:
    """Convex upsampling ``(B, 2, h, w) -> (B, 2, factor*h, factor*w)``.

    ``mask`` ``(B, 9 * factor**2, h, w)`` holds, for each of the ``factor x factor`` fine pixels of a
    coarse cell, logits over the cell's 3x3 coarse neighbourhood (layout ``(9, factor, factor)``,
    neighbour-major); the fine flow is the softmax-weighted combination of the neighbours' flows times
    ``factor``.
    """
    b, _, h, w = flow.shape
    weights = torch.softmax(mask.view(b, 1, 9, factor, factor, h, w), dim=2)
    neigh = F.unfold(factor * flow, [3, 3], padding=1).view(b, 2, 9, 1, 1, h, w)
    up = torch.sum(weights * neigh, dim=2)  # (B, 2, factor, factor, h, w)
    up = up.permute(0, 1, 4, 2, 5, 3)  # (B, 2, h, factor, w, factor)
    return up.reshape(b, 2, factor * h, factor * w)


class RAFT(nn.Module):
    """The RAFT optical-flow network.

    Args:
        small: build RAFT-S (``raft-small.pth``) instead of the full model (``raft-things.pth`` etc.).
        dropout: dropout of the encoders while training (0 as published for inference).

    Attributes:
        hidden_dim, context_dim: GRU state and context channels.
        corr_levels, corr_radius: correlation pyramid levels and lookup radius.
    """

    def __init__(self, small: bool = False, dropout: float = 0.0):
        super().__init__()
        self.small = small
        self.corr_levels = 4
        if small:
            self.hidden_dim, self.context_dim, self.corr_radius = 96, 64, 3
            self.fnet = SmallEncoder(output_dim=128, norm_fn="instance", dropout=dropout)
            self.cnet = SmallEncoder(output_dim=self.hidden_dim + self.context_dim, norm_fn="none", dropout=dropout)
            self.update_block = SmallUpdateBlock(self.hidden_dim, self.context_dim, self.corr_levels, self.corr_radius)
        else:
            self.hidden_dim, self.context_dim, self.corr_radius = 128, 128, 4
            self.fnet = BasicEncoder(output_dim=256, norm_fn="instance", dropout=dropout)
            self.cnet = BasicEncoder(output_dim=self.hidden_dim + self.context_dim, norm_fn="batch", dropout=dropout)
            self.update_block = BasicUpdateBlock(self.hidden_dim, self.context_dim, self.corr_levels, self.corr_radius)

    def freeze_bn(self) -> None:
        """Put every batch-norm layer in eval mode (the published fine-tuning recipe)."""
        for m in self.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.eval()

    @staticmethod
    def initialize_flow(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Two copies of the 1/8-resolution pixel grid ``(B, 2, H/8, W/8)``; flow = ``coords1 - coords0``."""
        b, _, h, w = image.shape
        coords0 = coords_grid(b, h // 8, w // 8, device=image.device)
        return coords0, coords0.clone()

    def upsample(self, flow: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """1/8 flow ``(B, 2, h, w)`` to full resolution: convex with ``mask``, bilinear without."""
        return upflow8(flow) if mask is None else convex_upsample(flow, mask)

    def forward(self, image1: torch.Tensor, image2: torch.Tensor, iters: int = 12,
                flow_init: torch.Tensor | None = None, upsample: bool = True, test_mode: bool = False):
        """Estimate the flow from ``image1`` to ``image2``.

        Args:
            image1, image2: ``(B, 3, H, W)`` RGB in [0, 255]; ``H, W`` multiples of 8.
            iters: number of update steps.
            flow_init: optional ``(B, 2, H/8, W/8)`` initial flow at 1/8 resolution (pixels of that grid).
            upsample: outside ``test_mode``, return full-resolution predictions (else the 1/8 ones).
            test_mode: return only the final estimate.

        Returns:
            ``test_mode``: ``(flow_low (B, 2, H/8, W/8), flow_up (B, 2, H, W))``.
            otherwise: the list of ``iters`` predictions, each ``(B, 2, H, W)``
            (``(B, 2, H/8, W/8)`` when ``upsample`` is False).
        """
        if image1.shape != image2.shape:
            raise ValueError(f"image shapes differ: {tuple(image1.shape)} vs {tuple(image2.shape)}")
        if image1.dim() != 4 or image1.shape[1] != 3:
            raise ValueError(f"expected (B, 3, H, W) images, got {tuple(image1.shape)}")
        h, w = image1.shape[-2:]
        if h % 8 or w % 8:
            raise ValueError(f"image size {h}x{w} is not a multiple of 8; pad the inputs first")

        image1 = (2 * (image1 / 255.0) - 1.0).contiguous()
        image2 = (2 * (image2 / 255.0) - 1.0).contiguous()

        fmap1, fmap2 = self.fnet([image1, image2])
        corr_fn = CorrBlock(fmap1.float(), fmap2.float(), num_levels=self.corr_levels, radius=self.corr_radius)

        net, inp = torch.split(self.cnet(image1), [self.hidden_dim, self.context_dim], dim=1)
        net = torch.tanh(net)
        inp = torch.relu(inp)

        coords0, coords1 = self.initialize_flow(image1)
        if flow_init is not None:
            coords1 = coords1 + flow_init

        predictions = []
        up_mask = None
        for _ in range(iters):
            coords1 = coords1.detach()
            corr = corr_fn(coords1)
            net, up_mask, delta_flow = self.update_block(net, inp, corr, coords1 - coords0)
            coords1 = coords1 + delta_flow
            if not test_mode:
                flow = coords1 - coords0
                predictions.append(self.upsample(flow, up_mask) if upsample else flow)

        if test_mode:
            flow_low = coords1 - coords0
            return flow_low, self.upsample(flow_low, up_mask)
        return predictions
