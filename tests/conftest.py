"""Shared fixtures: small synthetic sequences made once per test session by our own generator."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")


@pytest.fixture(scope="session")
def synth_dir(tmp_path_factory):
    """``synth_dir(scenario, frames, size=(W, H), seed=0, raw=False) -> Path`` (cached per session)."""
    from slam.synth import generate

    cache: dict = {}
    root = tmp_path_factory.mktemp("synth")

    def make(scenario: str, frames: int, size=(160, 128), seed: int = 0, raw: bool = False) -> Path:
        key = (scenario, frames, tuple(size), seed, raw)
        if key not in cache:
            out = root / f"{scenario}_{frames}_{size[0]}x{size[1]}_s{seed}{'_raw' if raw else ''}"
            cache[key] = generate(out, scenario, frames=frames, size=tuple(size), seed=seed, raw=raw)
        return cache[key]

    return make


def copy_with(src_root: Path, dst_root: Path, frames, write) -> Path:
    """A copy of the synthetic sequence ``src_root`` in ``dst_root`` whose images of ``frames``
    (both sides) are written by ``write(path)``; every other file a link to the original."""
    dst_root.mkdir()
    for src in src_root.rglob("*"):
        dst = dst_root / src.relative_to(src_root)
        if src.is_dir():
            dst.mkdir(exist_ok=True)
        elif src.parent.name == "video_frames" and int(src.name[:6]) in frames:
            write(dst)
        else:
            dst.symlink_to(src)
    return dst_root
