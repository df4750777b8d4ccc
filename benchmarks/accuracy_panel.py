"""What the accuracy gate runs: its panel of cases, the sequences they track, the real SCARED
sequence and its reference, and the copies of each sequence in a moved world frame.

The perturbation: run ``k`` of a case tracks a copy of its sequence whose ``groundtruth.txt``
(which anchors the first pose, and so the world frame of the map and the poses) is moved rigidly by
``T_k`` (``T_0`` the identity). Every commit honours it and no input changes; SE(3)-aligned figures
are blind to the move itself, but the map lives in the moved frame, so the rounding of every sum
over it changes, and frame2model, which feeds its map back into its poses, shows how far its result
moves under rounding alone. The real sequence has no ground truth of its own: its copies carry the
COLMAP reference, moved.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "benchmarks" / "reference"
REAL_TRAJECTORY = REFERENCE / "scared9_colmap_tum.txt"
REAL_POINTS = REFERENCE / "scared9_colmap_points.ply"
REAL_ENV = "ENDOSLAM_REAL"
REAL_DEFAULT = Path("~/.cache/endoslam-real/scared_640")
REAL_HOWTO = ("it is SCARED dataset_9's keyframe at 640x512 (191 stereo pairs, 5 fps), the folder scared_640/ of the "
              "public repository FelTris/camp2_3drecon: `git clone --depth 1 https://github.com/FelTris/camp2_3drecon "
              "/tmp/camp2 && mkdir -p ~/.cache/endoslam-real && cp -r /tmp/camp2/scared_640 ~/.cache/endoslam-real/`, "
              f"or give its folder with --real DIR or {REAL_ENV}=DIR (SCARED's terms: its images never enter this "
              "repository)")

#: the gate's own seeds, apart from every seed used to choose a setting (docs/benchmarks.md)
SEEDS = (9701, 9702)
LOOKS = {"default": "", "weak": "texture=0,highlights=1,haze=0.3", "random": "random"}
SCENARIOS = ("rigid", "scanning", "breathing", "deforming")
MODES = {"f2f": "frame2frame", "f2m": "frame2model"}
GENERATOR_FRAMES = 80
LOOP_FRAMES = 300


@dataclass(frozen=True)
class Sequence:
    """A sequence of the panel: the real one (``scenario`` empty) or one the working tree renders."""

    name: str
    scenario: str = ""
    frames: int = 0
    size: tuple = (640, 512)
    seed: int = 0
    appearance: str = ""
    raw: bool = False

    @property
    def real(self) -> bool:
        return not self.scenario


@dataclass(frozen=True)
class Case:
    """One row of the gate: a sequence tracked in one mode with ``options`` (``slam run``'s)."""

    name: str
    sequence: Sequence
    mode: str
    options: tuple = ()
    quick: bool = False

    @property
    def map_error(self) -> bool:
        """Whether the map is measured (the real sequence's reference points, frame2model)."""
        return self.sequence.real and self.mode == "frame2model"


REAL = Sequence("real")


def panel() -> list[Case]:
    """Every case of the full panel; those with ``quick`` make ``--quick``'s."""
    real_5fps = ("--set", "data.fps=5")
    real_2_5fps = ("--frames", "::2", "--set", "data.fps=5")     # timestamps stay the reference's: 2.5 fps
    cases = [
        Case("real-f2m", REAL, "frame2model", real_5fps, quick=True),
        Case("real-f2f", REAL, "frame2frame", real_5fps, quick=True),
        Case("real-2.5fps-f2m", REAL, "frame2model", real_2_5fps, quick=True),
        Case("real-2.5fps-f2f", REAL, "frame2frame", real_2_5fps),
    ]
    for look, spec in LOOKS.items():
        for scenario in SCENARIOS:
            for seed in SEEDS:
                seq = Sequence(f"{scenario}-{look}-s{seed}", scenario, GENERATOR_FRAMES, (640, 512), seed, spec)
                for short, mode in MODES.items():
                    quick = look == "weak" and scenario == "rigid" and seed == SEEDS[0]
                    cases.append(Case(f"{seq.name}-{short}", seq, mode, quick=quick))
    for seed in SEEDS:
        seq = Sequence(f"loop-s{seed}-320", "loop", LOOP_FRAMES, (320, 256), seed)
        cases.append(Case(f"{seq.name}-f2m", seq, "frame2model"))
    raw = Sequence(f"raw-rigid-weak-s{SEEDS[0]}", "rigid", GENERATOR_FRAMES, (640, 512), SEEDS[0], LOOKS["weak"], raw=True)
    cases += [Case(f"{raw.name}-f2f-constant", raw, "frame2frame", ("--weights", "constant")),
              Case(f"{raw.name}-f2m", raw, "frame2model")]
    return cases


def real_folder(given: str | None) -> Path:
    """The real sequence's folder: ``given``, else ``$ENDOSLAM_REAL``, else the default cache.
    Raises SystemExit with how to get it where it is missing."""
    folder = Path(given or os.environ.get(REAL_ENV) or REAL_DEFAULT).expanduser()
    if not ((folder / "left_image").is_dir() and (folder / "right_image").is_dir()):
        raise SystemExit(f"check_accuracy: error: the real sequence is not at {folder} (no left_image/ and right_image/): "
                         f"{REAL_HOWTO}")
    return folder


def world_move(k: int) -> np.ndarray:
    """``(4, 4)`` ``T_k`` (mm): the identity for ``k = 0``, else a rigid move of 10-30 degrees about
    a random axis and 10-40 mm, fixed by ``k``."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    if k == 0:
        return T
    rng = np.random.default_rng(1000 + k)
    axis = rng.normal(size=3)
    T[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(10, 30))).as_matrix()
    direction = rng.normal(size=3)
    T[:3, 3] = direction / np.linalg.norm(direction) * rng.uniform(10, 40)
    return T


def render(seq: Sequence, folder: Path) -> Path:
    """The sequence's original folder: the real one as given, a synthetic one rendered once by
    the working tree into ``folder``."""
    from benchmarks.runs import synthetic
    from slam.synth.appearance import parse_appearance

    return synthetic(folder, seq.scenario, frames=seq.frames, size=seq.size, seed=seq.seed, raw=seq.raw,
                     appearance=parse_appearance(seq.appearance or None, seq.seed), progress=False)


def moved_copy(original: Path, truth: Path, k: int, out: Path) -> Path:
    """A copy of the sequence ``original`` in ``out`` whose ``groundtruth.txt`` is ``truth`` (TUM)
    moved by :func:`world_move` ``(k)``; every other entry is a link to the original's."""
    from slam.io.tum import read_tum, write_tum

    done = out / "groundtruth.txt"
    if done.is_file():
        return out
    out.mkdir(parents=True, exist_ok=True)
    for entry in original.iterdir():
        if entry.name != "groundtruth.txt" and not (out / entry.name).exists():
            (out / entry.name).symlink_to(entry.resolve())
    stamps, poses = read_tum(truth)
    tmp = out / "groundtruth.txt.tmp"
    write_tum(tmp, stamps, world_move(k) @ poses)
    tmp.rename(done)                                  # last: the copy is complete
    return out
