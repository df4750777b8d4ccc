"""The health monitor's level bound: how far above the sequence's own level (``level_z``, the
largest robust z-score of the cost, the residual medians, the plane residual and the support,
:class:`slam.tracking.health.SequenceLevel`) a frame's figures may lie before it is flagged.

    .venv/bin/python tools/calibrate_health.py [--scenarios rigid scanning] [--looks default weak]
        [--seeds 9761] [--frames 200] [--size 640x512] [--steps 1 5 10] [--modes frame2frame frame2model]
        [--bounds 4 5 6 8 10 12 16] [--false-share 0.02] [--held-out RUN:TRUTH ...] [--workers 2]
        [--out runs/calibrate_health]

Calibration: the generator's sequences (known poses) in both looks (``weak``:
``texture=0,highlights=1,haze=0.3``), tracked in both modes at 25 fps and at the fast-motion steps
(``--frames ::S``), each frame's error the translation error of its motion from the last tracked
frame (mm). From each run's ``tracking.csv`` the z-scores are computed offline by the same code
the monitor runs (the level takes every tracked frame, as online). Per figure the ranking
quality (AUC) for frames above 0.5 and 1 mm; per candidate bound the frames it would add to the
flags (of the frames under 0.5 mm that no other rule flagged: the false share) and the frames
above 1 mm left unflagged before and after. The bound chosen is the smallest whose false share
stays within ``--false-share``. ``--held-out RUN:TRUTH``: run folders never used to choose it (the
real sequence, ``slam run`` output against its reference trajectory) reported with the same
figures and the bound chosen. Writes ``calibrate_health.md`` and ``.json``.
"""
from __future__ import annotations

import argparse
import csv
import os
from pathlib import Path

import numpy as np

from benchmarks.runs import one_thread_config, pipeline, run_in_workers, synthetic, write_report

LOOKS = {"default": "", "weak": "texture=0,highlights=1,haze=0.3"}
CUES = ("cost", "residual_2d_px", "residual_3d_mm", "plane_residual_mm", "support")
BAD_MM = (0.5, 1.0)


def run_job(job: dict) -> str:
    """One ``slam run`` of the calibration (skipped where its outputs exist); its folder."""
    out = Path(job["out"])
    if not (out / "tracking.csv").is_file():
        cfg = one_thread_config([f"tracking.mode={job['mode']}"])
        pipeline(cfg, job["data"], out, frames=f"::{job['step']}").run(progress=False)
    return str(out)


def read_run(run: Path, truth_file: Path) -> dict:
    """A run's per-frame figures, flags and errors: the translation error (mm) of each frame's
    motion from the last frame tracked before it (nan for the first and failed frames), on the
    poses as tracked (``trajectory_online.txt`` where the run wrote one)."""
    from slam.evaluation.chain import motion_error_mm
    from slam.evaluation.metrics import associate, default_max_diff
    from slam.io.tum import read_tum

    with open(run / "tracking.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    online = run / "trajectory_online.txt"
    stamps, poses = read_tum(online if online.is_file() else run / "trajectory.txt")
    gt_stamps, gt = read_tum(truth_file)
    gi, ei = associate(gt_stamps, stamps, default_max_diff(gt_stamps))
    if len(ei) != len(rows):
        raise SystemExit(f"calibrate_health: error: {run}: {len(ei)} of {len(rows)} poses match {truth_file}")
    truth, est = gt[gi], poses[ei]
    failed = np.array([r["failed"] == "1" for r in rows])
    flagged = np.array([r["flagged"] == "1" for r in rows]) & ~failed
    errors = np.full(len(rows), np.nan)
    last = 0
    for k in range(1, len(rows)):
        if not failed[k]:
            errors[k] = motion_error_mm(est, truth, last, k)
            last = k

    def column(name: str) -> np.ndarray:
        return np.array([float(r.get(name) or "nan") for r in rows])

    return {"run": str(run), "failed": failed, "flagged": flagged, "errors": errors,
            "model": np.array([r["reference"] == "model" for r in rows]),
            **{name: column(name) for name in (*CUES, "sigma_t_mm", "cross_check_d2")}}


def level_scores(run: dict) -> dict:
    """Per frame the z-score of each cue and the largest (``level_z``) against the run's level,
    computed as the monitor does online (:class:`slam.tracking.health.SequenceLevel`)."""
    from slam.tracking.health import SequenceLevel

    level = SequenceLevel()
    n = len(run["errors"])
    scores = {name: np.full(n, np.nan) for name in (*CUES, "level_z")}
    for k in range(n):
        if run["failed"][k] or not np.isfinite(run["cost"][k]):
            continue
        figures = {name: run[name][k] for name in CUES}
        against_model = bool(run["model"][k])
        for name in CUES:
            scores[name][k] = level._levels[against_model][name].z(figures[name])
        scores["level_z"][k], _ = level.score(figures, against_model)
        level.add(figures, against_model)
    return scores


def auc(score: np.ndarray, bad: np.ndarray) -> float | None:
    """The probability that a bad frame scores above a good one (ties half; nan scores lowest)."""
    from scipy.stats import rankdata

    score = np.where(np.isfinite(score), score, -np.inf)
    n_bad, n_good = int(bad.sum()), int((~bad).sum())
    if not n_bad or not n_good:
        return None
    ranks = rankdata(score)
    return float((ranks[bad].sum() - n_bad * (n_bad + 1) / 2) / (n_bad * n_good))


def pooled(runs: list[dict]) -> dict:
    """Every scored frame of ``runs`` in one set of arrays (frames tracked, with an error)."""
    keys = ("errors", "flagged", "sigma_t_mm", "cross_check_d2", *CUES, "level_z")
    out = {key: [] for key in keys}
    for run in runs:
        ok = ~run["failed"] & np.isfinite(run["errors"])
        for key in keys:
            out[key].append((run["z"][key] if key in (*CUES, "level_z") else run[key])[ok])
    return {key: np.concatenate(v) if v else np.array([]) for key, v in out.items()}


def ranking(frames: dict) -> list[dict]:
    """Per cue the AUC for frames above each of ``BAD_MM``."""
    rows = []
    for name in ("level_z", *CUES, "sigma_t_mm", "cross_check_d2"):
        rows.append({"figure": name, **{f"auc_{bad}": auc(frames[name], frames["errors"] > bad) for bad in BAD_MM}})
    return rows


def bound_rows(frames: dict, bounds: list[float]) -> list[dict]:
    """Per bound: the frames it adds to the flags and the silent ones it leaves."""
    errors, flagged, z = frames["errors"], frames["flagged"], frames["level_z"]
    good = (errors < BAD_MM[0]) & ~flagged
    silent = (errors > BAD_MM[1]) & ~flagged
    rows = []
    for bound in bounds:
        adds = ~flagged & (z > bound)
        rows.append({"bound": bound, "frames": int(len(errors)), "added": int(adds.sum()),
                     "false_share": float((adds & good).sum() / max(good.sum(), 1)),
                     "silent_before": int(silent.sum()), "silent_after": int((silent & ~adds).sum()),
                     "over_0.5_added": int((adds & (errors > BAD_MM[0])).sum())})
    return rows


def choose(rows: list[dict], false_share: float) -> float | None:
    """The smallest bound whose false share stays within ``false_share``."""
    fitting = [r["bound"] for r in rows if r["false_share"] <= false_share]
    return min(fitting) if fitting else None


def _fmt(x, spec=".2f") -> str:
    return "-" if x is None else format(x, spec)


def table(groups: dict, bounds: dict, chosen: float | None, held_out: dict) -> str:
    lines = ["## Ranking (AUC) of frames above 0.5 / 1 mm", "",
             "| frames | " + " | ".join(r["figure"] for r in groups["all"]) + " |",
             "|---|" + "---|" * len(groups["all"])]
    for name, rows in {**groups, **held_out.get("ranking", {})}.items():
        lines.append(f"| {name} | " + " | ".join(f"{_fmt(r['auc_0.5'])} / {_fmt(r['auc_1.0'])}" for r in rows) + " |")
    lines += ["", f"## Bounds on level_z (chosen: {_fmt(chosen, 'g')})", "",
              "| frames | bound | scored | added flags | false share | >0.5 mm added | silent >1 mm before -> after |",
              "|---|---|---|---|---|---|---|"]
    for name, rows in {**bounds, **held_out.get("bounds", {})}.items():
        for r in rows:
            lines.append(f"| {name} | {r['bound']:g} | {r['frames']} | {r['added']} | {100 * r['false_share']:.1f} % | "
                         f"{r['over_0.5_added']} | {r['silent_before']} -> {r['silent_after']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=["rigid", "scanning"])
    ap.add_argument("--looks", nargs="+", choices=sorted(LOOKS), default=list(LOOKS))
    ap.add_argument("--seeds", nargs="+", type=int, default=[9761])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--size", default="640x512")
    ap.add_argument("--steps", nargs="+", type=int, default=[1, 5, 10])
    ap.add_argument("--modes", nargs="+", default=["frame2frame", "frame2model"])
    ap.add_argument("--bounds", nargs="+", type=float, default=[4, 5, 6, 8, 10, 12, 16])
    ap.add_argument("--false-share", type=float, default=0.02)
    ap.add_argument("--held-out", nargs="*", default=[], metavar="RUN:TRUTH")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--out", default="runs/calibrate_health")
    args = ap.parse_args(argv)
    from slam.app.cli import parse_size
    from slam.synth.appearance import parse_appearance

    out = Path(args.out)
    size = parse_size(args.size)
    jobs = []
    for scenario in args.scenarios:
        for look in args.looks:
            for seed in args.seeds:
                name = f"{scenario}-{look}-s{seed}"
                data = synthetic(out / "data" / name, scenario, frames=args.frames, size=size, seed=seed,
                                 appearance=parse_appearance(LOOKS[look] or None, seed), progress=False)
                for step in args.steps:
                    for mode in args.modes:
                        jobs.append({"data": str(data), "mode": mode, "step": step, "group": f"{mode} step {step}",
                                     "out": str(out / "runs" / f"{name}_{mode}_step{step}")})
    folders = run_in_workers(run_job, jobs, args.workers)
    runs = []
    for job, folder in zip(jobs, folders):
        run = read_run(Path(folder), Path(job["data"]) / "groundtruth.txt")
        run["z"], run["group"] = level_scores(run), job["group"]
        runs.append(run)
    groups = {"all": ranking(pooled(runs))}
    for group in sorted({r["group"] for r in runs}):
        groups[group] = ranking(pooled([r for r in runs if r["group"] == group]))
    bounds = {"all": bound_rows(pooled(runs), args.bounds)}
    chosen = choose(bounds["all"], args.false_share)
    held_out = {"ranking": {}, "bounds": {}}
    for spec in args.held_out:
        folder, truth = spec.rsplit(":", 1)
        run = read_run(Path(folder), Path(truth))
        run["z"] = level_scores(run)
        frames = pooled([run])
        name = f"held out {Path(folder).name}"
        held_out["ranking"][name] = ranking(frames)
        held_out["bounds"][name] = bound_rows(frames, [chosen] if chosen else args.bounds)
    write_report(out, "calibrate_health", table(groups, bounds, chosen, held_out),
                 {"ranking": groups, "bounds": bounds, "chosen": chosen, "held_out": held_out})


if __name__ == "__main__":
    main()
