"""Poses in TUM format, read and written in one place.

A TUM row is ``timestamp tx ty tz qx qy qz qw`` with the translation in metres and the unit
quaternion (scalar last) of the rotation; ``#`` lines are comments. Poses here are 4x4
camera-to-world matrices ``T_wc``. The rest of the project works in millimetres: the helpers
below convert at the boundary (``scale_to_mm``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from slam.errors import DataError
from slam.io.row_file import RowFile

M_TO_MM = 1000.0


def read_tum(path: str | Path, scale_to_mm: bool = True, unique_stamps: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory.

    Args:
        path: text file with rows ``timestamp tx ty tz qx qy qz qw`` (metres).
        scale_to_mm: convert translations to millimetres (the project's internal unit).
        unique_stamps: refuse a timestamp that repeats an earlier row's (a trajectory to evaluate
            has one pose per time: a repeated one is associated with the wrong pose).

    Returns:
        timestamps ``(N,)`` float64 and poses ``(N, 4, 4)`` float64 ``T_wc``.

    Raises:
        DataError: naming the file and the first bad line.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: trajectory file not found")
    stamps, rows, lines = [], [], []
    with open(path) as fh:
        for lineno, line in enumerate(fh, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.replace(",", " ").split()
            if len(parts) != 8:
                raise DataError(f"{path}:{lineno}: expected 8 values (timestamp tx ty tz qx qy qz qw), got {len(parts)}")
            try:
                values = [float(v) for v in parts]
            except ValueError:
                raise DataError(f"{path}:{lineno}: not a number in '{line}'") from None
            stamps.append(values[0])
            rows.append(values[1:])
            lines.append(lineno)
    if not rows:
        raise DataError(f"{path}: no poses in trajectory file")
    if unique_stamps:
        refuse_repeated_stamps(path, stamps, lines)
    data = np.asarray(rows, dtype=np.float64)
    if not np.all(np.isfinite(data)):
        raise DataError(f"{path}: non-finite values in trajectory file")
    quat = data[:, 3:7]
    norms = np.linalg.norm(quat, axis=1)
    if np.any(norms < 1e-9):
        raise DataError(f"{path}: zero quaternion in trajectory file")
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(quat / norms[:, None]).as_matrix()
    poses[:, :3, 3] = data[:, :3] * (M_TO_MM if scale_to_mm else 1.0)
    return np.asarray(stamps, dtype=np.float64), poses


def refuse_repeated_stamps(path: Path, stamps: list[float], lines: list[int]) -> None:
    """DataError naming ``path``, the line of the first timestamp that repeats an earlier row's and
    that row's line, and how many repeat. ``stamps`` and their ``lines`` (1-based) in file order."""
    first: dict[float, int] = {}
    repeats = []
    for stamp, line in zip(stamps, lines):
        if stamp in first:
            repeats.append((line, stamp, first[stamp]))
        else:
            first[stamp] = line
    if repeats:
        line, stamp, earlier = repeats[0]
        count = f"{len(repeats)} repeated timestamp{'s' if len(repeats) > 1 else ''}"
        raise DataError(f"{path}:{line}: timestamp {stamp:.9g} repeats line {earlier}'s ({count}; a trajectory has one "
                        "pose per time)")


def format_tum_row(timestamp: float, pose: np.ndarray, scale_from_mm: bool = True) -> str:
    """One TUM row for a 4x4 pose ``T_wc`` (translation in mm if ``scale_from_mm``)."""
    pose = np.asarray(pose, dtype=np.float64)
    t = pose[:3, 3] / (M_TO_MM if scale_from_mm else 1.0)
    q = Rotation.from_matrix(pose[:3, :3]).as_quat()  # x y z w
    if q[3] < 0:  # a canonical sign keeps files diff-able
        q = -q
    return f"{timestamp:.9f} " + " ".join(f"{v:.9f}" for v in (*t, *q))


def write_tum(path: str | Path, timestamps: np.ndarray, poses: np.ndarray, scale_from_mm: bool = True) -> None:
    """Write poses ``(N, 4, 4)`` with timestamps ``(N,)`` as a TUM file (metres)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for ts, pose in zip(timestamps, poses):
            fh.write(format_tum_row(float(ts), pose, scale_from_mm) + "\n")


class TumStreamWriter:
    """Appends TUM rows as frames are processed, each on disk when written
    (:class:`slam.io.row_file.RowFile`), so an interrupted run leaves a valid trajectory of the
    frames done, and one whose disk filled up the rows before (the OSError naming the file)."""

    def __init__(self, path: str | Path, scale_from_mm: bool = True):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._scale = scale_from_mm
        self._fh: RowFile | None = RowFile(self.path)
        self._fh.write("# timestamp tx ty tz qx qy qz qw\n")
        self.rows = 0

    def write(self, timestamp: float, pose: np.ndarray) -> None:
        assert self._fh is not None, "writer closed"
        self._fh.write(format_tum_row(float(timestamp), pose, self._scale) + "\n")
        self.rows += 1

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> "TumStreamWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
