"""The paper's SCARED protocol (Table 3) and the map's accuracy: ``slam evaluate --protocol
scared``, and a synthetic stand-in to try it without the data.

    .venv/bin/python tools/evaluate_scared.py SCARED_ROOT [slam evaluate options]
    .venv/bin/python tools/evaluate_scared.py --synthetic DIR [--synthetic-frames 30]
        [--synthetic-size 320x256] [--datasets 1 8 9] [slam evaluate options]

The first form is ``slam evaluate SCARED_ROOT --protocol scared ...`` (``--datasets``,
``--keyframes``, ``--frames``, ``--gt-depth``, ``--no-map``, ``--modes``, ``--config``, ``--set``,
``--out``, ``--address``, ...: see ``slam evaluate --help`` and docs/evaluation.md).
``--synthetic DIR`` first writes rigid synthetic scenes in the SCARED keyframe layout, with
``left_depth_map.tiff``, for the paper's keyframes of ``--datasets``
(``slam.synth.scared_layout.make_scared_standin``), then evaluates them at native size
(``data.width=0``, ``data.height=0`` before your ``--set``) into ``DIR/results`` unless ``--out``
is given.
"""
from __future__ import annotations

import sys
from pathlib import Path

from slam.batch.protocols import PAPER_KEYFRAMES, SCARED_DATASETS
from slam.app.cli import OneLineParser, main as slam_main, parse_size
from slam.errors import SlamError


def main(argv: list[str] | None = None) -> int:
    ap = OneLineParser(prog="evaluate_scared.py", add_help=False)
    ap.add_argument("--synthetic", metavar="DIR")
    ap.add_argument("--synthetic-frames", type=int, default=30)
    ap.add_argument("--synthetic-size", default="320x256")
    ap.add_argument("--datasets", nargs="+", type=int, default=list(SCARED_DATASETS))
    args, rest = ap.parse_known_args(argv)
    if {"-h", "--help"} & set(rest):
        print(__doc__)
        return 0
    head = ["--datasets", *map(str, args.datasets)]
    if args.synthetic:
        from slam.synth.scared_layout import make_scared_standin

        folder = Path(args.synthetic)
        keyframes = [(int(n[1:].split("_")[0]), int(n.split("_k")[1])) for n in PAPER_KEYFRAMES]
        keyframes = [(d, k) for d, k in keyframes if d in args.datasets]
        if not keyframes or args.synthetic_frames < 2:
            print(f"{ap.prog}: error: --synthetic needs one of the paper's datasets (1 8 9) and at least 2 frames",
                  file=sys.stderr)
            return 2
        try:
            make_scared_standin(folder, keyframes, frames=args.synthetic_frames, size=parse_size(args.synthetic_size),
                                progress=True)
        except SlamError as err:
            print(f"{ap.prog}: error: {err}", file=sys.stderr)
            return 2
        head = [str(folder), *head, *([] if "--out" in rest else ["--out", str(folder / "results")]),
                "--set", "data.width=0", "--set", "data.height=0"]
    return slam_main(["evaluate", *head, "--protocol", "scared", *rest])


if __name__ == "__main__":
    sys.exit(main())
