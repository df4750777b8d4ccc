"""Dataset readers: StereoMIS (pre-processed and raw video), SCARED keyframes, plain folders.

``open_dataset(path, config)`` detects the layout and returns a :class:`StereoDataset` yielding
rectified, resized :class:`StereoFrame` objects. Names are imported lazily so that importing
``slam.io.datasets.config`` (e.g. to parse a configuration) does not pull in OpenCV and torch.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "StereoFrame": "slam.io.datasets.base",
    "DataConfig": "slam.io.datasets.config",
    "StereoDataset": "slam.io.datasets.dataset",
    "RawFrame": "slam.io.datasets.dataset",
    "combine_masks": "slam.io.datasets.masks",
    "specular_mask": "slam.io.datasets.masks",
    "READERS": "slam.io.datasets.registry",
    "detect_layout": "slam.io.datasets.registry",
    "open_dataset": "slam.io.datasets.registry",
    "parse_frames": "slam.io.datasets.selection",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'slam.io.datasets' has no attribute '{name}'")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
