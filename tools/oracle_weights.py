"""What would the weight maps gain by knowing which tissue moves? An oracle check on synthetic
sequences with the generator's non-rigid ground truth (``nonrigid/``).

    .venv/bin/python tools/oracle_weights.py DATA [DATA ...] [--gaps 1 5] [--thresholds 0.01 0.02 0.05]
        [--rest-scales 0.3 0] [--set weights.mode=learned ...] [--out runs/oracle_weights]

For frame pairs ``gap`` frames apart, the VO's pose is solved with the weights of the run's config
(learned 2D&3D by default), then again with w3D set to zero on the pixels whose tissue moved
non-rigidly between the two frames by more than a threshold (per-pair motion: the change of the
non-rigid displacement along the flow; exact for breathing, whose displacement keeps its
direction), and with both w2D and w3D zero there.  With ``--rest-scales F``, also with w3D times F
on the pixels the issue's check counts as moving (displaced from the rest shape by more than 0.5
mm: a w3D that meets the check by construction), as is, with the frame's total w3D kept (the
removed weight moved onto the other pixels), and with w2D times F there too.  It prints, per sequence, gap and weighting, the
mean translation error per pair (what the training loss of eq. 7 sees) and, for gap 1, the ATE of
the chained poses (first pose aligned; the static-camera ATE is what drifts).  It also reports the
learned w3D's ratio between moving and still pixels (by per-pair motion and by displacement from
the rest shape, the issue's check).  Tables are printed and written as markdown and JSON.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def run_sequence(data: Path, overrides: list[str], gaps: list[int], thresholds: list[float],
                 rest_scales: list[float] = ()) -> list[dict]:
    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from slam.errors import SlamError
    from slam.app.frame_view import frame_view
    from slam.training.trainer import relative_rect_transform
    from vo.geometry import change_along_flow
    from vo.odometry import StereoOdometry

    cfg = load_config(None, [*overrides])
    ds = open_dataset(data, cfg.data)
    if ds.gt_poses is None:
        raise SystemExit(f"{data}: needs groundtruth.txt")
    setting: dict = {}

    def oracle(cur, ref, flow, w2, w3):
        motion = change_along_flow(setting["cur"], setting["ref"], flow)
        if setting["mask"] == "none":          # the learned w3D where it weighs a pixel
            sel = w3 > 0
            setting["stats"].append((w3[sel], motion[sel], setting["cur"][sel]))
            return w2, w3
        if "rest" in setting["mask"]:   # the check met by construction: w3D (and w2D) scaled where displaced
            factor = torch.where(setting["cur"] > 0.5, setting["threshold"], 1.0).to(w3.dtype)
            scaled = w3 * factor
            if setting["mask"] == "w3D rest, same total":   # the 3D term keeps its weight, moved onto the rest
                scaled = scaled * (w3.sum() / scaled.sum().clamp(min=1e-12))
            return (w2 * factor if setting["mask"] == "w2D & w3D rest" else w2), scaled
        keep = (motion <= setting["threshold"]).to(w3.dtype)
        return (w2 * keep if setting["mask"] == "w2D & w3D" else w2), w3 * keep

    odo = StereoOdometry(ds.camera, cfg.vo(), weight_hook=oracle)
    views, nonrigid = [], []
    for k in range(len(ds)):
        f = ds.frame(k)
        if "nonrigid_mm" not in f.extras:
            raise SystemExit(f"{data}: no nonrigid/ ground truth (write it with `slam synth`)")
        try:
            views.append(frame_view(odo, f, data))       # depth.source: stereo or the generator's
        except SlamError as err:
            raise SystemExit(str(err)) from None
        nonrigid.append(torch.from_numpy(f.extras["nonrigid_mm"])[None, None].float())
    rows = []
    for gap in gaps:
        masks = ([("none", 0.0)] + [("w3D", t) for t in thresholds] + [("w2D & w3D", thresholds[0])]
                 + [(kind, f) for f in rest_scales for kind in ("w3D rest", "w3D rest, same total", "w2D & w3D rest")])
        for mask, threshold in masks:
            setting.update(mask=mask, threshold=threshold, stats=[])
            errors, T, T_gt, dev = [], np.eye(4), np.eye(4), []
            for k in range(gap, len(ds)):
                setting["cur"], setting["ref"] = nonrigid[k], nonrigid[k - gap]
                # with depth.temporal_gain < 1 each frame's depth is filtered against its reference
                ref = views[k - gap]
                result = odo.track(views[k], ref, filter_against=ref if odo.filters_depth() else None)
                rel_gt = relative_rect_transform(ds.gt_poses, ds.R1, k - gap, k)
                errors.append(float(np.linalg.norm(result.relative[:3, 3] - rel_gt[:3, 3])))
                if gap == 1:
                    T, T_gt = T @ result.relative, T_gt @ rel_gt
                    dev.append(float(np.linalg.norm(T[:3, 3] - T_gt[:3, 3])))
            row = {"sequence": data.name, "gap": gap, "mask": mask, "threshold_mm": threshold,
                   "pair_error_mm": float(np.mean(errors)),
                   "chained_ate_mm": float(np.sqrt(np.mean(np.square(dev)))) if dev else None}
            if mask == "none":
                row.update(weight_ratios(setting["stats"], thresholds))
            rows.append(row)
            print(format_row(row), flush=True)
    return rows


def weight_ratios(stats: list, thresholds: list[float]) -> dict:
    """Mean learned w3D on moving over still pixels: by per-pair motion (each threshold) and by
    displacement from the rest shape above 0.5 mm.  ``stats``: per pair, the weighed pixels' w3D,
    per-pair motion and displacement, 1-D tensors."""
    w3, motion, rest = (torch.cat([s[i] for s in stats]).numpy() for i in range(3))
    out = {}
    for name, moving in [(f"pair>{t}", motion > t) for t in thresholds] + [("rest>0.5", rest > 0.5)]:
        if moving.any() and (~moving).any():
            out[f"w3d_ratio_{name}"] = float(w3[moving].mean() / max(w3[~moving].mean(), 1e-12))
            out[f"share_{name}"] = float(moving.mean())
    out.update(detector_ratios(motion, rest, thresholds))
    return out


def detector_ratios(motion, rest, thresholds: list[float]) -> dict:
    """The issue's ratio (mean weight on pixels displaced from the rest shape by more than 0.5 mm
    over the mean on the others) for an ideal detector of per-pair motion, weight ``1`` where the
    tissue moved by at most ``t`` mm between the two frames and ``0`` elsewhere: how fine a motion
    a weight map of one frame pair must tell apart to meet the check.  ``motion``, ``rest``:
    1-D arrays of per-pair motion and displacement from the rest shape (mm)."""
    displaced = rest > 0.5
    out = {}
    if displaced.any() and (~displaced).any():
        for t in thresholds:
            kept = motion <= t
            out[f"detector_ratio_pair<={t}"] = float(kept[displaced].mean() / max(kept[~displaced].mean(), 1e-12))
    return out


def format_row(r: dict) -> str:
    ate = f"{r['chained_ate_mm']:.3f}" if r["chained_ate_mm"] is not None else "-"
    mask = (r["mask"] if r["mask"] == "none" else
            f"w3D x {r['threshold_mm']:g} where displaced from rest > 0.5 mm" if r["mask"] == "w3D rest" else
            f"w3D x {r['threshold_mm']:g} where displaced from rest > 0.5 mm, same total" if r["mask"] == "w3D rest, same total" else
            f"w2D and w3D x {r['threshold_mm']:g} where displaced from rest > 0.5 mm" if r["mask"] == "w2D & w3D rest" else
            f"{r['mask']} = 0 where motion > {r['threshold_mm']:g} mm")
    return f"| {r['sequence']} | {r['gap']} | {mask} | {r['pair_error_mm']:.4f} | {ate} |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", nargs="+", type=Path, help="synthetic sequences (slam synth) with nonrigid/")
    ap.add_argument("--gaps", nargs="+", type=int, default=[1, 5])
    ap.add_argument("--thresholds", nargs="+", type=float, default=[0.01, 0.02, 0.05])
    ap.add_argument("--rest-scales", nargs="*", type=float, default=[],
                    help="also solve with w3D multiplied by each factor on pixels displaced from the rest shape by "
                         "more than 0.5 mm (a w3D below half the rest's on displaced tissue by construction), as is, with the "
                         "frame's total w3D kept, and with w2D multiplied too")
    ap.add_argument("--set", action="append", default=[], help="config override, e.g. weights.mode=constant")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("runs/oracle_weights"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    header = ("| sequence | gap | weights | translation error per pair (mm) | ATE of the chained poses (mm) |\n"
              "|---|---|---|---|---|")
    print(header)
    rows = [r for data in args.data for r in run_sequence(data, args.set, args.gaps, args.thresholds, args.rest_scales)]
    ratio_keys = sorted({k for r in rows for k in r if k.startswith("w3d_ratio_")})
    ratios = ["| sequence | gap | " + " | ".join(k.removeprefix("w3d_ratio_") for k in ratio_keys) + " |",
              "|---" * (len(ratio_keys) + 2) + "|"]
    for r in rows:
        if r["mask"] == "none":
            ratios.append(f"| {r['sequence']} | {r['gap']} | "
                          + " | ".join(f"{r[k]:.2f}" if k in r else "-" for k in ratio_keys) + " |")
    detector_keys = sorted({k for r in rows for k in r if k.startswith("detector_ratio_")})
    if detector_keys:
        ratios += ["", "An ideal detector of per-pair motion (weight 0 where the tissue moved more than t "
                   "between the frames), its ratio by displacement from the rest shape above 0.5 mm:", "",
                   "| sequence | gap | " + " | ".join(k.removeprefix("detector_ratio_") for k in detector_keys) + " |",
                   "|---" * (len(detector_keys) + 2) + "|"]
        ratios += [f"| {r['sequence']} | {r['gap']} | " + " | ".join(f"{r[k]:.2f}" if k in r else "-" for k in detector_keys)
                   + " |" for r in rows if r["mask"] == "none"]
    ratio_table = "\n".join(ratios)
    print("\nLearned w3D, mean on moving / mean on still pixels (moving: per-pair motion above a threshold, "
          "or displaced from the rest shape by more than 0.5 mm):\n")
    print(ratio_table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "oracle.md").write_text(header + "\n" + "\n".join(format_row(r) for r in rows) + "\n\n" + ratio_table + "\n")
    (args.out / "oracle.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
