"""StereoMIS, pre-processed layout (also what ``slam synth`` writes).

::

    <seq>/
      video_frames/000000l.png 000000r.png ...   rectified RGB pairs (numbering may start anywhere)
      StereoCalibration.ini                      raw calibration (see slam.io.calibration)
      groundtruth.txt                            optional, TUM, metres, T_wc of the left camera
      masks/000000l.png ...                      optional, non-zero = tissue, 0 = instrument
      depth/000000l.png ...                      optional (synthetic), uint16 depth of the rectified left view
      nonrigid/000000l.png ...                   optional (synthetic), same units -> extras["nonrigid_mm"]
      synth.json                                 optional (synthetic), {"depth_scale_mm": 0.01, ...}

The frames are already rectified (``rectified: auto`` = yes): the rectified camera and ``R1`` are
those that rectifying ``StereoCalibration.ini`` in ``rectify_mode`` gives (the StereoMIS
pre-processing rectified with OpenCV, alpha = 0), and frames are only resized. With
``rectified: no`` the PNGs are treated as raw views and rectified. The calibration is fitted to
the size of the first readable left frame (:func:`slam.io.calibration.fit_to_frames`: an integer
multiple is scaled, any other size is a DataError naming the ``.ini``).
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

from slam.io.calibration import fit_calibration, read_stereomis_ini
from slam.io.datasets.config import DataConfig
from slam.io.datasets.dataset import (RawFrame, StereoDataset, first_readable_size, load_groundtruth, read_mask, read_rgb,
                                  read_scaled_uint)
from slam.errors import DataError
from slam.io.rectification import make_rectifier

FRAMES_DIR = "video_frames"
CALIB_FILE = "StereoCalibration.ini"
GT_FILE = "groundtruth.txt"
DEFAULT_DEPTH_SCALE_MM = 0.01

_LEFT = re.compile(r"^(\d+)l\.png$", re.IGNORECASE)
_RIGHT = re.compile(r"^(\d+)r\.png$", re.IGNORECASE)


def wants_prerectified(config: DataConfig, default: bool) -> bool:
    """Whether the input frames are already rectified under ``config.rectified``."""
    return default if config.rectified == "auto" else config.rectified == "yes"


def list_stereo_pngs(folder: Path) -> list[tuple[str, str]]:
    """``(left_name, right_name)`` pairs of ``%06dl.png`` / ``%06dr.png`` files sorted by number."""
    left, right = {}, {}
    for entry in folder.iterdir():
        m = _LEFT.match(entry.name)
        if m:
            left[int(m.group(1))] = entry.name
            continue
        m = _RIGHT.match(entry.name)
        if m:
            right[int(m.group(1))] = entry.name
    if not left and not right:
        raise DataError(f"{folder}: no frames (expected %06dl.png and %06dr.png)")
    if len(left) != len(right):
        raise DataError(f"{folder}: {len(left)} left frames (*l.png) but {len(right)} right frames (*r.png)")
    missing = sorted(set(left) ^ set(right))
    if missing:
        k = missing[0]
        which = "right" if k in left else "left"
        raise DataError(f"{folder}: frame {k} has no {which} image ({len(missing)} unpaired frame numbers)")
    return [(left[k], right[k]) for k in sorted(left)]


def read_depth_scale(path: Path) -> float:
    """``depth_scale_mm`` of ``synth.json`` (mm per depth unit), default 0.01 if absent."""
    if not path.exists():
        return DEFAULT_DEPTH_SCALE_MM
    try:
        with open(path, encoding="utf-8") as fh:
            meta = json.load(fh)
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: cannot parse JSON ({' '.join(str(exc).split())[:120]})") from None
    if not isinstance(meta, dict):
        raise DataError(f"{path}: expected a JSON object")
    scale = meta.get("depth_scale_mm", DEFAULT_DEPTH_SCALE_MM)
    try:
        scale = float(scale)
    except (TypeError, ValueError):
        raise DataError(f"{path}: depth_scale_mm is not a number: {scale!r}") from None
    if not math.isfinite(scale) or scale <= 0:
        raise DataError(f"{path}: depth_scale_mm must be positive, got {scale}")
    return scale


class StereoMISDataset(StereoDataset):
    layout = "stereomis"

    @staticmethod
    def detect(path: Path) -> bool:
        return (path / FRAMES_DIR).is_dir()

    def __init__(self, path: Path, config: DataConfig):
        path = Path(path)
        frames_dir = path / FRAMES_DIR
        if not frames_dir.is_dir():
            raise DataError(f"{path}: no {FRAMES_DIR}/ folder (StereoMIS pre-processed layout)")
        self._pairs = list_stereo_pngs(frames_dir)
        self._frames_dir = frames_dir
        calib = read_stereomis_ini(path / CALIB_FILE)
        size = first_readable_size([frames_dir / left for left, _ in self._pairs])
        if size is not None:        # none of the first frames reads: they fail one by one later
            calib = fit_calibration(calib, size)
        processor = make_rectifier(calib, config.rectify_mode, (config.width, config.height),
                                   already_rectified=wants_prerectified(config, True))
        n = len(self._pairs)
        stamps, poses = load_groundtruth(path / GT_FILE, n, None, config.fps)
        super().__init__(path, config, processor, n, stamps, poses)
        self._masks_dir = path / "masks"
        self._depth_dir = path / "depth"
        self._nonrigid_dir = path / "nonrigid"
        has_synth = self._depth_dir.is_dir() or self._nonrigid_dir.is_dir()
        self._depth_scale = read_depth_scale(path / "synth.json") if has_synth else DEFAULT_DEPTH_SCALE_MM

    def _read(self, index: int) -> RawFrame:
        left_name, right_name = self._pairs[index]
        left_path = self._frames_dir / left_name
        left = read_rgb(left_path)
        right_path = self._frames_dir / right_name
        right = read_rgb(right_path)
        if right.shape != left.shape:
            raise DataError(f"{right_path}: image is {right.shape[1]}x{right.shape[0]}, "
                            f"the left image {left_name} is {left.shape[1]}x{left.shape[0]}")
        instrument = None
        if self.config.use_mask_files:
            mask_path = self._masks_dir / left_name
            if mask_path.exists():
                instrument = read_mask(mask_path, left.shape)
        depth = None
        depth_path = self._depth_dir / left_name
        if depth_path.exists():
            depth = read_scaled_uint(depth_path, self._depth_scale, left.shape)
        extras = {}
        nonrigid_path = self._nonrigid_dir / left_name
        if nonrigid_path.exists():
            extras["nonrigid_mm"] = read_scaled_uint(nonrigid_path, self._depth_scale, left.shape)
        return RawFrame(left=left, right=right, instrument=instrument, depth=depth, extras=extras,
                        source=str(left_path))
