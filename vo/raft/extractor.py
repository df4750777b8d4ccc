"""RAFT feature and context encoders (Teed and Deng, ECCV 2020, Sec. 3.1).

Both encoders map an image ``(B, 3, H, W)`` to a feature map at 1/8 resolution
``(B, C, H/8, W/8)``: a stride-2 7x7 stem, three stages of two residual blocks (the second and third
stage halve the resolution again), and a 1x1 output projection.

* :class:`BasicEncoder` (the full model): residual blocks of two 3x3 convolutions,
  stage widths 64 / 96 / 128.
* :class:`SmallEncoder` (RAFT-S): bottleneck blocks (1x1 -> 3x3 -> 1x1 at a quarter of the width),
  stage widths 32 / 64 / 96.

Submodule names follow the published code so that ``raft-things.pth`` / ``raft-small.pth`` load
unchanged: ``conv1``, ``norm1``, ``layer1..3`` (``nn.Sequential`` of two blocks), ``conv2``; inside a
block ``conv1..3``, ``norm1..4`` and ``downsample`` (``Sequential(conv1x1, norm)``, the norm module
being shared with the block's last norm attribute, so batch-norm statistics appear under both names).
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

NORMS = ("group", "batch", "instance", "none")


def make_norm(kind: str, channels: int, groups: int) -> nn.Module:
    """A normalisation layer over ``channels`` feature maps.

    ``kind`` is one of ``"group"`` (``groups`` groups), ``"batch"`` (with running statistics: these are
    state-dict entries), ``"instance"`` (no affine, no running statistics: no state) or ``"none"``
    (an empty ``nn.Sequential``, the identity, no state).
    """
    if kind == "group":
        return nn.GroupNorm(num_groups=groups, num_channels=channels)
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "instance":
        return nn.InstanceNorm2d(channels)
    if kind == "none":
        return nn.Sequential()
    raise ValueError(f"unknown norm {kind!r}; expected one of {NORMS}")


class ResidualBlock(nn.Module):
    """Two 3x3 convolutions with a skip connection: ``(B, Cin, H, W) -> (B, C, H/s, W/s)``.

    With ``stride != 1`` the skip path is a strided 1x1 convolution followed by ``norm3``.
    """

    def __init__(self, in_planes: int, planes: int, norm_fn: str = "group", stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(in_planes, planes, kernel_size=3, padding=1, stride=stride)
        self.conv2 = nn.Conv2d(planes, planes, kernel_size=3, padding=1)
        self.relu = nn.ReLU(inplace=True)
        groups = planes // 8
        self.norm1 = make_norm(norm_fn, planes, groups)
        self.norm2 = make_norm(norm_fn, planes, groups)
        if stride != 1:
            self.norm3 = make_norm(norm_fn, planes, groups)
            self.downsample = nn.Sequential(nn.Conv2d(in_planes, planes, kernel_size=1, stride=stride), self.norm3)
        else:
            self.downsample = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.relu(self.norm1(self.conv1(x)))
        y = self.relu(self.norm2(self.conv2(y)))
        skip = x if self.downsample is None else self.downsample(x)
        return self.relu(skip + y)


class BottleneckBlock(nn.Module):
    """1x1 -> 3x3 (strided) -> 1x1 bottleneck at ``planes // 4`` width with a skip connection.

    ``(B, Cin, H, W) -> (B, planes, H/s, W/s)``; with ``stride != 1`` the skip path is a strided 1x1
    convolution followed by ``norm4``.
    """

    def __init__(self, in_planes: int, planes: int, norm_fn: str = "group", stride: int = 1):
        super().__init__()
        mid = planes // 4
        self.conv1 = nn.Conv2d(in_planes, mid, kernel_size=1, padding=0)
        self.conv2 = nn.Conv2d(mid, mid, kernel_size=3, padding=1, stride=stride)
        self.conv3 = nn.Conv2d(mid, planes, kernel_size=1, padding=0)
        self.relu = nn.ReLU(inplace=True)
        groups = planes // 8
        self.norm1 = make_norm(norm_fn, mid, groups)
        self.norm2 = make_norm(norm_fn, mid, groups)
        self.norm3 = make_norm(norm_fn, planes, groups)
        if stride != 1:
            self.norm4 = make_norm(norm_fn, planes, groups)
            self.downsample = nn.Sequential(nn.Conv2d(in_planes, planes, kernel_size=1, stride=stride), self.norm4)
        else:
            self.downsample = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.relu(self.norm1(self.conv1(x)))
        y = self.relu(self.norm2(self.conv2(y)))
        y = self.relu(self.norm3(self.conv3(y)))
        skip = x if self.downsample is None else self.downsample(x)
        return self.relu(skip + y)


class _Encoder(nn.Module):
    """Shared stem / three stages / projection skeleton of both encoders."""

    block: type[nn.Module]
    widths: tuple[int, int, int]

    def __init__(self, output_dim: int, norm_fn: str, dropout: float):
        super().__init__()
        self.norm_fn = norm_fn
        stem = self.widths[0]
        # norm1 is registered before conv1, as in the published checkpoints' key order
        self.norm1 = make_norm(norm_fn, stem, groups=8)
        self.conv1 = nn.Conv2d(3, stem, kernel_size=7, stride=2, padding=3)
        self.relu1 = nn.ReLU(inplace=True)
        self.in_planes = stem
        self.layer1 = self._make_layer(self.widths[0], stride=1)
        self.layer2 = self._make_layer(self.widths[1], stride=2)
        self.layer3 = self._make_layer(self.widths[2], stride=2)
        self.conv2 = nn.Conv2d(self.widths[2], output_dim, kernel_size=1)
        self.dropout = nn.Dropout2d(p=dropout) if dropout > 0 else None
        self._init_weights()

    def _make_layer(self, dim: int, stride: int) -> nn.Sequential:
        first = self.block(self.in_planes, dim, self.norm_fn, stride=stride)
        second = self.block(dim, dim, self.norm_fn, stride=1)
        self.in_planes = dim
        return nn.Sequential(first, second)

    def _init_weights(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, (nn.BatchNorm2d, nn.InstanceNorm2d, nn.GroupNorm)):
                if m.weight is not None:
                    nn.init.constant_(m.weight, 1)
                if m.bias is not None:
                    nn.init.constant_(m.bias, 0)

    def forward(self, x: torch.Tensor | Sequence[torch.Tensor]) -> torch.Tensor | tuple[torch.Tensor, ...]:
        """Encode ``(B, 3, H, W)`` -> ``(B, output_dim, H/8, W/8)``.

        A list/tuple of images (each ``(B, 3, H, W)``) is encoded in one batch and returned as a tuple
        of feature maps, one per input.
        """
        as_list = isinstance(x, (list, tuple))
        if as_list:
            sizes = [t.shape[0] for t in x]
            x = torch.cat(list(x), dim=0)
        x = self.relu1(self.norm1(self.conv1(x)))
        x = self.layer3(self.layer2(self.layer1(x)))
        x = self.conv2(x)
        if self.dropout is not None and self.training:
            x = self.dropout(x)
        if as_list:
            return tuple(torch.split(x, sizes, dim=0))
        return x


class BasicEncoder(_Encoder):
    """The full RAFT encoder: residual blocks, widths 64/96/128, output ``(B, output_dim, H/8, W/8)``."""

    block = ResidualBlock
    widths = (64, 96, 128)

    def __init__(self, output_dim: int = 128, norm_fn: str = "batch", dropout: float = 0.0):
        super().__init__(output_dim, norm_fn, dropout)


class SmallEncoder(_Encoder):
    """The RAFT-S encoder: bottleneck blocks, widths 32/64/96, output ``(B, output_dim, H/8, W/8)``."""

    block = BottleneckBlock
    widths = (32, 64, 96)

    def __init__(self, output_dim: int = 128, norm_fn: str = "batch", dropout: float = 0.0):
        super().__init__(output_dim, norm_fn, dropout)
