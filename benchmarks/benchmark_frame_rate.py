"""Fast motion and gaps: the same synthetic sequences tracked at lower frame rates, and with a gap
of black or unreadable frames in the middle.

    .venv/bin/python tools/benchmark_frame_rate.py [--scenarios rigid scanning] [--seeds 9201 9202]
        [--frames 240] [--size 640x512] [--steps 1 5 10 20] [--gaps 5 10] [--gap-kinds black unreadable]
        [--gap-step 5] [--bursts 20] [--burst-frames 6] [--modes frame2frame frame2model] [--workers 2]
        [--out runs/frame_rate] [--set KEY=VALUE ...]

Each sequence is rendered once at 25 fps and tracked on every ``S``-th frame (``--frames ::S``:
at step 5 the camera moves five times as far between frames; the frame rate, read off the
timestamps, scales the per-frame thresholds). A gap: ``G`` frames of the sequence at step
``--gap-step`` (default 5 fps) from its middle on, replaced by black images (the light off, the lens
covered) or by files that cannot be read (frames dropped), in a copy of the sequence that links
every other file. A burst: the motion speeding up and slowing down again, tracked at ``--gap-step``
with ``--burst-frames`` frames at step ``B`` in the middle (``--frames 0:60:5,60:180:20,180::5``;
the frame rate, the median step, stays that of ``--gap-step``).

Per row: ATE-RMSE of every frame and of the frames tracked (a failed frame keeps the last good
pose, so a gap's frames count in the first as if the camera stood still); each frame's error, the
translation error of its motion from the last frame that was tracked (not failed) against the
ground truth's; the frames flagged and failed; the silent errors along the chain of trusted poses
(:mod:`slam.evaluation.chain`: each frame neither flagged nor failed, its position against the last
such frame before it, so that a pose carried wrong from flagged frames counts at the first trusted
frame that carries it), the largest and the count above 1 mm (the worst thing a tracker can do);
recoveries (frames relocalised); for a gap or a burst,
the first frame after it (its error, and whether it was flagged or failed) and how many frames
after it the first good frame came (unflagged, tracked, error under 1 mm). Writes ``frame_rate.md`` and
``frame_rate.json``.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from benchmarks.runs import one_thread_config, pipeline, run_in_workers, synthetic, write_report
from slam.evaluation.chain import SILENT_MM, chain_errors

STEPS = (1, 5, 10, 20)          # 25, 5, 2.5 and 1.25 fps
GAPS = (5, 10)
BURSTS = (20,)                  # 1.25 fps for a while in a 5-fps sequence
GAP_KINDS = ("black", "unreadable")


def flow_px(data: Path, step: int) -> tuple[float, float]:
    """Median and 95th percentile of the rigid flow's magnitude (pixels) between frames ``step``
    apart, from the ground-truth poses and depth (every 5th pair)."""
    import torch

    from slam.io.datasets import open_dataset
    from slam.io.rectification import original_to_rect_pose
    from vo.geometry import backproject, pixel_grid, project

    ds = open_dataset(data)
    K = torch.as_tensor(ds.camera.K, dtype=torch.float64)
    poses = original_to_rect_pose(ds.gt_poses, ds.R1)
    mags = []
    for k in range(step, len(ds), 5 * step):
        depth = torch.as_tensor(ds.frame(k).gt_depth, dtype=torch.float64)[None, None]
        T = torch.as_tensor(np.linalg.inv(poses[k - step]) @ poses[k])
        moved = torch.einsum("ij,bjhw->bihw", T[:3, :3], backproject(depth, K)) + T[:3, 3].view(1, 3, 1, 1)
        flow = project(moved, K) - pixel_grid(*depth.shape[-2:], dtype=torch.float64)
        ok = (depth[0, 0] > 0) & (moved[0, 2] > 0)
        mags.append(flow[0].norm(dim=0)[ok].numpy())
    m = np.concatenate(mags)
    return float(np.median(m)), float(np.percentile(m, 95))


def frame_files(data: Path, index: int) -> list[Path]:
    """The left and right image files of frame ``index`` of a synthetic sequence."""
    return [data / "video_frames" / f"{index:06d}{side}.png" for side in ("l", "r")]


def with_gap(data: Path, out: Path, indices: range, kind: str) -> Path:
    """A copy of the sequence ``data`` in ``out`` whose frames ``indices`` (of the 25-fps
    sequence) are black images (``black``) or empty files that cannot be read (``unreadable``);
    every other file is a link to the original."""
    import cv2

    if (out / "synth.json").is_file():
        return out
    gap = {p for i in indices for p in frame_files(data, i)}
    out.mkdir(parents=True, exist_ok=True)
    for src in sorted(data.rglob("*")):
        dst = out / src.relative_to(data)
        if src.is_dir():
            dst.mkdir(parents=True, exist_ok=True)
        elif src in gap:
            if kind == "black":
                shape = cv2.imread(str(src), cv2.IMREAD_UNCHANGED).shape
                cv2.imwrite(str(dst), np.zeros(shape, np.uint8))
            else:
                dst.write_bytes(b"")
        elif src.name != "synth.json":
            dst.symlink_to(src.resolve())
    (out / "synth.json").symlink_to((data / "synth.json").resolve())     # last: the copy is complete
    return out


def frame_errors(poses: np.ndarray, truth: np.ndarray, failed: np.ndarray) -> np.ndarray:
    """Each frame's error (mm): the translation error of its motion from the last frame before
    it that was not failed, against the ground truth's motion between the same frames (nan for the
    first frame and for failed ones).

    Args:
        poses, truth: ``(N, 4, 4)`` estimated and true ``T_wc`` (mm), the same camera.
        failed: ``(N,)`` bool.
    """
    from slam.tracking.health import relative_error

    errors = np.full(len(poses), np.nan)
    last = 0
    for k in range(1, len(poses)):
        if failed[k]:
            continue
        estimate = np.linalg.inv(poses[last]) @ poses[k]
        motion = np.linalg.inv(truth[last]) @ truth[k]
        errors[k] = float(np.linalg.norm(relative_error(estimate, motion)[:3]))
        last = k
    return errors


def run_case(job: dict) -> dict:
    """One tracking run of the benchmark: its per-frame record and summary."""
    from slam.evaluation.metrics import align, ate_rmse

    cfg = one_thread_config([f"tracking.mode={job['mode']}"], job["extra"])
    pipe = pipeline(cfg, job["data"], job["out"], frames=job["frames"] or f"::{job['step']}")
    result = pipe.run(progress=False)
    records = result.records
    poses = np.stack([r.pose for r in records])
    truth = pipe.dataset.gt_poses
    failed = np.array([r.failed for r in records])
    flagged = np.array([r.flagged for r in records]) & ~failed
    errors = frame_errors(poses, truth, failed)
    chain = chain_errors(poses, truth, ~failed & ~flagged)
    tracked = ~failed          # the ATE of the frames with a pose of their own (a failed one keeps the last)
    ate_tracked = None
    if tracked.sum() >= 3:
        aligned, _ = align(truth[tracked], poses[tracked])
        ate_tracked = ate_rmse(truth[tracked], aligned)
    relocalised = [k for k, r in enumerate(records) if r.reference == "relocalised"]
    return {**{k: job[k] for k in ("scenario", "seed", "mode", "step", "gap", "kind", "gap_from", "burst", "after")},
            "ate_rmse_mm": result.metrics.get("ate_rmse_mm"), "ate_tracked_mm": ate_tracked, "frames": len(records),
            "errors_mm": [None if np.isnan(e) else round(float(e), 5) for e in errors],
            "chain_mm": [None if np.isnan(e) else round(float(e), 5) for e in chain],
            "flagged": np.flatnonzero(flagged).tolist(), "failed": np.flatnonzero(failed).tolist(),
            "relocalised": relocalised}


def summary(case: dict) -> dict:
    """The figures of a run's row (see the module docstring)."""
    errors = np.array([np.nan if e is None else e for e in case["errors_mm"]])
    bad = np.zeros(len(errors), bool)
    bad[case["flagged"] + case["failed"]] = True
    chain = np.array([np.nan if e is None else e for e in case["chain_mm"]])
    silent = chain[np.isfinite(chain)]
    row = {"ate": case["ate_rmse_mm"], "ate_tracked": case.get("ate_tracked_mm"), "flagged": len(case["flagged"]), "failed": len(case["failed"]),
           "silent_max": float(silent.max()) if silent.size else 0.0,
           "silent_over": int((silent > SILENT_MM).sum()), "recoveries": len(case["relocalised"]),
           "frames": case["frames"]}
    if case.get("after") is not None:
        after = case["after"]                        # the first frame after the gap or burst (selected positions)
        state = "failed" if after in case["failed"] else "flagged" if after in case["flagged"] else "tracked"
        row["first_after"] = (float(errors[after]) if np.isfinite(errors[after]) else None, state)
        good = [k for k in range(after, len(errors))
                if not bad[k] and np.isfinite(errors[k]) and errors[k] < SILENT_MM]
        row["back_after"] = good[0] - after + 1 if good else None
    return row


def _fmt(x, spec=".3f") -> str:
    return "-" if x is None else format(x, spec)


def table(cases: list[dict], flows: dict) -> str:
    head = ["sequence", "mode", "condition", "flow px median / p95", "ATE mm (tracked frames)", "flagged / failed / frames",
            "silent: max mm (> 1 mm)", "recoveries", "first after the gap or burst: mm (state)", "good again after"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for c in cases:
        s = summary(c)
        cond = f"{25 / c['step']:g} fps"
        if c["gap"]:
            cond = f"gap {c['gap']} {c['kind']} at {cond}"
        elif c.get("burst"):
            cond = f"{c['after'] - c['gap_from'] - 1} frames at {25 / c['burst']:g} fps in {cond}"
        med, p95 = flows[(c["scenario"], c["seed"], c.get("burst") or c["step"])]
        ended = c.get("after") is not None
        first = "-" if not ended else f"{_fmt(s['first_after'][0])} ({s['first_after'][1]})"
        back = "-" if not ended else (f"{s['back_after']} frames" if s["back_after"] else "never")
        lines.append("| " + " | ".join([
            f"{c['scenario']} s{c['seed']}", c["mode"], cond, f"{med:.1f} / {p95:.1f}", f"{_fmt(s['ate'])} ({_fmt(s['ate_tracked'])})",
            f"{s['flagged']} / {s['failed']} / {s['frames']}", f"{s['silent_max']:.2f} ({s['silent_over']})",
            str(s["recoveries"]), first, back]) + " |")
    return "\n".join(lines)


def jobs_for(data: Path, out: Path, scenario: str, seed: int, args) -> list[dict]:
    """The runs of one sequence: every step, then every gap at ``args.gap_step``."""
    base = {"scenario": scenario, "seed": seed, "extra": args.set, "gap": 0, "kind": "", "gap_from": None,
            "burst": 0, "after": None, "frames": None}
    jobs = []
    for step in args.steps:
        for mode in args.modes:
            jobs.append({**base, "mode": mode, "step": step, "data": str(data),
                         "out": str(out / "runs" / f"{data.name}_{mode}_step{step}")})
    selected = len(range(0, args.frames, args.gap_step))
    for gap in args.gaps:
        start = (selected - gap) // 2               # selected positions [start, start + gap)
        if start < 2:
            raise SystemExit(f"--gaps {gap}: a sequence of {selected} frames at step {args.gap_step} is too short")
        blanked = range(start * args.gap_step, (start + gap) * args.gap_step)
        for kind in args.gap_kinds:
            copy = with_gap(data, out / "data" / f"{data.name}_gap{gap}_{kind}", blanked, kind)
            for mode in args.modes:
                jobs.append({**base, "mode": mode, "step": args.gap_step, "gap": gap, "kind": kind,
                             "gap_from": start, "after": start + gap, "data": str(copy),
                             "out": str(out / "runs" / f"{copy.name}_{mode}")})
    for burst in args.bursts:
        frames, start = burst_selection(args.frames, args.gap_step, burst, args.burst_frames)
        for mode in args.modes:
            jobs.append({**base, "mode": mode, "step": args.gap_step, "burst": burst, "frames": frames,
                         "gap_from": start, "after": start + args.burst_frames + 1, "data": str(data),
                         "out": str(out / "runs" / f"{data.name}_{mode}_burst{burst}")})
    return jobs


def burst_selection(frames: int, step: int, burst: int, count: int) -> tuple[str, int]:
    """The ``--frames`` selection of a sequence of ``frames`` tracked at ``step`` with ``count``
    motions at step ``burst`` in its middle, and the selected position of the frame they start from
    (the first frame after the burst, the first whose motion is slow again, is ``count + 1`` later)."""
    span = count * burst
    first = (frames - span) // 2 // step * step
    if first < 2 * step or first + span >= frames - 2 * step:
        raise SystemExit(f"--burst-frames {count} at step {burst}: a sequence of {frames} frames is too short")
    return f"0:{first}:{step},{first}:{first + span}:{burst},{first + span}::{step}", len(range(0, first, step))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=["rigid", "scanning"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[9201, 9202])
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--size", default="640x512")
    ap.add_argument("--steps", nargs="*", type=int, default=list(STEPS))
    ap.add_argument("--gaps", nargs="*", type=int, default=list(GAPS))
    ap.add_argument("--gap-kinds", nargs="+", choices=GAP_KINDS, default=list(GAP_KINDS))
    ap.add_argument("--gap-step", type=int, default=5, help="the step the gap and burst sequences are tracked at")
    ap.add_argument("--bursts", nargs="*", type=int, default=list(BURSTS), help="the steps of the bursts")
    ap.add_argument("--burst-frames", type=int, default=6, help="how many frames a burst has")
    ap.add_argument("--modes", nargs="+", default=["frame2frame", "frame2model"])
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--out", default="runs/frame_rate")
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args(argv)
    from slam.app.cli import parse_size

    out = Path(args.out)
    size = parse_size(args.size)
    jobs, flows = [], {}
    for scenario in args.scenarios:
        for seed in args.seeds:
            data = synthetic(out / "data" / f"{scenario}_s{seed}_{size[0]}x{size[1]}_{args.frames}", scenario,
                             frames=args.frames, size=size, seed=seed, progress=False)
            for step in sorted({*args.steps, *args.bursts, args.gap_step}):
                flows[(scenario, seed, step)] = flow_px(data, step)
            jobs += jobs_for(data, out, scenario, seed, args)
    cases = run_in_workers(run_case, jobs, args.workers)
    write_report(out, "frame_rate", table(cases, flows),
                 {"cases": cases, "summaries": [summary(c) for c in cases],
                  "flow_px": {f"{k[0]}_s{k[1]}_step{k[2]}": v for k, v in flows.items()}})
