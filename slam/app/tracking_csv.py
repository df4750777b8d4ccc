"""``tracking.csv``: one row per processed frame with its health figures, written as frames are
processed (each row on disk when written, so an interrupted run keeps the rows of the frames done,
and a full disk leaves whole rows: :class:`slam.io.row_file.RowFile`)."""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from slam.io.row_file import RowFile
from slam.tracking.health import FIGURES

COLUMNS = ("frame", "timestamp", "failed", "flagged", "trust", "reason", "reference", "reference_frame") + FIGURES


class TrackingCsvWriter:
    """Streams :data:`COLUMNS` rows to ``path``."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: RowFile | None = RowFile(self.path)     # each row on disk, never half of one
        self._csv = csv.writer(self._fh)
        self._csv.writerow(COLUMNS)
        self._fh.flush()

    def write(self, frame: int, timestamp: float, failed: bool, flagged: bool, trust: str, reason: str,
              reference: str, reference_frame: int | None, figures: dict) -> None:
        assert self._fh is not None, "writer closed"
        row = [frame, f"{timestamp:.6f}", int(failed), int(flagged), trust, reason, reference,
               "" if reference_frame is None else reference_frame]
        row += [_number(figures.get(name)) for name in FIGURES]
        self._csv.writerow(row)
        self._fh.flush()

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def _number(value) -> str:
    if value is None:
        return "nan"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    value = float(value)
    return "nan" if not math.isfinite(value) else f"{value:.6g}"


def read_tracking_csv(path: str | Path) -> dict[str, np.ndarray]:
    """The columns of a ``tracking.csv`` as arrays (numbers as float, ``reason`` and
    ``reference`` as str)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    out = {}
    for name in COLUMNS:
        values = [r[name] for r in rows]
        if name in ("trust", "reason", "reference"):
            out[name] = np.array(values, dtype=object)
        else:
            out[name] = np.array([float(v) if v != "" else np.nan for v in values])
    return out
