"""Frame2model's cross-check: how the model view's and the last frame's estimates of each frame
disagree, which is right, and what a flag limit catches.

    .venv/bin/python tools/cross_check.py [--seeds 9811 9812 9813] [--appearance texture=0,highlights=1,haze=0.3]
        [--scenario rigid] [--frames 150] [--size 640x512] [--limits 12.6 22.5 50 100 200]
        [--workers 2] [--out runs/cross_check]

Generates one sequence per seed (``slam synth --appearance``, ``random``: drawn from the seed) and
runs frame2model with the last frame's estimate computed on every frame but never acted on (the
model view's estimate is reported: the run is the one without the cross-check). Per frame it keeps both relative
poses (to the last frame) with their covariances and their true errors. Prints, per flag limit on
the squared Mahalanobis distance ``d2``: the share of frames flagged on the sequences whose
per-frame error stays under 1 mm and on the others, the recall of frames with an error above 0.5,
1 and 2 mm, and the mean error of the pose the frame would keep (the smaller ``sigma_t``, the
model view's or the last frame's) against always the model view's. Writes ``cross_check.md``
and ``.json``. With ``--closed-loop LIMIT`` the runs use the cross-check (``slam.tracking.cross_check``:
combining, flagging, not fusing flagged frames, rebuilding) and the table gives each sequence's
ATE and flags against the run without the cross-check and flags (``health.cross_check=0``,
``health.flag_mm=1e9``).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np


def sequence(job: dict) -> Path:
    """The job's generated sequence (made once)."""
    from benchmarks.runs import synthetic
    from slam.synth.appearance import parse_appearance

    w, h = job["size"]
    return synthetic(Path(job["out"]) / "data" / f"{job['scenario']}_{job['seed']}", job["scenario"],
                     frames=job["frames"], size=(w, h), seed=job["seed"],
                     appearance=parse_appearance(job["appearance"], job["seed"]))


def run_open_loop(job: dict) -> dict:
    """Frame2model with the cross-check computed, never acted on: per frame both estimates."""
    import torch

    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from slam.tracking.health import relative_error
    from slam.app.pipeline import Pipeline

    torch.set_num_threads(1)
    data = sequence(job)
    cfg = load_config(None, ["tracking.mode=frame2model", "health.flag_mm=1e9", "threads=1"])
    ds = open_dataset(data, cfg.data)
    pipe = Pipeline(cfg, ds, Path(job["out"]) / "runs" / f"{data.name}_open")
    acceptance = pipe.tracker.acceptance
    seen: list[dict] = []

    def recording_check(estimate, result, state):      # (records both estimates, reports the model view's)
        relative_model = np.linalg.inv(state.pose) @ result.pose
        seen.append({"position": state.position + 1, "model": relative_model, "frame": estimate.estimate.relative,
                     "cov_model": result.covariance, "cov_frame": estimate.estimate.covariance})
        return result.pose

    acceptance.combine = recording_check
    res = pipe.run(progress=False)
    gt = np.stack([g @ pipe.R1.T for g in ds.gt_poses])
    frames = []
    for s in seen:
        k = s["position"]
        truth = np.linalg.inv(gt[k - 1]) @ gt[k]
        # both estimates are relative to the last frame's estimated pose, the truth to its true pose:
        # the frame's own error is that of the motion
        e_m = float(np.linalg.norm(relative_error(s["model"], truth)[:3]))
        e_f = float(np.linalg.norm(relative_error(s["frame"], truth)[:3]))
        delta = relative_error(s["model"], s["frame"])
        d2 = float(delta @ np.linalg.solve(s["cov_model"] + s["cov_frame"], delta)) if s["cov_model"] is not None else float("nan")
        frames.append({"k": k, "err_model": e_m, "err_frame": e_f, "d2": d2,
                       "sigma_model": float(np.sqrt(np.trace(s["cov_model"][:3, :3]))) if s["cov_model"] is not None else float("nan"),
                       "sigma_frame": float(np.sqrt(np.trace(s["cov_frame"][:3, :3])))})
    return {"name": data.name, "ate_rmse_mm": res.metrics.get("ate_rmse_mm"), "frames": frames}


def run_closed_loop(job: dict) -> dict:
    """Frame2model with and without the cross-check acting at ``job['limit']``."""
    import torch

    from slam.config import load_config
    from slam.app.runner import run_from_config

    torch.set_num_threads(1)
    data = sequence(job)
    out = {"name": data.name}
    off = ["health.cross_check=0", "health.flag_mm=1e9"]       # the model view's estimate alone, no flags
    for tag, overrides in (("off", off), ("on", [f"health.cross_check={job['limit']}", *job["set"]])):
        cfg = load_config(None, ["tracking.mode=frame2model", "threads=1", *overrides])
        res = run_from_config(data, cfg, Path(job["out"]) / "runs" / f"{data.name}_{tag}{job['tag'] if tag == 'on' else ''}",
                              print_summary=False, overwrite=True)
        m = res.metrics
        out[tag] = {"ate_rmse_mm": m.get("ate_rmse_mm"), "flagged": len(m["flagged_frames"]),
                    "failed": len(m["failed_frames"]), "rebuilds": m["model_rebuilds"], "frames": m["frames"],
                    "fps": m["fps"]}
    return out


def open_loop_table(results: list[dict], limits: list[float]) -> str:
    frames = [(r["name"], f) for r in results for f in r["frames"]]
    good_seq = {r["name"] for r in results if max((f["err_model"] for f in r["frames"]), default=0) < 1.0}
    err = np.array([f["err_model"] for _, f in frames])
    err_f = np.array([f["err_frame"] for _, f in frames])
    d2 = np.array([f["d2"] for _, f in frames])
    keep_frame = np.array([f["sigma_frame"] < f["sigma_model"] for _, f in frames])
    good = np.array([n in good_seq for n, _ in frames])
    lines = [f"{len(results)} sequences, {len(frames)} frames; {len(good_seq)} sequences with every per-frame "
             f"error under 1 mm ({int(good.sum())} frames). Per-frame error of the model view's estimate: "
             f"median {np.median(err):.3f} mm, max {err.max():.2f}; the last frame's: median {np.median(err_f):.3f}, "
             f"max {err_f.max():.2f}.", "",
             "| limit d2 | flagged (good seq.) | flagged (others) | recall >0.5 mm | recall >1 mm | recall >2 mm "
             "| mean error kept / model's, flagged frames (mm) |", "|---|---|---|---|---|---|---|"]
    for L in limits:
        flag = ~(d2 <= L)
        row = [f"{L:g}", _share(flag[good]), _share(flag[~good])]
        for bar in (0.5, 1.0, 2.0):
            bad = err > bar
            row.append(f"{int((flag & bad).sum())}/{int(bad.sum())}")
        kept = np.where(keep_frame, err_f, err)
        row.append(f"{kept[flag].mean():.3f} / {err[flag].mean():.3f}" if flag.any() else "-")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def _share(x: np.ndarray) -> str:
    return f"{100 * x.mean():.1f} % ({int(x.sum())}/{x.size})" if x.size else "-"


def closed_loop_table(results: list[dict], limit: float) -> str:
    lines = [f"cross-check limit d2 = {limit:g}", "",
             "| sequence | ATE off (mm) | ATE on (mm) | flagged | rebuilds | fps off / on |", "|---|---|---|---|---|---|"]
    for r in results:
        off, on = r["off"], r["on"]
        lines.append(f"| {r['name']} | {off['ate_rmse_mm']:.3f} | {on['ate_rmse_mm']:.3f} | {on['flagged']}/{on['frames']} "
                     f"| {on['rebuilds']} | {off['fps']:.2f} / {on['fps']:.2f} |")
    a = np.array([[r["off"]["ate_rmse_mm"], r["on"]["ate_rmse_mm"]] for r in results])
    lines.append(f"| mean | {a[:, 0].mean():.3f} | {a[:, 1].mean():.3f} | | | |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", nargs="+", type=int, default=[9811, 9812, 9813])
    ap.add_argument("--appearance", default="texture=0,highlights=1,haze=0.3")
    ap.add_argument("--scenario", default="rigid")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--size", default="640x512")
    ap.add_argument("--limits", nargs="+", type=float, default=[12.6, 22.5, 50, 100, 200])
    ap.add_argument("--closed-loop", type=float, default=None, metavar="LIMIT")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="overrides of the run with the cross-check")
    ap.add_argument("--tag", default="", help="suffix of the closed-loop runs' folders")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--out", default="runs/cross_check")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    jobs = [{"seed": s, "scenario": args.scenario, "frames": args.frames, "size": (w, h), "appearance": args.appearance,
             "out": args.out, "limit": args.closed_loop, "set": args.set, "tag": args.tag} for s in args.seeds]
    fn = run_open_loop if args.closed_loop is None else run_closed_loop
    with ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn")) as pool:
        results = list(pool.map(fn, jobs))
    head = (f"`python tools/cross_check.py --seeds {' '.join(map(str, args.seeds))} --appearance {args.appearance} "
            f"--scenario {args.scenario} --frames {args.frames} --size {args.size}"
            + (f" --closed-loop {args.closed_loop:g}" + "".join(f" --set {v}" for v in args.set)
               if args.closed_loop is not None else "") + "`")
    table = open_loop_table(results, args.limits) if args.closed_loop is None else closed_loop_table(results, args.closed_loop)
    text = head + "\n\n" + table
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tag = "" if args.closed_loop is None else "_closed" + args.tag
    (out / f"cross_check{tag}.md").write_text(text + "\n")
    (out / f"cross_check{tag}.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
