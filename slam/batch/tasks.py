"""A batch's tasks: what one worker does, where it writes, and whether it is done already.

* :class:`RunTask`: one sequence (or clip) tracked in one mode with one resolved configuration,
  into its own run folder (the usual ``slam run`` files, ``run.log`` among them).
  It is done when the folder's ``metrics.json`` has no ``interrupted`` key and records the
  provenance (``slam.app.provenance``: configuration digest, package version, checkpoint digests,
  frame selection) this task would record.
* :class:`SynthTask`: one synthetic sequence rendered by ``slam.synth.generate``; done when its
  ``synth.json`` holds the same parameters and generator version.

Tasks are plain picklable data: the driver makes them, workers (local processes or Ray) run
them with :func:`slam.batch.worker.execute`.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from slam.config import SlamConfig

METRICS = "metrics.json"
MAP_ACCURACY = "map_accuracy.json"
RUN_LOG = "run.log"


def read_json(path: Path) -> Optional[dict]:
    """A JSON file's object, or None when it is missing or unreadable."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


@dataclass
class MapAccuracySpec:
    """SCARED: compare the exported map with the keyframe's ground-truth depth
    (``slam.batch.map_accuracy``). ``gt_depth``: the file's name in the sequence folder (empty:
    the first of the known names); ``png_scale_mm``: mm per unit of a uint16 depth PNG."""

    gt_depth: str = ""
    png_scale_mm: float = 0.01


@dataclass
class RunTask:
    """One run of the pipeline (see the module docstring).

    Attributes:
        data: the sequence folder (or video file).
        out_dir: the run folder.
        config: the resolved configuration (``tracking.mode``, ``threads`` set).
        frames: the frame selection (``slam run --frames``), None for all.
        sequence, mode, scenario, group, sweep: what the tables show of the row (``group``: the
            subject of StereoMIS, the dataset of SCARED; ``sweep``: the swept values, e.g.
            ``solver.max_iters=5``, empty without a sweep).
        bounds: ``(start, end)`` frame positions the protocol names; a sequence shorter than
            ``end`` is an error row instead of a shorter run.
        require_groundtruth: a sequence without ground-truth poses is an error row.
        map_accuracy: SCARED's map accuracy after the run, or None.
        cost: the estimated work (frames x pixels, frame2model counted double): longest first.
    """

    data: str
    out_dir: str
    config: SlamConfig
    frames: Optional[str] = None
    sequence: str = ""
    mode: str = ""
    scenario: str = ""
    group: str = ""
    sweep: str = ""
    bounds: Optional[tuple] = None
    require_groundtruth: bool = False
    map_accuracy: Optional[MapAccuracySpec] = None
    cost: float = 0.0

    @property
    def label(self) -> str:
        what = f"{self.sequence} {self.frames}" if self.frames else self.sequence
        return f"{self.sweep + ' ' if self.sweep else ''}{what} {self.mode}"

    def provenance(self) -> dict:
        from slam.app.provenance import provenance

        return provenance(self.config, self.frames)

    def is_done(self) -> bool:
        """Whether the run folder holds this task's finished result."""
        metrics = read_json(Path(self.out_dir) / METRICS)
        if metrics is None or metrics.get("interrupted") or metrics.get("provenance") != self.provenance():
            return False
        return self.map_accuracy is None or (Path(self.out_dir) / MAP_ACCURACY).is_file()


@dataclass
class SynthTask:
    """One synthetic sequence (``slam synth``'s parameters; ``appearance_seed``: the seed a
    ``random`` look is drawn with, None for ``seed``)."""

    out_dir: str
    scenario: str
    seed: int
    frames: int = 150
    size: tuple = (640, 512)
    raw: bool = False
    codec: str = "mp4v"
    appearance: str = ""
    breathing_follows_tissue: float = 0.0
    camera_speed: float = 1.0
    appearance_seed: Optional[int] = None
    cost: float = 0.0

    @property
    def label(self) -> str:
        return Path(self.out_dir).name

    def look(self):
        """The sequence's :class:`slam.synth.appearance.Appearance`."""
        from slam.synth.appearance import parse_appearance

        return parse_appearance(self.appearance, self.seed if self.appearance_seed is None else self.appearance_seed)

    def expected(self) -> dict:
        """The ``synth.json`` entries a finished sequence of this task holds."""
        from slam.synth.generate import VERSION

        look = self.look().as_dict()
        return {"version": VERSION, "scenario": self.scenario, "seed": int(self.seed), "frames": int(self.frames),
                "size": [int(self.size[0]), int(self.size[1])], "raw": bool(self.raw),
                "breathing_follows_tissue": float(self.breathing_follows_tissue),
                "camera_speed": float(self.camera_speed), "appearance": look}

    def is_done(self) -> bool:
        meta = read_json(Path(self.out_dir) / "synth.json")
        if meta is None or not (Path(self.out_dir) / "groundtruth.txt").is_file():
            return False
        if self.raw and meta.get("video") is None:
            return False
        return all(meta.get(k) == v for k, v in self.expected().items())
