"""File layout of a synthetic sequence (StereoMIS pre-processed or raw), written in the background.

Pre-processed (rectified)::

    video_frames/000000l.png 000000r.png ...   RGB frames (BGR PNG as cv2 writes them)
    depth/000000l.png                          uint16, 0.01 mm, left view
    nonrigid/000000l.png                       uint16, 0.01 mm, |non-rigid displacement|
    masks/000000l.png                          uint8 255 = tissue, 0 = instrument (deforming)
    StereoCalibration.ini  groundtruth.txt  synth.json

Raw: ``<name>.mp4`` (left image on top of the right one, W x 2H), ``masks/`` (deforming),
``StereoCalibration.ini`` (unrectified), ``groundtruth.txt``, ``synth.json``.
"""
from __future__ import annotations

import json
import re
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from slam.errors import DataError
from slam.synth.cameras import StereoRig

DEPTH_SCALE_MM = 0.01
_FRAME_FILE = re.compile(r"^\d{6}[lr]\.png$")
SUBDIRS = ("video_frames", "depth", "nonrigid", "masks")


def to_uint16(values_mm: np.ndarray) -> np.ndarray:
    """Millimetres -> uint16 in units of ``DEPTH_SCALE_MM`` (non-finite -> 0)."""
    v = np.where(np.isfinite(values_mm), values_mm, 0.0) / DEPTH_SCALE_MM
    return np.clip(np.round(v), 0, 65535).astype(np.uint16)


def prepare_out_dir(out_dir: Path) -> None:
    """Create ``out_dir``; remove frame files of an earlier synthetic sequence written there (so
    a shorter sequence does not leave stale frames). Refuses a non-empty folder that is not a
    synthetic sequence. Marks the folder as one at once (a placeholder ``synth.json`` that the
    finished sequence overwrites), so a run interrupted half-way can be rerun into it."""
    if out_dir.exists() and not out_dir.is_dir():
        raise DataError(f"{out_dir}: exists and is not a folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    if any(out_dir.iterdir()) and not (out_dir / "synth.json").is_file():
        raise DataError(f"{out_dir}: folder is not empty and holds no synthetic sequence (synth.json); choose another")
    for sub in SUBDIRS:
        d = out_dir / sub
        if d.is_dir():
            for f in d.iterdir():
                if _FRAME_FILE.match(f.name):
                    f.unlink()
            if not any(d.iterdir()):  # an empty frame folder would mislead layout detection
                d.rmdir()
    for f in [*out_dir.glob("*.mp4"), *out_dir.glob("*.avi")]:
        f.unlink()
    (out_dir / "synth.json").write_text(json.dumps({"generator": "slam.synth", "complete": False}) + "\n")


def is_finished(out_dir: Path) -> bool:
    """Whether ``out_dir`` holds a finished synthetic sequence: a ``synth.json`` that is not the
    placeholder :func:`prepare_out_dir` writes first (a generation interrupted half-way leaves
    that one)."""
    try:
        meta = json.loads((Path(out_dir) / "synth.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("complete", True) is not False


def _imwrite(path: Path, img: np.ndarray) -> None:
    if not cv2.imwrite(str(path), img):
        raise DataError(f"{path}: cannot write image")


#: raw-video codecs -> file suffix: mp4v (lossy, as recorders write) or ffv1 (lossless)
VIDEO_CODECS = {"mp4v": ".mp4", "ffv1": ".avi"}


class SequenceWriter:
    """Writes frames in order; PNG encoding and video writing run on one background thread."""

    def __init__(self, out_dir: Path, raw: bool, width: int, height: int, fps: float,
                 masks: bool, video_name: Optional[str] = None, codec: str = "mp4v"):
        self.out_dir = out_dir
        self.raw = raw
        self.masks = masks
        self._pool = ThreadPoolExecutor(max_workers=1)
        self._pending: list[Future] = []
        self._video = None
        self.video_path: Optional[Path] = None
        if masks:
            (out_dir / "masks").mkdir(exist_ok=True)
        if raw:
            if codec not in VIDEO_CODECS:
                raise DataError(f"unknown video codec '{codec}' ({', '.join(VIDEO_CODECS)})")
            self.video_path = out_dir / f"{video_name or out_dir.name}{VIDEO_CODECS[codec]}"
            self._video = cv2.VideoWriter(str(self.video_path), cv2.VideoWriter_fourcc(*codec.upper()), float(fps),
                                          (width, 2 * height))
            if not self._video.isOpened():
                raise DataError(f"{self.video_path}: cannot open a {codec} video writer")
        else:
            for sub in ("video_frames", "depth", "nonrigid"):
                (out_dir / sub).mkdir(exist_ok=True)

    def _submit(self, fn, *args) -> None:
        self._pending.append(self._pool.submit(fn, *args))
        if len(self._pending) > 16:  # bounded memory; surfaces write errors early
            self._pending.pop(0).result()

    def write(self, index: int, left: np.ndarray, right: np.ndarray, depth: Optional[np.ndarray] = None,
              nonrigid: Optional[np.ndarray] = None, tissue: Optional[np.ndarray] = None) -> None:
        """One frame: RGB uint8 views, left depth / non-rigid magnitude (mm), tissue mask (bool)."""
        name = f"{index:06d}"
        if self.raw:
            frame = cv2.cvtColor(np.vstack([left, right]), cv2.COLOR_RGB2BGR)
            self._submit(self._video.write, frame)
        else:
            vf = self.out_dir / "video_frames"
            self._submit(_imwrite, vf / f"{name}l.png", cv2.cvtColor(left, cv2.COLOR_RGB2BGR))
            self._submit(_imwrite, vf / f"{name}r.png", cv2.cvtColor(right, cv2.COLOR_RGB2BGR))
            if depth is not None:
                self._submit(_imwrite, self.out_dir / "depth" / f"{name}l.png", to_uint16(depth))
            if nonrigid is not None:
                self._submit(_imwrite, self.out_dir / "nonrigid" / f"{name}l.png", to_uint16(nonrigid))
        if self.masks and tissue is not None:
            self._submit(_imwrite, self.out_dir / "masks" / f"{name}l.png", np.where(tissue, 255, 0).astype(np.uint8))

    def __enter__(self) -> "SequenceWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        try:
            for f in self._pending:
                f.result()
        finally:
            self._pending.clear()
            self._pool.shutdown(wait=True)
            if self._video is not None:
                self._video.release()
                self._video = None


def write_calibration(path: Path, rig: StereoRig) -> None:
    """``StereoCalibration.ini`` (StereoMIS keys; ``X_r = R X_l + T``, mm)."""
    lines = []
    for section, cam in (("StereoLeft", rig.left), ("StereoRight", rig.right)):
        lines.append(f"[{section}]")
        vals = [("res_x", cam.width), ("res_y", cam.height), ("fc_x", cam.K[0, 0]), ("fc_y", cam.K[1, 1]),
                ("cc_x", cam.K[0, 2]), ("cc_y", cam.K[1, 2])]
        vals += [(f"kc_{i}", cam.dist[i]) for i in range(8)]
        if section == "StereoRight":
            vals += [(f"T_{i}", rig.T[i]) for i in range(3)]
            vals += [(f"R_{i}", rig.R.reshape(-1)[i]) for i in range(9)]
        for k, v in vals:
            lines.append(f"{k} = {int(v)}" if isinstance(v, (int, np.integer)) else f"{k} = {float(v):.12g}")
        lines.append("")
    path.write_text("\n".join(lines))


def write_metadata(path: Path, meta: dict) -> None:
    path.write_text(json.dumps(meta, indent=2) + "\n")
