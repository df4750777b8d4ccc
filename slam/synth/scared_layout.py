"""Synthetic stand-ins in the SCARED keyframe layout (for ``tools/evaluate_scared.py`` and tests).

:func:`write_scared_keyframe` converts a synthetic sequence written by :func:`slam.synth.generate`
(StereoMIS pre-processed layout, rectified, with ``depth/``) into the layout
:class:`slam.io.datasets.scared.ScaredDataset` reads, plus the keyframe's ground-truth geometry::

    <keyframe>/
      endoscope_calibration.yaml     OpenCV FileStorage: M1 D1 M2 D2 R T (mm, X_r = R X_l + T),
                                     width/height of one view
      data/rgb.mp4                   mp4v video, left view on top of the right view (W x 2H)
      data/frame_data/frame_data000000.json ...
                                     {"camera-calibration": {...}, "camera-pose": 4x4}
      left_depth_map.tiff            H x W x 3 float32: x y z (mm) of the surface seen by each pixel
                                     of the keyframe's left image (frame 0), in that left camera's
                                     frame; 0 where there is no surface (as SCARED ships it)
      Left_Image.png Right_Image.png the keyframe's views (frame 0), as in SCARED

``camera-pose`` is written in the convention the reader assumes (see ``slam/io/datasets/scared.py``):
the world-to-camera transform of the left camera at frame i, world = the keyframe's (frame 0's) left
camera, translation in mm: ``camera-pose_i = inv(T_wc_i) @ T_wc_0`` with the generator's
``T_wc``. The reader's ``T_wc = inv(camera-pose)`` is then ``inv(T_wc_0) @ T_wc_i``.

Channel order of the TIFF: the file stores x, y, z per pixel (what ``tifffile.imread`` returns, as
the SCARED toolkits read it). OpenCV reverses the channels of 3-channel TIFFs both ways (it treats
them as RGB <-> BGR), so :func:`write_xyz_tiff` / :func:`read_xyz_tiff` flip them.

The synthetic rig is already rectified (no distortion, R = I, equal intrinsics), so the SCARED
reader's rectification (``pseudo`` or ``full``) leaves the images unchanged. The video is lossy
(mp4v), like SCARED's.

:func:`make_scared_standin` renders several keyframes (``dataset_<d>/keyframe_<k>``) at once.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Optional

import cv2
import numpy as np

from slam.errors import DataError

VIDEO_FILE = "data/rgb.mp4"
FRAME_DATA_DIR = "data/frame_data"
CALIB_FILE = "endoscope_calibration.yaml"
GT_DEPTH_FILE = "left_depth_map.tiff"
STANDIN_FILE = "standin.json"  # parameters of a synthetic stand-in (not part of SCARED)

#: the keyframes of the paper's Table 3 (dataset, keyframe), the default of the stand-in.
PAPER_KEYFRAMES = ((1, 2), (8, 1), (9, 1), (9, 3))


def write_xyz_tiff(path: str | Path, xyz: np.ndarray) -> None:
    """Write an ``(H, W, 3)`` float32 point map as a TIFF storing x, y, z per pixel (file order)."""
    xyz = np.ascontiguousarray(np.asarray(xyz, dtype=np.float32)[..., ::-1])  # OpenCV writes BGR order
    if not cv2.imwrite(str(path), xyz):
        raise DataError(f"{path}: cannot write TIFF")


def read_xyz_tiff(path: str | Path) -> np.ndarray:
    """An ``(H, W, 3)`` float32 point map (x, y, z in file order) from a SCARED ``*_depth_map.tiff``."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 3 or img.shape[2] != 3:
        shape = "unreadable" if img is None else "x".join(map(str, img.shape))
        raise DataError(f"{path}: expected an H x W x 3 float TIFF (x y z per pixel), got {shape}")
    return np.ascontiguousarray(img[..., ::-1]).astype(np.float32)  # OpenCV returns BGR order


def depth_to_xyz(depth_mm: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Back-project a z-depth map ``(H, W)`` (mm, 0 = none) with intrinsics ``K`` (pixel centres at
    integer coordinates) to an ``(H, W, 3)`` float32 point map; 0 where the depth is 0 or invalid."""
    depth = np.asarray(depth_mm, dtype=np.float64)
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    z = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=-1).astype(np.float32)


def _dist(D: np.ndarray) -> np.ndarray:
    """OpenCV distortion as a 1 x 5 row (1 x 8 when k4..k6 are used)."""
    D = np.asarray(D, dtype=np.float64).reshape(-1)
    n = 8 if len(D) >= 8 and np.any(D[5:8] != 0) else 5
    return np.r_[D, np.zeros(max(0, n - len(D)))][:n].reshape(1, n)


def _write_calibration(path: Path, calib, size: tuple[int, int]) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise DataError(f"{path}: cannot write calibration")
    fs.write("M1", calib.K1)
    fs.write("D1", _dist(calib.D1))
    fs.write("M2", calib.K2)
    fs.write("D2", _dist(calib.D2))
    fs.write("R", calib.R)
    fs.write("T", calib.T.reshape(3, 1))
    fs.write("width", int(size[0]))
    fs.write("height", int(size[1]))
    fs.release()


def write_scared_keyframe(src: str | Path, out: str | Path, fps: float = 25.0) -> Path:
    """Convert a synthetic sequence (``slam.synth.generate``, pre-processed layout) to a SCARED
    keyframe folder ``out`` (see the module docstring). Frame 0 is the keyframe.

    Args:
        src: the synthetic sequence folder (``video_frames/``, ``StereoCalibration.ini``,
            ``groundtruth.txt``, ``depth/``).
        out: the keyframe folder to write (created; existing files are overwritten).
        fps: frame rate of the video.

    Returns:
        ``out`` as a Path.
    """
    from slam.io.calibration import read_stereomis_ini
    from slam.io.datasets.dataset import read_rgb, read_scaled_uint
    from slam.io.datasets.stereomis import list_stereo_pngs, read_depth_scale
    from slam.io.tum import read_tum

    src, out = Path(src), Path(out)
    pairs = list_stereo_pngs(src / "video_frames")
    calib = read_stereomis_ini(src / "StereoCalibration.ini")
    _, T_wc = read_tum(src / "groundtruth.txt", scale_to_mm=True)
    if len(T_wc) < len(pairs):
        raise DataError(f"{src}: {len(T_wc)} poses for {len(pairs)} frames")
    (out / FRAME_DATA_DIR).mkdir(parents=True, exist_ok=True)
    for old in (out / FRAME_DATA_DIR).glob("*.json"):
        old.unlink()

    first = read_rgb(src / "video_frames" / pairs[0][0])
    h, w = first.shape[:2]
    _write_calibration(out / CALIB_FILE, calib, (w, h))
    video_path = out / VIDEO_FILE
    writer = cv2.VideoWriter(str(video_path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, 2 * h))
    if not writer.isOpened():
        raise DataError(f"{video_path}: cannot open an mp4v video writer")
    T0 = T_wc[0]
    cam_calib = {"KL": calib.K1.tolist(), "KR": calib.K2.tolist(), "DL": _dist(calib.D1)[0].tolist(),
                 "DR": _dist(calib.D2)[0].tolist(), "R": calib.R.tolist(), "T": calib.T.tolist()}
    try:
        for i, (lname, rname) in enumerate(pairs):
            left = first if i == 0 else read_rgb(src / "video_frames" / lname)
            right = read_rgb(src / "video_frames" / rname)
            writer.write(cv2.cvtColor(np.vstack([left, right]), cv2.COLOR_RGB2BGR))
            if i == 0:
                cv2.imwrite(str(out / "Left_Image.png"), cv2.cvtColor(left, cv2.COLOR_RGB2BGR))
                cv2.imwrite(str(out / "Right_Image.png"), cv2.cvtColor(right, cv2.COLOR_RGB2BGR))
            camera_pose = np.linalg.inv(T_wc[i]) @ T0  # world (keyframe camera) -> camera i, mm
            data = {"camera-calibration": cam_calib, "camera-pose": camera_pose.tolist()}
            (out / FRAME_DATA_DIR / f"frame_data{i:06d}.json").write_text(json.dumps(data))
    finally:
        writer.release()

    depth_path = src / "depth" / pairs[0][0]
    if depth_path.is_file():
        depth = read_scaled_uint(depth_path, read_depth_scale(src / "synth.json"), first.shape)
        write_xyz_tiff(out / GT_DEPTH_FILE, depth_to_xyz(depth, calib.K1))
    return out


def make_scared_standin(root: str | Path, keyframes: Iterable[tuple[int, int]] = PAPER_KEYFRAMES,
                        frames: int = 30, size: tuple[int, int] = (320, 256), seed: int = 8100,
                        scenario: str = "rigid", progress: bool = False,
                        work: Optional[str | Path] = None) -> list[Path]:
    """Render synthetic keyframe sequences into ``root/dataset_<d>/keyframe_<k>`` (SCARED layout).

    Each keyframe is its own scene (seed ``seed + 10 * d + k``); ``scenario`` ``rigid`` (SCARED
    scenes are rigid). The intermediate StereoMIS-layout renderings go to ``work``
    (default ``root/_synth``). A keyframe folder already written with the same parameters
    (``standin.json``) is kept, not re-rendered.

    Returns:
        the keyframe folders, in the order of ``keyframes``.
    """
    from slam.synth.generate import generate

    root = Path(root)
    work = Path(work) if work else root / "_synth"
    folders = []
    for d, k in keyframes:
        folder = root / f"dataset_{d}" / f"keyframe_{k}"
        params = {"frames": int(frames), "size": [int(size[0]), int(size[1])], "seed": int(seed + 10 * d + k),
                  "scenario": scenario}
        marker = folder / STANDIN_FILE
        try:
            done = json.loads(marker.read_text()) == params and (folder / VIDEO_FILE).is_file()
        except (OSError, ValueError):
            done = False
        if not done:
            src = work / f"d{d}_k{k}"
            if progress:
                print(f"rendering synthetic SCARED stand-in d{d}_k{k} ({frames} frames, {size[0]}x{size[1]}, "
                      f"{scenario}) ...", flush=True)
            generate(src, scenario, frames=int(frames), size=tuple(size), seed=params["seed"])
            write_scared_keyframe(src, folder)
            marker.write_text(json.dumps(params))
        folders.append(folder)
    return folders
