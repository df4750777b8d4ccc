"""Stereo frame folders as recordings circulate: a left and a right folder of images beside a
calibration file.

::

    <seq>/
      left_image/  right_image/      the two views; found by name, case-insensitive: left*/right*
                                     (same suffix), image01/image02, image_0/image_1, l/r
        frame_00001.jpg ...          PNG, JPEG or TIFF, grey or colour, 8 or 16 bit; paired by stem
                                     with the side token stripped (Left_0001 / Right_0001), else
                                     by order when the counts agree
      endoscope_calibration.yaml     or StereoCalibration.ini, calibration.yaml, calibration.json
                                     (slam.io.calibration.read_calibration), or data.calibration, or
                                     the only .ini/.json/.yaml/.yml/.xml (a warning names it)
      timestamps.txt                 optional: one timestamp per frame (seconds); else index / fps
      groundtruth.txt                optional, TUM, metres, T_wc of the original left camera
      masks/                         optional, per left frame (paired like the frames), non-zero = tissue

Rectification (``data.rectified: auto``): the frames are taken as rectified when the calibration
says so (no distortion and no rotation between the cameras, :func:`slam.io.calibration.is_rectified`;
a plain ``calibration.yaml`` always), else rectified with it in ``data.rectify_mode``. A calibration
made at another size than the frames is scaled by the integer factor that fits, or refused
(:func:`slam.io.calibration.fit_to_frames`).
"""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Optional

import numpy as np

from slam.io.calibration import (CALIBRATION_NAMES, RawStereoCalibration, fit_calibration, fit_camera, is_rectified,
                              read_calibration, rectified_camera)
from slam.io.datasets.config import DataConfig
from slam.io.datasets.dataset import RawFrame, StereoDataset, load_groundtruth
from slam.io.datasets.images import (bit_depth, list_frame_images, pair_files, pairing_stem, read_image, read_timestamps,
                                  to_rgb8)
from slam.errors import ConfigError, DataError
from slam.io.rectification import ResizeOnly, make_rectifier
from vo.camera import StereoCamera

GT_FILE = "groundtruth.txt"
TIMESTAMPS_FILE = "timestamps.txt"
MASKS_DIR = "masks"
# (left, right) folder names, case-insensitive; "left*" pairs with "right*" of the same suffix
_FIXED_PAIRS = (("image01", "image02"), ("image_0", "image_1"), ("l", "r"))
log = logging.getLogger("slam")
_SIDE_PREFIX = re.compile(r"^(left|right)(.*)$", re.IGNORECASE)


def find_stereo_folders(path: Path) -> Optional[tuple[Path, Path]]:
    """The left and right folders of a sequence folder, or None. DataError when the names are
    ambiguous (two candidate pairs)."""
    dirs = {d.name.lower(): d for d in path.iterdir() if d.is_dir()}
    pairs = []
    sides: dict[str, dict[str, Path]] = {"left": {}, "right": {}}
    for name, d in dirs.items():
        m = _SIDE_PREFIX.match(name)
        if m:
            sides[m.group(1).lower()][m.group(2)] = d
    for suffix in sorted(set(sides["left"]) & set(sides["right"])):
        pairs.append((sides["left"][suffix], sides["right"][suffix]))
    for left, right in _FIXED_PAIRS:
        if left in dirs and right in dirs:
            pairs.append((dirs[left], dirs[right]))
    if not pairs:
        return None
    if len(pairs) > 1:
        names = ", ".join(f"{a.name}/{b.name}" for a, b in pairs)
        raise DataError(f"{path}: several left/right folder pairs ({names}); keep one")
    return pairs[0]


#: files a sequence folder may hold that are never its calibration (a run's config, ``slam synth``'s
#: description of the sequence)
NOT_CALIBRATIONS = ("config.yaml", "synth.json")
CANDIDATE_SUFFIXES = (".ini", ".json", ".yaml", ".yml", ".xml")


def calibration_candidates(path: Path) -> list[Path]:
    """The files of folder ``path`` that may be its calibration (``.ini``, ``.json``, ``.yaml``,
    ``.yml``, ``.xml``; not :data:`NOT_CALIBRATIONS`), sorted by name."""
    return [p for p in sorted(path.iterdir()) if p.is_file() and p.suffix.lower() in CANDIDATE_SUFFIXES
            and p.name not in NOT_CALIBRATIONS]


def find_calibration(path: Path, config: DataConfig, beside: str = "the frames") -> Path:
    """``data.calibration`` if set, else the folder's calibration file: one of the known names, or
    the only candidate in it (:func:`calibration_candidates`; a warning names the file taken, the
    calibration file ``beside`` the data)."""
    if config.calibration:
        given = Path(config.calibration).expanduser()
        if not given.is_file():
            raise DataError(f"{given}: calibration file not found (data.calibration)")
        return given
    for name in CALIBRATION_NAMES:
        if (path / name).is_file():
            return path / name
    candidates = calibration_candidates(path)
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise DataError(f"{path}: no calibration file ({', '.join(CALIBRATION_NAMES)}; or --calibration FILE)")
    raise DataError(f"{path}: several calibration candidates ({', '.join(p.name for p in candidates)}); "
                    "name one with --calibration FILE")


def load_calibration(path: Path, config: DataConfig, beside: str = "the frames"
                     ) -> tuple[Path, RawStereoCalibration | StereoCamera]:
    """The calibration :func:`find_calibration` finds, read. A file taken only for being the one
    candidate that does not read as a calibration (a ``metadata.json``) is a DataError naming it
    and suggesting --calibration."""
    calib_path = find_calibration(path, config, beside)
    guessed = not config.calibration and calib_path.name not in CALIBRATION_NAMES
    try:
        calib = read_calibration(calib_path)
    except DataError as err:
        if not guessed:
            raise
        reason = str(err).removeprefix(f"{calib_path}: ")
        raise DataError(f"{calib_path}: not a calibration file ({reason}); it was taken as the only "
                        f"{'/'.join(CANDIDATE_SUFFIXES)} file beside {beside}: name the calibration with "
                        "--calibration FILE") from None
    if guessed:
        log.warning("using calibration %s (the only calibration file beside %s; --calibration FILE to choose)",
                    calib_path, beside)
    return calib_path, calib


def calibration_processor(calib: RawStereoCalibration | StereoCamera, frame_size: tuple[int, int],
                          config: DataConfig, where: str):
    """The frame processor (rectifier or resizer) of a calibration used with frames of
    ``frame_size``: the calibration fitted to the frames, rectified views taken as they are."""
    out = (config.width, config.height)
    if isinstance(calib, StereoCamera):
        if config.rectified == "no":
            raise ConfigError(f"{where}: data.rectified is no, but the calibration is a rectified camera "
                              "(fx fy cx cy baseline_mm)")
        return ResizeOnly(fit_camera(calib, frame_size, where), out)
    fitted = fit_calibration(calib, frame_size)
    rectified = is_rectified(fitted) if config.rectified == "auto" else config.rectified == "yes"
    if rectified and is_rectified(fitted):
        return ResizeOnly(rectified_camera(fitted), out)
    return make_rectifier(fitted, config.rectify_mode, out, already_rectified=rectified)


class FrameFolderDataset(StereoDataset):
    layout = "frames"

    @staticmethod
    def detect(path: Path) -> bool:
        return find_stereo_folders(path) is not None

    def __init__(self, path: Path, config: DataConfig):
        path = Path(path)
        folders = find_stereo_folders(path)
        if folders is None:
            raise DataError(f"{path}: no left and right image folders (left*/right*, image01/image02, "
                            "image_0/image_1 or l/r)")
        left_dir, right_dir = folders
        self._pairs = pair_files(list_frame_images(left_dir), list_frame_images(right_dir), left_dir, right_dir)
        first = [read_image(p) for p in self._pairs[0]]
        if first[0].shape[:2] != first[1].shape[:2]:
            raise DataError(f"{self._pairs[0][0]} is {first[0].shape[1]}x{first[0].shape[0]} but "
                            f"{self._pairs[0][1]} is {first[1].shape[1]}x{first[1].shape[0]}")
        self.bit_depth = bit_depth(first)
        frame_size = (first[0].shape[1], first[0].shape[0])
        calib_path, calib = load_calibration(path, config, "the frames")
        self.calibration_path = calib_path
        processor = calibration_processor(calib, frame_size, config, str(calib_path))
        n = len(self._pairs)
        stamps = read_timestamps(path / TIMESTAMPS_FILE, n)
        self.timestamps_source = "timestamps.txt" if stamps is not None else "fps"
        stamps, poses = load_groundtruth(path / GT_FILE, n, stamps, config.fps)
        super().__init__(path, config, processor, n, stamps, poses)
        self.frame_size = frame_size
        self._masks = self._pair_masks(path / MASKS_DIR, left_dir) if config.use_mask_files else {}

    def _pair_masks(self, masks_dir: Path, left_dir: Path) -> dict[int, Path]:
        """Mask files by frame, paired with the left frames like the frames are paired."""
        if not masks_dir.is_dir():
            return {}
        masks = list_frame_images(masks_dir)
        if not masks:
            return {}
        lefts = [left for left, _ in self._pairs]
        pairs = pair_files(lefts, masks, left_dir, masks_dir) if len(masks) == len(lefts) else None
        if pairs is None:
            by_stem = {pairing_stem(m): m for m in masks}
            found = {k: by_stem[pairing_stem(p)] for k, p in enumerate(lefts) if pairing_stem(p) in by_stem}
            if not found:
                raise DataError(f"{masks_dir}: {len(masks)} masks pair with none of the {len(lefts)} frames of {left_dir}")
            return found
        return {k: m for k, (_, m) in enumerate(pairs)}

    def _read(self, index: int) -> RawFrame:
        left_path, right_path = self._pairs[index]
        left = to_rgb8(read_image(left_path), self.bit_depth, left_path)
        right = to_rgb8(read_image(right_path), self.bit_depth, right_path)
        if left.shape != right.shape or (left.shape[1], left.shape[0]) != self.frame_size:
            raise DataError(f"{left_path}: frame size {left.shape[1]}x{left.shape[0]} differs from the sequence's "
                            f"{self.frame_size[0]}x{self.frame_size[1]} (or from its right view)")
        instrument = None
        mask_path = self._masks.get(index)
        if mask_path is not None:
            mask = read_image(mask_path)
            if mask.shape[:2] != left.shape[:2]:
                raise DataError(f"{mask_path}: mask is {mask.shape[1]}x{mask.shape[0]}, the frame {left.shape[1]}x{left.shape[0]}")
            instrument = (mask.max(axis=2) if mask.ndim == 3 else mask) > 0
        return RawFrame(left=left, right=right, instrument=instrument, source=str(left_path))
