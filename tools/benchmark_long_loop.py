"""Frame2model on a long synthetic loop, with and without loop closure: memory and time per frame.

    .venv/bin/python tools/benchmark_long_loop.py [--frames 5000] [--size 160x128] [--seed 8201]
        [--methods rendered loop_closure] [--block 500] [--workers 2] [--out runs/long_loop]
        [--set KEY=VALUE ...]

A loop sequence of ``--frames`` frames goes round the same closed path about once every 360
frames (``slam.synth.camera_paths.loop_path``), so a 5,000-frame one circles the same tissue 14
times. Each method (``benchmark_frame2model.py``'s: ``rendered`` is frame2model with
``graph.loop_closure=false``, ``loop_closure`` with it on) runs in its own worker process with
one torch thread. Prints, and writes as markdown and JSON, per method: the mean time per frame
(the pipeline's ``total``) in blocks of ``--block`` frames (a cost that grows with the sequence
shows as a rising row), the loop detection's share, the process's peak resident memory, the
map's surfels at the end, the graph's keyframes (kept and culled) and loops, and the ATE of the
tracked and the optimised trajectory.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from benchmarks.benchmark_frame2model import METHODS
from benchmarks.runs import one_thread_config, pipeline, run_in_workers, synthetic, write_report


def run_one(job: dict) -> dict:
    import resource

    run = pipeline(one_thread_config(METHODS[job["method"]], job["extra"]), job["data"], job["out"])
    result = run.run(progress=False)
    m = result.metrics
    total = np.asarray(run.timings.get("total", []))
    block = job["block"]
    lc = m.get("loop_closure", {})
    return {"method": job["method"], "frames": m["frames"], "fps": m["fps"],
            "ms_blocks": [float(total[i:i + block].mean()) for i in range(0, len(total), block)],
            "loop_ms_per_frame": lc.get("ms_per_frame", 0.0),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "map_points": result.map_points, "keyframes": lc.get("keyframes"), "culled": lc.get("culled"),
            "loops": lc.get("accepted"), "rejected": lc.get("rejected"),
            "ate_rmse_mm": m["ate_rmse_mm"], "online_ate_rmse_mm": m.get("online", {}).get("ate_rmse_mm", m["ate_rmse_mm"]),
            "flagged": len(m.get("flagged_frames", []))}


def format_table(rows: list[dict], block: int) -> str:
    nblocks = max(len(r["ms_blocks"]) for r in rows)
    head = ["method", *(f"ms {i * block}-" for i in range(nblocks)), "loop ms", "peak MB", "surfels",
            "keyframes (culled)", "loops (rejected)", "ATE online", "ATE optimised", "flagged"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in rows:
        blocks = [f"{v:.0f}" for v in r["ms_blocks"]] + ["-"] * (nblocks - len(r["ms_blocks"]))
        kf = "-" if r["keyframes"] is None else f"{r['keyframes']} ({r['culled']})"
        loops = "-" if r["loops"] is None else f"{r['loops']} ({r['rejected']})"
        lines.append("| " + " | ".join([r["method"], *blocks, f"{r['loop_ms_per_frame']:.1f}", f"{r['peak_rss_mb']:.0f}",
                                        f"{r['map_points']:,}", kf, loops, f"{r['online_ate_rmse_mm']:.3f}",
                                        f"{r['ate_rmse_mm']:.3f}", str(r["flagged"])]) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=5000)
    ap.add_argument("--size", default="160x128")
    ap.add_argument("--seed", type=int, default=8201)
    ap.add_argument("--methods", nargs="+", default=["rendered", "loop_closure"], choices=["rendered", "loop_closure"])
    ap.add_argument("--block", type=int, default=500)
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--out", default="runs/long_loop")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    out = Path(args.out)
    data = synthetic(out / "data" / f"loop_s{args.seed}_{args.frames}_{w}x{h}", "loop", frames=args.frames,
                     size=(w, h), seed=args.seed)
    jobs = [{"method": m, "data": str(data), "out": str(out / m), "block": args.block, "extra": args.set}
            for m in args.methods]
    rows = run_in_workers(run_one, jobs, args.workers)
    table = format_table(rows, args.block)
    write_report(out, "long_loop", table, rows, indent=1)


if __name__ == "__main__":
    main()
