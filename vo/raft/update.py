"""RAFT iterative update operator (Sec. 3.3): motion encoder, convolutional GRU, flow head, upsampling mask.

Every tensor here lives at 1/8 of the (padded) image resolution, ``(B, C, h, w)`` with ``h = H/8``,
``w = W/8``. One update step:

    motion = MotionEncoder(flow, corr)                     # (B, M, h, w), last 2 channels = flow
    net    = GRU(net, cat[context, motion])                # hidden state (B, hidden, h, w)
    delta  = FlowHead(net)                                 # (B, 2, h, w)
    mask   = 0.25 * MaskHead(net)                          # (B, 64*9, h, w), full model only

Layer names follow the published code (``encoder.convc1`` ..., ``gru.convz1`` ..., ``flow_head.conv1``,
``mask.0`` / ``mask.2``) so the published checkpoints load unchanged.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def corr_planes(levels: int, radius: int) -> int:
    """Channels of a correlation lookup: ``levels * (2 radius + 1)**2``."""
    return levels * (2 * radius + 1) ** 2


class FlowHead(nn.Module):
    """Two 3x3 convolutions: hidden state ``(B, input_dim, h, w)`` -> flow update ``(B, 2, h, w)``."""

    def __init__(self, input_dim: int = 128, hidden_dim: int = 256):
        super().__init__()
        self.conv1 = nn.Conv2d(input_dim, hidden_dim, 3, padding=1)
        self.conv2 = nn.Conv2d(hidden_dim, 2, 3, padding=1)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv2(self.relu(self.conv1(x)))


def _gru_step(h: torch.Tensor, x: torch.Tensor, convz: nn.Conv2d, convr: nn.Conv2d, convq: nn.Conv2d) -> torch.Tensor:
    """One convolutional GRU update of ``h`` ``(B, Ch, h, w)`` given input ``x`` ``(B, Cx, h, w)``.

    ``z = sigmoid(Wz [h, x])``, ``r = sigmoid(Wr [h, x])``, ``q = tanh(Wq [r*h, x])``,
    ``h' = (1 - z) h + z q``.
    """
    hx = torch.cat([h, x], dim=1)
    z = torch.sigmoid(convz(hx))
    r = torch.sigmoid(convr(hx))
    q = torch.tanh(convq(torch.cat([r * h, x], dim=1)))
    return (1 - z) * h + z * q


class ConvGRU(nn.Module):
    """GRU with 3x3 convolutional gates (RAFT-S): ``h (B, hidden, h, w), x (B, input, h, w) -> h'``."""

    def __init__(self, hidden_dim: int = 128, input_dim: int = 192 + 128):
        super().__init__()
        cin = hidden_dim + input_dim
        self.convz = nn.Conv2d(cin, hidden_dim, 3, padding=1)
        self.convr = nn.Conv2d(cin, hidden_dim, 3, padding=1)
        self.convq = nn.Conv2d(cin, hidden_dim, 3, padding=1)

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return _gru_step(h, x, self.convz, self.convr, self.convq)


class SepConvGRU(nn.Module):
    """Separable GRU (full RAFT): a 1x5 (horizontal) GRU step followed by a 5x1 (vertical) one.

    ``h (B, hidden, h, w), x (B, input, h, w) -> h' (B, hidden, h, w)``.
    """

    def __init__(self, hidden_dim: int = 128, input_dim: int = 192 + 128):
        super().__init__()
        cin = hidden_dim + input_dim
        self.convz1 = nn.Conv2d(cin, hidden_dim, (1, 5), padding=(0, 2))
        self.convr1 = nn.Conv2d(cin, hidden_dim, (1, 5), padding=(0, 2))
        self.convq1 = nn.Conv2d(cin, hidden_dim, (1, 5), padding=(0, 2))
        self.convz2 = nn.Conv2d(cin, hidden_dim, (5, 1), padding=(2, 0))
        self.convr2 = nn.Conv2d(cin, hidden_dim, (5, 1), padding=(2, 0))
        self.convq2 = nn.Conv2d(cin, hidden_dim, (5, 1), padding=(2, 0))

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        h = _gru_step(h, x, self.convz1, self.convr1, self.convq1)
        return _gru_step(h, x, self.convz2, self.convr2, self.convq2)


class BasicMotionEncoder(nn.Module):
    """Motion features of the full model.

    ``flow (B, 2, h, w)``, ``corr (B, levels*(2r+1)**2, h, w)`` -> ``(B, 128, h, w)``: 126 learned
    channels (corr branch 256 -> 192, flow branch 128 -> 64, fused by a 3x3 conv) followed by the flow.
    """

    out_dim = 128

    def __init__(self, corr_levels: int = 4, corr_radius: int = 4):
        super().__init__()
        self.convc1 = nn.Conv2d(corr_planes(corr_levels, corr_radius), 256, 1, padding=0)
        self.convc2 = nn.Conv2d(256, 192, 3, padding=1)
        self.convf1 = nn.Conv2d(2, 128, 7, padding=3)
        self.convf2 = nn.Conv2d(128, 64, 3, padding=1)
        self.conv = nn.Conv2d(64 + 192, 128 - 2, 3, padding=1)

    def forward(self, flow: torch.Tensor, corr: torch.Tensor) -> torch.Tensor:
        cor = F.relu(self.convc2(F.relu(self.convc1(corr))))
        flo = F.relu(self.convf2(F.relu(self.convf1(flow))))
        out = F.relu(self.conv(torch.cat([cor, flo], dim=1)))
        return torch.cat([out, flow], dim=1)


class SmallMotionEncoder(nn.Module):
    """Motion features of RAFT-S.

    ``flow (B, 2, h, w)``, ``corr (B, levels*(2r+1)**2, h, w)`` -> ``(B, 82, h, w)``: 80 learned
    channels (corr branch -> 96, flow branch 64 -> 32, fused by a 3x3 conv) followed by the flow.
    """

    out_dim = 82

    def __init__(self, corr_levels: int = 4, corr_radius: int = 3):
        super().__init__()
        self.convc1 = nn.Conv2d(corr_planes(corr_levels, corr_radius), 96, 1, padding=0)
        self.convf1 = nn.Conv2d(2, 64, 7, padding=3)
        self.convf2 = nn.Conv2d(64, 32, 3, padding=1)
        self.conv = nn.Conv2d(128, 80, 3, padding=1)

    def forward(self, flow: torch.Tensor, corr: torch.Tensor) -> torch.Tensor:
        cor = F.relu(self.convc1(corr))
        flo = F.relu(self.convf2(F.relu(self.convf1(flow))))
        out = F.relu(self.conv(torch.cat([cor, flo], dim=1)))
        return torch.cat([out, flow], dim=1)


class BasicUpdateBlock(nn.Module):
    """Update operator of the full model (SepConvGRU, hidden 128, context 128, convex-upsampling mask).

    ``forward(net, inp, corr, flow)`` with ``net (B, hidden, h, w)``, ``inp (B, context, h, w)``,
    ``corr (B, levels*(2r+1)**2, h, w)``, ``flow (B, 2, h, w)`` returns ``(net', mask, delta_flow)``:
    ``(B, hidden, h, w)``, ``(B, 9 * mask_size**2, h, w)`` (already scaled by 0.25) and ``(B, 2, h, w)``.
    """

    def __init__(self, hidden_dim: int = 128, context_dim: int = 128, corr_levels: int = 4, corr_radius: int = 4,
                 mask_size: int = 8):
        super().__init__()
        self.encoder = BasicMotionEncoder(corr_levels, corr_radius)
        self.gru = SepConvGRU(hidden_dim=hidden_dim, input_dim=context_dim + BasicMotionEncoder.out_dim)
        self.flow_head = FlowHead(hidden_dim, hidden_dim=256)
        self.mask = nn.Sequential(
            nn.Conv2d(hidden_dim, 256, 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(256, mask_size**2 * 9, 1, padding=0),
        )

    def forward(self, net: torch.Tensor, inp: torch.Tensor, corr: torch.Tensor, flow: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        motion = self.encoder(flow, corr)
        net = self.gru(net, torch.cat([inp, motion], dim=1))
        delta_flow = self.flow_head(net)
        mask = 0.25 * self.mask(net)  # the published scaling (balances gradients during training)
        return net, mask, delta_flow


class SmallUpdateBlock(nn.Module):
    """Update operator of RAFT-S (ConvGRU, hidden 96, context 64, no mask: bilinear upsampling).

    ``forward(net, inp, corr, flow)`` returns ``(net' (B, hidden, h, w), None, delta_flow (B, 2, h, w))``.
    """

    def __init__(self, hidden_dim: int = 96, context_dim: int = 64, corr_levels: int = 4, corr_radius: int = 3):
        super().__init__()
        self.encoder = SmallMotionEncoder(corr_levels, corr_radius)
        self.gru = ConvGRU(hidden_dim=hidden_dim, input_dim=context_dim + SmallMotionEncoder.out_dim)
        self.flow_head = FlowHead(hidden_dim, hidden_dim=128)

    def forward(self, net: torch.Tensor, inp: torch.Tensor, corr: torch.Tensor, flow: torch.Tensor
                ) -> tuple[torch.Tensor, None, torch.Tensor]:
        motion = self.encoder(flow, corr)
        net = self.gru(net, torch.cat([inp, motion], dim=1))
        return net, None, self.flow_head(net)
