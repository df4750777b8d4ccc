"""Frame images as people store them: PNG, JPEG or TIFF, grey or colour, 8 or 16 bit, in folders
whose file names pair a left frame with its right one.

16-bit frames are scaled to 8 bit by the data's real bit depth (a 12-bit sensor stored in 16-bit
PNGs spans 0-4095, not 0-65535), read once per sequence from its first frames.
"""
from __future__ import annotations

import logging
import math
import re
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from slam.errors import DataError

log = logging.getLogger("slam")

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
_NUMBER = re.compile(r"(\d+)")
# side tokens stripped from a file stem before pairing (longest first, case-insensitive)
_SIDE_TOKENS = re.compile(r"(left|right|masks?|image_?0[12]|cam_?[01]|l|r)", re.IGNORECASE)


def natural_key(name: str) -> tuple:
    """Sort key that orders ``frame_2`` before ``frame_10``."""
    return tuple(int(part) if part.isdigit() else part.lower() for part in _NUMBER.split(name))


def list_frame_images(folder: Path) -> list[Path]:
    """The image files of ``folder`` in natural order."""
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                  key=lambda p: natural_key(p.name))


def pairing_stem(path: Path) -> str:
    """A file's stem with its side tokens taken out (``Left_0001``, ``Right_0001`` and
    ``mask_0001`` -> ``_0001``): a token counts where it stands apart, beside a separator, a digit
    or the end of the name (not the 'l' inside 'frame')."""
    stem = path.stem
    parts, last = [], 0
    for m in _SIDE_TOKENS.finditer(stem):
        a, b = m.span()
        before = stem[a - 1] if a > 0 else ""
        after = stem[b] if b < len(stem) else ""
        if (not before or not before.isalpha()) and (not after or not after.isalpha()):
            parts.append(stem[last:a])
            last = b
    parts.append(stem[last:])
    return "".join(parts).lower()


def numbered_stem(path: Path) -> str:
    """:func:`pairing_stem` with every number written without leading zeros (``frame_0007`` and
    ``frame_7`` -> ``frame_7``): frames numbered with and without padding pair by their number."""
    return _NUMBER.sub(lambda m: str(int(m.group(1))), pairing_stem(path))


def _paired_by(key, left: list[Path], right: list[Path]) -> Optional[list[tuple[Path, Path]]]:
    """``left`` and ``right`` paired by ``key(file)`` when every file of both has exactly one
    partner, else None."""
    left_keys = [key(p) for p in left]
    by_key = {key(p): p for p in right}
    if len(left) == len(right) == len(by_key) == len(set(left_keys)) and all(k in by_key for k in left_keys):
        return [(p, by_key[k]) for p, k in zip(left, left_keys)]
    return None


def pair_files(left: list[Path], right: list[Path], left_dir: Path, right_dir: Path) -> list[tuple[Path, Path]]:
    """Left and right files paired by their stems with the side token stripped, else by those
    stems' numbers (``0007.png`` / ``7.png``), else by their natural order when no name pairs and
    the counts agree. DataError naming both folders otherwise."""
    if not left:
        raise DataError(f"{left_dir}: no images ({', '.join(IMAGE_SUFFIXES)})")
    for key in (pairing_stem, numbered_stem):
        pairs = _paired_by(key, left, right)
        if pairs is not None:
            return pairs
    by_stem = {numbered_stem(p): p for p in right}
    stems = [numbered_stem(p) for p in left]
    matched = [s for s in stems if s in by_stem]
    if not matched and len(left) == len(right):
        return list(zip(left, right))
    if matched:
        missing = [p.name for p, s in zip(left, stems) if s not in by_stem]
        extra = sorted(set(by_stem) - set(stems))
        detail = f"{len(missing)} left frames without a right one (first {missing[0]})" if missing else \
            f"{len(extra)} right frames without a left one" if extra else "their names repeat a frame number"
        raise DataError(f"{left_dir} and {right_dir}: the frames do not pair: {detail}")
    raise DataError(f"{left_dir} has {len(left)} images but {right_dir} has {len(right)}, and their names "
                    "do not pair")


def read_image(path: Path) -> np.ndarray:
    """An image file as it is stored: ``(H, W)`` or ``(H, W, 3)`` (BGR), uint8 or uint16."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: image file not found")
    try:
        img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    except cv2.error:
        img = None
    if img is None or img.size == 0:
        raise DataError(f"{path}: cannot read image (corrupt or not an image)")
    if img.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: unsupported image type {img.dtype} (8- or 16-bit integer images)")
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    return img


def bit_depth(images: list[np.ndarray]) -> int:
    """The bit depth the pixel values of ``images`` use: 8 for uint8, else the smallest of 10, 12,
    14 and 16 bits that holds their maximum."""
    if all(img.dtype == np.uint8 for img in images):
        return 8
    top = max(int(img.max()) for img in images)
    bits = max(8, math.ceil(math.log2(top + 1))) if top > 0 else 8
    for depth in (8, 10, 12, 14, 16):
        if bits <= depth:
            return depth
    return 16


def to_rgb8(img: np.ndarray, depth: int, source: Path) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB from an image of ``read_image`` whose values use ``depth`` bits."""
    if img.dtype != np.uint8:
        if int(img.max()) >= (1 << depth):
            raise DataError(f"{source}: values up to {int(img.max())} exceed the sequence's {depth}-bit range "
                            "(read off its first frame)")
        img = np.clip(np.rint(img.astype(np.float32) * (255.0 / ((1 << depth) - 1))), 0, 255).astype(np.uint8)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


#: the units a ``timestamps.txt`` may be written in: name, units in a second
TIME_UNITS = (("milliseconds", 1e3), ("microseconds", 1e6), ("nanoseconds", 1e9))
#: frame rates (fps) whose timestamps are taken as seconds (those of ``StereoDataset.fps``)
SECONDS_RATES = (1.0, 1000.0)
#: frame rates (fps) a camera records at: steps that give one in another unit are read in it
CAMERA_RATES = (1.0, 120.0)


def in_seconds(stamps: np.ndarray, source: Path) -> np.ndarray:
    """Timestamps ``(N,)`` in seconds. Their median step decides the unit: seconds where it gives
    1-1000 fps; else milliseconds, microseconds or nanoseconds where one of them gives 1-120 fps
    (a warning names the unit and the rate: 40 ms steps are 25 fps, where in seconds they would be
    one frame every 40 s); else as they are (the frame rate then falls back, with a warning)."""
    if len(stamps) < 2:
        return stamps
    step = float(np.median(np.diff(stamps)))
    if SECONDS_RATES[0] <= 1.0 / step <= SECONDS_RATES[1]:
        return stamps
    for name, per_second in TIME_UNITS:
        rate = per_second / step
        if CAMERA_RATES[0] <= rate <= CAMERA_RATES[1]:
            log.warning("%s: steps of %g (median) read as %s (%.4g fps); the trajectory's timestamps are in seconds",
                        source, step, name, rate)
            return stamps / per_second
    return stamps


def read_timestamps(path: Path, n_frames: int) -> Optional[np.ndarray]:
    """``timestamps.txt``: one timestamp per frame and line, the last number of the line (``index
    timestamp`` rows work too), ``#`` lines are comments; in seconds, or in milliseconds,
    microseconds or nanoseconds recognised by their steps (:func:`in_seconds`). None when the file
    is absent; DataError naming it for another count than ``n_frames`` or values that do not
    increase."""
    if not path.is_file():
        return None
    stamps = []
    for k, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            stamps.append(float(line.replace(",", " ").split()[-1]))
        except ValueError:
            raise DataError(f"{path}:{k}: not a timestamp: '{line[:40]}'") from None
    stamps = np.asarray(stamps, dtype=np.float64)
    if len(stamps) != n_frames:
        raise DataError(f"{path}: {len(stamps)} timestamps for {n_frames} frames (need one per frame)")
    if n_frames > 1 and not np.all(np.diff(stamps) > 0):
        raise DataError(f"{path}: timestamps must increase")
    return in_seconds(stamps, path)
