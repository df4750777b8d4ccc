"""A run's figure: the fused map seen along the camera's mean viewing direction with the camera's
path drawn over it, beside the estimated trajectory against the ground truth.

    .venv/bin/python tools/make_figure.py RUN_DIR [--gt GROUNDTRUTH.txt] [--out FIGURE.png]

``RUN_DIR`` is a ``slam run`` output folder with ``map.ply`` (frame2model, or ``--export-map``) and
``trajectory.txt``; ``--gt`` adds the sequence's ground truth. The README's picture is made with

    .venv/bin/slam synth runs/demo_data --scenario scanning --frames 100 --size 320x256 --seed 7
    .venv/bin/slam run runs/demo_data --mode frame2model --out runs/demo
    .venv/bin/python tools/make_figure.py runs/demo --gt runs/demo_data/groundtruth.txt --out docs/demo.png
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def map_panel(ax, points: np.ndarray, colours: np.ndarray, poses: np.ndarray) -> None:
    """The map's points ``(N, 3)`` mm with colours ``(N, 3)`` in [0, 1] projected orthographically
    along the cameras' mean optical axis (nearest points drawn last), and the camera centres of
    ``poses`` ``(T, 4, 4)`` (camera to world, mm) over them."""
    axis = poses[:, :3, 2].mean(0)
    axis /= np.linalg.norm(axis)
    right = poses[:, :3, 0].mean(0)
    right -= axis * (right @ axis)
    right /= np.linalg.norm(right)
    down = np.cross(axis, right)
    depth = points @ axis
    order = np.argsort(-depth)          # far first: the visible surface is drawn last
    u, v = points @ right, points @ down
    ax.scatter(u[order], v[order], c=colours[order], s=0.6, marker="s", linewidths=0, rasterized=True)
    centres = poses[:, :3, 3]
    ax.plot(centres @ right, centres @ down, color="tab:blue", linewidth=1.5, label="camera path")
    ax.plot(*(centres[0] @ np.stack([right, down], 1)), "o", color="tab:blue", markersize=5)
    ax.set_aspect("equal")
    ax.invert_yaxis()
    ax.set_xlabel("mm")
    ax.set_ylabel("mm")
    ax.set_title(f"fused map, {len(points):,} points", fontsize=10)
    ax.legend(loc="lower right", fontsize=8)


def trajectory_panel(ax, est: np.ndarray, gt: np.ndarray | None) -> str:
    """The estimated camera centres against the ground truth (aligned as ATE aligns them), in the
    plane of their two largest spreads; returns a caption with the ATE."""
    from slam.evaluation import metrics as ev

    caption = ""
    if gt is not None:
        caption = f"ATE-RMSE {ev.evaluate(gt, est)['ate_rmse_mm']:.2f} mm"
        est, _ = ev.align(gt, est)
    xyz = est[:, :3, 3]
    ref = gt[:, :3, 3] if gt is not None else xyz
    a, b = np.argsort(-np.ptp(ref, axis=0))[:2]
    if gt is not None:
        ax.plot(ref[:, a], ref[:, b], "k--", linewidth=1.3, label="ground truth")
    ax.plot(xyz[:, a], xyz[:, b], color="tab:red", linewidth=1.2, label="estimate")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.set_xlabel(f"{'xyz'[a]} [mm]")
    ax.set_ylabel(f"{'xyz'[b]} [mm]")
    ax.set_title(f"trajectory ({caption})" if caption else "trajectory", fontsize=10)
    ax.legend(fontsize=8)
    return caption


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a slam run output folder (map.ply, trajectory.txt)")
    ap.add_argument("--gt", type=Path, help="ground-truth TUM file")
    ap.add_argument("--out", type=Path, help="figure file (default RUN/figure.png)")
    ap.add_argument("--points", type=int, default=60000, help="map points drawn at most (evenly sampled)")
    args = ap.parse_args(argv)
    import open3d as o3d
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from slam.io.tum import read_tum

    ply, traj = args.run / "map.ply", args.run / "trajectory.txt"
    for path in (ply, traj):
        if not path.is_file():
            print(f"{path}: not found (run `slam run ... --mode frame2model` or add --export-map)", file=sys.stderr)
            return 2
    cloud = o3d.io.read_point_cloud(str(ply))
    points, colours = np.asarray(cloud.points) * 1000.0, np.asarray(cloud.colors)
    if len(points) == 0:
        print(f"{ply}: the map is empty", file=sys.stderr)
        return 2
    step = max(1, len(points) // args.points)
    points, colours = points[::step], colours[::step]
    _, est = read_tum(traj)
    gt = read_tum(args.gt)[1] if args.gt else None
    fig = Figure(figsize=(10, 4.6), dpi=100)
    FigureCanvasAgg(fig)
    left, right = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.25, 1]})
    map_panel(left, points, colours, est)
    trajectory_panel(right, est, gt)
    fig.tight_layout()
    out = args.out or args.run / "figure.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
