"""Which reader opens a folder: auto-detection and :func:`open_dataset`.

Detection (first match wins; ``config.layout`` other than ``auto`` skips it):

1. ``video_frames/``                                   -> ``stereomis`` (pre-processed StereoMIS / synthetic)
2. ``data/rgb.mp4`` (or the calibration beside ``data/``) -> ``scared``
3. ``left/`` and ``right/`` with ``calibration.yaml`` (or no other calibration candidate,
   :func:`slam.io.datasets.frames.calibration_candidates`) -> ``plain``
4. left and right image folders by name (docs/inputs.md) -> ``frames``
5. a ``*.mp4`` with ``StereoCalibration.ini`` (or no other calibration candidate) -> ``stereomis_raw``
6. one video file (or a video file given as DATA)      -> ``video``

A detected layout with missing pieces (e.g. no calibration) fails in its reader with a DataError
naming the missing file.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from slam.io.datasets.config import DataConfig
from slam.io.datasets.dataset import StereoDataset
from slam.io.datasets.frames import FrameFolderDataset
from slam.io.datasets.plain import PlainDataset
from slam.io.datasets.scared import ScaredDataset
from slam.io.datasets.stereomis import StereoMISDataset
from slam.io.datasets.stereomis_raw import StereoMISRawDataset
from slam.io.datasets.video import VIDEO_SUFFIXES
from slam.io.datasets.video_file import VideoFileDataset
from slam.errors import ConfigError, DataError

#: layout name -> reader class, in detection order.
READERS: dict[str, type[StereoDataset]] = {
    "stereomis": StereoMISDataset,
    "scared": ScaredDataset,
    "plain": PlainDataset,
    "frames": FrameFolderDataset,
    "stereomis_raw": StereoMISRawDataset,
    "video": VideoFileDataset,
}

LOOKED_FOR = ("video_frames/ (StereoMIS)", "endoscope_calibration.yaml + data/rgb.mp4 (SCARED)",
              "left/ + right/ + calibration.yaml (plain)",
              "left and right image folders + a calibration file (left*/right*, image01/image02, image_0/image_1, l/r)",
              "*.mp4 + StereoCalibration.ini (StereoMIS raw)", "a stereo video file + a calibration file")


def validate_config(config: DataConfig) -> None:
    """Raise ConfigError for values the readers cannot use."""
    if config.layout != "auto" and config.layout not in READERS:
        raise ConfigError(f"data.layout: unknown layout '{config.layout}' (expected auto, {', '.join(READERS)})")
    if config.rectified not in ("auto", "yes", "no"):
        raise ConfigError(f"data.rectified: expected auto, yes or no, got '{config.rectified}'")
    if config.rectify_mode not in ("full", "pseudo"):
        raise ConfigError(f"data.rectify_mode: expected full or pseudo, got '{config.rectify_mode}'")
    for key in ("width", "height"):
        value = getattr(config, key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ConfigError(f"data.{key}: expected an integer >= 0 (0 = native size), got {value!r}")
    if not 0 < float(config.specular_threshold):
        raise ConfigError(f"data.specular_threshold: expected a value in (0, 1] (> 1 disables), got {config.specular_threshold}")
    if not 0 <= float(config.dark_threshold) < 1:
        raise ConfigError(f"data.dark_threshold: expected a value in [0, 1) (0 disables), got {config.dark_threshold}")
    if int(config.specular_dilate_px) < 0:
        raise ConfigError(f"data.specular_dilate_px: expected >= 0, got {config.specular_dilate_px}")
    if not float(config.fps) >= 0:
        raise ConfigError(f"data.fps: expected a frame rate >= 0 (0 = from the data), got {config.fps}")
    if config.stereo_layout not in ("auto", "top-bottom", "side-by-side"):
        raise ConfigError(f"data.stereo_layout: expected auto, top-bottom or side-by-side, got '{config.stereo_layout}'")


def detect_layout(path: str | Path) -> str:
    """The layout name of a sequence folder; DataError naming the folder if none matches."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file" if path.suffix.lower() in VIDEO_SUFFIXES else f"{path}: no such folder")
    if path.is_file():
        if VideoFileDataset.detect(path):
            return "video"
        raise DataError(f"{path}: not a folder or a video file (give the sequence folder, or a stereo video "
                        "with --calibration FILE)")
    for name, reader in READERS.items():
        if reader.detect(path):
            return name
    empty = not any(path.iterdir())
    what = "empty folder" if empty else "unknown dataset layout"
    raise DataError(f"{path}: {what}; looked for {'; '.join(LOOKED_FOR)}")


def open_dataset(path: str | Path, config: Optional[DataConfig] = None) -> StereoDataset:
    """Open the sequence in ``path`` with the reader of ``config.layout`` (``auto``: detected)."""
    config = config or DataConfig()
    validate_config(config)
    path = Path(path)
    layout = detect_layout(path) if config.layout == "auto" else config.layout
    if config.layout != "auto" and not path.is_dir() and not (layout == "video" and path.is_file()):
        raise DataError(f"{path}: no such folder" if not path.exists() else f"{path}: not a folder")
    if config.calibration and layout not in ("frames", "video"):
        raise ConfigError(f"{path}: --calibration / data.calibration applies to frame folders and video files; "
                          f"the {layout} layout reads its own calibration file")
    return READERS[layout](path, config)
