"""What reading a stereo video costs against rendered rectified frames, and why: compression, the
rectification of a raw rig, or the rectification mode.

    .venv/bin/python tools/benchmark_video_input.py [--scenarios rigid scanning] [--seeds 9301 9302]
        [--frames 150] [--size 320x256] [--modes frame2frame frame2model] [--workers 2]
        [--out runs/video_input] [--set KEY=VALUE ...]

Each sequence is rendered three ways from the same scene and camera path: rectified PNGs (the
StereoMIS layout), and a raw rig (lens distortion, a right camera rotated by 0.5-2 deg) written
lossless (FFV1) and as an mp4 (mp4v, as recorders write). The raw ones are tracked with
``data.rectify_mode`` full and pseudo. The table gives the ATE-RMSE of each; compression is the step
lossless -> mp4, the rectification the step PNG -> lossless full, the mode full -> pseudo.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

VARIANTS = {
    "rectified PNG": ("png", []),
    "raw lossless, full": ("ffv1", ["data.rectify_mode=full"]),
    "raw mp4, full": ("mp4v", ["data.rectify_mode=full"]),
    "raw lossless, pseudo": ("ffv1", ["data.rectify_mode=pseudo"]),
    "raw mp4, pseudo": ("mp4v", ["data.rectify_mode=pseudo"]),
}


def run_one(job: dict) -> dict:
    import torch

    torch.set_num_threads(1)
    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from slam.app.pipeline import Pipeline

    cfg = load_config(None, [f"tracking.mode={job['mode']}", "threads=1", *job["extra"]])
    m = Pipeline(cfg, open_dataset(Path(job["data"]), cfg.data), Path(job["out"])).run(progress=False).metrics
    return {**{k: job[k] for k in ("scenario", "seed", "mode", "variant")}, "ate_rmse_mm": m["ate_rmse_mm"],
            "failed": len(m["failed_frames"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=["rigid", "scanning"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[9301, 9302])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--size", default="320x256")
    ap.add_argument("--modes", nargs="+", default=["frame2frame", "frame2model"])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--out", default="runs/video_input")
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args()
    from benchmarks.runs import synthetic
    from slam.app.cli import parse_size

    out = Path(args.out)
    size = parse_size(args.size)
    jobs = []
    for sc in args.scenarios:
        for seed in args.seeds:
            for variant in args.variants:
                kind, extra = VARIANTS[variant]
                data = out / "data" / f"{sc}_s{seed}_{size[0]}x{size[1]}_{args.frames}_{kind}"
                synthetic(data, sc, frames=args.frames, size=size, seed=seed, raw=kind != "png",
                          codec=kind if kind != "png" else "mp4v", progress=False)
                for mode in args.modes:
                    jobs.append({"scenario": sc, "seed": seed, "mode": mode, "variant": variant, "data": str(data),
                                 "out": str(out / "runs" / f"{sc}_s{seed}_{mode}_{variant.replace(' ', '').replace(',', '_')}"),
                                 "extra": [*extra, *args.set]})
    with ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn")) as pool:
        results = list(pool.map(run_one, jobs))
    ate = {(r["scenario"], r["seed"], r["mode"], r["variant"]): r for r in results}
    head = ["sequence", "mode", *args.variants]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for mode in args.modes:
        for sc in args.scenarios:
            for seed in args.seeds:
                cells = [f"{sc} s{seed}", mode]
                for v in args.variants:
                    r = ate[(sc, seed, mode, v)]
                    cells.append(f"{r['ate_rmse_mm']:.3f}" + (f" ({r['failed']} failed)" if r["failed"] else ""))
                lines.append("| " + " | ".join(cells) + " |")
        means = [np.mean([ate[(sc, seed, mode, v)]["ate_rmse_mm"] for sc in args.scenarios for seed in args.seeds])
                 for v in args.variants]
        lines.append("| mean | " + mode + " | " + " | ".join(f"{m:.3f}" for m in means) + " |")
    table = "\n".join(lines)
    print(table)
    (out / "video_input.md").write_text(table + "\n")
    (out / "video_input.json").write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
