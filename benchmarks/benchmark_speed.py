"""Speed benchmark of the whole pipeline, end to end including correspondences.

    .venv/bin/python tools/benchmark_speed.py [--frames 100] [--sizes 320x256 640x512]
                                             [--modes frame2frame frame2model] [--set key=value ...]

For each size it renders a synthetic `scanning` sequence (seed 4242, an evaluation seed), then runs
`slam run` in a fresh process per (mode, size) in the default configuration (plus any --set),
and prints a table of per-stage milliseconds (wall time: stages of different threads overlap),
the CPU milliseconds per frame of the main thread, the read-ahead thread and the whole process
(with the pools' workers), fps, peak memory and ATE, so speed bought with accuracy shows in the
same table; below it the thread pools' sizes (torch, OpenCV, numba). The maps of these runs hold 0.1-0.3 M surfels; a second table
gives the map's cost per frame with a million surfels (``tools/benchmark_mapping.py`` on
``--map-sizes``: fusion, depth-only and colour render, fusion + colour render, the frame2model
default's cost). Results are also written as markdown and JSON.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

from benchmarks.runs import write_report

#: metrics.json's thread_cpu_ms: CPU ms per frame of the main thread, the read-ahead thread and the
#: whole process (those two plus the pools' workers of torch, OpenCV and numba)
THREADS = ["main", "reader", "process"]
STAGES = ["read", "stereo", "flow", "flow_back", "weights", "solve", "verify", "cross_check", "render", "fusion", "logging", "total"]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--sizes", nargs="+", default=["320x256", "640x512"])
    ap.add_argument("--modes", nargs="+", default=["frame2frame", "frame2model"])
    ap.add_argument("--scenario", default="scanning")
    ap.add_argument("--out", default="runs/benchmark_speed")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--map-surfels", type=int, default=1_000_000,
                    help="map size of the fusion + render table (0: skip it)")
    ap.add_argument("--map-sizes", nargs="+", default=["320x256"])
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    slam = [sys.executable, "-m", "slam"]
    rows = []
    for size in args.sizes:
        data = out / f"data_{args.scenario}_{size}_{args.frames}"
        if not (data / "groundtruth.txt").is_file():
            subprocess.run([*slam, "synth", str(data), "--scenario", args.scenario, "--frames", str(args.frames),
                            "--size", size, "--seed", "4242"], check=True, capture_output=True)
        for mode in args.modes:
            run_dir = out / f"{mode}_{size}"
            shutil.rmtree(run_dir, ignore_errors=True)     # a run refuses a folder holding an earlier one
            cmd = [*slam, "run", str(data), "--mode", mode, "--out", str(run_dir), "--quiet"]
            for s in args.set:
                cmd += ["--set", s]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                print(proc.stderr, file=sys.stderr)
                rows.append({"size": size, "mode": mode, "error": proc.stderr.strip().splitlines()[-1:]})
                continue
            m = json.loads((run_dir / "metrics.json").read_text())
            rows.append({"size": size, "mode": mode, "fps": m["fps"], "ate_rmse_mm": m.get("ate_rmse_mm"),
                         "peak_rss_mb": m.get("peak_rss_mb"), "failed": len(m["failed_frames"]),
                         **{f"{k}_ms": m["timings_ms"].get(k) for k in STAGES},
                         **{f"cpu_{k}_ms": m.get("thread_cpu_ms", {}).get(k) for k in THREADS},
                         "pools": m.get("thread_pools")})
    header = ["size", "mode", *[f"{k}_ms" for k in STAGES], *[f"cpu_{k}_ms" for k in THREADS], "fps",
              "peak_rss_mb", "ate_rmse_mm", "failed"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        cells = []
        for h in header:
            v = r.get(h)
            cells.append("-" if v is None else (f"{v:.1f}" if isinstance(v, float) and h != "ate_rmse_mm" else
                                                (f"{v:.3f}" if isinstance(v, float) else str(v))))
        lines.append("| " + " | ".join(cells) + " |")
    pools = sorted({json.dumps(r["pools"], sort_keys=True) for r in rows if r.get("pools")})
    table = "\n".join(lines) + "".join(f"\n\nthread pools: {p}" for p in pools)
    map_rows = map_cost(args.map_sizes, args.map_surfels, out) if args.map_surfels > 0 else []
    if map_rows:
        table += "\n\n" + map_table(map_rows, args.map_surfels)
    write_report(out, "speed", table, {"runs": rows, "map_cost": map_rows})


def map_cost(sizes: list[str], surfels: int, out: Path) -> list[dict]:
    """Fusion and render medians with a ``surfels``-surfel map (``benchmarks/benchmark_mapping.py``, in
    its own process)."""
    path = out / "map_cost.json"
    cmd = [sys.executable, "-m", "benchmarks.benchmark_mapping", "--sizes", ",".join(sizes),
           "--surfels", str(surfels), "--json", str(path)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        print(proc.stderr, file=sys.stderr)
        return [{"size": ",".join(sizes), "error": proc.stderr.strip().splitlines()[-1:]}]
    return json.loads(path.read_text())["results"]


def map_table(rows: list[dict], surfels: int) -> str:
    lines = [f"map cost per frame with a {surfels / 1e6:g} M-surfel map (medians, ms):", "",
             "| size | surfels | visible | fusion | render (depth) | render (colour) | fusion + colour render |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['size']} | error: {r['error']} | | | | | |")
            continue
        lines.append(f"| {r['size']} | {r['surfels']} | {int(r['visible'])} | {r['fuse']:.1f} | {r['render']:.1f} | "
                     f"{r['render_rgb']:.1f} | {r['total_rgb']:.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
