"""Which reader opens a folder: auto-detection and :func:`open_dataset`.

Detection (first match wins; ``config.layout`` other than ``auto`` skips it):

1. ``video_frames/``                                   -> ``stereomis`` (pre-processed StereoMIS / synthetic)
2. ``data/rgb.mp4`` (or the calibration beside ``data/``) -> ``scared``
3. ``left/`` and ``right/`` with ``calibration.yaml`` (or no other calibration candidate,
   :func:`slam.io.datasets.frames.calibration_candidates`) -> ``plain``
4. left and right image folders by name (docs/inputs.md) -> ``frames``
5. a ``*.mp4`` with ``StereoCalibration.ini`` (or no other calibration candidate) -> ``stereomis_raw``
6. one video file (or a video file given as DATA)      -> ``video``

``left/`` and ``right/`` given a calibration (``data.calibration``, ``--calibration``) are frame
folders (4.) with that calibration, not a plain folder.

A detected layout with missing pieces (e.g. no calibration) fails in its reader with a DataError
naming the missing file. Plain folders, frame folders and video files, whose frames and calibration
people put together themselves, are checked on their first, middle and last frames: a pair that
keeps a vertical disparity as the pipeline gets it, or whose disparities are negative, is a
DataError naming the calibration (:func:`slam.io.stereo_check.check_rectified_rows`).
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

#: the layouts whose frames people arrange and calibrate themselves: their first, middle and last
#: pairs are checked when they open (:func:`check_pairs`); the datasets' own layouts are not
CHECKED_PAIRS = ("plain", "frames", "video")

LOOKED_FOR = ("video_frames/ (StereoMIS)", "endoscope_calibration.yaml + data/rgb.mp4 (SCARED)",
              "left/ + right/ + calibration.yaml (plain)",
              "left and right image folders + a calibration file (left*/right*, image01/image02, image_0/image_1, l/r)",
              "*.mp4 + StereoCalibration.ini (StereoMIS raw)", "a stereo video file + a calibration file")


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


def open_dataset(path: str | Path, config: Optional[DataConfig] = None, check_rows: bool = True) -> StereoDataset:
    """Open the sequence in ``path`` with the reader of ``config.layout`` (``auto``: detected).
    ``check_rows``: refuse the layouts of :data:`CHECKED_PAIRS` whose views are not row-aligned
    pairs (:func:`check_pairs`; ``slam inspect`` reports the figure instead)."""
    config = config or DataConfig()
    path = Path(path)
    layout = detect_layout(path) if config.layout == "auto" else config.layout
    if config.layout == "auto" and layout == "plain" and config.calibration:
        layout = "frames"           # left/ and right/ with a calibration of their own
    if config.layout != "auto" and not path.is_dir() and not (layout == "video" and path.is_file()):
        raise DataError(f"{path}: no such folder" if not path.exists() else f"{path}: not a folder")
    if config.calibration and layout not in ("frames", "video"):
        raise ConfigError(f"{path}: --calibration / data.calibration applies to frame folders and video files; "
                          f"the {layout} layout reads its own calibration file")
    dataset = READERS[layout](path, config)
    if check_rows and layout in CHECKED_PAIRS:
        check_pairs(dataset)
    return dataset


def check_pairs(dataset: StereoDataset) -> None:
    """The first, middle and last frames' views as the pipeline gets them must be row-aligned, the
    left view's features to the right of the right view's
    (:func:`slam.io.stereo_check.check_rectified_rows`), except in ``rectify_mode: pseudo`` (which
    keeps the parallax of the cameras' rotation by design). Frames that cannot be read are not
    checked (they fail when tracked); DataError naming the calibration and the frame otherwise."""
    from slam.io.rectification import ResizeOnly
    from slam.io.stereo_check import check_rectified_rows

    rectified_here = not isinstance(dataset.processor, ResizeOnly)
    if rectified_here and dataset.config.rectify_mode == "pseudo":
        return
    where = str(getattr(dataset, "calibration_path", None) or dataset.path)
    n = len(dataset)
    for k in sorted({0, n // 2, n - 1}):
        try:
            frame = dataset.frame(k)
        except DataError:
            continue
        try:
            check_rectified_rows(frame.left, frame.right, where, rectified_here,
                                 "the first frame" if k == 0 else f"frame {k}")
        except DataError:
            dataset.close()
            raise
