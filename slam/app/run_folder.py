"""A run's output folder: which files a run writes, who owns the folder, how files are replaced.

A run owns its folder. A folder that holds an earlier run's results (``trajectory.txt`` or
``metrics.json``) is refused unless the caller passes ``overwrite`` (``slam run --overwrite``),
which removes the files a run writes before the new run writes any, so that two runs never mix
in one folder and an interrupted re-run never silently replaces a complete earlier trajectory.

Files that other programs read while a run may be stopped (``metrics.json``, which
``slam evaluate``'s resume reads, the rewritten ``trajectory.txt`` of loop closure, the map and
the plot) are written under a temporary name and renamed into place: a reader sees the old file
or the new one, never half of one. A file that cannot be written (a full disk, no permission) is
an OSError naming it, its temporary file removed; a PLY is checked for its whole body before the
rename (:func:`complete_ply`: open3d's writer does not always say it failed). The rows streamed as
frames are processed are :class:`slam.io.row_file.RowFile`'s.
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import sys
from pathlib import Path
from typing import Callable, Iterator, Optional

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
def replaced_atomically(path: Path, check: Optional[Callable[[Path], None]] = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix, so writers that choose the format by
    the extension still do); on success (and ``check(tmp)`` raising no OSError) rename it to
    ``path``, on any exception remove it. An OSError is raised again naming ``path`` (a failed
    write names no file, or the temporary one)."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        yield tmp
        if check is not None:
            check(tmp)
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        reason = err.strerror or str(err).replace(str(tmp), str(path))
        raise OSError(err.errno or errno.EIO, reason, str(path)) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


#: bytes of the PLY property types
_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
              "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def complete_ply(path: Path) -> None:
    """OSError naming ``path`` when a binary PLY of points or triangles is shorter than its header
    declares: what open3d's writer leaves on a full disk while reporting success (ENOSPC where
    the disk has no room for the rest; a list property is taken as a triangle's three indices).
    ASCII PLYs are not checked."""
    with open(path, "rb") as fh:
        header = fh.read(4096)
    end = header.find(b"end_header\n")
    if end < 0:
        full = shutil.disk_usage(Path(path).parent).free < 4096     # not a block left
        raise OSError(errno.ENOSPC if full else errno.EIO, f"{'No space left on device: ' if full else ''}"
                      f"{len(header)} bytes written, not a PLY header", str(path))
    lines = header[:end].decode("ascii", "replace").splitlines()
    if not any(line.startswith("format binary") for line in lines):
        return
    body, count = 0, 0
    for line in lines:
        words = line.split()
        if words[:1] == ["element"]:
            count = int(words[2])
        elif words[:2] == ["property", "list"]:
            body += count * (_PLY_SIZES[words[2]] + 3 * _PLY_SIZES[words[3]])
        elif words[:1] == ["property"]:
            body += count * _PLY_SIZES[words[1]]
    size, expected = os.path.getsize(path), end + len("end_header\n") + body
    if size < expected:
        full = shutil.disk_usage(Path(path).parent).free < expected - size
        raise OSError(errno.ENOSPC if full else errno.EIO, f"{'No space left on device: ' if full else ''}"
                      f"{size} of its {expected} bytes written", str(path))


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """Standard error's file descriptor pointed at /dev/null for the block: open3d's PLY writer
    (RPly) prints a line per element it fails to write (thousands on a full disk), where
    :func:`complete_ply` says it once. Python's own ``sys.stderr`` is flushed first."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def write_text_atomically(path: Path, text: str) -> None:
    """``path.write_text(text)`` through :func:`replaced_atomically`."""
    with replaced_atomically(path) as tmp:
        tmp.write_text(text)


def write_json_atomically(path: Path, data: dict) -> None:
    """``data`` as indented JSON, through :func:`replaced_atomically`. Where it cannot be written
    the file there before is removed (it no longer says what happened: metrics.json listing no
    output that failed) and the write tried once more in the space that frees."""
    text = json.dumps(data, indent=2) + "\n"
    try:
        write_text_atomically(path, text)
    except OSError:
        Path(path).unlink(missing_ok=True)
        write_text_atomically(path, text)
