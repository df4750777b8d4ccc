"""Which health figure tells a wrong pose: each figure of tracking.csv against the frame's true
relative pose error.

    .venv/bin/python tools/health_cues.py RUN [RUN ...] [--bad-mm 0.1] [--out runs/health_cues]

Each RUN is a ``slam run`` output folder of a sequence with ground truth (its ``config.yaml``
names the data). Per frame the error is the translation of ``log(est_rel gt_rel^-1)``, the
frame's motion from its reference frame against the ground truth's. Prints per figure of
``slam.tracking.health.FIGURES`` the Spearman rank correlation with the error over all frames, and the
area under the ROC curve (AUC: 0.5 is chance, 1 separates perfectly) for telling frames whose
error exceeds ``--bad-mm`` (default: the 90th percentile of all errors) from the others. Writes
``health_cues.md`` and ``.json``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import rankdata, spearmanr


def frame_errors(run: Path) -> tuple[dict, np.ndarray]:
    """The run's tracking.csv columns and each frame's relative translation error (mm, nan where
    there is no reference or ground truth)."""
    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from slam.tracking.health import relative_error
    from slam.app.tracking_csv import read_tracking_csv
    from slam.io.tum import read_tum

    rows = read_tracking_csv(run / "tracking.csv")
    cfg = load_config(run / "config.yaml", [])
    data = Path(json.loads((run / "metrics.json").read_text())["data"])
    ds = open_dataset(data, cfg.data)
    gt = ds.gt_poses
    _, est = read_tum(run / "trajectory.txt")          # mm
    if gt is None or len(est) != len(ds) or len(rows["frame"]) != len(ds):
        raise SystemExit(f"{run}: needs a run over every frame of a sequence with ground truth ({data})")
    pos = {int(f): k for k, f in enumerate(ds.indices)}
    errors = np.full(len(rows["frame"]), np.nan)
    for k, ref in enumerate(rows["reference_frame"]):
        if not np.isfinite(ref) or rows["failed"][k]:
            continue
        r = pos[int(ref)]
        truth = np.linalg.inv(gt[r]) @ gt[k]
        estimate = np.linalg.inv(est[r]) @ est[k]
        errors[k] = float(np.linalg.norm(relative_error(estimate, truth)[:3]))
    return rows, errors


def auc(scores: np.ndarray, bad: np.ndarray) -> float:
    """Area under the ROC curve of ``scores`` (higher = more suspicious) for the ``bad`` frames."""
    n_bad, n_good = int(bad.sum()), int((~bad).sum())
    if not n_bad or not n_good:
        return float("nan")
    ranks = rankdata(scores)
    return float((ranks[bad].sum() - n_bad * (n_bad + 1) / 2) / (n_bad * n_good))


def main() -> None:
    from slam.tracking.health import FIGURES

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--bad-mm", type=float, default=None)
    ap.add_argument("--out", default="runs/health_cues")
    args = ap.parse_args()
    pooled: dict = {name: [] for name in FIGURES}
    errs = []
    for run in args.runs:
        rows, e = frame_errors(run)
        for name in FIGURES:
            pooled[name].append(rows[name])
        errs.append(e)
    err = np.concatenate(errs)
    bad_mm = args.bad_mm if args.bad_mm is not None else float(np.nanpercentile(err, 90))
    lines = [f"frames {int(np.isfinite(err).sum())}, error median {np.nanmedian(err):.3f} mm, "
             f"bad: above {bad_mm:.3f} mm ({int((err > bad_mm).sum())} frames)", "",
             "| figure | Spearman with the error | AUC for bad frames |", "|---|---|---|"]
    table = []
    for name in FIGURES:
        if name == "nees":
            continue
        x = np.concatenate(pooled[name])
        ok = np.isfinite(x) & np.isfinite(err)
        if ok.sum() < 5:
            continue
        rho = float(spearmanr(x[ok], err[ok]).statistic)
        a = auc(x[ok], err[ok] > bad_mm)
        table.append({"figure": name, "spearman": rho, "auc": a})
        lines.append(f"| {name} | {rho:.2f} | {a:.2f} |")
    text = "\n".join(lines)
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "health_cues.md").write_text(text + "\n")
    (out / "health_cues.json").write_text(json.dumps({"bad_mm": bad_mm, "figures": table}, indent=2))


if __name__ == "__main__":
    main()
