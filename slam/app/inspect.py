"""``slam inspect DATA``: what the readers found in a sequence, whether its rectification is right,
and a picture to see it at a glance.

Prints the layout, frame count, image sizes, the calibration's source, whether the frames are
taken as rectified, the rectified focal length and baseline, the frame rate and where it comes
from, ground truth and masks. It matches corners between the left and right view of the first frame
as stored and as rectified (sub-pixel, Lucas-Kanade there and back): rectified views have no vertical disparity, and the left view's
features lie to the right of the right view's (positive disparity). It warns when frames the rule
calls unrectified are row-aligned already (``data.rectified: yes``?), when the rectified pair keeps
a vertical disparity (a calibration that does not fit), and when disparities are negative (left
and right swapped). It writes the rectified pair side by side with horizontal lines across it.
"""
from __future__ import annotations

import errno
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from slam.app.run_folder import replaced_atomically
from slam.io.stereo_check import ROW_ALIGNED_PX, disparities


def epipolar_picture(left: np.ndarray, right: np.ndarray, every_px: int = 32) -> np.ndarray:
    """The two views side by side (BGR) with a horizontal line every ``every_px`` rows."""
    pair = cv2.cvtColor(np.hstack([left, right]), cv2.COLOR_RGB2BGR)
    for y in range(every_px // 2, pair.shape[0], every_px):
        colour = (0, 255, 0) if (y // every_px) % 2 == 0 else (255, 0, 255)
        cv2.line(pair, (0, y), (pair.shape[1] - 1, y), colour, 1, cv2.LINE_AA)
    return pair


def inspect(data: str | Path, config, out: Optional[Path] = None) -> dict:
    """Open ``data`` with ``config`` (a :class:`slam.config.SlamConfig`), print the report, write
    the picture into ``out`` (default ``runs/inspect_<name>``); returns the figures."""
    from slam.io.datasets import open_dataset
    from slam.io.rectification import ResizeOnly

    ds = open_dataset(Path(data), config.data, check_rows=False)    # (the report gives the rows' figure)
    try:
        cam = ds.camera
        proc = ds.processor
        rectifies = not isinstance(proc, ResizeOnly)
        raw = ds._read(int(ds.indices[0]))
        frame = ds.frame(0)
        calib = getattr(ds, "calibration_path", None) or _calibration_file(ds)
        gt = ds.gt_poses
        gt_text = "no"
        if gt is not None:
            known = int(np.all(np.isfinite(gt.reshape(len(gt), -1)), axis=1).sum())
            gt_text = f"yes ({known} of {len(gt)} frames have a pose)"
        stamps = _rate_source(ds, config.data.fps)
        report = {
            "layout": ds.layout,
            "frames": len(ds),
            "input_size": f"{raw.left.shape[1]}x{raw.left.shape[0]}",
            "output_size": f"{cam.width}x{cam.height}",
            "calibration": str(calib) if calib else "-",
            "rectified": f"no: rectified here ({config.data.rectify_mode})" if rectifies else _taken_as_rectified(proc),
            "fx_px": float(cam.fx),
            "baseline_mm": float(cam.baseline_mm),
            "fps": float(ds.fps),
            "fps_from": stamps,
            "ground_truth": gt_text,
            "masks": "yes" if raw.instrument is not None else "no",
        }
        stored = disparities(raw.left, raw.right)
        rectified = disparities(frame.left, frame.right)
        report["stored_pair"] = stored.line()
        report["rectified_pair"] = rectified.line()
        warnings = []
        if rectifies and stored.matches >= 20 and stored.vertical_px < ROW_ALIGNED_PX:
            warnings.append("the stored views are row-aligned already: if they were rectified before, "
                            "set data.rectified=yes")
        if rectified.matches >= 20 and rectified.vertical_px >= ROW_ALIGNED_PX:
            warnings.append(f"the rectified views keep a vertical disparity of {rectified.vertical_px:.2f} px: "
                            "the calibration does not fit these frames (or try data.rectify_mode=pseudo/full)")
        if rectified.matches >= 20 and rectified.negative_share > 0.5:
            warnings.append("most disparities are negative: the left and right views look swapped")
        report["warnings"] = warnings
        out = Path(out) if out else Path("runs") / f"inspect_{Path(data).resolve().stem}"
        out.mkdir(parents=True, exist_ok=True)
        picture = out / "rectified_pair.png"
        with replaced_atomically(picture) as tmp:
            if not cv2.imwrite(str(tmp), epipolar_picture(frame.left, frame.right)):
                raise OSError(errno.EIO, "could not be written", str(picture))
        report["picture"] = str(picture)
    finally:
        ds.close()
    width = max(len(k) for k in report)
    for key, value in report.items():
        if key == "warnings":
            continue
        text = f"{value:.2f}" if isinstance(value, float) else str(value)
        print(f"{key.replace('_', ' '):<{width}}  {text}")
    for w in report["warnings"]:
        print(f"warning: {w}")
    return report


def _taken_as_rectified(proc) -> str:
    """How the report words frames taken as rectified: resized or not (a ``ResizeOnly``'s sizes)."""
    if tuple(proc.output_size) == tuple(proc.input_size):
        return "taken as rectified, not resized"
    return "taken as rectified, resized from {}x{}".format(*proc.input_size)


def _rate_source(ds, fps: float) -> str:
    """Where the frame rate of ``ds`` comes from (see docs/inputs.md, Timestamps)."""
    if getattr(ds, "timestamps_source", "") == "timestamps.txt":
        return "timestamps.txt"
    if ds.gt_poses is not None:
        return "the ground truth's timestamps"
    if fps > 0:
        return "data.fps"
    video = getattr(ds, "video", None)
    if video is not None and video.fps > 0:
        return "the video's header"
    return "none given: the default"


def _calibration_file(ds) -> Optional[Path]:
    from slam.io.calibration import CALIBRATION_NAMES

    for name in CALIBRATION_NAMES:
        if (ds.path / name).is_file():
            return ds.path / name
    return None
