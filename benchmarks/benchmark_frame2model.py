"""Frame2model against frame2frame on synthetic rigid and loop sequences.

    .venv/bin/python tools/benchmark_frame2model.py [--scenarios rigid loop] [--seeds 8001 8002 8003 8004]
        [--frames rigid=150 loop=300] [--size 320x256] [--workers 2] [--out runs/benchmark_f2m]
        [--methods frame2frame rendered refined loop_closure] [--appearance SPEC]
        [--set KEY=VALUE ...]

Each sequence is tracked frame to frame (``frame2frame``) and frame to model, the flow against the
model's rendered colour: ``rendered`` (without loop closure), ``refined`` (rendered, plus one
refinement pass against the model rendered at the first estimate, ``tracking.refine_passes=1``) and
``loop_closure`` (rendered, with the pose graph and loop closure, ``graph.loop_closure=true``;
its ATE is that of the optimised trajectory, the poses as tracked are in the JSON), all with the
same weights. Prints, and writes as markdown and JSON, the ATE-RMSE of every run and the ratio
frame2model / frame2frame per sequence (the target is at most 0.7), with the mean over
sequences. Sequences run in parallel worker processes; ``--set`` overrides apply to every run
(e.g. ``correspondence.lr_check_px=0``).
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from benchmarks.runs import one_thread_config, pipeline, run_in_workers, synthetic, write_report

METHODS = {
    "frame2frame": ["tracking.mode=frame2frame"],
    "rendered": ["tracking.mode=frame2model", "graph.loop_closure=false"],
    "refined": ["tracking.mode=frame2model", "tracking.refine_passes=1", "graph.loop_closure=false"],
    "loop_closure": ["tracking.mode=frame2model", "graph.loop_closure=true"],
}
DEFAULT_METHODS = ["frame2frame", "rendered", "refined"]
DEFAULT_FRAMES = {"rigid": 150, "loop": 300}


def run_one(job: dict) -> dict:
    cfg = one_thread_config(METHODS[job["method"]], job["extra"])
    result = pipeline(cfg, job["data"], job["out"]).run(progress=False)
    m = result.metrics
    return {**{k: job[k] for k in ("scenario", "seed", "method")}, "ate_rmse_mm": m["ate_rmse_mm"],
            "rpe_trans_mm": m["rpe_trans_mm"], "fps": m["fps"], "frames": m["frames"], "failed": len(m["failed_frames"]),
            "model_fallbacks": m.get("model_fallbacks", 0), "flagged": len(m.get("flagged_frames", [])),
            "online_ate_rmse_mm": m.get("online", {}).get("ate_rmse_mm"),
            "loops_accepted": m.get("loop_closure", {}).get("accepted"),
            "loops_rejected": m.get("loop_closure", {}).get("rejected")}


def parse_frames(items: list[str]) -> dict[str, int]:
    frames = dict(DEFAULT_FRAMES)
    for item in items:
        key, _, value = item.partition("=")
        if not value:
            raise SystemExit(f"--frames wants SCENARIO=N, got '{item}'")
        frames[key] = int(value)
    return frames


def format_table(results: list[dict], methods: list[str]) -> str:
    """One row per sequence: ATE of each method and each frame2model method's ratio to frame2frame."""
    model = [m for m in methods if m != "frame2frame"]
    has_f2f = "frame2frame" in methods
    head = ["sequence", *(f"{m} ATE mm" for m in methods)]
    if has_f2f:
        head += [f"{m} / f2f" for m in model]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    seqs = sorted({(r["scenario"], r["seed"]) for r in results})
    ate = {(r["scenario"], r["seed"], r["method"]): r["ate_rmse_mm"] for r in results}
    ratios: dict[str, list[float]] = {m: [] for m in model}
    for s, seed in seqs:
        cells = [f"{ate[(s, seed, m)]:.3f}" if (s, seed, m) in ate else "-" for m in methods]
        if has_f2f:
            for m in model:
                if (s, seed, m) in ate and (s, seed, "frame2frame") in ate:
                    r = ate[(s, seed, m)] / ate[(s, seed, "frame2frame")]
                    ratios[m].append(r)
                    cells.append(f"{r:.2f}")
                else:
                    cells.append("-")
        lines.append(f"| {s} s{seed} | " + " | ".join(cells) + " |")
    mean = [f"{np.mean([ate[k] for k in ate if k[2] == m]):.3f}" for m in methods]
    if has_f2f:
        mean += [f"{np.mean(ratios[m]):.2f} (max {np.max(ratios[m]):.2f})" if ratios[m] else "-" for m in model]
    lines.append("| mean | " + " | ".join(mean) + " |")
    shares = []
    for m in model:
        rows = [r for r in results if r["method"] == m and r.get("frames")]
        if rows:
            share = sum(r["model_fallbacks"] for r in rows) / sum(r["frames"] for r in rows)
            shares.append(f"{m} {100 * share:.0f} %")
    if shares:
        lines.append("\nframes tracked against the previous frame (model view too empty): " + ", ".join(shares))
    closing = [r for r in results if r.get("online_ate_rmse_mm") is not None]
    if closing:
        lines.append(f"loop closure: mean ATE as tracked {np.mean([r['online_ate_rmse_mm'] for r in closing]):.3f} mm, "
                     f"optimised {np.mean([r['ate_rmse_mm'] for r in closing]):.3f}; loops accepted "
                     f"{sum(r['loops_accepted'] for r in closing)}, rejected {sum(r['loops_rejected'] for r in closing)}; "
                     f"flagged frames {sum(r['flagged'] for r in closing)}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=["rigid", "loop"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[8001, 8002, 8003, 8004])
    ap.add_argument("--frames", nargs="*", default=[], help="SCENARIO=N (defaults rigid=150 loop=300)")
    ap.add_argument("--size", default="320x256")
    ap.add_argument("--methods", nargs="+", default=DEFAULT_METHODS, choices=list(METHODS))
    ap.add_argument("--appearance", default=None, metavar="SPEC",
                    help="generate the sequences with this look (slam synth --appearance; 'random': one per seed)")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--out", default="runs/benchmark_f2m")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    args.scenarios, args.seeds, args.methods = (list(dict.fromkeys(v)) for v in (args.scenarios, args.seeds, args.methods))
    frames = parse_frames(args.frames)
    w, h = (int(v) for v in args.size.split("x"))
    out = Path(args.out)
    from slam.synth.appearance import appearance_tag, parse_appearance

    jobs = []
    for scenario in args.scenarios:
        n = frames.get(scenario, 150)
        for seed in args.seeds:
            data = out / "data" / f"{scenario}_s{seed}_{args.size}_{n}{appearance_tag(args.appearance)}"
            synthetic(data, scenario, frames=n, size=(w, h), seed=seed,
                      appearance=parse_appearance(args.appearance, seed))
            for method in args.methods:
                jobs.append({"scenario": scenario, "seed": seed, "method": method, "data": str(data),
                             "extra": args.set, "out": str(out / "runs" / f"{scenario}_s{seed}_{method}")})
    results = run_in_workers(run_one, jobs, args.workers)
    table = format_table(results, args.methods)
    settings = f"size {args.size}, frames {frames}, look {args.appearance or 'default'}, overrides {args.set or 'none'}"
    write_report(out, "frame2model", table + "\n\n" + settings,
                 {"settings": {"size": args.size, "frames": frames, "overrides": args.set}, "results": results})


if __name__ == "__main__":
    main()
