"""The weight maps w2D and w3D (paper eqs. 5-6): two small UNets with sigmoid outputs, run at a
reduced resolution and upsampled, and the constant alternative.

Inputs of the networks (all at 1/``downscale`` of the image, area-averaged), layout version 2:
- w2D: pixel coordinates (2, in [-1, 1]), current image I_t (3), current depth D_t / D_max (1),
  temporal flow F_t (2), stereo parallax flow F'_t (2), valid mask (1), and the temporal flow again
  on a sub-pixel scale, ``asinh(F_t / 0.5 px)`` (2): 13 channels.
- w3D: the same 13, plus the reference image I_ref (3), its depth D_ref / D_max (1) and its parallax
  flow F'_ref (2), warped by the flow onto the current pixel grid (the paper feeds them unwarped;
  aligned inputs let a small network compare the two views pixel by pixel), and the relative depth
  change ``asinh((D_t - D_ref(x + F_t)) / D_t / 0.003)`` computed at full resolution where both
  depths are valid (1): 20 channels.
The last two groups make the non-rigid motion visible at the scale it has between frames (about
0.02-0.1 mm, 0.1-0.4 px at 25 fps on our synthetic tissue); on the version-1 scales (kept for old
checkpoints: 11 and 17 channels, without them) a 0.06 mm depth change is 2e-4 of the depth input.
Flows are scaled by ``20 / W`` (a flow of 5 % of the width is 1); the vertical parallax by ``W0 / (2 W)``
with ``W0 = 640`` (2 px at the paper's resolution is 1).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from vo.geometry import sample_by_flow

INPUT_VERSION = 2
IN_CHANNELS = {1: (11, 17), 2: (13, 20)}  # input layout version -> (w2D, w3D) channels
IN_CHANNELS_2D, IN_CHANNELS_3D = IN_CHANNELS[INPUT_VERSION]
FLOW_FINE_PX = 0.5  # sub-pixel flow scale of the version-2 inputs
DEPTH_CHANGE_REL = 0.003  # relative depth change scale (0.2 mm at 70 mm, the stereo noise at 1/8)
CHECKPOINT_DIR = Path(__file__).parent / "checkpoints"

log = logging.getLogger(__name__)


@dataclass
class WeightInputs:
    """Full-resolution inputs of the weight networks (batch ``B``).

    Attributes:
        image_cur, image_ref: ``(B, 3, H, W)`` RGB in [0, 1].
        depth_cur, depth_ref: ``(B, 1, H, W)`` normalised depth (0 where invalid).
        flow: ``(B, 2, H, W)`` temporal flow current -> reference (pixels).
        parallax_cur, parallax_ref: ``(B, 2, H, W)`` stereo parallax flows (pixels).
        valid: ``(B, 1, H, W)`` bool pixels that enter the objective.
        depth_ref_along_flow: ``depth_ref`` sampled at ``x + flow`` (bilinear) where the residual
            problem already did (its reference points' z), else None: sampled here.
        lands_on_ref_depth: ``(B, 1, H, W)`` bool pixels whose flow draws on valid reference depth
            only (the 3D residual's pixels), given with ``depth_ref_along_flow``.
    """

    image_cur: torch.Tensor
    depth_cur: torch.Tensor
    flow: torch.Tensor
    parallax_cur: torch.Tensor
    image_ref: torch.Tensor
    depth_ref: torch.Tensor
    parallax_ref: torch.Tensor
    valid: torch.Tensor
    depth_ref_along_flow: torch.Tensor | None = None
    lands_on_ref_depth: torch.Tensor | None = None


def _scale_flow(flow: torch.Tensor, width: int) -> torch.Tensor:
    return flow * (20.0 / width)


def _scale_parallax(parallax: torch.Tensor, width: int) -> torch.Tensor:
    return torch.cat([parallax[:, 0:1] * (20.0 / width), parallax[:, 1:2] * (640.0 / (2.0 * width))], 1)


def _downsample(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    return F.adaptive_avg_pool2d(x, size) if x.shape[-2:] != size else x


def network_inputs(inp: WeightInputs, downscale: int, version: int = INPUT_VERSION) -> tuple[torch.Tensor, torch.Tensor]:
    """Assemble the inputs at reduced resolution (everything is area-averaged first, then the
    reference maps are warped by the downsampled flow, which keeps this step cheap; the relative
    depth change of version 2 is formed at full resolution, then averaged).

    Returns:
        ``x2d`` ``(B, C2, h, w)`` and ``x3d`` ``(B, C3, h, w)`` with ``h = ceil(H / downscale)`` and
        ``(C2, C3) = IN_CHANNELS[version]``; ``x2d`` is the first ``C2`` channels of ``x3d``.
    """
    if version not in IN_CHANNELS:
        raise ValueError(f"unknown weight-network input version {version}")
    B, _, H, W = inp.image_cur.shape
    h, w = -(-H // downscale), -(-W // downscale)
    dtype, device = inp.flow.dtype, inp.flow.device
    ys, xs = torch.meshgrid(torch.linspace(-1, 1, h, device=device, dtype=dtype),
                            torch.linspace(-1, 1, w, device=device, dtype=dtype), indexing="ij")
    coords = torch.stack([xs, ys])[None].expand(B, 2, h, w)
    flow = _downsample(inp.flow, (h, w))
    cur = _downsample(torch.cat([inp.image_cur, inp.depth_cur, _scale_flow(inp.flow, W),
                                 _scale_parallax(inp.parallax_cur, W), inp.valid.to(dtype)], 1), (h, w))
    ref = _downsample(torch.cat([inp.image_ref, inp.depth_ref, _scale_parallax(inp.parallax_ref, W)], 1), (h, w))
    flow_low = torch.stack([flow[:, 0] * (w / W), flow[:, 1] * (h / H)], 1)
    ref_warped = sample_by_flow(ref, flow_low)
    if version == 1:
        x3 = torch.cat([coords, cur, ref_warped], 1)
        return x3[:, :IN_CHANNELS[1][0]], x3
    flow_fine = torch.asinh(flow / FLOW_FINE_PX)
    # relative depth change between the views along the flow (zero where either depth is invalid)
    if inp.depth_ref_along_flow is None:
        warped = sample_by_flow(torch.cat([inp.depth_ref, (inp.depth_ref > 0).to(dtype)], 1), inp.flow)
        depth_ref_along_flow, lands = warped[:, 0:1], warped[:, 1:2] > 0.999
    else:
        depth_ref_along_flow, lands = inp.depth_ref_along_flow, inp.lands_on_ref_depth
    both = inp.valid & (inp.depth_cur > 0) & lands
    rel = torch.where(both, (inp.depth_cur - depth_ref_along_flow) / inp.depth_cur.clamp(min=1e-6), torch.zeros_like(inp.depth_cur))
    change = torch.asinh(_downsample(rel, (h, w)) / DEPTH_CHANGE_REL)
    x3 = torch.cat([coords, cur, flow_fine, ref_warped, change], 1)
    return x3[:, :IN_CHANNELS[2][0]], x3


class _Block(nn.Sequential):
    def __init__(self, cin: int, cout: int):
        super().__init__(
            nn.Conv2d(cin, cout, 3, padding=1), nn.GroupNorm(4, cout), nn.LeakyReLU(0.1, inplace=True),
            nn.Conv2d(cout, cout, 3, padding=1), nn.GroupNorm(4, cout), nn.LeakyReLU(0.1, inplace=True),
        )


class WeightUNet(nn.Module):
    """A 3-level encoder-decoder with skip connections and a sigmoid output.

    Input ``(B, C, h, w)`` -> output ``(B, 1, h, w)`` in (0, 1). Any ``h, w`` (padded internally).
    """

    def __init__(self, in_channels: int, base: int = 16, initial_weight: float = 0.5):
        super().__init__()
        self.enc1 = _Block(in_channels, base)
        self.enc2 = _Block(base, 2 * base)
        self.bottom = _Block(2 * base, 4 * base)
        self.dec2 = _Block(4 * base + 2 * base, 2 * base)
        self.dec1 = _Block(2 * base + base, base)
        self.head = nn.Conv2d(base, 1, 1)
        nn.init.constant_(self.head.bias, math.log(initial_weight / (1.0 - initial_weight)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        ph, pw = (-h) % 4, (-w) % 4
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
        e1 = self.enc1(x)
        e2 = self.enc2(F.max_pool2d(e1, 2))
        b = self.bottom(F.max_pool2d(e2, 2))
        d2 = self.dec2(torch.cat([F.interpolate(b, scale_factor=2.0, mode="bilinear", align_corners=False), e2], 1))
        d1 = self.dec1(torch.cat([F.interpolate(d2, scale_factor=2.0, mode="bilinear", align_corners=False), e1], 1))
        return torch.sigmoid(self.head(d1))[..., :h, :w]


class WeightNetworks(nn.Module):
    """The pair of weight networks ``g(.; theta_2D)`` and ``g(.; theta_3D)``.

    Args:
        downscale: the networks run at 1/downscale resolution; outputs are bilinearly upsampled.
        residuals: ``2d3d`` | ``2d`` | ``3d`` (the unused map is zero).
        initial_w2d, initial_w3d: the networks' outputs at initialisation (their last bias).
        inputs: input layout version (see :func:`network_inputs`; checkpoints record theirs).
    """

    def __init__(self, downscale: int = 8, residuals: str = "2d3d", base: int = 16,
                 initial_w2d: float = 0.5, initial_w3d: float = 0.02, inputs: int = INPUT_VERSION):
        super().__init__()
        if inputs not in IN_CHANNELS:
            raise ValueError(f"unknown weight-network input version {inputs}")
        self.downscale = downscale
        self.residuals = residuals
        self.inputs = inputs
        self.in_channels_2d, in3 = IN_CHANNELS[inputs]
        # The 3D residual is far larger than the 2D one for the same error (the constant sweep's
        # best balance is w3d/w2d = 0.01, the paper reports a factor ~100 too): the 3D network
        # starts near that balance instead of 1:1.
        self.net2d = WeightUNet(self.in_channels_2d, base, initial_w2d)
        self.net3d = WeightUNet(in3, base, initial_w3d)

    def low_res(self, x2: torch.Tensor, x3: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Weight maps at the networks' resolution, ``(B, 1, h, w)`` each (zero for an unused residual)."""
        B, _, h, w = x2.shape
        zero = torch.zeros(B, 1, h, w, dtype=x2.dtype, device=x2.device)
        w2 = self.net2d(x2) if self.residuals in ("2d3d", "2d") else zero
        w3 = self.net3d(x3) if self.residuals in ("2d3d", "3d") else zero
        return w2, w3

    def forward(self, inp: WeightInputs) -> tuple[torch.Tensor, torch.Tensor]:
        """``(w2d, w3d)``, each ``(B, 1, H, W)`` in [0, 1], zero on invalid pixels."""
        H, W = inp.image_cur.shape[-2:]
        x2, x3 = network_inputs(inp, self.downscale, self.inputs)
        valid = inp.valid.to(inp.flow.dtype)
        zero = torch.zeros_like(valid)

        def run(net: nn.Module, x: torch.Tensor) -> torch.Tensor:
            w = net(x)
            if w.shape[-2:] != (H, W):
                w = F.interpolate(w, size=(H, W), mode="bilinear", align_corners=False)
            return w * valid

        w2 = run(self.net2d, x2) if self.residuals in ("2d3d", "2d") else zero
        w3 = run(self.net3d, x3) if self.residuals in ("2d3d", "3d") else zero
        return w2, w3


def sample_weights(w_low: torch.Tensor, pixels: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Bilinear upsampling of low-resolution weight maps evaluated at given pixels only
    (equal to ``F.interpolate(..., size=(height, width), mode="bilinear")`` then indexing).

    Args:
        w_low: ``(B, 1, h, w)``.
        pixels: ``(B, 2, n)`` pixel coordinates (x, y) in the full-resolution image.

    Returns:
        ``(B, n)`` weights.
    """
    gx = (pixels[:, 0] + 0.5) / width * 2.0 - 1.0
    gy = (pixels[:, 1] + 0.5) / height * 2.0 - 1.0
    grid = torch.stack([gx, gy], -1)[:, None]  # (B, 1, n, 2)
    return F.grid_sample(w_low, grid.to(w_low.dtype), mode="bilinear", padding_mode="border", align_corners=False)[:, 0, 0]


def constant_weights(valid: torch.Tensor, w2d: float, w3d: float, residuals: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Constant weight maps ``(B, 1, H, W)`` for the valid pixels; the ablation mode zeroes one."""
    v = valid.float()
    w2 = v * (w2d if residuals in ("2d3d", "2d") else 0.0)
    w3 = v * (w3d if residuals in ("2d3d", "3d") else 0.0)
    return w2, w3


def default_checkpoint(residuals: str, filtered_depth: bool = False) -> Path:
    """The packaged checkpoint for a residual mode; with ``filtered_depth`` (``depth.temporal_gain``
    < 1) the one trained on filtered depth, ``weights_{residuals}_filtered.pt``, where there is one."""
    if filtered_depth:
        filtered = CHECKPOINT_DIR / f"weights_{residuals}_filtered.pt"
        if filtered.is_file():
            return filtered
    return CHECKPOINT_DIR / f"weights_{residuals}.pt"


def model_reference_checkpoint(checkpoint: str, checkpoint_model: str, residuals: str) -> Path | None:
    """The checkpoint for tracking against a view rendered from the map, or None for "the same
    networks as against camera frames": ``checkpoint_model`` if given; else, when ``checkpoint`` is
    the packaged default, the packaged ``weights_{residuals}_model.pt`` if there is one."""
    if checkpoint_model:
        return Path(checkpoint_model)
    packaged = CHECKPOINT_DIR / f"weights_{residuals}_model.pt"
    return packaged if not checkpoint and packaged.is_file() else None


class MissingWeightsError(ValueError):
    """``weights.mode: learned`` without a usable checkpoint."""


def load_weight_networks(path: str | Path | None, residuals: str, device: str = "cpu",
                         filtered_depth: bool = False) -> tuple[WeightNetworks, dict]:
    """Load weight networks from a checkpoint written by ``slam train``.

    Args:
        path: checkpoint file; None/empty = the packaged one for ``residuals`` (and
            ``filtered_depth``, see :func:`default_checkpoint`).

    Returns:
        the networks in eval mode and the checkpoint's metadata (training config, image size,
        correspondence backend, maximum depth).
    """
    path = Path(path) if path else default_checkpoint(residuals, filtered_depth)
    if not path.is_file():
        raise MissingWeightsError(
            f"{path}: weight-network checkpoint not found (train one with `slam train`, or run with --weights constant)"
        )
    ckpt = torch.load(path, map_location=device, weights_only=False)
    meta = ckpt.get("meta", {})
    nets = WeightNetworks(downscale=int(meta.get("downscale", 8)), residuals=meta.get("residuals", residuals),
                          base=int(meta.get("base", 16)), inputs=int(meta.get("inputs", 1)))
    nets.load_state_dict(ckpt["state_dict"])
    nets.residuals = residuals
    return nets.to(device).eval(), meta


@dataclass
class TrackingNetworks:
    """The weight networks tracking chooses from for one pair of views (the same object may fill
    several roles).

    Attributes:
        filtered: for a frame whose depth is filtered along the flow (``depth.temporal_gain`` < 1;
            without the filter, the one set of networks).
        stereo: for a frame that keeps its own stereo depth (a moving camera's frame).
        model: against a view rendered from the map (frame2model).
        meta: the metadata of the ``filtered`` networks' checkpoint.
    """

    filtered: WeightNetworks
    stereo: WeightNetworks
    model: WeightNetworks
    meta: dict

    def select(self, model_reference: bool, filtered_depth: bool) -> WeightNetworks:
        """The networks for a current view against a model view (``model_reference``) or a
        camera frame, whose depth is filtered or not."""
        if model_reference:
            return self.model
        return self.filtered if filtered_depth else self.stereo

    def to(self, device) -> "TrackingNetworks":
        for nets in {id(n): n for n in (self.filtered, self.stereo, self.model)}.values():
            nets.to(device).eval()
        return self


def tracking_checkpoint_paths(checkpoint: str, checkpoint_model: str, residuals: str, temporal_gain: float,
                              temporal_still_mm: float) -> dict[str, Path]:
    """The checkpoint files tracking loads for ``weights.checkpoint`` / ``weights.checkpoint_model``
    (empty: the packaged ones) and the depth filter's settings, by role (see
    :class:`TrackingNetworks`: ``filtered``, ``stereo``, ``model``; one file may fill several).

    With the filter on (``temporal_gain`` < 1) the packaged filtered networks weigh the filtered
    frames and, when the filter runs only while the camera is still (``temporal_still_mm`` > 0),
    the packaged stereo-depth networks weigh the moving camera's frames. A named checkpoint weighs
    every camera frame. Against the map: ``checkpoint_model``, else the packaged model-view
    networks when no checkpoint is named, else the camera-frame networks.
    """
    filtered = temporal_gain < 1.0
    main = Path(checkpoint) if checkpoint else default_checkpoint(residuals, filtered_depth=filtered)
    stereo = main
    if filtered and temporal_still_mm > 0 and not checkpoint:
        stereo = default_checkpoint(residuals, filtered_depth=False)
    model = model_reference_checkpoint(checkpoint, checkpoint_model, residuals) or main
    return {"filtered": main, "stereo": stereo, "model": model}


def load_tracking_networks(checkpoint: str, checkpoint_model: str, residuals: str, temporal_gain: float,
                           temporal_still_mm: float, device: str = "cpu") -> TrackingNetworks:
    """The networks of :func:`tracking_checkpoint_paths`, each file loaded once."""
    paths = tracking_checkpoint_paths(checkpoint, checkpoint_model, residuals, temporal_gain, temporal_still_mm)
    loaded: dict[Path, tuple[WeightNetworks, dict]] = {}
    for path in paths.values():
        if path not in loaded:
            loaded[path] = load_weight_networks(path, residuals, device)
    nets, meta = loaded[paths["filtered"]]
    warn_depth_filter_mismatch(meta, temporal_gain, checkpoint)
    return TrackingNetworks(filtered=nets, stereo=loaded[paths["stereo"]][0], model=loaded[paths["model"]][0],
                            meta=meta).to(device)


def warn_depth_filter_mismatch(meta: dict, temporal_gain: float, checkpoint: str) -> None:
    """Log a warning when the named weight networks were trained on depth filtered with another
    ``depth.temporal_gain`` than tracking uses (their weights then suit another depth noise); for
    the packaged networks of an ablation mode that has no filtered variant, a note."""
    trained = (meta.get("train_config") or {}).get("depth", {}).get("temporal_gain", 1.0)
    if abs(float(trained) - float(temporal_gain)) > 1e-9:
        (log.warning if checkpoint else log.info)(
            "the weight networks (%s) were trained with depth.temporal_gain=%g, tracking uses %g: "
            "their 3D weights suit another depth noise (docs/training.md)",
            checkpoint or "packaged", float(trained), float(temporal_gain))
