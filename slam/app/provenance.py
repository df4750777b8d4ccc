"""What a run's results depend on, recorded in its ``metrics.json`` (``provenance``).

A run's trajectory follows from its resolved configuration, the code, the weight-network (and
RAFT) checkpoint files it loads and the frames it selects. ``provenance(config, frames)`` names
each of them by a digest, so that a later run can tell whether a finished run folder still holds
the result it would compute (``slam evaluate`` re-runs only the tasks whose provenance differs):

* ``config_sha256``: SHA-256 of the resolved configuration as YAML (every value, the fixed ones
  and the analysis switches included);
* ``version``: the package's version, and in a git checkout its commit, with a digest of the
  uncommitted changes to the code (``vo/``, ``mapping/``, ``slam/``) when there are any;
* ``checkpoints``: SHA-256 of each checkpoint file tracking loads (none with constant weights);
* ``frames``: the frame selection as given (``slam run --frames``; ``all`` for every frame).
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import subprocess
from importlib import metadata
from pathlib import Path

import yaml

from slam.config import SlamConfig

REPO = Path(__file__).resolve().parents[2]
CODE_DIRS = ("vo", "mapping", "slam")


def config_digest(config: SlamConfig) -> str:
    """SHA-256 of the resolved configuration."""
    return hashlib.sha256(yaml.safe_dump(dataclasses.asdict(config), sort_keys=True).encode()).hexdigest()


@functools.lru_cache(maxsize=None)
def package_version() -> str:
    """``endoslam``'s version; in a git checkout ``VERSION+gCOMMIT`` and ``.dirty-DIGEST`` when the
    code differs from that commit (the digest of the diff, so the same edits give the same
    version)."""
    try:
        version = metadata.version("endoslam")
    except metadata.PackageNotFoundError:
        version = "unknown"
    if not (REPO / ".git").exists():
        return version
    try:
        commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short=12", "HEAD"], capture_output=True,
                                text=True, timeout=10, check=True).stdout.strip()
        diff = subprocess.run(["git", "-C", str(REPO), "diff", "HEAD", "--", *CODE_DIRS], capture_output=True,
                              timeout=30, check=True).stdout
        untracked = subprocess.run(["git", "-C", str(REPO), "ls-files", "--others", "--exclude-standard", "--",
                                    *(f"{d}/*.py" for d in CODE_DIRS)], capture_output=True, timeout=30,
                                   check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return version
    version += f"+g{commit}"
    if diff or untracked:
        h = hashlib.sha256(diff)
        for name in sorted(untracked.decode().split()):
            h.update(name.encode())
            h.update((REPO / name).read_bytes())
        version += f".dirty-{h.hexdigest()[:12]}"
    return version


@functools.lru_cache(maxsize=64)
def _file_digest(path: str, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file's bytes (``missing`` when there is no such file)."""
    path = Path(path)
    try:
        st = path.stat()
    except OSError:
        return "missing"
    return _file_digest(str(path.resolve()), st.st_size, st.st_mtime_ns)


def checkpoint_files(config: SlamConfig) -> dict[str, Path]:
    """The checkpoint files a run with ``config`` loads, by role."""
    from vo.weights import tracking_checkpoint_paths

    files: dict[str, Path] = {}
    if config.weights.mode == "learned":
        roles = tracking_checkpoint_paths(config.weights.checkpoint, config.weights.checkpoint_model,
                                          config.weights.residuals, config.depth.temporal_gain,
                                          config.depth.temporal_still_mm)
        files.update({f"weights_{role}": path for role, path in roles.items()})
    if config.correspondence.backend == "raft":
        files["raft"] = Path(config.correspondence.raft_checkpoint)
    return files


def provenance(config: SlamConfig, frames: str | int | None = None) -> dict:
    """The provenance record of a run (see the module docstring)."""
    return {
        "config_sha256": config_digest(config),
        "version": package_version(),
        "checkpoints": {role: f"{Path(path).name}:{file_digest(path)}"
                        for role, path in sorted(checkpoint_files(config).items())},
        "frames": "all" if frames in (None, "") else str(frames),
    }
