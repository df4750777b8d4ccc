"""The map where a loop closes: frame2model's exported map with and without loop closure against
the true surface.

    .venv/bin/python tools/benchmark_loop_map.py [--seeds 8001 8002] [--frames 300] [--size 320x256]
        [--methods rendered loop_closure] [--workers 2] [--out runs/loop_map] [--set KEY=VALUE ...]

Each seed's ``loop`` sequence (the camera returns to its start at the last frame) is run by each
method (``benchmark_frame2model.py``'s: ``rendered`` is frame2model with
``graph.loop_closure=false``, ``loop_closure`` with it on; one torch thread per worker). The
exported ``map.ply`` (stable surfels) is projected into the ground-truth frames 0, N/4, N/2, 3N/4
and N-1 (``slam.evaluation.map_error``). Printed and written as markdown and JSON, per run: the ATE, the
stable surfels, the median distance to the true surface over every point a check frame sees, and
in the overlap (the points both the first and the last frame see, where the loop closes) the
median distance and the share of points more than 2 mm off the true surface: a doubled surface
(the old tissue and the same tissue fused again at a drifted pose) shows there.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from benchmarks.benchmark_frame2model import METHODS
from benchmarks.runs import one_thread_config, pipeline, run_in_workers, synthetic, write_report

# a stable surfel this far from the true surface in the overlap counts as doubled (mm)
DOUBLED_MM = 2.0


def map_surface_errors(ply: Path, data: Path) -> dict:
    """The exported map ``ply`` (metres) against the true depth of the sequence ``data``."""
    import open3d as o3d

    from slam.io.datasets import open_dataset
    from slam.evaluation.map_error import depth_errors_mm

    pts_mm = np.asarray(o3d.io.read_point_cloud(str(ply)).points) * 1000.0
    ds = open_dataset(data)
    n = len(ds)
    checks = sorted({0, n // 4, n // 2, 3 * n // 4, n - 1})
    err_all, seen_by = [], {}
    for i in checks:
        seen, err = depth_errors_mm(pts_mm, ds.gt_poses[i], ds.camera.K, ds.R1, ds.frame(i).gt_depth)
        err_all.append(np.abs(err))
        seen_by[i] = (seen, err)
    first_seen, _ = seen_by[0]
    last_seen, last_err = seen_by[n - 1]
    overlap = first_seen[last_seen]            # of the points the last frame sees, those the first sees too
    off = np.abs(last_err[overlap])
    all_err = np.concatenate(err_all)
    return {"points": int(len(pts_mm)), "median_mm": float(np.median(all_err)) if len(all_err) else float("nan"),
            "overlap_points": int(overlap.sum()),
            "overlap_median_mm": float(np.median(off)) if len(off) else float("nan"),
            "doubled_share": float((off > DOUBLED_MM).mean()) if len(off) else float("nan")}


def run_one(job: dict) -> dict:
    cfg = one_thread_config(METHODS[job["method"]], job["extra"])
    result = pipeline(cfg, job["data"], job["out"]).run(progress=False)
    m = result.metrics
    lc = m.get("loop_closure", {})
    return {"sequence": job["sequence"], "method": job["method"], "ate_rmse_mm": m["ate_rmse_mm"],
            "loops": lc.get("accepted"), **map_surface_errors(Path(job["out"]) / "map.ply", Path(job["data"]))}


def format_table(rows: list[dict]) -> str:
    lines = ["| sequence | method | ATE mm | loops | stable surfels | median to surface mm | overlap points "
             f"| overlap median mm | overlap > {DOUBLED_MM:g} mm |", "|---" * 9 + "|"]
    for r in rows:
        loops = "-" if r["loops"] is None else str(r["loops"])
        lines.append(f"| {r['sequence']} | {r['method']} | {r['ate_rmse_mm']:.3f} | {loops} | {r['points']:,} "
                     f"| {r['median_mm']:.3f} | {r['overlap_points']:,} | {r['overlap_median_mm']:.3f} "
                     f"| {100 * r['doubled_share']:.2f} % |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[8001, 8002])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", default="320x256")
    ap.add_argument("--methods", nargs="+", default=["rendered", "loop_closure"], choices=["rendered", "loop_closure"])
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--out", default="runs/loop_map")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    out = Path(args.out)
    jobs = []
    for seed in args.seeds:
        data = synthetic(out / "data" / f"loop_s{seed}_{args.frames}_{w}x{h}", "loop", frames=args.frames,
                         size=(w, h), seed=seed)
        jobs += [{"sequence": f"loop s{seed}", "method": m, "data": str(data), "out": str(out / "runs" / f"s{seed}_{m}"),
                  "extra": args.set} for m in args.methods]
    rows = run_in_workers(run_one, jobs, args.workers)
    table = format_table(rows)
    write_report(out, "loop_map", table, rows, indent=1)


if __name__ == "__main__":
    main()
