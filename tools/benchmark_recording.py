"""How big a rerun recording (``slam run --rerun x.rrd``) is, what in it, and what logging costs.

    .venv/bin/python tools/benchmark_recording.py [--sizes 320x256:30 640x512:20]
        [--repo after=.] [--repo before=/tmp/rr_base ...] [--scenario scanning] [--seed 3]
        [--out runs/benchmark_recording] [--set KEY=VALUE ...]

For each size a synthetic sequence is rendered once (``slam synth``) and tracked with
``slam run SEQ --mode frame2model --rerun run.rrd --set threads=1 --quiet`` by the code of each
``--repo`` (``LABEL=PATH``: a checkout, e.g. a ``git worktree`` of another commit, run with
``PYTHONPATH=PATH``; the repos run one after the other, per size). The recording is then split
exactly with rerun's own ``rerun rrd filter --drop-entity``: the bytes of a group of entities are
the file's size minus that of the file without them. Per frame: the camera and image views
(image, depth, flow, w2d, w3d, valid, camera pose), the trajectories and the scalar series
(metrics/*, health/*); the map (every ``logging.map_every`` frames, 10 by default, and once at
the end) is given on its own, as its share of the file. The rest is the blueprint and the static
data (pinhole, annotation context, series styles). ``logging ms`` is ``timings_ms.logging`` of
``metrics.json``: the mean time of a frame's ``log_frame`` (encoding included; the rerun SDK
compresses and writes in its own thread, which this does not count).
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.checkout import run_slam
from slam.synth.writer import is_finished

ROOT = Path(__file__).resolve().parents[1]
RERUN = Path(sys.executable).parent / "rerun"

IMAGE_VIEWS = ["/world/camera", "/world/camera/image", "/world/camera/depth", "/world/camera/flow",
               "/world/camera/weights/w2d", "/world/camera/weights/w3d", "/world/camera/valid"]
MAP = "/world/map"


def slam(repo: Path, *args: str) -> None:
    """Run the ``slam`` command of the checkout ``repo``."""
    res = run_slam(repo, *args, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"slam {' '.join(args)} failed:\n{res.stdout[-2000:]}\n{res.stderr[-3000:]}")


def entities(path: Path) -> tuple[dict, list]:
    """{entity path: rows on the ``frame`` timeline} of the recording, and the points of each map
    logged."""
    from rerun.chunk import RrdReader

    rows: dict = {}
    map_points = []
    for chunk in RrdReader(path).stream():
        if not chunk.is_static and "frame" in chunk.timeline_names:
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
            if chunk.entity_path == MAP:
                batch = chunk.to_record_batch()
                map_points += [len(v) for v in batch.column("Points3D:positions").to_pylist() if v is not None]
    return rows, map_points


def bytes_of(path: Path, drop: list[str]) -> int:
    """The bytes of the entities ``drop`` in the recording ``path`` (exact: the file's size minus
    that of the file rerun writes without them)."""
    if not drop:
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rest.rrd"
        cmd = [str(RERUN), "rrd", "filter", str(path), "-o", str(out)]
        for entity in drop:
            cmd += ["--drop-entity", entity]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"rerun rrd filter failed: {res.stderr[-2000:]}")
        return path.stat().st_size - out.stat().st_size


def measure(rrd: Path, metrics: dict) -> dict:
    rows, map_points = entities(rrd)
    frames = int(metrics["frames"])
    traj = [e for e in rows if e.startswith("/world/trajectory/")]
    scalars = [e for e in rows if e.startswith(("/metrics/", "/health/"))]
    images = [e for e in IMAGE_VIEWS if e in rows]
    per_frame = {"images": bytes_of(rrd, images), "trajectories": bytes_of(rrd, traj),
                 "scalars": bytes_of(rrd, scalars)}
    views = bytes_of(rrd, images + traj + scalars)
    total = rrd.stat().st_size
    map_bytes = bytes_of(rrd, [MAP] if MAP in rows else [])
    return {
        "frames": frames, "total_bytes": total, "views_bytes": views,
        "views_kb_per_frame": views / frames / 1000.0,
        **{f"{k}_kb_per_frame": v / frames / 1000.0 for k, v in per_frame.items()},
        "map_bytes": map_bytes, "map_logs": rows.get(MAP, 0), "map_share": map_bytes / total,
        "map_last_points": map_points[-1] if map_points else 0,
        "map_bytes_per_point": map_bytes / max(sum(map_points), 1),
        "rest_bytes": total - views - map_bytes,
        "logging_ms": float(metrics.get("timings_ms", {}).get("logging", float("nan"))),
    }


def table(results: list[dict]) -> str:
    lines = ["| code | size | frames | total MB | per-frame views, kB a frame (images / trajectories / scalars) "
             "| map MB (logs, share) | map: last points, B a point | rest kB | logging ms a frame |",
             "|---|---|---:|---:|---|---|---|---:|---:|"]
    for r in results:
        views = (f"**{r['views_kb_per_frame']:.0f}** ({r['images_kb_per_frame']:.0f} / "
                 f"{r['trajectories_kb_per_frame']:.1f} / {r['scalars_kb_per_frame']:.1f})")
        map_ = f"{r['map_bytes'] / 1e6:.1f} ({r['map_logs']}, {100 * r['map_share']:.0f} %)"
        points = f"{r['map_last_points'] / 1e3:.0f} k, {r['map_bytes_per_point']:.1f}"
        lines.append(f"| {r['label']} | {r['size']} | {r['frames']} | {r['total_bytes'] / 1e6:.1f} | {views} | {map_} "
                     f"| {points} | {r['rest_bytes'] / 1e3:.0f} | {r['logging_ms']:.1f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", default=["320x256:30", "640x512:20"], help="WxH:FRAMES ...")
    ap.add_argument("--repo", action="append", default=[], help="LABEL=PATH of a checkout to run (repeatable); "
                    "default: this one")
    ap.add_argument("--scenario", default="scanning")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", default="runs/benchmark_recording")
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE for slam run (e.g. logging.map_every=0)")
    args = ap.parse_args()

    repos = []
    for item in args.repo or [f"this={ROOT}"]:
        label, _, path = item.partition("=")
        repos.append((label, Path(path or label).resolve()))
    out = Path(args.out).resolve()
    results = []
    for spec in args.sizes:
        size, _, frames = spec.partition(":")
        frames = int(frames or 30)
        data = out / "data" / f"{args.scenario}_s{args.seed}_{size}_{frames}"
        if not is_finished(data):
            slam(ROOT, "synth", str(data), "--scenario", args.scenario, "--frames", str(frames), "--size", size,
                 "--seed", str(args.seed), "--quiet")
        for label, repo in repos:
            run = out / "runs" / f"{label}_{size}_{frames}"
            shutil.rmtree(run, ignore_errors=True)     # a run refuses a folder holding an earlier one
            sets = [x for s in ["threads=1", *args.set] for x in ("--set", s)]
            slam(repo, "run", str(data), "--mode", "frame2model", "--out", str(run), "--rerun", str(run / "run.rrd"),
                 *sets, "--quiet")
            metrics = json.loads((run / "metrics.json").read_text())
            r = {"label": label, "repo": str(repo), "size": size, **measure(run / "run.rrd", metrics)}
            results.append(r)
            print(f"{label} {size}: {r['total_bytes'] / 1e6:.1f} MB, {r['views_kb_per_frame']:.0f} kB a frame",
                  file=sys.stderr)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    print(table(results))


if __name__ == "__main__":
    main()
