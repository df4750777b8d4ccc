"""The paper's StereoMIS protocol (Tables 1 and 2): ``slam evaluate --protocol stereomis``, and a
synthetic stand-in to try it without the data.

    .venv/bin/python tools/evaluate_stereomis.py STEREOMIS_ROOT [slam evaluate options]
    .venv/bin/python tools/evaluate_stereomis.py --synthetic DIR [--synthetic-frames 24]
        [--synthetic-size 320x256] [slam evaluate options]

The first form is ``slam evaluate STEREOMIS_ROOT --protocol stereomis ...`` (``--csv``, ``--split``,
``--modes``, ``--config``, ``--set``, ``--sweep``, ``--out``, ``--address``, ...: see
``slam evaluate --help`` and docs/evaluation.md). ``--synthetic DIR`` first writes a stand-in with
``slam.synth.generate`` in the StereoMIS pre-processed layout: ``DIR/P2_0`` (scanning),
``DIR/P2_1`` (breathing), ``DIR/P3_0`` (deforming) and ``DIR/protocol.csv`` (two clips and one
``full`` row per sequence); it then evaluates it at native size (``data.width=0``,
``data.height=0`` before your ``--set``) into ``DIR/results`` unless ``--out`` is given. Sequences
already generated are reused. A check that the protocol runs end to end, not a result.
"""
from __future__ import annotations

import sys
from pathlib import Path

from slam.batch.protocols import STEREOMIS_COLUMNS
from slam.batch.tasks import SynthTask
from slam.app.cli import OneLineParser, main as slam_main, parse_size
from slam.errors import ConfigError, SlamError

# seeds disjoint from training (1000+), the baseline comparison (7001+) and the scenario benchmark (9001+)
SYNTHETIC_SEQUENCES = (("P2_0", "scanning", 8201), ("P2_1", "breathing", 8202), ("P3_0", "deforming", 8203))


def make_synthetic(folder: Path, frames: int, size: tuple[int, int]) -> Path:
    """Generate (or reuse) the stand-in sequences in ``folder``; write and return ``folder/protocol.csv``."""
    from slam.synth import generate

    if frames < 4:
        raise ConfigError(f"--synthetic-frames {frames}: need at least 4 (two clips of 2 frames)")
    folder.mkdir(parents=True, exist_ok=True)
    half = frames // 2
    lines = ["# Synthetic stand-in for the StereoMIS protocol (tools/evaluate_stereomis.py --synthetic).",
             "# Each sequence holds one generator scenario; two clips per sequence + the full sequence.",
             ",".join(STEREOMIS_COLUMNS)]
    for name, scenario, seed in SYNTHETIC_SEQUENCES:
        task = SynthTask(out_dir=str(folder / name), scenario=scenario, seed=seed, frames=frames, size=size)
        if not task.is_done():
            print(f"generating synthetic {name} ({scenario}, {frames} frames, {size[0]}x{size[1]}) ...", flush=True)
            generate(task.out_dir, scenario, frames=frames, size=size, seed=seed)
        lines += [f"{name},0,{half},{scenario},test", f"{name},{half},{frames},{scenario},test", f"{name},,,full,test"]
    (folder / "protocol.csv").write_text("\n".join(lines) + "\n")
    return folder / "protocol.csv"


def main(argv: list[str] | None = None) -> int:
    ap = OneLineParser(prog="evaluate_stereomis.py", add_help=False)
    ap.add_argument("--synthetic", metavar="DIR")
    ap.add_argument("--synthetic-frames", type=int, default=24)
    ap.add_argument("--synthetic-size", default="320x256")
    args, rest = ap.parse_known_args(argv)
    if {"-h", "--help"} & set(rest):
        print(__doc__)
        return 0
    head = []
    if args.synthetic:
        folder = Path(args.synthetic)
        try:
            csv_path = make_synthetic(folder, args.synthetic_frames, parse_size(args.synthetic_size))
        except SlamError as err:
            print(f"{ap.prog}: error: {err}", file=sys.stderr)
            return 2
        head = [str(folder), *([] if "--csv" in rest else ["--csv", str(csv_path)]),
                *([] if "--out" in rest else ["--out", str(folder / "results")]),
                "--set", "data.width=0", "--set", "data.height=0"]
    return slam_main(["evaluate", *head, "--protocol", "stereomis", *rest])


if __name__ == "__main__":
    sys.exit(main())
