"""Error budget: how much of the trajectory error comes from stereo depth, and how much from flow
and weighting. Runs frame2frame on synthetic evaluation sequences twice, once with stereo depth
and once with the generator's exact depth (``analysis.depth_source=groundtruth``), and prints a table.

    .venv/bin/python tools/benchmark_error_budget.py [--scenarios rigid scanning breathing deforming]
        [--frames 100] [--size 320x256] [--seeds 9001 9002] [--weights constant] [--out runs/error_budget]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks.runs import synthetic, write_report
from slam.app.runner import run_from_config
from slam.config import load_config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=["rigid", "scanning", "breathing", "deforming"])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--size", default="320x256")
    ap.add_argument("--seeds", nargs="+", type=int, default=[9001, 9002])
    ap.add_argument("--weights", default="constant", choices=["constant", "learned"])
    ap.add_argument("--out", default="runs/error_budget")
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    out = Path(args.out)
    rows = []
    for scenario in args.scenarios:
        for source in ("stereo", "groundtruth"):
            ates = []
            for seed in args.seeds:
                data = synthetic(out / "data" / f"{scenario}_s{seed}_{args.size}_{args.frames}", scenario,
                                 frames=args.frames, size=(w, h), seed=seed)
                cfg = load_config(None, [f"weights.mode={args.weights}", f"analysis.depth_source={source}",
                                         *args.set])
                res = run_from_config(data, cfg, out / "runs" / f"{scenario}_s{seed}_{source}", print_summary=False,
                                      overwrite=True)
                ates.append(res.metrics["ate_rmse_mm"])
            rows.append({"scenario": scenario, "depth": source, "ate_mean_mm": float(np.mean(ates)),
                         "ate_std_mm": float(np.std(ates)), "runs": len(ates)})
    lines = ["| scenario | depth | ATE-RMSE mm (mean ± std) |", "|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scenario']} | {r['depth']} | {r['ate_mean_mm']:.3f} ± {r['ate_std_mm']:.3f} |")
    table = "\n".join(lines)
    write_report(out, "error_budget", table, rows)


if __name__ == "__main__":
    main()
