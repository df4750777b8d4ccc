"""RAFT as a correspondence backend: dense temporal flow and stereo parallax flow.

:class:`RaftFlow` implements :class:`vo.correspondence.base.FlowEstimator` with our own RAFT
(:mod:`vo.raft`) and a published checkpoint (``raft-things.pth`` or ``raft-small.pth``; which of the
two variants it holds is read off its tensors). Pretrained weights are never downloaded: the
checkpoint must be a local file.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch
import torch.nn.functional as F

from vo.raft import RAFT

MISSING_CHECKPOINT_MESSAGE = (
    "the raft correspondence backend needs a checkpoint (correspondence.raft_checkpoint: path to "
    "raft-things.pth); pretrained weights cannot be downloaded here"
)

_SHOW = 5  # names listed in a mismatch error


class MissingCheckpointError(ValueError):
    """No RAFT checkpoint was configured."""

    def __init__(self, message: str = MISSING_CHECKPOINT_MESSAGE):
        super().__init__(message)


class CheckpointMismatchError(ValueError):
    """The checkpoint's parameter names or shapes do not match the RAFT variant being built."""


def _unwrap_state_dict(obj: object, path: Path) -> dict[str, torch.Tensor]:
    """The tensors of a checkpoint: a plain state dict or one under ``'state_dict'`` / ``'model'``.

    DataParallel's ``module.`` prefix is stripped from every name.
    """
    if isinstance(obj, Mapping):
        for key in ("state_dict", "model"):
            inner = obj.get(key)
            if isinstance(inner, Mapping):
                obj = inner
                break
    if not isinstance(obj, Mapping) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise CheckpointMismatchError(f"{path}: not a RAFT state dict (expected a mapping of names to tensors)")
    return {(k[len("module."):] if k.startswith("module.") else k): v for k, v in obj.items()}


def _check_state_dict(model: torch.nn.Module, state: Mapping[str, torch.Tensor], path: Path, small: bool) -> None:
    """Raise :class:`CheckpointMismatchError` listing the first missing/unexpected/mis-shaped names."""
    expected = model.state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    shapes = [
        f"{k}: checkpoint {tuple(state[k].shape)} vs model {tuple(v.shape)}"
        for k, v in expected.items()
        if k in state and tuple(state[k].shape) != tuple(v.shape)
    ]
    if not (missing or unexpected or shapes):
        return
    variant = "RAFT-S (small=True)" if small else "RAFT (small=False)"
    parts = [f"{path} does not match {variant}:"]
    for label, names in (("missing", missing), ("unexpected", unexpected), ("shape mismatch", shapes)):
        if names:
            more = f" (+{len(names) - _SHOW} more)" if len(names) > _SHOW else ""
            parts.append(f"{len(names)} {label}: {', '.join(names[:_SHOW])}{more}")
    other = RAFT(small=not small).state_dict()
    if set(other) == set(state) and all(tuple(other[k].shape) == tuple(state[k].shape) for k in other):
        hint = "small=True (raft-small.pth)" if not small else "small=False (raft-things.pth)"
        parts.append(f"it is a checkpoint of the other variant: use {hint}")
    raise CheckpointMismatchError("; ".join(parts))


def _is_small(state: Mapping[str, torch.Tensor]) -> bool:
    """Whether a state dict holds RAFT-S: its names and shapes are RAFT-S's and not RAFT's."""
    def matches(model_state) -> bool:
        return set(model_state) == set(state) and all(tuple(v.shape) == tuple(state[k].shape)
                                                      for k, v in model_state.items())
    return not matches(RAFT(small=False).state_dict()) and matches(RAFT(small=True).state_dict())


def load_raft(checkpoint: str | Path | None, small: bool | None = None, device: str | torch.device = "cpu") -> RAFT:
    """Build :class:`~vo.raft.RAFT` and load ``checkpoint`` strictly; returns the model in eval mode.

    ``small``: build RAFT-S (True) or RAFT (False); None reads the variant off the checkpoint.

    Raises:
        MissingCheckpointError: ``checkpoint`` is None or empty.
        FileNotFoundError: the file does not exist.
        CheckpointMismatchError: names or shapes do not match (first few listed).
    """
    if checkpoint is None or str(checkpoint).strip() == "":
        raise MissingCheckpointError()
    path = Path(checkpoint).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"raft checkpoint not found: {path}")
    state = _unwrap_state_dict(torch.load(path, map_location="cpu", weights_only=True), path)
    if small is None:
        small = _is_small(state)
    model = RAFT(small=small)
    _check_state_dict(model, state, path, small)
    model.load_state_dict(state, strict=True)
    return model.to(device).eval()


class InputPadder:
    """Replicate-pad ``(B, C, H, W)`` images to multiples of ``multiple`` (split evenly, extra at the end)."""

    def __init__(self, height: int, width: int, multiple: int = 8):
        pad_h = (-height) % multiple
        pad_w = (-width) % multiple
        # F.pad order: (left, right, top, bottom)
        self.pad = (pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2)

    def pad_images(self, *images: torch.Tensor) -> list[torch.Tensor]:
        if not any(self.pad):
            return list(images)
        return [F.pad(x, self.pad, mode="replicate") for x in images]

    def unpad(self, x: torch.Tensor) -> torch.Tensor:
        """Crop ``(..., H_padded, W_padded)`` back to the original size."""
        left, right, top, bottom = self.pad
        h, w = x.shape[-2:]
        return x[..., top:h - bottom, left:w - right]


class RaftFlow:
    """Dense flow with RAFT: ``flow(image1, image2)`` -> ``(B, 2, H, W)`` pixel displacements (x, y).

    Args:
        checkpoint: path to ``raft-things.pth`` or ``raft-small.pth``; a plain state dict or one
            wrapped in ``{'state_dict': ...}`` / ``{'model': ...}``, with or without DataParallel's
            ``module.`` prefix.
        small: use RAFT-S (True), RAFT (False), or whichever the checkpoint holds (None).
        iters: update iterations per estimate (12 as in the published evaluation on KITTI-sized images).
        device: torch device the model runs on; inputs are moved there, results are returned there.

    Stereo parallax flow is ``flow(left, right)`` (horizontal part = minus the disparity).
    """

    name = "raft"

    def __init__(self, checkpoint: str | Path | None, small: bool | None = None, iters: int = 12,
                 device: str | torch.device = "cpu"):
        if iters < 1:
            raise ValueError(f"iters must be >= 1, got {iters}")
        self.iters = int(iters)
        self.device = torch.device(device)
        self.model = load_raft(checkpoint, small=small, device=self.device)
        self.small = self.model.small

    @torch.no_grad()
    def flow(self, image1: torch.Tensor, image2: torch.Tensor, start: torch.Tensor | None = None) -> torch.Tensor:
        """Flow from ``image1`` to ``image2``, both ``(B, 3, H, W)`` float RGB in [0, 1]; returns
        ``(B, 2, H, W)``. ``start``: ``(B, 2, H, W)`` flow the updates start from (RAFT's
        ``flow_init``, averaged onto its 1/8 grid), None: from zero."""
        if image1.shape != image2.shape or image1.dim() != 4 or image1.shape[1] != 3:
            raise ValueError(f"expected two (B, 3, H, W) images of equal shape, got {tuple(image1.shape)} "
                             f"and {tuple(image2.shape)}")
        self.model.eval()
        x1 = image1.to(self.device, torch.float32) * 255.0
        x2 = image2.to(self.device, torch.float32) * 255.0
        padder = InputPadder(*x1.shape[-2:])
        x1, x2 = padder.pad_images(x1, x2)
        flow_init = None
        if start is not None:
            padded = padder.pad_images(start.to(self.device, torch.float32))[0]
            flow_init = F.avg_pool2d(padded, 8) / 8.0
        _, flow_up = self.model(x1, x2, iters=self.iters, flow_init=flow_init, test_mode=True)
        return padder.unpad(flow_up).contiguous()
