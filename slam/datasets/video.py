"""Reading stereo videos stored left-over-right (left view in the top half of each frame).

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


class StackedStereoVideo:
    """A video whose frames hold the left view on top of the right view.

    Attributes:
        path: the video file.
        num_frames: frames in the video (from its header).
        view_size: ``(width, height)`` of one view.
        fps: the video's frame rate (0 if unknown).
    """

    def __init__(self, path: str | Path):
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
        if height % 2:
            self.close()
            raise DataError(f"{self.path}: frame height {height} is odd; expected the left view on top of the right view")
        self.view_size = (width, height // 2)
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
        if frame.shape[0] != 2 * h or frame.shape[1] != w:
            raise DataError(f"{self.path}: frame {index} is {frame.shape[1]}x{frame.shape[0]}, expected {w}x{2 * h}")
        if frame.ndim == 2:
            frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        rgb = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        return np.ascontiguousarray(rgb[:h]), np.ascontiguousarray(rgb[h:])
