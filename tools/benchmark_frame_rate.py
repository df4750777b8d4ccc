"""Tracking at a lower frame rate: the same synthetic sequences at 25 fps and subsampled to 5 fps.

    .venv/bin/python tools/benchmark_frame_rate.py [--scenarios rigid scanning loop] [--seeds 9201 9202]
        [--frames 150] [--size 640x512] [--steps 1 5] [--modes frame2frame frame2model] [--workers 2]
        [--out runs/frame_rate] [--set KEY=VALUE ...]

Video sampled at 5 fps moves the camera five times as far between frames (at 640x512 the flow is
16 px per frame at the median and up to tens of pixels). Each sequence is rendered once at 25 fps
and tracked on every ``S``-th frame (``--frames ::S``; the frame rate, read off the timestamps,
scales the per-frame thresholds). Prints per sequence and mode the ATE-RMSE at each step, the ratio
to step 1, the median and 95th percentile of the ground-truth flow magnitude per step, and the
failed frames; writes ``frame_rate.md`` and ``frame_rate.json``.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np


def flow_px(data: Path, step: int) -> tuple[float, float]:
    """Median and 95th percentile of the rigid flow's magnitude (pixels) between frames ``step``
    apart, from the ground-truth poses and depth (every 5th pair)."""
    from slam.io.datasets import open_dataset
    from slam.io.rectification import original_to_rect_pose
    from vo.geometry import backproject, pixel_grid, project
    import torch

    ds = open_dataset(data)
    K = torch.as_tensor(ds.camera.K, dtype=torch.float64)
    poses = original_to_rect_pose(ds.gt_poses, ds.R1)
    mags = []
    for k in range(step, len(ds), 5 * step):
        depth = torch.as_tensor(ds.frame(k).gt_depth, dtype=torch.float64)[None, None]
        T = torch.as_tensor(np.linalg.inv(poses[k - step]) @ poses[k])
        pts = backproject(depth, K)
        moved = torch.einsum("ij,bjhw->bihw", T[:3, :3], pts) + T[:3, 3].view(1, 3, 1, 1)
        flow = project(moved, K) - pixel_grid(*depth.shape[-2:], dtype=torch.float64)
        ok = (depth[0, 0] > 0) & (moved[0, 2] > 0)
        mags.append(flow[0].norm(dim=0)[ok].numpy())
    m = np.concatenate(mags)
    return float(np.median(m)), float(np.percentile(m, 95))


def run_one(job: dict) -> dict:
    import torch

    torch.set_num_threads(1)
    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from slam.app.pipeline import Pipeline

    cfg = load_config(None, [f"tracking.mode={job['mode']}", "threads=1", *job["extra"]])
    dataset = open_dataset(Path(job["data"]), cfg.data).select(f"::{job['step']}")
    m = Pipeline(cfg, dataset, Path(job["out"])).run(progress=False).metrics
    return {**{k: job[k] for k in ("scenario", "seed", "mode", "step")}, "ate_rmse_mm": m["ate_rmse_mm"],
            "frames": m["frames"], "failed": len(m["failed_frames"]), "frame_rate": m["frame_rate"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=["rigid", "scanning", "loop"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[9201, 9202])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--size", default="640x512")
    ap.add_argument("--steps", nargs="+", type=int, default=[1, 5])
    ap.add_argument("--modes", nargs="+", default=["frame2frame", "frame2model"])
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--out", default="runs/frame_rate")
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args()
    from slam.app.cli import parse_size
    from slam.synth import generate

    out = Path(args.out)
    size = parse_size(args.size)
    jobs, flows = [], {}
    for sc in args.scenarios:
        for seed in args.seeds:
            data = out / "data" / f"{sc}_s{seed}_{size[0]}x{size[1]}_{args.frames}"
            if not (data / "groundtruth.txt").is_file():
                generate(data, sc, frames=args.frames, size=size, seed=seed, progress=False)
            for step in args.steps:
                flows[(sc, seed, step)] = flow_px(data, step)
                for mode in args.modes:
                    jobs.append({"scenario": sc, "seed": seed, "mode": mode, "step": step, "data": str(data),
                                 "out": str(out / "runs" / f"{sc}_s{seed}_{mode}_step{step}"), "extra": args.set})
    with ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn")) as pool:
        results = list(pool.map(run_one, jobs))
    ate = {(r["scenario"], r["seed"], r["mode"], r["step"]): r for r in results}
    base = min(args.steps)
    head = ["sequence", "mode"] + [f"step {s}: ATE mm (flow px median / p95, failed)" for s in args.steps] + \
        [f"step {s} / step {base}" for s in args.steps if s != base]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    ratios: dict = {}
    for sc in args.scenarios:
        for seed in args.seeds:
            for mode in args.modes:
                cells = [f"{sc} s{seed}", mode]
                for s in args.steps:
                    r = ate[(sc, seed, mode, s)]
                    med, p95 = flows[(sc, seed, s)]
                    cells.append(f"{r['ate_rmse_mm']:.3f} ({med:.1f} / {p95:.1f}, {r['failed']})")
                for s in args.steps:
                    if s != base:
                        q = ate[(sc, seed, mode, s)]["ate_rmse_mm"] / ate[(sc, seed, mode, base)]["ate_rmse_mm"]
                        ratios.setdefault((mode, s), []).append(q)
                        cells.append(f"{q:.2f}")
                lines.append("| " + " | ".join(cells) + " |")
    for (mode, s), qs in sorted(ratios.items()):
        mean_s = np.mean([ate[(sc, seed, mode, s)]["ate_rmse_mm"] for sc in args.scenarios for seed in args.seeds])
        mean_b = np.mean([ate[(sc, seed, mode, base)]["ate_rmse_mm"] for sc in args.scenarios for seed in args.seeds])
        lines.append(f"\n{mode}, step {s}: mean ATE {mean_s:.3f} against {mean_b:.3f} mm at step {base} "
                     f"({mean_s / mean_b:.2f}x; per sequence median {np.median(qs):.2f}x, max {max(qs):.2f}x)")
    table = "\n".join(lines)
    print(table)
    (out / "frame_rate.md").write_text(table + "\n")
    (out / "frame_rate.json").write_text(json.dumps({"results": results,
                                                    "flow_px": {f"{k[0]}_s{k[1]}_step{k[2]}": v for k, v in flows.items()}},
                                                   indent=2))


if __name__ == "__main__":
    main()
