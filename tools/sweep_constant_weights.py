"""Sweep of the constant 2D/3D balance on the *training* pairs (the defaults of
``weights.w2d`` / ``weights.w3d`` come from here; w = 1 for both is an arbitrary balance).

    .venv/bin/python tools/sweep_constant_weights.py [--config configs/train.yaml] [--out runs/sweep]
        [--set key=value ...]   (training-config overrides, e.g. depth.temporal_gain=0.1)

For each ratio ``w3d / w2d`` (w2d = 1) it solves every training/validation pair's pose with
constant weights and reports the mean L1 pose loss of eq. 7 and the mean translation (mm) and
rotation (deg) errors; prints a table and writes JSON.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from slam.training.trainer import TrainConfig, collate, load_train_config, training_data
from vo.ddn import declarative_pose
from vo.lie import se3_exp
from vo.residuals import PoseProblem


def pose_errors(samples, cfg: TrainConfig, w2: float, w3: float) -> dict:
    dmax = cfg.depth.max_depth_mm
    l1, t_err, r_err, failed = [], [], [], 0
    for k in range(0, len(samples), 32):
        b = collate(samples[k:k + 32])
        H, W = b["size"]
        s2, s3 = PoseProblem.scales(H, W)
        a = b["valid2"].float() * w2
        c = b["valid3"].float() * w3
        prob = PoseProblem(b["points_cur"], b["target"], b["points_ref"], a, c, b["K"], s2, s3)
        with torch.no_grad():
            p, ok = declarative_pose(a, c, prob, cfg.solver, cfg.optim.grad_tol)
        failed += int((~ok).sum())
        E = torch.linalg.inv(se3_exp(b["p_gt"].double())) @ se3_exp(p.double())
        l1 += ((p - b["p_gt"]).abs().sum(1))[ok].tolist()
        t_err += (E[:, :3, 3].norm(dim=1) * dmax)[ok].tolist()
        cos = ((E[:, 0, 0] + E[:, 1, 1] + E[:, 2, 2] - 1) / 2).clamp(-1, 1)
        r_err += torch.rad2deg(torch.acos(cos))[ok].tolist()
    return {"l1": float(np.mean(l1)), "trans_mm": float(np.mean(t_err)), "rot_deg": float(np.mean(r_err)), "failed": failed}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="configs/train.yaml")
    ap.add_argument("--out", default="runs/sweep")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="training-config override")
    args = ap.parse_args()
    cfg = load_train_config(args.config, args.set)
    _, train_set, val = training_data(cfg)
    samples = train_set + val
    rows = []
    for ratio in [0.0, 0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 10.0, 100.0, float("inf")]:
        w2, w3 = (0.0, 1.0) if ratio == float("inf") else (1.0, ratio)
        r = pose_errors(samples, cfg, w2, w3)
        rows.append({"w2d": w2, "w3d": w3, **r})
        print(f"w2d={w2:<4} w3d={w3:<7} L1={r['l1']:.5f}  trans={r['trans_mm']:.4f} mm  rot={r['rot_deg']:.4f} deg  failed={r['failed']}")
    best = min(rows, key=lambda r: r["l1"])
    print(f"best constant balance on {len(samples)} training pairs: w2d={best['w2d']} w3d={best['w3d']}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "sweep.json").write_text(json.dumps({"pairs": len(samples), "rows": rows, "best": best}, indent=2))


if __name__ == "__main__":
    main()
