"""The interface every dataset reader implements, and the per-frame pipeline they share.

A reader (one per layout) knows where a sequence's files are; :class:`StereoDataset` turns what
it reads into :class:`~slam.io.datasets.base.StereoFrame` objects: rectification/resizing
(:mod:`slam.io.rectification`), the validity mask (:mod:`slam.io.datasets.masks`), ground truth.

Indexing. ``len(ds)``, ``ds.frame(i)``, ``iter(ds)``, ``ds.timestamps`` and ``ds.gt_poses`` all
refer to the frames of the current *view*: ``ds.select("2:8:2")`` returns a view of frames 2, 4, 6
in which ``frame(0)`` is sequence frame 2. ``ds.indices`` maps view positions to sequence
indices, and ``StereoFrame.index`` is always the sequence index. A freshly opened dataset is a
view of all frames.

Ground truth. A TUM file with one pose per frame gives the frames' poses in order; with another
count its poses are associated by timestamp (:func:`load_groundtruth`), frames without one
within half a frame period getting NaN poses and a warning. SCARED's per-frame poses
(:func:`match_groundtruth`) must be one per frame: fewer is a DataError naming them, extra
trailing ones are dropped with a warning (recordings often log kinematics slightly past the last
video frame, and the frames are what is processed). Warnings go to the ``slam`` logger, one line
each (not ``warnings.warn``, whose output names a source line). Poses are ``T_wc`` of the *original* left camera in mm, as in
the files; the VO's rectified-camera poses convert with ``R1`` (see :mod:`slam.io.rectification`).
"""
from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional, Sequence

import cv2
import numpy as np

from slam.io.datasets.base import StereoFrame
from slam.io.datasets.config import MIN_FRAME_PX, DataConfig
from slam.io.datasets.masks import combine_masks, specular_mask
from slam.io.datasets.selection import parse_frames
from slam.errors import DataError
from slam.io.tum import read_tum

log = logging.getLogger("slam")

#: the frame rate assumed where neither the data nor ``data.fps`` gives one
DEFAULT_FPS = 25.0


@dataclass
class RawFrame:
    """What a reader returns for one frame, before rectification and resizing.

    Attributes:
        left, right: ``(H, W, 3)`` uint8 RGB at the reader's input size.
        instrument: ``(H, W)`` bool instrument mask of the left view (True = tissue), or None.
        depth: ``(H, W)`` float32 depth of the left view in mm (0 = unknown), or None.
        extras: per-frame arrays of the left view at the input size (mapped like ``depth``) or
            other values (passed through).
        source: how error messages name the frame (a file or ``video:frame``).
    """

    left: np.ndarray
    right: np.ndarray
    instrument: Optional[np.ndarray] = None
    depth: Optional[np.ndarray] = None
    extras: dict = field(default_factory=dict)
    source: str = ""


class StereoDataset:
    """A stereo sequence: rectified camera, timestamps, optional ground truth and lazy frames.

    Attributes:
        path: the sequence folder.
        layout: ``stereomis`` | ``stereomis_raw`` | ``scared`` | ``plain``.
        config: the :class:`DataConfig` it was opened with.
        camera: the rectified :class:`~vo.camera.StereoCamera` at the output size.
        R1: ``(3, 3)`` rotation from the original to the rectified left camera frame
            (``T_wc_original = T_wc_rect @ [[R1, 0], [0, 1]]``, see :mod:`slam.io.rectification`).
        indices: ``(N,)`` sequence indices of the frames of this view.
        timestamps: ``(N,)`` float64 of this view (ground truth's where it exists, else index / fps).
        gt_poses: ``(N, 4, 4)`` float64 ``T_wc`` of the original left camera in mm, or None.
        num_frames_total: frames in the whole sequence.
    """

    layout: str = "?"

    def __init__(self, path: Path, config: DataConfig, processor, n_frames: int,
                 timestamps: Optional[np.ndarray] = None, gt_poses: Optional[np.ndarray] = None):
        self.path = Path(path)
        self.config = config
        self.processor = processor
        self.camera = processor.camera
        if min(self.camera.width, self.camera.height) < MIN_FRAME_PX:
            raise DataError(f"{self.path}: frames of {self.camera.width}x{self.camera.height} px are too small to track "
                            f"(at least {MIN_FRAME_PX}x{MIN_FRAME_PX}: the optical flow's smallest image)")
        self.R1 = np.asarray(processor.R1, dtype=np.float64)
        self.num_frames_total = int(n_frames)
        if timestamps is None:
            fps = config.fps if config.fps and config.fps > 0 else DEFAULT_FPS
            if not config.fps > 0 and self.num_frames_total > 1:
                log.warning("%s: no timestamps (timestamps.txt, ground truth, a video's rate) and no --fps: the frames "
                            "are taken at %g fps", self.path, DEFAULT_FPS)
            timestamps = np.arange(self.num_frames_total, dtype=np.float64) / fps
        self._timestamps = np.asarray(timestamps, dtype=np.float64)
        self._gt_poses = None if gt_poses is None else np.asarray(gt_poses, dtype=np.float64)
        self.indices = np.arange(self.num_frames_total, dtype=np.int64)

    # -- implemented by readers -----------------------------------------------------------------
    def _read(self, index: int) -> RawFrame:
        """Read sequence frame ``index`` (0-based) at the input size."""
        raise NotImplementedError

    def close(self) -> None:
        """Release open files (videos). The dataset must not be used afterwards."""

    # -- the view ----------------------------------------------------------------------------------
    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps[self.indices]

    @property
    def gt_poses(self) -> Optional[np.ndarray]:
        return None if self._gt_poses is None else self._gt_poses[self.indices]

    def __len__(self) -> int:
        return len(self.indices)

    @property
    def fps(self) -> float:
        """The frame rate of this view (frames per second): from its timestamps' median step
        (rounded to 1e-3), where they imply 1-1000 fps, else ``data.fps`` or ``DEFAULT_FPS`` (a
        warning says so). A view of every S-th frame runs at a S-th of the sequence's rate."""
        stamps = self.timestamps
        fallback = self.config.fps if self.config.fps > 0 else DEFAULT_FPS
        if len(stamps) > 1:
            step = float(np.median(np.diff(stamps)))
            if step > 0 and 1.0 <= 1.0 / step <= 1000.0:
                return round(1.0 / step, 3)
            log.warning("%s: the frames' timestamps step by %g (median), not 1-1000 frames a second: the frames are "
                        "taken at %g fps (%s)", self.path, step, fallback,
                        "--fps" if self.config.fps > 0 else "the default; --fps to give the rate")
        return fallback

    def __iter__(self) -> Iterator[StereoFrame]:
        for i in range(len(self)):
            yield self.frame(i)

    def __enter__(self) -> "StereoDataset":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        cam = self.camera
        return (f"<{type(self).__name__} {self.layout} '{self.path}': {len(self)}/{self.num_frames_total} frames, "
                f"{cam.width}x{cam.height}, fx={cam.fx:.1f}, baseline={cam.baseline_mm:.3f} mm, "
                f"gt={'yes' if self._gt_poses is not None else 'no'}>")

    def select(self, spec: str | int | None) -> "StereoDataset":
        """A view restricted to the frames ``spec`` selects among this view's frames
        (see :func:`slam.io.datasets.selection.parse_frames`). Shares files with this dataset."""
        positions = parse_frames(spec, len(self))
        view = copy.copy(self)
        view.indices = self.indices[positions]
        return view

    def frame(self, i: int) -> StereoFrame:
        """Frame at position ``i`` of this view, rectified and resized (reads only that frame)."""
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for {n} frames")
        index = int(self.indices[i])
        raw = self._read(index)
        return self._process(index, raw)

    def _process(self, index: int, raw: RawFrame) -> StereoFrame:
        proc, cfg = self.processor, self.config
        src = raw.source or f"{self.path} frame {index}"
        left, right = proc.rectify(raw.left, raw.right, src)
        instrument = None
        if raw.instrument is not None and cfg.use_mask_files:
            instrument = proc.rectify_left_mask(raw.instrument, src)
        specular = np.stack([specular_mask(left, cfg.specular_threshold, cfg.specular_dilate_px),
                             specular_mask(right, cfg.specular_threshold, cfg.specular_dilate_px)])
        mask = combine_masks(left, instrument, cfg.specular_threshold, cfg.specular_dilate_px, proc.valid_mask,
                             cfg.dark_threshold, specular=specular[0])
        depth = None
        if raw.depth is not None:
            depth = proc.rectify_left_nearest(np.asarray(raw.depth, dtype=np.float32), src)
        extras = {}
        for key, value in raw.extras.items():
            if isinstance(value, np.ndarray) and value.ndim >= 2 and value.shape[:2] == raw.left.shape[:2]:
                value = proc.rectify_left_nearest(value, src)
            extras[key] = value
        gt = None if self._gt_poses is None else self._gt_poses[index].copy()
        return StereoFrame(
            index=index,
            timestamp=float(self._timestamps[index]),
            left=np.ascontiguousarray(left),
            right=np.ascontiguousarray(right),
            mask=mask,
            gt_pose=gt,
            gt_depth=depth,
            extras=extras,
            specular=specular,
        )


# --------------------------------------------------------------------------------------------
# helpers shared by the readers
# --------------------------------------------------------------------------------------------

def read_rgb(path: Path) -> np.ndarray:
    """An image file as ``(H, W, 3)`` uint8 RGB; DataError naming the file if unreadable."""
    img = _imread(path, cv2.IMREAD_COLOR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


#: how many of its first frames a reader tries for the frames' size before it gives up
SIZE_PROBE_FRAMES = 5


def first_readable_size(paths: Sequence[Path], tries: int = SIZE_PROBE_FRAMES) -> Optional[tuple[int, int]]:
    """``(width, height)`` of the first image among the first ``tries`` of ``paths`` that reads,
    or None when none of them does (those frames then fail one by one when they are read)."""
    for path in list(paths)[:tries]:
        try:
            img = _imread(path, cv2.IMREAD_UNCHANGED)
        except DataError:
            continue
        return int(img.shape[1]), int(img.shape[0])
    return None


def read_mask(path: Path, shape: Optional[tuple[int, ...]] = None) -> np.ndarray:
    """A mask image as ``(H, W)`` bool, True where any channel is non-zero.

    ``shape``: the frame's ``(H, W, ...)``; a mask of another size is a DataError naming the file.
    """
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    _check_shape(img, shape, path)
    if img.ndim == 3:
        img = img.max(axis=2)
    return img > 0


def read_scaled_uint(path: Path, scale: float, shape: Optional[tuple[int, ...]] = None) -> np.ndarray:
    """An integer image (e.g. uint16 depth) times ``scale``, float32 (size checked against ``shape``)."""
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    _check_shape(img, shape, path)
    return img.astype(np.float32) * np.float32(scale)


def _check_shape(img: np.ndarray, shape: Optional[tuple[int, ...]], path: Path) -> None:
    if shape is not None and img.shape[:2] != tuple(shape[:2]):
        raise DataError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, but the frame is {shape[1]}x{shape[0]}")


def _imread(path: Path, flags: int) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: image file not found")
    try:
        img = cv2.imread(str(path), flags)
    except cv2.error:
        img = None
    if img is None or img.size == 0:
        raise DataError(f"{path}: cannot read image (corrupt or not an image)")
    if img.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: unsupported image type {img.dtype}")
    if flags == cv2.IMREAD_COLOR and img.dtype != np.uint8:
        img = (img >> 8).astype(np.uint8)
    return img


def match_groundtruth(source: str, stamps: Optional[np.ndarray], poses: np.ndarray, n_frames: int
                      ) -> tuple[Optional[np.ndarray], np.ndarray]:
    """Reconcile ground truth with the frame count.

    One pose per frame, in order. More poses than frames: the extra trailing poses are dropped
    with a warning (recordings often log kinematics a little past the last video frame); fewer:
    DataError naming ``source``.
    """
    if len(poses) < n_frames:
        raise DataError(f"{source}: {len(poses)} poses for {n_frames} frames (need one pose per frame)")
    if len(poses) > n_frames:
        log.warning("%s: %d poses for %d frames; ignoring the last %d", source, len(poses), n_frames,
                    len(poses) - n_frames)
        poses = poses[:n_frames]
        stamps = None if stamps is None else stamps[:n_frames]
    return stamps, poses


def load_groundtruth(path: Path, n_frames: int, frame_stamps: Optional[np.ndarray] = None, fps: float = 0.0
                     ) -> tuple[Optional[np.ndarray], Optional[np.ndarray]]:
    """The frames' timestamps and their ground-truth poses ``(N, 4, 4)`` ``T_wc`` in mm from a TUM
    file (metres), or ``(frame_stamps, None)`` where there is none.

    With one pose per frame the poses are the frames' in order, and frames without timestamps of
    their own (``frame_stamps`` None) take the ground truth's. Otherwise poses are associated by
    timestamp, never by index: each frame
    gets the pose nearest in time within half a frame period (frames without one get NaN rows,
    which evaluation leaves out); frames without timestamps are taken at ``fps`` (``DEFAULT_FPS``
    when 0) from the first pose's time. DataError naming the file when no frame gets a pose.
    """
    if not path.exists():
        return frame_stamps, None
    gt_stamps, poses = read_tum(path, scale_to_mm=True)
    if len(poses) == n_frames:      # one pose per frame, in order
        return (gt_stamps if frame_stamps is None else frame_stamps), poses
    if frame_stamps is None:
        rate = fps if fps and fps > 0 else DEFAULT_FPS
        frame_stamps = gt_stamps[0] + np.arange(n_frames, dtype=np.float64) / rate
    return frame_stamps, associate_poses(str(path), gt_stamps, poses, np.asarray(frame_stamps, dtype=np.float64))


def associate_poses(source: str, gt_stamps: np.ndarray, poses: np.ndarray, frame_stamps: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` poses at ``frame_stamps``: the nearest of ``gt_stamps`` within half a frame
    period (the median step of ``frame_stamps``, or of ``gt_stamps`` for one frame), NaN where none."""
    steps = np.diff(frame_stamps) if len(frame_stamps) > 1 else np.diff(gt_stamps)
    half = 0.5 * float(np.median(steps)) if len(steps) else np.inf
    order = np.argsort(gt_stamps, kind="stable")
    sorted_stamps = gt_stamps[order]
    idx = np.searchsorted(sorted_stamps, frame_stamps)
    lo, hi = np.clip(idx - 1, 0, len(sorted_stamps) - 1), np.clip(idx, 0, len(sorted_stamps) - 1)
    nearest = np.where(np.abs(frame_stamps - sorted_stamps[lo]) <= np.abs(sorted_stamps[hi] - frame_stamps), lo, hi)
    found = np.abs(sorted_stamps[nearest] - frame_stamps) <= half * (1 + 1e-9)
    out = np.full((len(frame_stamps), 4, 4), np.nan)
    out[found] = poses[order[nearest[found]]]
    if not found.any():
        raise DataError(f"{source}: no ground-truth pose within half a frame period of any frame (timestamps in "
                        f"another unit or clock? give the frames' timestamps.txt or --fps)")
    if not found.all():
        log.warning("%s: %d of %d frames have no ground-truth pose within half a frame period (left out of the "
                    "evaluation)", source, int((~found).sum()), len(found))
    return out
