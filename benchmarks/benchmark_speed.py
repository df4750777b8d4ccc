"""Speed benchmark of the whole pipeline, end to end including correspondences.

    .venv/bin/python tools/benchmark_speed.py [--frames 100] [--sizes 320x256 640x512]
                                             [--modes frame2frame frame2model] [--set key=value ...]
                                             [--scenarios scanning rigid] [--real [DIR]] [--repeat 3]
                                             [--repo before=/tmp/base --repo after=.]

For each scenario and size it renders a synthetic sequence (seed 4242, an evaluation seed), then
runs `slam run` in a fresh process per (mode, size) in the default configuration (plus any --set).
``--real`` adds the real SCARED sequence of ``tools/check_accuracy.py`` (640x512, 5 fps; its ATE
against the reference trajectory; ``--real`` alone reads ``$ENDOSLAM_REAL`` or the cache, ``--real
DIR`` the folder), and ``--scenarios`` with no name leaves the synthetic ones out. It prints a
table of per-stage milliseconds (wall time: stages of different threads overlap), the CPU
milliseconds per frame of the main, read-ahead and mapping threads and of the whole process (with
the pools' workers), fps, peak memory and ATE, so speed bought with accuracy shows in the same
table; below it the thread pools' sizes (torch, OpenCV, numba).

With ``--repo NAME=PATH`` (repeatable) it runs each checkout's own ``slam`` (e.g. a ``git
worktree`` of a baseline commit) on the same sequences, the checkouts alternating run by run,
``--repeat`` times: each row is then the median run of its checkout (by fps), with the fps range
over the repeats, and a second table gives each checkout's median fps over the first one's. The
maps of these runs hold 0.1-0.3 M surfels; a last table gives the map's cost per frame with a
million surfels (``tools/benchmark_mapping.py`` on ``--map-sizes``: fusion, depth-only and
colour render, fusion + colour render, the frame2model default's cost). Results are also written
as markdown and JSON.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

from benchmarks.checkout import run_slam
from benchmarks.runs import write_report

#: metrics.json's thread_cpu_ms: CPU ms per frame of the main, read-ahead and mapping threads and
#: the whole process (those plus the pools' workers of torch, OpenCV and numba)
THREADS = ["main", "reader", "mapping", "process"]
STAGES = ["read", "stereo", "flow_ahead", "flow", "weights", "solve", "verify", "cross_check", "render", "fusion",
          "map_wait", "logging", "total"]
SEED = 4242


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--sizes", nargs="+", default=["320x256", "640x512"])
    ap.add_argument("--modes", nargs="+", default=["frame2frame", "frame2model"])
    ap.add_argument("--scenarios", "--scenario", nargs="*", default=["scanning"],
                    help="synthetic scenarios (none: only --real)")
    ap.add_argument("--out", default="runs/benchmark_speed")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--real", nargs="?", const="", default=None, metavar="DIR",
                    help="also the real sequence (check_accuracy's; DIR, $ENDOSLAM_REAL or the cache)")
    ap.add_argument("--repo", action="append", default=[], metavar="NAME=PATH",
                    help="a checkout to run (repeatable; default: this one)")
    ap.add_argument("--repeat", type=int, default=1, help="runs per checkout and case (the median is reported)")
    ap.add_argument("--map-surfels", type=int, default=1_000_000,
                    help="map size of the fusion + render table (0: skip it)")
    ap.add_argument("--map-sizes", nargs="+", default=["320x256"])
    args = ap.parse_args(argv)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    repos = [tuple(r.split("=", 1)) for r in args.repo] or [("this", str(Path(__file__).resolve().parents[1]))]
    sequences = [(scenario, size, synthesise(out, scenario, size, args.frames), [])
                 for scenario in args.scenarios for size in args.sizes]
    if args.real is not None:
        sequences.append(("real", "640x512", real_sequence(out, args.real), ["data.fps=5"]))
    runs = []
    for rep in range(args.repeat):
        for scenario, size, data, sets in sequences:
            for mode in args.modes:
                for name, tree in repos:      # alternating: the machine's drift hits every checkout alike
                    runs.append({"repo": name, "scenario": scenario, "size": size, "mode": mode, "rep": rep,
                                 **run_case(tree, data, out / f"{name}_{scenario}_{mode}_{size}", mode,
                                            sets + args.set)})
    rows = median_rows(runs, repos)
    table = speed_table(rows, multi=len(repos) > 1 or args.repeat > 1)
    if len(repos) > 1:
        table += "\n\n" + ratio_table(rows, repos)
    pools = sorted({json.dumps(r["pools"], sort_keys=True) for r in rows if r.get("pools")})
    table += "".join(f"\n\nthread pools: {p}" for p in pools)
    map_rows = map_cost(args.map_sizes, args.map_surfels, out) if args.map_surfels > 0 else []
    if map_rows:
        table += "\n\n" + map_table(map_rows, args.map_surfels)
    write_report(out, "speed", table, {"repos": dict(repos), "runs": runs, "rows": rows, "map_cost": map_rows})


def synthesise(out: Path, scenario: str, size: str, frames: int) -> Path:
    """The benchmark's sequence (made once, by this checkout's generator)."""
    data = out / f"data_{scenario}_{size}_{frames}"
    if not (data / "groundtruth.txt").is_file():
        subprocess.run([sys.executable, "-m", "slam", "synth", str(data), "--scenario", scenario, "--frames",
                        str(frames), "--size", size, "--seed", str(SEED)], check=True, capture_output=True)
    return data


def real_sequence(out: Path, given: str) -> Path:
    """The real sequence with its reference as ``groundtruth.txt`` (a folder of links in ``out``)."""
    from benchmarks.accuracy_panel import REAL_TRAJECTORY, moved_copy, real_folder

    return moved_copy(real_folder(given or None), REAL_TRAJECTORY, 0, out / "data_real")


def run_case(tree: str, data: Path, run_dir: Path, mode: str, sets: list[str]) -> dict:
    """One ``slam run`` of the checkout ``tree``: its figures, or its error."""
    shutil.rmtree(run_dir, ignore_errors=True)     # a run refuses a folder holding an earlier one
    args = ["run", str(data), "--mode", mode, "--out", str(run_dir), "--quiet"]
    for s in sets:
        args += ["--set", s]
    proc = run_slam(tree, *args, capture_output=True, text=True)
    if proc.returncode != 0:
        print(proc.stderr, file=sys.stderr)
        return {"error": proc.stderr.strip().splitlines()[-1:]}
    m = json.loads((run_dir / "metrics.json").read_text())
    return {"fps": m["fps"], "ate_rmse_mm": m.get("ate_rmse_mm"), "peak_rss_mb": m.get("peak_rss_mb"),
            "failed": len(m["failed_frames"]), **{f"{k}_ms": m["timings_ms"].get(k) for k in STAGES},
            **{f"cpu_{k}_ms": m.get("thread_cpu_ms", {}).get(k) for k in THREADS}, "pools": m.get("thread_pools")}


def median_rows(runs: list[dict], repos: list[tuple[str, str]]) -> list[dict]:
    """Per checkout and case, its median run by fps, with the fps range over the repeats."""
    rows = []
    cases = list(dict.fromkeys((r["scenario"], r["size"], r["mode"]) for r in runs))
    for scenario, size, mode in cases:
        for name, _ in repos:
            mine = [r for r in runs if (r["repo"], r["scenario"], r["size"], r["mode"]) == (name, scenario, size, mode)]
            done = sorted((r for r in mine if "fps" in r), key=lambda r: r["fps"])
            if not done:
                rows.append(mine[0])
                continue
            row = dict(done[(len(done) - 1) // 2])
            row["fps"] = statistics.median(r["fps"] for r in done)
            row["fps_range"] = f"{done[0]['fps']:.2f}-{done[-1]['fps']:.2f}"
            rows.append(row)
    return rows


def speed_table(rows: list[dict], multi: bool) -> str:
    header = ["scenario", "size", "mode", *(["repo"] if multi else []), *[f"{k}_ms" for k in STAGES],
              *[f"cpu_{k}_ms" for k in THREADS], "fps", *(["fps_range"] if multi else []), "peak_rss_mb",
              "ate_rmse_mm", "failed"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scenario']} | {r['size']} | {r['mode']} | error: {r['error']} |")
            continue
        cells = []
        for h in header:
            v = r.get(h)
            cells.append("-" if v is None else (f"{v:.1f}" if isinstance(v, float) and h != "ate_rmse_mm" else
                                                (f"{v:.3f}" if isinstance(v, float) else str(v))))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def ratio_table(rows: list[dict], repos: list[tuple[str, str]]) -> str:
    """Each checkout's median fps over the first checkout's, per case."""
    first = repos[0][0]
    others = [name for name, _ in repos[1:]]
    lines = [f"median fps over {first}'s:", "", "| scenario | size | mode | " + " | ".join(others) + " |",
             "|---|---|---|" + "---|" * len(others)]
    base = {(r["scenario"], r["size"], r["mode"]): r.get("fps") for r in rows if r["repo"] == first}
    for key, b in base.items():
        cells = []
        for name in others:
            f = next((r.get("fps") for r in rows if r["repo"] == name and (r["scenario"], r["size"], r["mode"]) == key), None)
            cells.append(f"{f / b:.2f}x" if f and b else "-")
        lines.append("| " + " | ".join(key) + " | " + " | ".join(cells) + " |")
    return "\n".join(lines)


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
