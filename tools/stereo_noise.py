"""How noisy is the stereo depth, and how much of that noise changes from one frame to the next?

    .venv/bin/python tools/stereo_noise.py DATA [DATA ...] [--start 40] [--frames 20] [--set key=value ...]
        [--out runs/stereo_noise]

On synthetic sequences (``slam synth``, with ground-truth depth) it makes each frame's view as
tracking does (default config: DIS stereo, left-right check, highlight inpainting) and compares its
depth with the generator's. It prints, per sequence, the median absolute depth error (mm and pixels
of disparity), the median frame-to-frame change of that error at the same pixel (what the 3D
residual of eq. 2 sees on a static camera: the error of two independent stereo matches does not
cancel), its 90th percentile, and the median non-rigid motion of the tissue between the frames
(``nonrigid/``, where the sequence has it), so the two can be compared. Markdown and JSON are written.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def sequence_noise(data: Path, overrides: list[str], start: int, frames: int) -> dict:
    """The statistics of one sequence over frames ``start .. start + frames - 1`` (see module doc)."""
    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from slam.app.frame_view import frame_view
    from vo.odometry import StereoOdometry

    cfg = load_config(None, [*overrides])
    ds = open_dataset(data, cfg.data)
    odo = StereoOdometry(ds.camera, cfg.vo())
    fxb = ds.camera.depth_from_disparity_scale()
    stop = min(len(ds), start + frames)
    if stop - start < 2:
        raise SystemExit(f"{data}: needs at least two frames from frame {start}")
    errors, changes, changes_px, motion, depths = [], [], [], [], []
    prev_err = prev_nonrigid = None
    for k in range(start, stop):
        f = ds.frame(k)
        if f.gt_depth is None:
            raise SystemExit(f"{data}: no ground-truth depth (a synthetic sequence from `slam synth` has it)")
        # analysis.depth_source=groundtruth gives the generator's depth to the view: a zero-noise reference
        depth = frame_view(odo, f, data).depth[0, 0].numpy()
        ok = (depth > 0) & (f.gt_depth > 0)
        err = np.where(ok, depth - f.gt_depth, np.nan)
        errors.append(err[ok])
        depths.append(f.gt_depth[ok])
        if prev_err is not None:
            both = np.isfinite(err) & np.isfinite(prev_err)
            change = (err - prev_err)[both]
            changes.append(change)
            # depth error -> disparity error: d = fxb / Z, so |dd| = fxb |dZ| / Z^2
            changes_px.append(change * fxb / np.square(f.gt_depth[both]))
        nonrigid = f.extras.get("nonrigid_mm")
        if nonrigid is not None and prev_nonrigid is not None:
            motion.append(np.abs(nonrigid - prev_nonrigid)[ok])
        prev_err, prev_nonrigid = err, nonrigid
    errors, changes, changes_px, depths = (np.concatenate(v) for v in (errors, changes, changes_px, depths))
    return {
        "sequence": data.name, "frames": stop - start,
        "median_depth_mm": float(np.median(depths)),
        "median_abs_error_mm": float(np.median(np.abs(errors))),
        "median_abs_error_px": float(np.median(np.abs(errors) * fxb / np.square(depths))),
        "median_change_mm": float(np.median(np.abs(changes))),
        "p90_change_mm": float(np.percentile(np.abs(changes), 90)),
        "median_change_px": float(np.median(np.abs(changes_px))),
        "median_nonrigid_motion_mm": float(np.median(np.concatenate(motion))) if motion else None,
        "p90_nonrigid_motion_mm": float(np.percentile(np.concatenate(motion), 90)) if motion else None,
    }


def format_row(r: dict) -> str:
    motion = "-" if r["median_nonrigid_motion_mm"] is None else \
        f"{r['median_nonrigid_motion_mm']:.3f} / {r['p90_nonrigid_motion_mm']:.3f}"
    return (f"| {r['sequence']} | {r['median_depth_mm']:.1f} | {r['median_abs_error_mm']:.3f} "
            f"({r['median_abs_error_px']:.3f} px) | {r['median_change_mm']:.3f} ({r['median_change_px']:.3f} px) "
            f"| {r['p90_change_mm']:.3f} | {motion} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", nargs="+", type=Path, help="synthetic sequences (slam synth)")
    ap.add_argument("--start", type=int, default=40, help="first frame (after the exposure settles)")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--set", action="append", default=[], help="config override, e.g. correspondence.lr_check_px=0")
    ap.add_argument("--out", type=Path, default=Path("runs/stereo_noise"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = [sequence_noise(d, args.set, args.start, args.frames) for d in args.data]
    table = "\n".join([
        "| sequence | depth (mm) | median abs. depth error (mm) | median frame-to-frame change of the error (mm) "
        "| its 90th percentile (mm) | non-rigid motion per frame, median / p90 (mm) |",
        "|---|---|---|---|---|---|", *(format_row(r) for r in rows)])
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "stereo_noise.md").write_text(table + "\n")
    (args.out / "stereo_noise.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
