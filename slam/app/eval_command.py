"""``slam eval GT.txt EST.txt``: a trajectory's ATE and RPE against the ground truth, printed, and
optionally a plot and a JSON file (:mod:`slam.evaluation.metrics` computes them)."""
from __future__ import annotations

import json
from pathlib import Path

from slam.evaluation.metrics import evaluate, load_associated


def format_metrics(metrics: dict) -> str:
    """A short human-readable block of the metrics returned by :func:`evaluate`."""
    lines = [
        f"  frames         {metrics.get('frames', '?')}  (alignment: {metrics.get('alignment', '?')})",
        f"  ATE-RMSE       {metrics['ate_rmse_mm']:10.4f} mm",
        f"  RPE trans      {metrics['rpe_trans_mm']:10.4f} mm   (std {metrics['rpe_trans_std_mm']:.4f})",
        f"  RPE rot        {metrics['rpe_rot_deg']:10.4f} deg  (std {metrics['rpe_rot_std_deg']:.4f})",
    ]
    return "\n".join(lines)


def main_eval(gt_path, est_path, align_method: str = "auto", plot_path=None, json_path=None,
              max_diff: float | None = None) -> int:
    """``slam eval GT.txt EST.txt``: print the metrics; optionally save a plot / JSON.

    Returns 0; bad input raises SlamError (``EvaluationError``, ``DataError``) naming the file,
    which the command prints as one line (exit 2, as every command's input errors).
    """
    data = load_associated(gt_path, est_path, max_diff)
    metrics = evaluate(data["gt"], data["est"], align_method)
    print(f"ground truth: {gt_path} ({data['n_gt']} poses)")
    print(f"estimate:     {est_path} ({data['n_est']} poses, {metrics['frames']} matched)")
    print(format_metrics(metrics))
    if json_path is not None:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps(metrics, indent=2) + "\n")
        print(f"metrics written to {json_path}")
    if plot_path is not None:
        from slam.app.plots import plot_trajectory  # matplotlib only when asked for

        plot_trajectory(plot_path, data["est"], gt=data["gt"], timestamps=data["stamps"],
                        title=f"{Path(est_path).name} vs {Path(gt_path).name}",
                        align_method=align_method)
        print(f"plot written to {plot_path}")
    return 0
