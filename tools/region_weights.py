"""Could a weight that knows only *where* the tissue is meet the moving-tissue check?

    .venv/bin/python tools/region_weights.py DATA [DATA ...] [--keep 0.5 0.25] [--out runs/region_weights]

The paper says its weight maps learn "which regions are more affected by breathing" (Sec. 3.3):
a weight per tissue region, the same in every frame, not a detector of each frame pair's motion.
On synthetic sequences with a static camera (breathing, deforming: ``nonrigid/`` ground truth)
this tool builds the ideal such weight: 1 on the share ``keep`` of the view whose largest
non-rigid displacement over the sequence is smallest, 0 on the rest. It prints the ratio the
issue's check asks about (mean weight on pixels displaced from the rest shape by more than 0.5 mm
over the mean on the others, all frames pooled); below 0.5 meets it. Instrument pixels (``masks/``)
are left out. Markdown and JSON are written.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

THRESHOLD_MM = 0.5


def region_ratio(nonrigid: np.ndarray, tissue: np.ndarray, keep: float, threshold_mm: float = THRESHOLD_MM) -> float | None:
    """The check's ratio for the ideal region weight.

    Args:
        nonrigid: ``(T, H, W)`` non-rigid displacement from the rest shape, mm, of a static-camera
            sequence (a pixel sees the same tissue in every frame).
        tissue: ``(T, H, W)`` bool, False where the instrument covers the tissue.
        keep: share of the view (pixels that are tissue in every frame) given weight 1.

    Returns:
        mean weight on displaced tissue / mean weight on the rest, or None if either set is empty.
    """
    peak = np.where(tissue, nonrigid, 0.0).max(0)
    always = tissue.all(0)
    if not always.any():
        return None
    limit = np.quantile(peak[always], keep)
    weight = np.broadcast_to(peak <= limit, nonrigid.shape)
    moving, still = tissue & (nonrigid > threshold_mm), tissue & (nonrigid <= threshold_mm)
    if not moving.any() or not still.any():
        return None
    return float(weight[moving].mean() / max(weight[still].mean(), 1e-12))


def read_sequence(data: Path) -> tuple[np.ndarray, np.ndarray]:
    """``nonrigid`` (mm) and ``tissue`` stacks ``(T, H, W)`` of a synthetic sequence folder."""
    from slam.io.datasets.dataset import read_scaled_uint
    from slam.io.datasets.stereomis import read_depth_scale

    files = sorted((data / "nonrigid").glob("*l.png"))
    if not files:
        raise SystemExit(f"{data}: no nonrigid/ ground truth (a synthetic sequence from `slam synth` is needed)")
    scale = read_depth_scale(data / "synth.json")  # nonrigid/ is written in the depth's units
    nonrigid = np.stack([read_scaled_uint(f, scale) for f in files])
    masks = [data / "masks" / f.name for f in files]
    if all(m.is_file() for m in masks):
        tissue = np.stack([cv2.imread(str(m), cv2.IMREAD_GRAYSCALE) > 0 for m in masks])
    else:
        tissue = np.ones(nonrigid.shape, bool)
    return nonrigid, tissue


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", nargs="+", type=Path)
    ap.add_argument("--keep", nargs="+", type=float, default=[0.5, 0.25])
    ap.add_argument("--out", type=Path, default=Path("runs/region_weights"))
    args = ap.parse_args()
    rows = []
    for data in args.data:
        nonrigid, tissue = read_sequence(data)
        row = {"sequence": data.name, "displaced_share": float((tissue & (nonrigid > THRESHOLD_MM)).mean())}
        row.update({f"keep {k:g}": region_ratio(nonrigid, tissue, k) for k in args.keep})
        rows.append(row)
    keys = [f"keep {k:g}" for k in args.keep]
    lines = ["| sequence | share displaced > 0.5 mm | " + " | ".join(f"ratio, {k} of the view kept" for k in keys) + " |",
             "|---" * (len(keys) + 2) + "|"]
    lines += [f"| {r['sequence']} | {r['displaced_share']:.2f} | " +
              " | ".join("-" if r[k] is None else f"{r[k]:.2f}" for k in keys) + " |" for r in rows]
    table = "\n".join(lines)
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "region_weights.md").write_text(table + "\n")
    (args.out / "region_weights.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
