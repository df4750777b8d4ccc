"""``slam compare``: both tracking modes on one sequence, a table and one plot.

Each mode runs into its own folder (``OUT/frame2frame``, ``OUT/frame2model``) and, with
``--rerun X.rrd``, its own recording (``X_frame2frame.rrd``, ``X_frame2model.rrd``). Ctrl-C or
SIGTERM stops the command: the modes run so far are tabulated, the one cut short marked with the
frames it did, and the next mode does not start.
"""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np

from slam.config import SlamConfig
from slam.app.run_folder import check_out_dir, replaced_atomically, write_text_atomically
from slam.app.runner import exit_status, run_from_config

MODES = ("frame2frame", "frame2model")
COLUMNS = [("frames", "frames"), ("ATE-RMSE mm", "ate_rmse_mm"), ("RPE-trans mm", "rpe_trans_mm"),
           ("RPE-rot deg", "rpe_rot_deg"), ("fps", "fps"), ("failed", "failed"), ("map points", "map_points")]


def row_label(mode: str, metrics: dict, selected: int) -> str:
    """The table's name of a run: the mode, marked when the run is not a full one (interrupted
    or not a result), so that runs of different lengths are never compared unmarked."""
    notes = []
    if metrics.get("interrupted"):
        notes.append(f"interrupted: {metrics['frames']} of {selected} frames")
    if metrics.get("status", "ok") != "ok":
        notes.append(metrics["status"])
    return f"{mode} ({'; '.join(notes)})" if notes else mode


def format_table(rows: dict[str, dict], selected: int) -> str:
    """A markdown table, one row per mode (``selected``: the frames each run was given)."""
    head = "| mode | " + " | ".join(c for c, _ in COLUMNS) + " |"
    sep = "|---" * (len(COLUMNS) + 1) + "|"
    lines = [head, sep]
    for mode, m in rows.items():
        cells = []
        for _, key in COLUMNS:
            v = len(m["failed_frames"]) if key == "failed" else m.get(key)
            cells.append("-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v)))
        lines.append(f"| {row_label(mode, m, selected)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def mode_config(config: SlamConfig, mode: str) -> SlamConfig:
    """``config`` in ``mode``, its rerun recording (if any) named after the mode."""
    cfg = copy.deepcopy(config)
    cfg.tracking.mode = mode
    if cfg.logging.rerun:
        path = Path(cfg.logging.rerun)
        cfg.logging.rerun = str(path.with_name(f"{path.stem}_{mode}{path.suffix or '.rrd'}"))
    return cfg


def compare(data: str | Path, config: SlamConfig, out: str | Path | None = None, frames: str | None = None,
            overwrite: bool = False, progress: bool = True, spawn: bool = False) -> int:
    """Run frame2frame and frame2model with the same settings; write ``comparison.md``,
    ``comparison.json`` and ``comparison.png`` into ``out``. Returns the command's exit code:
    that of the first run that was stopped, else 3 when a run is not a result, else 0."""
    out_dir = Path(out) if out else Path("runs") / f"{Path(data).resolve().name}_compare"
    for mode in MODES:      # refuse before anything runs, not after the first mode
        check_out_dir(out_dir / mode, overwrite)
    rows, estimates, codes = {}, {}, []
    selected = 0
    for mode in MODES:
        result = run_from_config(data, mode_config(config, mode), out_dir / mode, frames, print_summary=False,
                                 overwrite=overwrite, progress=progress, spawn=spawn)
        rows[mode] = result.metrics
        estimates[mode] = np.stack([r.pose for r in result.records]) if result.records else np.zeros((0, 4, 4))
        selected = result.metrics["selected_frames"]
        codes.append(exit_status(result))
        if result.interrupted:
            break
    write_comparison(data, config, frames, out_dir, rows, estimates, selected)
    stopped = [c for c in codes if c >= 128]
    return stopped[0] if stopped else max(codes)


def write_comparison(data, config: SlamConfig, frames, out_dir: Path, rows: dict, estimates: dict,
                     selected: int) -> None:
    """The table (printed and written) and the plot of the runs in ``rows``."""
    from slam.io.datasets import open_dataset
    from slam.app.plots import plot_comparison

    table = format_table(rows, selected)
    print(table)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomically(out_dir / "comparison.md", table + "\n")
    write_text_atomically(out_dir / "comparison.json", json.dumps(rows, indent=2) + "\n")
    n = min(len(e) for e in estimates.values())
    if n < 2:
        print(f"wrote {out_dir / 'comparison.md'} (too few frames for a plot)")
        return
    dataset = open_dataset(Path(data), config.data)
    if frames:
        dataset = dataset.select(frames)
    gt = dataset.gt_poses[:n] if dataset.gt_poses is not None else None
    title = f"{Path(data).name}: frame2frame vs frame2model"
    if any(len(e) != n for e in estimates.values()) or n < len(dataset):
        title += f" (first {n} of {len(dataset)} frames)"
    with replaced_atomically(out_dir / "comparison.png") as tmp:
        plot_comparison(tmp, gt, {k: v[:n] for k, v in estimates.items()}, dataset.timestamps[:n], title=title)
    print(f"wrote {out_dir / 'comparison.md'}, {out_dir / 'comparison.png'}")
