"""What `slam evaluate` costs against the same runs one after the other: wall time, the share of it
the workers spent tracking, and whether every ATE is the same.

    .venv/bin/python tools/benchmark_evaluate.py [--data DIR] [--out DIR] [--frames 40] [--size 320x256]
        [--how sequential local ray] [--workers 2] [--repeat 1]

The workload: 6 synthetic sequences (``slam synth``, scenarios rigid, breathing, scanning,
deforming, loop, scanning; seeds 5001-5006; rendered into ``--data`` once) in both modes, 12 runs:

* ``sequential``: 12 ``slam run SEQ --mode M --set threads=1`` processes one after the other, as
  the protocol scripts ran them before ``slam evaluate``;
* ``local``: ``slam evaluate DATA --executor local --workers W`` (spawned worker processes, one CPU
  and one torch thread per task);
* ``ray``: ``slam evaluate DATA --executor ray --workers W`` (a local Ray runtime with W CPUs, one per
  task).

Columns: the wall time of the whole command (start-up included); the tracking time, the sum over
runs of frames / fps from their ``metrics.json`` (the pipeline's own time); the task time, the sum
over runs of what each took as a task (``sequential``: each process from start to exit, imports
included; ``slam evaluate``: the worker's time from opening the sequence to the last file
written); outside tasks, the wall time minus the task time over the runs going at once (1 or W):
what the engine itself cost (the driver's and Ray's start and stop, the workers' start-up and
imports, scheduling) and the tail where one worker waits for the other; and whether every run's
ATE equals the sequential run's.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from slam.batch.executors import ray_available  # noqa: E402
from slam.batch.runner import BatchOptions  # noqa: E402
from slam.batch.synth import synthesize_or_fail  # noqa: E402
from slam.batch.tasks import SynthTask  # noqa: E402
from slam.app.cli import parse_size  # noqa: E402

SEQUENCES = (("s1_rigid", "rigid", 5001), ("s2_breathing", "breathing", 5002), ("s3_scanning", "scanning", 5003),
             ("s4_deforming", "deforming", 5004), ("s5_loop", "loop", 5005), ("s6_scanning", "scanning", 5006))
MODES = ("frame2frame", "frame2model")
SLAM = [sys.executable, "-m", "slam"]


def make_data(folder: Path, frames: int, size: tuple[int, int]) -> None:
    tasks = [SynthTask(out_dir=str(folder / name), scenario=scenario, seed=seed, frames=frames, size=size)
             for name, scenario, seed in SEQUENCES]
    synthesize_or_fail(tasks, BatchOptions(executor="local", progress=False))


def tracking_s(metrics: dict) -> float:
    return metrics["frames"] / metrics["fps"] if metrics.get("fps") else 0.0


def run_sequential(data: Path, out: Path) -> dict:
    ates, busy, tasks = {}, 0.0, 0.0
    t0 = time.perf_counter()
    for name, _, _ in SEQUENCES:
        for mode in MODES:
            run = out / name / mode
            shutil.rmtree(run, ignore_errors=True)     # a run refuses a folder holding an earlier one
            t = time.perf_counter()
            subprocess.run([*SLAM, "run", str(data / name), "--mode", mode, "--set", "threads=1", "--out", str(run),
                            "--quiet"], check=True, capture_output=True)
            tasks += time.perf_counter() - t
            m = json.loads((run / "metrics.json").read_text())
            ates[(name, mode)] = m["ate_rmse_mm"]
            busy += tracking_s(m)
    return {"wall_s": time.perf_counter() - t0, "tracking_s": busy, "task_s": tasks, "at_once": 1, "ates": ates}


def run_evaluate(data: Path, out: Path, executor: str, workers: int) -> dict:
    t0 = time.perf_counter()
    subprocess.run([*SLAM, "evaluate", str(data), "--executor", executor, "--workers", str(workers), "--out", str(out),
                    "--force", "--quiet"], check=True, capture_output=True)
    wall = time.perf_counter() - t0
    summary = json.loads((out / "summary.json").read_text())
    busy = sum(tracking_s(json.loads((Path(r["out"]) / "metrics.json").read_text())) for r in summary["rows"])
    ates = {(r["sequence"], r["mode"]): r["ate_rmse_mm"] for r in summary["rows"]}
    return {"wall_s": wall, "tracking_s": busy, "task_s": sum(r["seconds"] for r in summary["rows"]),
            "at_once": workers, "ates": ates, "batch_wall_s": summary["batch"]["wall_s"]}


def median(values: list[float]) -> float:
    return float(statistics.median(values))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="cache/benchmark_evaluate", help="the sequences' folder (rendered once)")
    ap.add_argument("--out", default="runs/benchmark_evaluate")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--size", default="320x256")
    ap.add_argument("--how", nargs="+", default=["sequential", "local", "ray"], choices=["sequential", "local", "ray"])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=1,
                    help="passes over --how, alternating (the machine drifts: compare within a pass)")
    args = ap.parse_args(argv)
    data, out = Path(args.data) / f"{args.size}_n{args.frames}", Path(args.out)
    make_data(data, args.frames, parse_size(args.size))
    hows = [h for h in args.how if h != "ray" or ray_available()]
    if len(hows) < len(args.how):
        print("ray: not installed (pip install 'endoslam[cluster]'), skipped")
    passes: list[dict] = []
    for k in range(args.repeat):
        results = {}
        for how in hows:
            print(f"pass {k + 1}/{args.repeat}: {how} ...", flush=True)
            results[how] = (run_sequential(data, out / how) if how == "sequential"
                            else run_evaluate(data, out / how, how, args.workers))
        passes.append(results)
    first = passes[0]
    reference = first.get("sequential", next(iter(first.values())))["ates"]
    print(f"\n12 runs (6 sequences x 2 modes, {args.frames} frames, {args.size}), {args.workers} workers, "
          f"{args.repeat} pass(es): median (min-max)\n")
    print("| how | wall s | tracking s | task s | runs at once | outside tasks s | share of wall | vs sequential | ATE equal |")
    print("|---|---|---|---|---|---|---|---|---|")

    def spread(values: list[float]) -> str:
        text = f"{median(values):.1f}"
        return text if len(values) == 1 else f"{text} ({min(values):.1f}-{max(values):.1f})"

    for how in hows:
        runs = [p[how] for p in passes]
        outside = [r["wall_s"] - r["task_s"] / r["at_once"] for r in runs]
        same = all(abs(r["ates"][k] - v) <= 1e-9 * max(1.0, abs(v)) for r in runs for k, v in reference.items())
        speedup = "-" if "sequential" not in hows else \
            f"{median([p['sequential']['wall_s'] / p[how]['wall_s'] for p in passes]):.2f}x"
        print(f"| {how} | {spread([r['wall_s'] for r in runs])} | {spread([r['tracking_s'] for r in runs])} | "
              f"{spread([r['task_s'] for r in runs])} | {runs[0]['at_once']} | {spread(outside)} | "
              f"{100 * median(outside) / median([r['wall_s'] for r in runs]):.0f} % | {speedup} | "
              f"{'yes' if same else 'NO'} |")
    if "local" in hows and "ray" in hows:
        extra = [p["ray"]["wall_s"] - p["local"]["wall_s"] for p in passes]
        share = [100 * e / p["ray"]["wall_s"] for e, p in zip(extra, passes)]
        print(f"\nRay against the local workers, per pass: {', '.join(f'{e:+.1f} s' for e in extra)}; median "
              f"{median(extra):+.1f} s, {median(share):+.0f} % of Ray's wall time")
    (out / "benchmark_evaluate.json").write_text(json.dumps(
        [{how: {k: v for k, v in r.items() if k != "ates"} for how, r in p.items()} for p in passes], indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
