"""SCARED (MICCAI 2019 EndoVis) keyframe layout.

::

    <keyframe>/
      endoscope_calibration.yaml       OpenCV FileStorage: M1 D1 M2 D2 R T (mm), see slam.io.calibration
      data/rgb.mp4                     left view on top of the right view, 1280x1024 per view
      data/frame_data/frame_data000000.json ...   per-frame json with "camera-pose" (4x4), or
      data/frame_data.tar.gz           the same json files inside (read in place with tarfile)

The video is not rectified (``rectified: auto`` = no) and is rectified in ``data.rectify_mode``
(default ``full``: the ``pseudo`` mode, which rotates neither view, tracked worse on real SCARED
video and on raw synthetic rigs, docs/experiments.md).

Pose convention
---------------
``camera-pose`` is taken as the **world-to-camera** transform ``T_cw`` of the left camera at that
frame, translation in **mm**, where "world" is the camera frame of the keyframe (the first frame
of ``rgb.mp4``, whose structured-light point cloud ``point_cloud.obj`` is expressed in it): a point
``X_kf`` of the keyframe's point cloud has coordinates ``camera-pose @ X_kf`` in the camera at
frame i. The reader therefore reports ``T_wc = inv(camera-pose)`` (rotation orthonormalised
first; kinematics-derived rotations are not exactly orthonormal).

Evidence (public code using these files):

* ``dimitrisPs/scared_toolkit`` (scripts/generate_sequence_dataset.py, scaredtk/convertions.py)
  regenerates SCARED's per-frame ground-truth depth by ``transform_pts(point_cloud_kf, pose)``
  and projecting the result with the left intrinsics of the *current* frame, i.e. it uses
  ``camera-pose`` as ``X_ci = P_i X_kf``; the point clouds are in mm, so the translation is in mm.
  Its authors report that this reproduces the official ``scene_points`` except for small
  differences they attribute to arithmetic precision: the strongest, geometric evidence.
* A monodepth2-derived SCARED ground-truth pose export computes the motion between frames
  ``j`` and ``k`` as ``P_k @ inv(P_j)`` (world-to-camera composition), and NeRF-style SCARED
  loaders compute ``c2w = inv(camera-pose)``; a unit test of another loader checks that a
  translation of ``1000`` becomes ``-1`` m after conversion (inverse, mm -> m).
* Counter-evidence: ``aimi-lab/robust-pose-estimator`` writes ``camera-pose`` unchanged into a
  TUM/freiburg file (i.e. as ``T_wc``) with translation / 1000 (mm -> m). It agrees on mm but not
  on the direction; the geometric use above is what the dataset's own ground truth relies on.

Under this reading the world frame is the keyframe's camera, so ``camera-pose`` of the first
frame should be (close to) the identity. The direction matters through rotations (with pure
translation the two readings differ only by a sign, which trajectory alignment does not absorb
either). If a sequence evaluates clearly better with the other reading, flip
:data:`CAMERA_POSE_IS_WORLD_TO_CAMERA`.

Timestamps: a numeric ``timestamp`` key of the json files when every file has one, else
frame index / ``fps``.
"""
from __future__ import annotations

import json
import re
import tarfile
from pathlib import Path
from typing import Optional

import numpy as np

from slam.io.calibration import fit_calibration, read_scared_yaml
from slam.io.datasets.config import DataConfig
from slam.io.datasets.dataset import RawFrame, StereoDataset, match_groundtruth
from slam.io.datasets.stereomis import wants_prerectified
from slam.io.datasets.video import StackedStereoVideo
from slam.errors import DataError
from slam.io.rectification import make_rectifier

CALIB_FILE = "endoscope_calibration.yaml"
VIDEO_FILE = "data/rgb.mp4"
FRAME_DATA_DIR = "data/frame_data"
FRAME_DATA_TAR = "data/frame_data.tar.gz"

#: ``camera-pose`` is world(keyframe camera)-to-camera: the reader inverts it (see module docstring).
CAMERA_POSE_IS_WORLD_TO_CAMERA = True

_DIGITS = re.compile(r"(\d+)")


def _frame_number(name: str) -> int:
    found = _DIGITS.findall(Path(name).stem)
    return int(found[-1]) if found else -1


def _rigid(pose: np.ndarray, where: str) -> np.ndarray:
    """Validate a 4x4 pose and project its rotation onto SO(3)."""
    if pose.shape != (4, 4):
        raise DataError(f"{where}: camera-pose is {'x'.join(map(str, pose.shape))}, expected 4x4")
    if not np.all(np.isfinite(pose)):
        raise DataError(f"{where}: camera-pose has non-finite values")
    if np.abs(pose[3] - [0, 0, 0, 1]).max() > 1e-6:
        raise DataError(f"{where}: camera-pose's last row is not [0 0 0 1]")
    R = pose[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-2 or np.linalg.det(R) <= 0:
        raise DataError(f"{where}: camera-pose's rotation is not a rotation matrix")
    U, _, Vt = np.linalg.svd(R)
    out = pose.copy()
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return out


def _invert(pose: np.ndarray) -> np.ndarray:
    inv = np.eye(4)
    inv[:3, :3] = pose[:3, :3].T
    inv[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return inv


def _parse_frame_json(text: bytes | str, where: str) -> tuple[np.ndarray, Optional[float]]:
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise DataError(f"{where}: cannot parse JSON ({' '.join(str(exc).split())[:120]})") from None
    if not isinstance(data, dict) or "camera-pose" not in data:
        raise DataError(f"{where}: no 'camera-pose' key")
    try:
        pose = np.asarray(data["camera-pose"], dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{where}: camera-pose is not a numeric 4x4 matrix") from None
    pose = _rigid(pose, where)
    stamp = data.get("timestamp")
    if isinstance(stamp, bool) or not isinstance(stamp, (int, float, str)):
        stamp = None
    else:
        try:
            stamp = float(stamp)
        except ValueError:
            stamp = None
    return pose, stamp


def read_scared_poses(path: Path) -> tuple[np.ndarray, Optional[np.ndarray], str]:
    """SCARED ``camera-pose`` matrices (as in the files, sorted by frame number) from
    ``data/frame_data/*.json`` or ``data/frame_data.tar.gz``.

    Returns:
        poses ``(N, 4, 4)`` (raw ``camera-pose``), timestamps ``(N,)`` or None, and the source name.
        ``N = 0`` (with source "") when neither exists.
    """
    folder = path / FRAME_DATA_DIR
    archive = path / FRAME_DATA_TAR
    poses, stamps = [], []
    if folder.is_dir():
        files = sorted((p for p in folder.iterdir() if p.suffix.lower() == ".json"), key=lambda p: (_frame_number(p.name), p.name))
        if not files:
            raise DataError(f"{folder}: no *.json frame data")
        for f in files:
            try:
                text = f.read_bytes()
            except OSError as exc:
                raise DataError(f"{f}: cannot read ({exc.strerror})") from None
            pose, stamp = _parse_frame_json(text, str(f))
            poses.append(pose)
            stamps.append(stamp)
        source = str(folder)
    elif archive.is_file():
        try:
            with tarfile.open(archive, "r:*") as tar:
                members = [m for m in tar.getmembers() if m.isfile() and m.name.lower().endswith(".json")]
                members.sort(key=lambda m: (_frame_number(m.name), m.name))
                if not members:
                    raise DataError(f"{archive}: no *.json frame data inside")
                for m in members:
                    fh = tar.extractfile(m)
                    if fh is None:
                        raise DataError(f"{archive}:{m.name}: cannot read")
                    pose, stamp = _parse_frame_json(fh.read(), f"{archive}:{m.name}")
                    poses.append(pose)
                    stamps.append(stamp)
        except (tarfile.TarError, OSError, EOFError) as exc:
            raise DataError(f"{archive}: cannot read archive ({' '.join(str(exc).split())[:120]})") from None
        source = str(archive)
    else:
        return np.zeros((0, 4, 4)), None, ""
    times = None if any(s is None for s in stamps) else np.asarray(stamps, dtype=np.float64)
    return np.stack(poses), times, source


def scared_pose_to_T_wc(camera_pose: np.ndarray) -> np.ndarray:
    """Our ``T_wc`` (mm) of the left camera from SCARED ``camera-pose`` matrices ``(..., 4, 4)``."""
    camera_pose = np.asarray(camera_pose, dtype=np.float64)
    if not CAMERA_POSE_IS_WORLD_TO_CAMERA:
        return camera_pose.copy()
    if camera_pose.ndim == 2:
        return _invert(camera_pose)
    return np.stack([_invert(p) for p in camera_pose])


class ScaredDataset(StereoDataset):
    layout = "scared"

    @staticmethod
    def detect(path: Path) -> bool:
        # (a calibration without data/ is a frame folder's or a video's)
        return (path / VIDEO_FILE).is_file() or ((path / CALIB_FILE).is_file() and (path / "data").is_dir())

    def __init__(self, path: Path, config: DataConfig):
        path = Path(path)
        calib_path = path / CALIB_FILE
        if not calib_path.is_file():
            raise DataError(f"{calib_path}: calibration file not found (SCARED layout)")
        video_path = path / VIDEO_FILE
        if not video_path.is_file():
            raise DataError(f"{video_path}: video file not found (SCARED layout)")
        video = StackedStereoVideo(video_path)
        try:
            # SCARED files rarely name their image size: the principal point tells it
            calib = fit_calibration(read_scared_yaml(calib_path), video.view_size)
            processor = make_rectifier(calib, config.rectify_mode, (config.width, config.height),
                                       already_rectified=wants_prerectified(config, False))
            n = video.num_frames
            raw_poses, stamps, source = read_scared_poses(path)
            poses = None
            if len(raw_poses):
                stamps, raw_poses = match_groundtruth(source, stamps, raw_poses, n)
                poses = scared_pose_to_T_wc(raw_poses)
        except Exception:
            video.close()
            raise
        super().__init__(path, config, processor, n, stamps, poses)
        self.video = video

    def close(self) -> None:
        self.video.close()

    def _read(self, index: int) -> RawFrame:
        left, right = self.video.read(index)
        return RawFrame(left=left, right=right, source=f"{self.video.path} frame {index}")
