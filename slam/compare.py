"""``slam compare``: both tracking modes on one sequence, a table and one plot."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np

from slam.config import SlamConfig
from slam.runner import run_from_config

COLUMNS = [("ATE-RMSE mm", "ate_rmse_mm"), ("RPE-trans mm", "rpe_trans_mm"), ("RPE-rot deg", "rpe_rot_deg"),
           ("fps", "fps"), ("failed", "failed"), ("map points", "map_points")]


def format_table(rows: dict[str, dict]) -> str:
    """A markdown table, one row per mode."""
    head = "| mode | " + " | ".join(c for c, _ in COLUMNS) + " |"
    sep = "|---" * (len(COLUMNS) + 1) + "|"
    lines = [head, sep]
    for mode, m in rows.items():
        cells = []
        for _, key in COLUMNS:
            v = len(m["failed_frames"]) if key == "failed" else m.get(key)
            cells.append("-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v)))
        lines.append(f"| {mode} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def compare(data: str | Path, config: SlamConfig, out: str | Path | None = None, frames: str | None = None) -> dict:
    """Run frame2frame and frame2model with the same settings; write ``comparison.md``,
    ``comparison.json`` and ``comparison.png`` into ``out``."""
    from slam.datasets import open_dataset
    from slam.plots import plot_comparison
    from slam.tum import read_tum

    out_dir = Path(out) if out else Path("runs") / f"{Path(data).resolve().name}_compare"
    rows, estimates = {}, {}
    for mode in ("frame2frame", "frame2model"):
        cfg = copy.deepcopy(config)
        cfg.tracking.mode = mode
        result = run_from_config(data, cfg, out_dir / mode, frames, print_summary=False)
        rows[mode] = result.metrics
        estimates[mode] = np.stack([r.pose for r in result.records])
    table = format_table(rows)
    print(table)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "comparison.md").write_text(table + "\n")
    (out_dir / "comparison.json").write_text(json.dumps(rows, indent=2))
    dataset = open_dataset(Path(data), config.data)
    if frames:
        dataset = dataset.select(frames)
    n = min(len(e) for e in estimates.values())
    gt = dataset.gt_poses[:n] if dataset.gt_poses is not None else None
    plot_comparison(out_dir / "comparison.png", gt, {k: v[:n] for k, v in estimates.items()},
                    dataset.timestamps[:n], title=f"{Path(data).name}: frame2frame vs frame2model")
    print(f"wrote {out_dir / 'comparison.md'}, {out_dir / 'comparison.png'}")
    return rows
