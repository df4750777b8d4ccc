"""Which sequences an evaluation runs, by protocol (``slam evaluate --protocol``).

* ``folder``: every sub-folder of ROOT that holds a sequence in a layout the readers know (or
  ROOT itself when it is one); the scenario is the one ``slam synth`` wrote in ``synth.json``.
  ``--frames`` selects the frames of every sequence.
* ``stereomis``: the paper's StereoMIS protocol (Tables 1 and 2): a CSV of clips and whole
  sequences, one folder per sequence under ROOT (pre-processed or raw layout), ground truth
  required. The CSV (``--csv``; default ``configs/stereomis_protocol.csv``, a TEMPLATE to replace
  with the official clip list of the paper's supplementary material) has the columns
  ``sequence,start,end,scenario,split``; ``#`` lines are comments. ``start``, ``end``: 0-based
  frame positions, ``end`` exclusive, empty = first / last frame; ``scenario``: ``breathing`` |
  ``scanning`` | ``deforming`` (150-frame clips, Table 1) or ``full`` (a whole test sequence,
  Table 2); rows of another ``split`` than ``--split`` are skipped. A structurally bad CSV stops
  before any run with a one-line error naming the line; a row whose data fails (missing
  sequence, a range beyond it, no ground truth) is an error row.
* ``scared``: the paper's SCARED protocol (Table 3): ``ROOT/dataset_<d>/keyframe_<k>/`` (also
  ``dataset<d>/keyframe<k>`` or flat ``ROOT/d<d>_k<k>/``) for the test datasets (default 1 8 9;
  d4 and d5 are excluded for bad calibrations, d2 d3 d6 d7 are training data), each in the SCARED
  keyframe layout; with ground-truth depth in the keyframe folder, the exported map's accuracy
  (``slam.batch.map_accuracy``). A missing dataset or keyframe is an error row.
"""
from __future__ import annotations

import csv
import io
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from slam.errors import ConfigError, DataError

REPO = Path(__file__).resolve().parents[2]
CONFIGS = REPO / "configs"
PROTOCOLS = ("folder", "stereomis", "scared")
MODES = ("frame2frame", "frame2model")
CLIP_SCENARIOS = ("breathing", "scanning", "deforming")
STEREOMIS_SCENARIOS = (*CLIP_SCENARIOS, "full")
STEREOMIS_COLUMNS = ("sequence", "start", "end", "scenario", "split")
SCARED_DATASETS = (1, 8, 9)
PAPER_KEYFRAMES = ("d1_k2", "d8_k1", "d9_k1", "d9_k3")   # the paper's Table 3 columns
_KEYFRAME_DIR = re.compile(r"^keyframe_?(\d+)$", re.IGNORECASE)


@dataclass
class Entry:
    """One sequence (or clip) an evaluation runs in every mode.

    Attributes:
        name: its run folder's name under ``OUT/runs``.
        sequence: the name the tables show.
        path: the sequence folder; None when it could not be found (``error`` says why).
        frames: the frame selection (``slam run --frames``), None for all.
        scenario, group: the tables' scenario and group (StereoMIS subject, SCARED dataset).
        bounds: ``(start, end)`` the protocol names (an error row when the sequence is shorter).
        error: a one-line error: the entry becomes an error row without a run.
    """

    name: str
    sequence: str
    path: Optional[Path]
    frames: Optional[str] = None
    scenario: str = ""
    group: str = ""
    bounds: Optional[tuple] = None
    error: str = ""


# ------------------------------------------------------------------------------------------------
# folder
def folder_entries(root: Path, frames: Optional[str], exclude: tuple = ()) -> tuple[list[Entry], list[str]]:
    """The sequences of a folder (see the module docstring) and notes on sub-folders skipped."""
    from slam.io.datasets import detect_layout

    if not root.is_dir():
        raise DataError(f"{root}: no such folder")
    excluded = {Path(p).resolve() for p in exclude}
    try:
        detect_layout(root)
        candidates = [root]
    except DataError:
        candidates = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith((".", "_"))
                            and p.resolve() not in excluded)
    entries, notes = [], []
    for path in candidates:
        try:
            detect_layout(path)
        except DataError:
            notes.append(f"{path.name}: not a sequence (no known layout), skipped")
            continue
        meta = {}
        try:
            meta = json.loads((path / "synth.json").read_text())
        except (OSError, ValueError):
            pass
        scenario = str(meta.get("scenario", "")) if isinstance(meta, dict) else ""
        entries.append(Entry(name=path.name, sequence=path.name, path=path, frames=frames, scenario=scenario))
    if not entries:
        raise DataError(f"{root}: no sequence folders found (sub-folders in a layout of docs/inputs.md)")
    return entries, notes


# ------------------------------------------------------------------------------------------------
# StereoMIS
def read_stereomis_csv(path: Path) -> list[dict]:
    """Rows of a StereoMIS protocol CSV (see the module docstring); ConfigError naming ``file:line``."""
    if not path.is_file():
        raise ConfigError(f"{path}: protocol CSV not found")
    lines = path.read_text().splitlines()
    body = [(i + 1, line) for i, line in enumerate(lines) if line.strip() and not line.lstrip().startswith("#")]
    if not body:
        raise ConfigError(f"{path}: no header line ({','.join(STEREOMIS_COLUMNS)})")
    header_no, header = body[0]
    names = [c.strip().lower() for c in next(csv.reader([header]))]
    missing = [c for c in STEREOMIS_COLUMNS if c not in names]
    if missing:
        raise ConfigError(f"{path}:{header_no}: header lacks column(s) {', '.join(missing)} "
                          f"(expected {','.join(STEREOMIS_COLUMNS)})")
    rows = []
    for lineno, line in body[1:]:
        values = [v.strip() for v in next(csv.reader(io.StringIO(line)))]
        if len(values) != len(names):
            raise ConfigError(f"{path}:{lineno}: {len(values)} values, the header has {len(names)}")
        rec = dict(zip(names, values))
        where = f"{path}:{lineno}"
        if not rec["sequence"]:
            raise ConfigError(f"{where}: empty sequence name")
        bounds = {}
        for key in ("start", "end"):
            text = rec[key]
            if text == "":
                bounds[key] = None
                continue
            try:
                bounds[key] = int(text)
            except ValueError:
                raise ConfigError(f"{where}: {key} '{text}' is not an integer frame number") from None
            if bounds[key] < 0:
                raise ConfigError(f"{where}: {key} {bounds[key]} is negative")
        if bounds["start"] is not None and bounds["end"] is not None and bounds["end"] <= bounds["start"]:
            raise ConfigError(f"{where}: end {bounds['end']} <= start {bounds['start']}")
        scenario = rec["scenario"].lower()
        if scenario not in STEREOMIS_SCENARIOS:
            raise ConfigError(f"{where}: scenario '{rec['scenario']}' is not one of {', '.join(STEREOMIS_SCENARIOS)}")
        rows.append({"sequence": rec["sequence"], "start": bounds["start"], "end": bounds["end"],
                     "scenario": scenario, "split": rec["split"].lower() or "test", "line": lineno})
    if not rows:
        raise ConfigError(f"{path}: no rows after the header")
    return rows


def subject_of(sequence: str) -> str:
    """The StereoMIS subject of a sequence name (``P2_7`` -> ``P2``)."""
    return sequence.split("_")[0]


def stereomis_entries(root: Path, csv_path: Path, split: str) -> tuple[list[Entry], list[str]]:
    """The CSV's rows of ``split`` as entries, and notes (skipped rows, the template warning)."""
    if not root.is_dir():
        raise DataError(f"{root}: no such folder (the StereoMIS root)")
    rows = read_stereomis_csv(csv_path)
    todo = [r for r in rows if r["split"] == split.lower()]
    if not todo:
        raise ConfigError(f"{csv_path}: no rows of split '{split}'")
    notes = []
    if csv_path.resolve() == (CONFIGS / "stereomis_protocol.csv").resolve():
        notes.append("configs/stereomis_protocol.csv is a TEMPLATE, not the paper's clip list: "
                     "replace it with the official split (paper, supplementary material).")
    if len(rows) > len(todo):
        notes.append(f"{len(rows) - len(todo)} CSV row(s) of other splits skipped.")
    entries = []
    seen: dict[str, int] = {}
    for r in todo:
        s = "start" if r["start"] is None else str(r["start"])
        e = "end" if r["end"] is None else str(r["end"])
        name = f"{r['sequence']}_{s}-{e}_{r['scenario']}"
        if name in seen:
            raise ConfigError(f"{csv_path}:{r['line']}: the same clip as line {seen[name]} "
                              f"({r['sequence']} {s}-{e} {r['scenario']})")
        seen[name] = r["line"]
        whole = r["start"] is None and r["end"] is None
        frames = None if whole else f"{'' if r['start'] is None else r['start']}:{'' if r['end'] is None else r['end']}"
        path = root / r["sequence"]
        entries.append(Entry(name=name, sequence=r["sequence"], path=path,
                             frames=frames, scenario=r["scenario"], group=subject_of(r["sequence"]),
                             bounds=None if whole else (r["start"], r["end"]),
                             error="" if path.is_dir() or path.is_file() else f"{path}: no such folder"))
    return entries, notes


# ------------------------------------------------------------------------------------------------
# SCARED
def scared_entries(root: Path, datasets, wanted: Optional[list[str]], frames: Optional[str]) -> list[Entry]:
    """One entry per keyframe of ``datasets`` (``wanted``: only these ``dD_kK`` names); a missing
    dataset or keyframe is an entry with its error."""
    if not root.is_dir():
        raise DataError(f"{root}: no such folder (the SCARED root)")
    if wanted:
        bad = [k for k in wanted if not re.fullmatch(r"d\d+_k\d+", k)]
        if bad:
            raise ConfigError(f"--keyframes {' '.join(bad)}: expected names like d1_k2")
    entries: list[Entry] = []
    for d in datasets:
        folders: dict[int, Path] = {}
        dataset_dir = next((p for p in (root / f"dataset_{d}", root / f"dataset{d}", root / f"d{d}") if p.is_dir()), None)
        if dataset_dir is not None:
            for child in dataset_dir.iterdir():
                m = _KEYFRAME_DIR.match(child.name)
                if m and child.is_dir():
                    folders.setdefault(int(m.group(1)), child)
        flat = re.compile(rf"^d{d}_k(\d+)$", re.IGNORECASE)
        for child in root.iterdir():
            m = flat.match(child.name)
            if m and child.is_dir():
                folders.setdefault(int(m.group(1)), child)
        names = {f"d{d}_k{k}": folders[k] for k in sorted(folders)}
        if wanted is not None:
            for name in wanted:
                if name.startswith(f"d{d}_") and name not in names:
                    entries.append(Entry(name, name, None, group=f"d{d}", error=f"{root}: keyframe {name} not found "
                                         f"(looked for dataset_{d}/keyframe_* and d{d}_k*)"))
            names = {n: p for n, p in names.items() if n in wanted}
            if not names:
                continue
        if not names:
            where = f"dataset_{d}/keyframe_*" if dataset_dir is None else f"{dataset_dir.name}/keyframe_*"
            entries.append(Entry(f"d{d}", f"d{d}", None, group=f"d{d}",
                                 error=f"{root}: no {where} (or d{d}_k*) folders"))
        entries += [Entry(n, n, p, frames=frames, group=f"d{d}") for n, p in names.items()]
    return entries
