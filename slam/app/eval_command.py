"""``slam eval GT.txt EST.txt``: a trajectory's ATE and RPE against the ground truth, printed, and
optionally a plot and a JSON file (:mod:`slam.evaluation.metrics` computes them); with ``--map
MAP.ply --points REF.ply`` also the map's error against a reference reconstruction's points (each
point's distance to the nearest map point, the map moved by the trajectory's alignment;
:func:`slam.evaluation.map_error.reference_point_errors`)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from slam.app.run_folder import replaced_atomically, write_text_atomically
from slam.errors import SlamError
from slam.evaluation.metrics import align, alignment_transform, evaluate, load_associated


def format_metrics(metrics: dict) -> str:
    """A short human-readable block of the metrics returned by :func:`evaluate`."""
    lines = [
        f"  frames         {metrics.get('frames', '?')}  (alignment: {metrics.get('alignment', '?')})",
        f"  ATE-RMSE       {metrics['ate_rmse_mm']:10.4f} mm",
        f"  RPE trans      {metrics['rpe_trans_mm']:10.4f} mm   (std {metrics['rpe_trans_std_mm']:.4f})",
        f"  RPE rot        {metrics['rpe_rot_deg']:10.4f} deg  (std {metrics['rpe_rot_std_deg']:.4f})",
    ]
    return "\n".join(lines)


def map_metrics(data: dict, align_method: str, cloud: np.ndarray, reference: np.ndarray) -> dict:
    """A map's points ``cloud`` ``(M, 3)`` (mm, the estimate's world frame) against a reference's
    points ``reference`` ``(R, 3)`` (mm, the ground truth's world frame), after the alignment of
    the associated trajectories ``data``: ``map_median_mm``, ``map_within_1mm`` (share),
    ``map_points`` (the reference's)."""
    from slam.evaluation.map_error import reference_point_errors

    aligned, _ = align(data["gt"], data["est"], align_method)
    A = alignment_transform(data["est"], aligned)
    errors = reference_point_errors(reference, cloud @ A[:3, :3].T + A[:3, 3])
    return {"map_median_mm": errors["median_mm"], "map_within_1mm": errors["within"], "map_points": errors["points"]}


def main_eval(gt_path, est_path, align_method: str = "auto", plot_path=None, json_path=None,
              max_diff: float | None = None, map_path=None, points_path=None) -> int:
    """``slam eval GT.txt EST.txt``: print the metrics; optionally save a plot / JSON.

    Returns 0; bad input raises SlamError (``EvaluationError``, ``DataError``) naming the file,
    which the command prints as one line (exit 2, as every command's input errors).
    """
    if (map_path is None) != (points_path is None):
        raise SlamError("--map and --points go together: the map (the estimate's world frame) and the reference points")
    data = load_associated(gt_path, est_path, max_diff)
    if map_path is not None:
        from slam.evaluation.map_error import read_points_mm

        cloud, reference = read_points_mm(map_path), read_points_mm(points_path)
    metrics = evaluate(data["gt"], data["est"], align_method)
    print(f"ground truth: {gt_path} ({data['n_gt']} poses)")
    print(f"estimate:     {est_path} ({data['n_est']} poses, {metrics['frames']} matched)")
    print(format_metrics(metrics))
    if map_path is not None:
        metrics.update(map_metrics(data, align_method, cloud, reference))
        print(f"  map error      {metrics['map_median_mm']:10.4f} mm median over {metrics['map_points']} reference "
              f"points, {100 * metrics['map_within_1mm']:.1f} % within 1 mm")
    if json_path is not None:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        write_text_atomically(Path(json_path), json.dumps(metrics, indent=2) + "\n")
        print(f"metrics written to {json_path}")
    if plot_path is not None:
        from slam.app.plots import plot_trajectory  # matplotlib only when asked for

        Path(plot_path).parent.mkdir(parents=True, exist_ok=True)
        with replaced_atomically(Path(plot_path)) as tmp:
            plot_trajectory(tmp, data["est"], gt=data["gt"], timestamps=data["stamps"],
                            title=f"{Path(est_path).name} vs {Path(gt_path).name}", align_method=align_method)
        print(f"plot written to {plot_path}")
    return 0
