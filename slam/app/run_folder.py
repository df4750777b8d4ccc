"""A run's output folder: which files a run writes, who owns the folder, how files are replaced.

A run owns its folder. A folder that holds an earlier run's results (``trajectory.txt`` or
``metrics.json``) is refused unless the caller passes ``overwrite`` (``slam run --overwrite``),
which removes the files a run writes before the new run writes any, so that two runs never mix
in one folder and an interrupted re-run never silently replaces a complete earlier trajectory.

Files that other programs read while a run may be stopped (``metrics.json``, which
``slam evaluate``'s resume reads, the rewritten ``trajectory.txt`` of loop closure, the map and
the plot) are written under a temporary name and renamed into place: a reader sees the old file
or the new one, never half of one.
"""
from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Iterator

from slam.errors import SlamError

#: what marks a folder as holding a run's results
RESULT_FILES = ("trajectory.txt", "metrics.json")
#: every file ``slam run`` writes into its folder (``*.rrd`` recordings are removed too)
RUN_FILES = ("trajectory.txt", "trajectory_online.txt", "metrics.json", "tracking.csv", "config.yaml",
             "trajectory.png", "map.ply", "mesh.ply", "run.log")


def check_out_dir(out: Path, overwrite: bool) -> None:
    """Raise SlamError (one line) when ``out`` cannot be this run's folder: it is a file, or it
    holds an earlier run's results and ``overwrite`` is False."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise SlamError(f"{out}: is a file, not a folder (--out names the run's folder)")
    earlier = [name for name in RESULT_FILES if (out / name).exists()]
    if earlier and not overwrite:
        raise SlamError(f"{out}: holds an earlier run ({', '.join(earlier)}); give another --out, "
                        "or --overwrite to replace it")


def clear_run_files(out: Path) -> list[str]:
    """Remove the files a run writes (and ``*.rrd``) from ``out``; returns their names."""
    out = Path(out)
    if not out.is_dir():
        return []
    removed = []
    for path in [out / name for name in RUN_FILES] + sorted(out.glob("*.rrd")):
        if path.is_file():
            path.unlink()
            removed.append(path.name)
    return removed


@contextlib.contextmanager
def replaced_atomically(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix, so writers that choose the format by
    the extension still do); on success rename it to ``path``, on any exception remove it."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomically(path: Path, text: str) -> None:
    """``path.write_text(text)`` through :func:`replaced_atomically`."""
    with replaced_atomically(path) as tmp:
        tmp.write_text(text)


def write_json_atomically(path: Path, data: dict) -> None:
    """``data`` as indented JSON, through :func:`replaced_atomically`."""
    write_text_atomically(path, json.dumps(data, indent=2) + "\n")
