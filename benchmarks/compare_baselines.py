"""Our pipeline against Open3D baselines on the same sequences and the same stereo depth.

    .venv/bin/python tools/compare_baselines.py [DATA ...] [--out DIR] [--size WxH] [--frames N]
        [--methods o3d_color o3d_hybrid o3d_slam ours_f2f ours_f2m static] [--set key=value ...]

Without DATA it generates the default evaluation sequences into ``--out/data``: synthetic
``rigid``, ``scanning``, ``breathing``, ``deforming`` and ``loop`` with evaluation seeds 7001-7005
(disjoint from the training seeds 1000-1004 the baselines were tuned on and from the scenario
benchmark's 9001+), at ``--size`` (default 640x512), 150 frames each and 300 for ``loop``
(``--frames N``: N each, 2N for loop, which still closes at its last frame). With DATA (any layout
``slam run`` reads) ``--size`` resizes the frames and ``--frames N`` keeps the first N.

Fairness. Every method gets the same frames and the same depth: our stereo depth
(``StereoOdometry.make_view``: DIS stereo flow, the default depth limits, instrument and specular
masks applied) is computed once per sequence and cached in ``--out/depth/*.npz`` (uint16,
0.01 mm); the baselines read it, our pipeline recomputes it with the same function and
configuration (deterministic). Colour = the rectified left image; intrinsics = the rectified K.

Methods (one row each; both Open3D odometry variants are reported, not the better one):
  o3d_color   Open3D RGB-D odometry frame-to-frame, RGBDOdometryJacobianFromColorTerm (photometric)
  o3d_hybrid  Open3D RGB-D odometry frame-to-frame, RGBDOdometryJacobianFromHybridTerm
              (photometric + depth)
  o3d_slam    Open3D dense SLAM (open3d.t.pipelines.slam.Model: TSDF voxel blocks, frame-to-model
              tracking against the model's ray-cast view, as Open3D's dense_slam.py)
  ours_f2f    our pipeline, tracking.mode=frame2frame, learned weights
  ours_f2m    our pipeline, tracking.mode=frame2model, learned weights
  static      reference: a camera that never moves (every pose = the first ground-truth pose)
If the learned checkpoint is missing, ours runs with ``weights.mode=constant`` and the table says so.

Every method runs on every sequence in its own process (Open3D 0.20's dense SLAM was seen to
segfault inside libOpen3D on some 640x512 sequences): a child that dies is reported, never
propagated. The dense SLAM is retried with voxels x2 and x4 after a crash; if all fail its cells
read "crash". A tracking failure (an exception from ``track_frame_to_model``, ``success = False``
from ``compute_rgbd_odometry``) keeps the previous pose and is counted in "failed".

Metrics (``slam.evaluation.metrics.evaluate``, as ``slam run``): ATE-RMSE (mm, SE(3)-aligned; first-pose
aligned on static-camera sequences), RPE-trans (mm) and RPE-rot (deg) between consecutive frames.
Every trajectory starts at the first ground-truth pose. "fps" is the tracking throughput without
our stereo depth and without reading frames: Open3D odometry = building Open3D's images + the
odometry call; Open3D SLAM = its whole per-frame loop (tracking, integration, ray casting); ours =
the pipeline's tracking work per frame, on whichever thread it ran, without reading and stereo
depth (flow, weights, solver, and in frame2model rendering, the cross-check and fusion). "fps +
depth" adds the stereo depth time (measured when the cache was made) to every method. The machine is shared: fps are indicative only.

Outputs in ``--out``: ``baselines.md`` (tables), ``baselines.json`` (rows with parameters),
``runs/SEQ/METHOD/trajectory.txt`` (TUM) and our pipeline's usual files, ``logs/`` (child output).

Tuning (training-like sequences only, never the evaluation data): seeds 1000-1004, one per scenario
(rigid s1000, scanning s1001, breathing s1002, deforming s1003, loop s1004), 60 frames at 640x512
(the evaluation size) and a 40-frame 320x256 check. Criterion: mean ATE-RMSE (mm) over the five;
RPE-trans in brackets. The chosen values are ``baselines_open3d.ODOMETRY_DEFAULTS`` and
``SLAM_DEFAULTS``.

  Open3D RGB-D odometry, 640x512, iterations [20, 10, 5] unless given (per sequence: rigid
  scanning breathing deforming loop):
    hybrid, depth_diff_max  2 mm   0.39 0.86 3.19 2.14 0.37  mean 1.388 (0.138)  <- chosen
    hybrid, depth_diff_max 10 mm   0.50 0.84 3.34 2.16 0.51  mean 1.470 (0.138)
    hybrid, depth_diff_max 30 mm   0.58 0.64 3.30 2.17 0.41  mean 1.419 (0.138)
    hybrid, 2 mm, [20,10,5,3]                                mean 1.464 (0.144)
    hybrid, 2 mm, [40,20,10]                                 mean 1.683 (0.150)
    colour, depth_diff_max  2 mm   0.43 0.89 3.28 2.66 0.60  mean 1.574 (0.157)
    colour, depth_diff_max 10 mm   0.45 0.77 3.24 2.44 0.39  mean 1.457 (0.151)  <- chosen
    colour, depth_diff_max 30 mm   0.51 0.88 3.21 2.36 0.37  mean 1.465 (0.155)
    colour, 2 mm, [20,10,5,3]                                mean 1.711 (0.152)
  At 320x256 (40 frames) 2 mm was best for both (hybrid 1.698 / 1.847 / 1.821, colour 2.387 /
  2.421 / 2.398 for 2 / 10 / 30 mm). The depth threshold moves the mean by < 10 %, less than the
  spread between sequences: 2 mm (hybrid) and 10 mm (colour) are the per-Jacobian optima at the
  evaluation size, not a strong effect. Open3D's default schedule [20, 10, 5] beat more levels and
  more iterations.

  Open3D dense SLAM, 640x512, iterations [6, 3, 1], truncation 8 voxels unless given:
    PointToPlane, voxel 2 mm,     depth_diff 2 mm             mean 14.61 (0.920)
    PointToPlane, voxel 1 mm,     depth_diff 2 / 5 mm         mean 4.679 / 4.775
    PointToPlane, voxel 0.5 mm,   depth_diff 2 / 5 / 10 mm    mean 1.991 / 2.025 / 2.054
    PointToPlane, voxel 0.5 mm,   iterations [20, 10, 5]      mean 2.370
    PointToPlane, voxel 0.5 mm,   truncation 4 voxels         mean 3.414
    PointToPlane, voxel 0.25 mm,  depth_diff 2 mm  0.68 1.20 1.27 1.65 0.85  mean 1.128 (0.281)
    PointToPlane, voxel 0.125 mm, depth_diff 2 mm  0.60 0.87 1.30 1.03 0.74  mean 0.905 (0.237) <- chosen
    Hybrid, voxel 1 / 0.5 / 0.25 mm, depth_diff 5 mm          mean 4.774 / 4.058 / 3.280
      (good on the static-camera and loop sequences, 0.4-1.7 mm, but it diverges on rigid and
      scanning, 5-15 mm; depth_diff 2 / 10 mm, truncation 4 and [20, 10, 5] did not fix it)
    Intensity (320x256 rigid only): 16.9 mm, diverged.
  Finer voxels were monotonically better, at 320x256 too (0.125 / 0.25 / 0.5 mm: mean 1.892 /
  2.299 / 2.882), far below the ~1 mm first guess: the tissue is ~75 mm away and a 640x512 pixel
  covers ~0.135 mm, so a 1 mm TSDF smooths away the relief the point-to-plane ICP needs. 0.125 mm
  (about one pixel) was not refined further. The block hash map grows by itself (block_count is
  only its initial capacity; 7.6k blocks after 60 loop frames at 0.125 mm).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks import baselines_open3d as B

METHODS = {
    "o3d_color": "Open3D RGB-D odometry, photometric (f2f)",
    "o3d_hybrid": "Open3D RGB-D odometry, hybrid (f2f)",
    "o3d_slam": "Open3D dense SLAM, TSDF (f2m)",
    "ours_f2f": "ours frame2frame",
    "ours_f2m": "ours frame2model",
    "static": "camera that never moves (reference)",
}
DEFAULT_METHODS = list(METHODS)
DEFAULT_SEQUENCES = [("rigid", 7001), ("scanning", 7002), ("breathing", 7003), ("deforming", 7004), ("loop", 7005)]
DEFAULT_FRAMES = 150  # loop: twice as many
SLAM_VOXEL_FACTORS = (1, 2, 4)  # dense SLAM retries after a crash
METRICS = ("ate_rmse_mm", "rpe_trans_mm", "rpe_rot_deg")


def parse_size(text: str | None) -> tuple[int, int] | None:
    if not text:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SystemExit(f"--size: expected WIDTHxHEIGHT, e.g. 640x512, got '{text}'") from None
    return w, h


# ------------------------------------------------------------------------------------------------
# sequences
def default_sequences(out: Path, size: tuple[int, int], frames: int | None) -> list[Path]:
    """Generate (once) the default evaluation sequences; returns their folders."""
    from slam.synth import generate

    paths = []
    for scenario, seed in DEFAULT_SEQUENCES:
        n = frames or DEFAULT_FRAMES
        if scenario == "loop":
            n *= 2
        path = out / "data" / f"{scenario}_s{seed}_{size[0]}x{size[1]}_{n}"
        if not (path / "groundtruth.txt").is_file():
            print(f"generating {path.name} ...", flush=True)
            generate(path, scenario, frames=n, size=size, seed=seed)
        paths.append(path)
    return paths


def learned_weights_available(overrides: list[str]) -> bool:
    from slam.config import load_config
    from vo.weights import default_checkpoint

    cfg = load_config(None, list(overrides))
    if cfg.weights.mode != "learned":
        return True
    path = Path(cfg.weights.checkpoint) if cfg.weights.checkpoint else default_checkpoint(cfg.weights.residuals, cfg.depth.temporal_gain < 1.0)
    return path.is_file()


# ------------------------------------------------------------------------------------------------
# running
def method_jobs(method: str, seq: dict, overrides: list[str], ours_overrides: list[str], out: Path) -> list[dict]:
    """The job(s) of one method on one sequence; several = attempts tried in order after a crash."""
    common = {"data": seq["data"], "overrides": overrides, "frames": seq["frames"]}
    if method in ("o3d_color", "o3d_hybrid"):
        return [{"kind": "odometry", "args": {**common, "depth_cache": seq["depth"],
                                              "jacobian": method.split("_")[1]}}]
    if method == "o3d_slam":
        voxel = B.SLAM_DEFAULTS["voxel_mm"]
        return [{"kind": "dense_slam", "args": {**common, "depth_cache": seq["depth"], "voxel_mm": voxel * f}}
                for f in SLAM_VOXEL_FACTORS]
    if method in ("ours_f2f", "ours_f2m"):
        mode = "frame2frame" if method == "ours_f2f" else "frame2model"
        return [{"kind": "ours", "args": {**common, "overrides": [*overrides, *ours_overrides], "mode": mode,
                                          "out": str(out / "runs" / seq["name"] / method)}}]
    raise ValueError(f"unknown method '{method}' (choose from {', '.join(METHODS)})")


def run_method(method: str, seq: dict, overrides: list[str], ours_overrides: list[str], out: Path,
               timeout: float | None = None, runner=B.run_isolated) -> dict:
    """Run one method on one sequence (each attempt in its own process) and evaluate it."""
    row = {"sequence": seq["name"], "method": method, "label": METHODS[method], "status": "ok", "notes": []}
    if method == "static":
        poses = np.repeat(seq["gt"][:1], len(seq["gt"]), axis=0) if seq["gt"] is not None else None
        result = {"poses": poses.tolist() if poses is not None else [], "failed_frames": [], "track_s": 0.0,
                  "frames": len(seq["gt"]) if seq["gt"] is not None else 0, "params": {}}
        return finish_row(row, result, seq, out)
    attempts = method_jobs(method, seq, overrides, ours_overrides, out)
    log = out / "logs" / f"{seq['name']}_{method}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    outcome = None
    for i, job in enumerate(attempts):
        t0 = time.perf_counter()
        outcome = runner(job, log_path=log, timeout=timeout)
        wall = time.perf_counter() - t0
        print(f"  {seq['name']:<28} {method:<10} {outcome['status']:<7} {wall:7.1f} s"
              + (f"  ({outcome['message']})" if outcome["status"] != "ok" else ""), flush=True)
        if outcome["status"] == "ok":
            if i > 0:
                row["notes"].append(f"voxel {job['args']['voxel_mm']:g} mm after {i} failed attempt(s)")
            break
        row.setdefault("attempts", []).append({k: outcome[k] for k in ("status", "signal", "returncode", "message")}
                                              | {"args": {k: v for k, v in job["args"].items()
                                                          if k not in ("data", "overrides", "depth_cache")}})
        if outcome["status"] == "timeout":
            break
    if outcome["status"] != "ok":
        row["status"] = outcome["status"]
        row["message"] = outcome["message"]
        return row
    return finish_row(row, outcome["result"], seq, out)


def finish_row(row: dict, result: dict, seq: dict, out: Path) -> dict:
    """Metrics of a finished run; writes its trajectory (TUM) unless our pipeline already did."""
    from slam.evaluation.metrics import evaluate
    from slam.io.tum import write_tum

    est = np.asarray(result["poses"], dtype=np.float64)
    n = int(result["frames"])
    row.update(frames=n, failed=len(result["failed_frames"]), params=result.get("params", {}))
    if result.get("failures"):
        row["failures"] = result["failures"]
    track_s = float(result["track_s"])
    depth_s = float(np.sum(seq["stereo_ms"][:n])) / 1000.0
    row["fps"] = n / track_s if track_s > 0 else None
    row["fps_with_depth"] = n / (track_s + depth_s) if track_s + depth_s > 0 else None
    if row["method"] == "static":
        row["fps"] = row["fps_with_depth"] = None
    traj = out / "runs" / seq["name"] / row["method"] / "trajectory.txt"
    if len(est) and not row["method"].startswith("ours"):  # our pipeline wrote its own
        write_tum(traj, seq["timestamps"][: len(est)], est)
    row["trajectory"] = str(traj)
    if seq["gt"] is not None and len(est) >= 2:
        m = evaluate(seq["gt"][: len(est)], est)
        row.update({k: float(m[k]) for k in (*METRICS, "rpe_trans_std_mm", "rpe_rot_std_deg")})
        row["alignment"] = m.get("alignment")
    return row


def prepare_sequence(data: Path, out: Path, overrides: list[str], frames, name: str) -> dict:
    """Open the sequence, compute (or load) the cached stereo depth."""
    dataset = B.open_sequence(data, overrides, frames)
    key = B.depth_cache_key(data, overrides, frames)
    cache = out / "depth" / f"{name}_{dataset.camera.width}x{dataset.camera.height}_{len(dataset)}_{key}.npz"
    if not cache.is_file():
        print(f"stereo depth of {name} ({len(dataset)} frames, {dataset.camera.width}x{dataset.camera.height}) ...",
              flush=True)
    B.compute_depth_cache(data, cache, overrides, frames, progress=sys.stderr.isatty())
    with np.load(cache) as z:
        stereo_ms = z["stereo_ms"]
    return {"name": name, "data": str(data), "frames": frames, "depth": str(cache), "stereo_ms": stereo_ms,
            "gt": dataset.gt_poses, "timestamps": dataset.timestamps,
            "size": f"{dataset.camera.width}x{dataset.camera.height}", "n": len(dataset)}


# ------------------------------------------------------------------------------------------------
# tables
def _fmt(v, digits=3) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def average_rows(rows: list[dict], methods: list[str], sequences: list[str], labels: dict | None = None) -> list[dict]:
    """Per method: mean and std over the sequences it finished (crashes listed, not averaged)."""
    labels = labels or METHODS
    out = []
    for m in methods:
        done = [r for r in rows if r["method"] == m and r["status"] == "ok" and r.get("ate_rmse_mm") is not None]
        bad = [r["sequence"] for r in rows if r["method"] == m and r["status"] != "ok"]
        avg = {"method": m, "label": labels[m], "n": len(done), "of": len(sequences), "not_finished": bad,
               "failed": sum(r["failed"] for r in done)}
        for key in (*METRICS, "fps", "fps_with_depth"):
            vals = [r[key] for r in done if r.get(key) is not None]
            avg[key] = float(np.mean(vals)) if vals else None
            avg[key + "_std"] = float(np.std(vals)) if vals else None
        out.append(avg)
    return out


def format_tables(rows: list[dict], methods: list[str], sequences: list[str], notes: list[str] | None = None,
                  labels: dict | None = None) -> str:
    """Markdown: ATE per method x sequence, the averages, and every (sequence, method) row.
    A run that did not finish shows its status ("crash", "error", "timeout") in its cells."""
    labels = labels or METHODS
    by = {(r["sequence"], r["method"]): r for r in rows}
    avgs = {a["method"]: a for a in average_rows(rows, methods, sequences, labels)}

    def cell(seq, m, key="ate_rmse_mm", digits=2):
        r = by.get((seq, m))
        if r is None:
            return "-"
        if r["status"] != "ok":
            return r["status"]
        return _fmt(r.get(key), digits)

    lines = ["### ATE-RMSE (mm) per sequence", "",
             "| method | " + " | ".join(sequences) + " | average |", "|---" * (len(sequences) + 2) + "|"]
    for m in methods:
        a = avgs[m]
        avg = _fmt(a["ate_rmse_mm"], 2) + ("" if a["n"] == a["of"] else f" ({a['n']}/{a['of']})")
        lines.append(f"| {labels[m]} | " + " | ".join(cell(s, m) for s in sequences) + f" | {avg} |")
    lines += ["", "### Average over sequences (mean ± std)", "",
              "| method | ATE-RMSE mm | RPE-trans mm | RPE-rot deg | fps | fps + depth | failed frames | sequences |",
              "|---|---|---|---|---|---|---|---|"]
    for m in methods:
        a = avgs[m]

        def ms(key, d=3):
            return "-" if a[key] is None else f"{a[key]:.{d}f} ± {a[key + '_std']:.{d}f}"

        seqs = f"{a['n']}/{a['of']}" + (f" ({', '.join(a['not_finished'])} not finished)" if a["not_finished"] else "")
        lines.append(f"| {labels[m]} | {ms('ate_rmse_mm')} | {ms('rpe_trans_mm')} | {ms('rpe_rot_deg', 4)} | "
                     f"{_fmt(a['fps'], 1)} | {_fmt(a['fps_with_depth'], 1)} | {a['failed']} | {seqs} |")
    lines += ["", "### Every run", "",
              "| sequence | method | ATE-RMSE mm | RPE-trans mm | RPE-rot deg | fps | fps + depth | failed | notes |",
              "|---|---|---|---|---|---|---|---|---|"]
    for s in sequences:
        for m in methods:
            r = by.get((s, m))
            if r is None:
                continue
            if r["status"] != "ok":
                lines.append(f"| {s} | {labels[m]} | {r['status']} | {r['status']} | {r['status']} | - | - | - | "
                             f"{r.get('message', '')} |")
                continue
            lines.append(f"| {s} | {labels[m]} | {_fmt(r.get('ate_rmse_mm'))} | {_fmt(r.get('rpe_trans_mm'))} | "
                         f"{_fmt(r.get('rpe_rot_deg'), 4)} | {_fmt(r.get('fps'), 1)} | {_fmt(r.get('fps_with_depth'), 1)} | "
                         f"{r.get('failed', 0)}/{r.get('frames', 0)} | {'; '.join(r.get('notes', []))} |")
    if notes:
        lines += ["", *[f"- {n}" for n in notes]]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="Details: the module docstring (benchmarks/compare_baselines.py).")
    ap.add_argument("data", nargs="*", help="sequence folders (default: generated synthetic evaluation sequences)")
    ap.add_argument("--out", default="runs/baselines")
    ap.add_argument("--size", default=None, help="WxH: generation size of the default data (640x512), "
                                                  "resize of given DATA (native size when omitted)")
    ap.add_argument("--frames", type=int, default=None,
                    help="default data: frames per sequence (loop: twice); DATA: first N frames")
    ap.add_argument("--methods", nargs="+", default=DEFAULT_METHODS, choices=list(METHODS))
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for our pipeline and the stereo depth (e.g. depth.max_depth_mm=200)")
    ap.add_argument("--workers", type=int, default=1, help="runs in parallel (1 keeps fps comparable)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per run")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    size = parse_size(args.size)
    if args.data:
        data = [Path(d) for d in args.data]
        overrides = [*B.data_overrides(size), *args.set]
        frames = args.frames
    else:
        data = default_sequences(out, size or (640, 512), args.frames)
        overrides, frames = list(args.set), None
    names, seqs = [], []
    for d in data:
        name = d.resolve().name
        while name in names:
            name += "_"
        names.append(name)
        seqs.append(prepare_sequence(d, out, overrides, frames, name))

    notes = ["Same stereo depth for every method (ours, cached per sequence); colour = rectified left image.",
             "fps = tracking only (no frame reading, no stereo depth); fps + depth adds our stereo depth time. "
             "Shared 2-core machine: indicative.",
             f"Open3D odometry: iterations per level {B.ODOMETRY_DEFAULTS['iterations']} (coarsest first), "
             "depth_diff_max " + ", ".join(f"{v:g} mm ({k})" for k, v in B.ODOMETRY_DEFAULTS["depth_diff_max_mm"].items())
             + "; both Jacobians reported.",
             "Open3D dense SLAM: " + ", ".join(f"{k} {v}" for k, v in B.SLAM_DEFAULTS.items())
             + f"; retried with voxels x{SLAM_VOXEL_FACTORS[1]}, x{SLAM_VOXEL_FACTORS[2]} after a crash."]
    labels = dict(METHODS)
    ours_overrides: list[str] = []
    if any(m.startswith("ours") for m in args.methods):
        if learned_weights_available(args.set):
            notes.append("ours: learned weights (weights.mode=learned).")
        else:
            ours_overrides = ["weights.mode=constant"]
            notes.append("ours: CONSTANT weights (weights.mode=constant): the learned checkpoint is missing.")
            for key in ("ours_f2f", "ours_f2m"):
                labels[key] += " (constant weights)"
    if frames or args.frames:
        notes.append(f"--frames {args.frames}" + ("" if args.data else " (loop: twice as many)") + ".")

    jobs = [(m, s) for s in seqs for m in args.methods]
    print(f"{len(jobs)} runs on {len(seqs)} sequence(s)", flush=True)

    def work(item):
        m, s = item
        return run_method(m, s, overrides, ours_overrides, out, args.timeout)

    if args.workers > 1:
        with ThreadPoolExecutor(args.workers) as pool:
            rows = list(pool.map(work, jobs))
    else:
        rows = [work(j) for j in jobs]
    for r in rows:
        r["label"] = labels[r["method"]]
    table = format_tables(rows, args.methods, names, notes, labels)
    print()
    print(table)
    (out / "baselines.md").write_text(table + "\n")
    report = {"sequences": [{k: s[k] for k in ("name", "data", "frames", "depth", "size", "n")} for s in seqs],
              "methods": {m: labels[m] for m in args.methods}, "notes": notes,
              "defaults": {"odometry": B.ODOMETRY_DEFAULTS, "dense_slam": B.SLAM_DEFAULTS},
              "rows": rows, "averages": average_rows(rows, args.methods, names, labels)}
    (out / "baselines.json").write_text(json.dumps(report, indent=2, default=str))
    print(f"\nwrote {out / 'baselines.md'} and {out / 'baselines.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
