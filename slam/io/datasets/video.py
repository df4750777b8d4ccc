"""Reading stereo videos: both views in each frame, the left above the right (top-bottom, as
StereoMIS and SCARED record them) or beside it (side-by-side).

Frames are decoded sequentially; a request for a frame behind the decoder or far ahead of it
seeks (``CAP_PROP_POS_FRAMES``), a request a little ahead skips frames with ``grab``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from slam.errors import DataError

# Skip forward by decoding (grab) rather than seeking when the target is at most this far ahead.
_MAX_GRAB_AHEAD = 64


STEREO_LAYOUTS = ("top-bottom", "side-by-side")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".webm", ".wmv")


def frame_size_of(path: Path) -> tuple[int, int]:
    """``(width, height)`` of a video's frames (from its header, else its first frame)."""
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise DataError(f"{path}: cannot open video (unsupported codec or corrupt file)")
        size = (int(round(cap.get(cv2.CAP_PROP_FRAME_WIDTH))), int(round(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))))
        if min(size) <= 0:
            ok, first = cap.read()
            if not ok or first is None:
                raise DataError(f"{path}: cannot decode the first video frame")
            size = (first.shape[1], first.shape[0])
        return size
    finally:
        cap.release()


def stereo_layout_of(frame_size: tuple[int, int], calib_size: tuple[int, int] | None, requested: str,
                     where: str, video: str = "the video") -> str:
    """How a video frame of ``(width, height)`` holds its two views: ``requested`` unless
    ``auto``; else the layout whose view size is the calibration's (or an integer multiple or
    fraction of it, keeping its aspect); without a size in the calibration, the frame's aspect
    ratio (twice as tall as wide an image is top-bottom: endoscope views are wider than tall).
    A calibration size that fits neither layout is a DataError naming ``where`` (the calibration
    file) and ``video``."""
    if requested in STEREO_LAYOUTS:
        return requested
    W, H = frame_size
    views = {"top-bottom": (W, H // 2), "side-by-side": (W // 2, H)}
    if calib_size is not None:
        cw, ch = calib_size
        fits = [name for name, (w, h) in views.items()
                if any((w * k, h * k) == (cw, ch) or (w, h) == (cw * k, ch * k) for k in (1, 2, 3, 4))]
        if len(fits) == 1:
            return fits[0]
        if not fits:
            raise DataError(f"{where}: calibration for {cw}x{ch} views does not fit the {W}x{H} frames of {video}: "
                            "they hold neither two such views (or an integer multiple or fraction of them) one above "
                            "the other nor side by side (--stereo-layout, or another calibration)")
    return "top-bottom" if H > W * 0.7 else "side-by-side"


class StackedStereoVideo:
    """A video whose frames hold both views: the left above the right (``top-bottom``) or to its
    left (``side-by-side``).

    Attributes:
        path: the video file.
        layout: ``top-bottom`` or ``side-by-side``.
        num_frames: frames in the video (from its header).
        frame_size: ``(width, height)`` of a whole video frame.
        view_size: ``(width, height)`` of one view.
        fps: the video's frame rate (0 if unknown).
    """

    def __init__(self, path: str | Path, layout: str = "top-bottom"):
        if layout not in STEREO_LAYOUTS:
            raise ValueError(f"unknown stereo layout '{layout}' ({', '.join(STEREO_LAYOUTS)})")
        self.layout = layout
        self.path = Path(path)
        if not self.path.is_file():
            raise DataError(f"{self.path}: video file not found")
        self._cap: Optional[cv2.VideoCapture] = None
        self._open()
        cap = self._cap
        self.num_frames = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        width = int(round(cap.get(cv2.CAP_PROP_FRAME_WIDTH)))
        height = int(round(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        fps = cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and np.isfinite(fps) and fps > 0 else 0.0
        if width <= 0 or height <= 0:
            ok, first = cap.read()
            if not ok or first is None:
                self.close()
                raise DataError(f"{self.path}: cannot decode the first video frame")
            height, width = first.shape[:2]
            self._reopen()
        if self.num_frames <= 0:
            self.close()
            raise DataError(f"{self.path}: cannot determine the number of video frames")
        self.frame_size = (width, height)
        if layout == "top-bottom" and height % 2:
            self.close()
            raise DataError(f"{self.path}: frame height {height} is odd; expected the left view on top of the right view")
        if layout == "side-by-side" and width % 2:
            self.close()
            raise DataError(f"{self.path}: frame width {width} is odd; expected the left view beside the right view")
        self.view_size = (width, height // 2) if layout == "top-bottom" else (width // 2, height)
        self._next = 0  # index of the frame the next cap.read() returns

    def _open(self) -> None:
        try:
            cap = cv2.VideoCapture(str(self.path))
        except Exception:  # noqa: BLE001 - any backend failure is "cannot open"
            cap = None
        if cap is None or not cap.isOpened():
            raise DataError(f"{self.path}: cannot open video (unsupported codec or corrupt file)")
        self._cap = cap

    def _reopen(self) -> None:
        if self._cap is not None:
            self._cap.release()
        self._open()
        self._next = 0

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __len__(self) -> int:
        return self.num_frames

    def read(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``index`` as ``(left, right)`` ``(H, W, 3)`` uint8 RGB."""
        if not 0 <= index < self.num_frames:
            raise IndexError(f"{self.path}: frame {index} out of range for {self.num_frames} frames")
        if self._cap is None:
            self._open()
            self._next = 0
        cap = self._cap
        if index != self._next:
            if 0 <= self._next < index <= self._next + _MAX_GRAB_AHEAD:
                while self._next < index:
                    if not cap.grab():
                        raise DataError(f"{self.path}: cannot decode frame {self._next}")
                    self._next += 1
            elif index == 0:
                self._reopen()
                cap = self._cap
            else:
                if not cap.set(cv2.CAP_PROP_POS_FRAMES, float(index)):
                    self._reopen()
                    cap = self._cap
                    for k in range(index):
                        if not cap.grab():
                            raise DataError(f"{self.path}: cannot decode frame {k}")
                self._next = index
        ok, frame = cap.read()
        if not ok or frame is None:
            self._next = -1  # unknown position: the next request seeks
            raise DataError(f"{self.path}: cannot decode frame {index} of {self.num_frames}")
        self._next = index + 1
        w, h = self.view_size
        if (frame.shape[1], frame.shape[0]) != self.frame_size:
            raise DataError(f"{self.path}: frame {index} is {frame.shape[1]}x{frame.shape[0]}, expected "
                            f"{self.frame_size[0]}x{self.frame_size[1]}")
        if frame.ndim == 2:
            frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        rgb = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        if self.layout == "top-bottom":
            return np.ascontiguousarray(rgb[:h]), np.ascontiguousarray(rgb[h:])
        return np.ascontiguousarray(rgb[:, :w]), np.ascontiguousarray(rgb[:, w:])
