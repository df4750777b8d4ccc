"""Trajectory figures (PNG etc.), drawn with matplotlib's Agg canvas: no window, no pyplot
state, safe on headless machines and in threads.

Layout: a "top" view spanned by the two axes of largest spread, a "side" view (largest-spread
axis against the remaining one), both in mm with equal aspect, and -- when ground truth is
given -- a panel with the per-frame translation error over time. Estimates are aligned to the
ground truth with :func:`slam.evaluation.metrics.align` first (same rule as the metrics), so what the
figure shows is what ATE measures.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from slam.evaluation import metrics as ev

AXIS_NAMES = ("x", "y", "z")
GT_STYLE = dict(color="black", linestyle="--", linewidth=1.4)
COLORS = ("tab:blue", "tab:red", "tab:green", "tab:orange", "tab:purple", "tab:brown",
          "tab:pink", "tab:olive", "tab:cyan", "tab:gray")


def _view_axes(positions: list[np.ndarray]) -> tuple[tuple[int, int], tuple[int, int]]:
    """(top, side) pairs of axis indices: top = the two axes of largest spread (extent),
    side = the largest-spread axis against the remaining one."""
    pts = np.concatenate(positions, axis=0)
    spread = np.ptp(pts, axis=0)
    order = [int(a) for a in np.argsort(-spread, kind="stable")]
    return (order[0], order[1]), (order[0], order[2])


def _draw_path(ax, xyz: np.ndarray, axes: tuple[int, int], label: str | None, style: dict) -> None:
    a, b = axes
    ax.plot(xyz[:, a], xyz[:, b], label=label, **style)
    color = style.get("color")
    ax.plot(xyz[0, a], xyz[0, b], marker="o", color=color, markersize=6, linestyle="none",
            markerfacecolor="white" if color == "black" else color)
    ax.plot(xyz[-1, a], xyz[-1, b], marker="s", color=color, markersize=6, linestyle="none",
            markerfacecolor="white" if color == "black" else color)


def _spatial_panel(ax, axes, gt_xyz, est_xyz: dict, view: str) -> None:
    if gt_xyz is not None:
        _draw_path(ax, gt_xyz, axes, "ground truth", GT_STYLE)
    for k, (name, xyz) in enumerate(est_xyz.items()):
        _draw_path(ax, xyz, axes, name, dict(color=COLORS[k % len(COLORS)], linewidth=1.2))
    ax.set_xlabel(f"{AXIS_NAMES[axes[0]]} [mm]")
    ax.set_ylabel(f"{AXIS_NAMES[axes[1]]} [mm]")
    ax.set_title(f"{view} view ({AXIS_NAMES[axes[0]]}-{AXIS_NAMES[axes[1]]})  o start, \u25a1 end",
                 fontsize=9)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)


def _time_axis(n: int, timestamps) -> tuple[np.ndarray, str]:
    if timestamps is None:
        return np.arange(n, dtype=np.float64), "frame"
    t = np.asarray(timestamps, dtype=np.float64).ravel()
    if len(t) != n:
        raise ValueError(f"timestamps: expected {n} values, got {len(t)}")
    if not np.all(np.isfinite(t)):
        raise ValueError("timestamps: non-finite values")
    return t - t[0], "time since start"


def _prepare(gt, estimates: dict, align_method: str):
    """Validate, align each estimate to gt; returns (gt or None, aligned dict, labels dict, errors dict)."""
    if not estimates:
        raise ValueError("no trajectory to plot")
    gt_arr = None if gt is None else ev._check_poses(gt, "ground truth", 1)
    aligned, labels, errors = {}, {}, {}
    for name, est in estimates.items():
        est_arr = ev._check_poses(est, f"estimate '{name}'", 1)
        if gt_arr is None:
            aligned[name], labels[name] = est_arr, name
            continue
        if len(est_arr) != len(gt_arr):
            raise ValueError(f"estimate '{name}' has {len(est_arr)} poses, ground truth {len(gt_arr)}; "
                             "associate them first")
        if len(gt_arr) >= 2:
            est_al, used = ev.align(gt_arr, est_arr, align_method)
        else:
            est_al, used = ev.align_first_pose(gt_arr, est_arr), "first"
        err = ev.per_frame_translation_error(gt_arr, est_al)
        aligned[name] = est_al
        errors[name] = err
        labels[name] = f"{name} (ATE {np.sqrt(np.mean(err ** 2)):.2f} mm, align {used})"
    return gt_arr, aligned, labels, errors


def plot_comparison(path, gt, estimates: dict, timestamps=None, title: str = "",
                    align_method: str = "auto", dpi: int = 110) -> None:
    """One figure with the ground truth (or None) and several estimated trajectories.

    Args:
        path: output image file (format from the suffix, e.g. ``.png``).
        gt: ``(N, 4, 4)`` ground truth ``T_wc`` in mm, or None.
        estimates: name -> ``(N, 4, 4)`` poses in mm (associated with ``gt`` when it is given).
        timestamps: ``(N,)`` stamps for the error panel's time axis (else frame numbers).
        align_method: see :func:`slam.evaluation.metrics.align` (each estimate aligned separately).
    """
    gt_arr, aligned, labels, errors = _prepare(gt, dict(estimates), align_method)
    est_xyz = {labels[k]: v[:, :3, 3] for k, v in aligned.items()}
    gt_xyz = None if gt_arr is None else gt_arr[:, :3, 3]
    top, side = _view_axes(([gt_xyz] if gt_xyz is not None else []) + list(est_xyz.values()))

    with_err = gt_arr is not None
    fig = Figure(figsize=(12, 9.5 if with_err else 5.5), layout="constrained")
    FigureCanvasAgg(fig)
    if with_err:
        grid = fig.add_gridspec(2, 2, height_ratios=(3, 2))
        ax_top, ax_side = fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 1])
        ax_err = fig.add_subplot(grid[1, :])
    else:
        ax_top, ax_side = fig.subplots(1, 2)
        ax_err = None
    _spatial_panel(ax_top, top, gt_xyz, est_xyz, "top")
    _spatial_panel(ax_side, side, gt_xyz, est_xyz, "side")
    ax_top.legend(fontsize=8, loc="best")

    if ax_err is not None:
        t, t_label = _time_axis(len(gt_arr), timestamps)
        for k, (name, err) in enumerate(errors.items()):
            ax_err.plot(t, err, color=COLORS[k % len(COLORS)], linewidth=1.2, label=labels[name])
        ax_err.set_xlabel(t_label)
        ax_err.set_ylabel("translation error [mm]")
        ax_err.set_title("translation error after alignment", fontsize=9)
        ax_err.set_ylim(bottom=0)
        ax_err.grid(True, alpha=0.3)
        ax_err.legend(fontsize=8, loc="upper left")
    if title:
        fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)


def plot_trajectory(path, est, gt=None, timestamps=None, title: str = "",
                    align_method: str = "auto", dpi: int = 110) -> None:
    """One estimated trajectory (mm), aligned to the ground truth when given; see
    :func:`plot_comparison` for the layout."""
    plot_comparison(path, gt, {"estimate": est}, timestamps=timestamps, title=title,
                    align_method=align_method, dpi=dpi)
