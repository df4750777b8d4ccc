"""Which input makes a pose wrong: the stereo depth, the temporal flow, or the weights?

    .venv/bin/python tools/error_attribution.py [--appearances default texture=0,highlights=1 ...]
        [--seeds 9501 9502] [--frames 60] [--size 320x256] [--step 1] [--out runs/error_attribution]

On rigid synthetic sequences (camera motion only, so the exact flow follows from the generator's
depth and poses), each consecutive pair is tracked as frame2frame tracks a moving camera (the
current frame against the previous one, its own depth) with every combination of

- depth: the stereo depth, or the generator's exact depth (as ``analysis.depth_source: groundtruth``);
- flow: DIS (the default), or the exact flow ``pi(T_ref_cur D K^-1 p)`` where the pixel is seen in
  both views (visibility checked against the reference's exact depth);
- weights: the learned maps, or the constant ``weights.w2d`` / ``w3d``.

It prints per appearance and variant the per-pair translation error of the relative pose (mean,
95th percentile, max, pairs above 1 mm) and, for the DIS flow, its end-point error against the
exact flow (median over pixels, share above 1 px, both weighted by the learned w2D as the solve
sees them), and the DIS flow's end-point error from three starts (from scratch; from the motion
field of the last true motion continued, a constant-velocity prediction; of the true motion):
whether predicting the motion first would let DIS find what it loses (``--step 10``: 2.5 fps).
The variant that closes the gap names the input to fix. Markdown and JSON in ``--out``.
"""
from __future__ import annotations

import argparse
from itertools import product
from pathlib import Path

import numpy as np
import torch

from benchmarks.runs import synthetic, write_report

VARIANTS = list(product(("stereo", "exact"), ("dis", "exact"), ("learned", "constant")))
# where the DIS flow starts: from scratch (tracking's default), from the motion field of the last
# true motion continued (a constant-velocity prediction), of the true motion (a perfect prediction)
STARTS = ("scratch", "last motion", "true motion")


def exact_flow(depth_cur: np.ndarray, depth_ref: np.ndarray, K: np.ndarray, T_ref_cur: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """The rigid flow ``(2, H, W)`` of the current view's pixels into the reference view, and the
    ``(H, W)`` bool pixels seen in both (in front, inside, not occluded: the reference's depth at
    the target within 2 % of the point's)."""
    H, W = depth_cur.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    Z = depth_cur.astype(np.float64)
    X = np.stack([(u - K[0, 2]) / K[0, 0] * Z, (v - K[1, 2]) / K[1, 1] * Z, Z], 0).reshape(3, -1)
    Xr = T_ref_cur[:3, :3] @ X + T_ref_cur[:3, 3:4]
    zr = Xr[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        ur = K[0, 0] * Xr[0] / zr + K[0, 2]
        vr = K[1, 1] * Xr[1] / zr + K[1, 2]
    ok = (Z.ravel() > 0) & (zr > 0) & (ur >= 0) & (ur <= W - 1) & (vr >= 0) & (vr <= H - 1)
    ui = np.clip(np.round(ur), 0, W - 1).astype(int)
    vi = np.clip(np.round(vr), 0, H - 1).astype(int)
    seen = depth_ref.astype(np.float64)[vi, ui]
    ok &= np.abs(seen - zr) < 0.02 * np.maximum(zr, 1e-6)
    flow = np.stack([ur - u.ravel(), vr - v.ravel()], 0).reshape(2, H, W)
    return np.where(ok.reshape(H, W)[None], flow, 0.0).astype(np.float32), ok.reshape(H, W)


def pose_error_mm(est: np.ndarray, gt: np.ndarray) -> float:
    """Translation of ``est^-1 gt`` (both ``(4, 4)`` mm)."""
    return float(np.linalg.norm((np.linalg.inv(est) @ gt)[:3, 3]))


def attribute_sequence(data: Path, step: int, overrides: list[str]) -> dict:
    """Per-pair errors of every variant on one sequence (see the module doc)."""
    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from vo.health import weighted_median
    from vo.odometry import AheadFlow, Correspondences, StereoOdometry

    cfg = load_config(None, [*overrides])
    ds = open_dataset(data, cfg.data)
    odo = {w: StereoOdometry(ds.camera, load_config(None, [f"weights.mode={w}",
                                                           *overrides]).vo())
           for w in ("learned", "constant")}
    K = np.asarray(ds.camera.K, np.float64)
    errors = {v: [] for v in VARIANTS}
    epe_median, epe_over_1px, dis_failed = [], [], 0
    started = {start: [] for start in STARTS}
    prev, last_motion = None, None
    for k in range(0, len(ds), step):
        f = ds.frame(k)
        if f.gt_depth is None or f.gt_pose is None:
            raise SystemExit(f"{data}: needs ground-truth depth and poses (a `slam synth` sequence)")
        views = {"stereo": odo["learned"].make_view(f.left, f.right, f.mask, None, None, f.specular),
                 "exact": odo["learned"].make_view(f.left, f.right, f.mask, f.gt_depth, None, f.specular)}
        if prev is not None:
            pf, pviews = prev
            T_gt = np.linalg.inv(pf.gt_pose) @ f.gt_pose            # cur -> ref, mm
            flow_np, seen = exact_flow(f.gt_depth, pf.gt_depth, K, T_gt)
            flow_x = torch.from_numpy(flow_np)[None]
            seen_t = torch.from_numpy(seen)[None, None]
            for depth, flow, weights in VARIANTS:
                cur, ref = views[depth], pviews[depth]
                exact = AheadFlow(ref, Correspondences(flow_x, seen_t)) if flow == "exact" else None
                res = odo[weights].track(cur, ref, ahead=exact)
                errors[(depth, flow, weights)].append(np.nan if res.failed else pose_error_mm(res.relative, T_gt))
                if (depth, flow, weights) == ("stereo", "dis", "learned"):
                    dis_failed += int(res.failed)
                    epe = (res.flow[0] - flow_x[0]).norm(dim=0)
                    w = res.w2d[0, 0] * seen_t[0, 0]
                    if float(w.sum()) > 0:
                        epe_median.append(weighted_median(epe.flatten(), w.flatten()))
                        epe_over_1px.append(float((w * (epe > 1.0)).sum() / w.sum()))
            for start, motion in (("scratch", None), ("last motion", last_motion), ("true motion", T_gt)):
                if start != "last motion" or motion is not None:
                    corr = odo["learned"].correspondences(views["stereo"], pviews["stereo"], round_trip=False,
                                                          motion=motion)
                    epe = (corr.flow[0] - flow_x[0]).norm(dim=0)[seen_t[0, 0]]
                    started[start].append(float(epe.median()) if epe.numel() else float("nan"))
            last_motion = T_gt
        prev = (f, views)
    return {"errors": {"/".join(v): e for v, e in errors.items()}, "epe_median_px": epe_median,
            "epe_over_1px": epe_over_1px, "dis_failed": dis_failed, "epe_from_start_px": started}


def summarise(values: list[float]) -> dict:
    a = np.asarray(values, float)
    ok = a[np.isfinite(a)]
    return {"mean": float(ok.mean()) if ok.size else float("nan"),
            "p95": float(np.percentile(ok, 95)) if ok.size else float("nan"),
            "max": float(ok.max()) if ok.size else float("nan"),
            "over_1mm": int((ok > 1.0).sum()), "failed": int((~np.isfinite(a)).sum()), "pairs": int(a.size)}


def main(argv: list[str] | None = None) -> None:
    from slam.synth.appearance import parse_appearance

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--appearances", nargs="+", default=["default", "texture=0", "texture=0,highlights=1"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[9501, 9502])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", default="320x256")
    ap.add_argument("--step", type=int, default=1, help="track every STEP-th frame (5: a 5 fps video)")
    ap.add_argument("--out", default="runs/error_attribution")
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    w, h = (int(v) for v in args.size.split("x"))
    out = Path(args.out)
    rows = []
    for look in args.appearances:
        pooled: dict = {}
        epe_med, epe_1 = [], []
        from_start: dict = {start: [] for start in STARTS}
        for seed in args.seeds:
            name = f"rigid_s{seed}_{args.size}_{args.frames}_{look.replace(',', '_').replace('=', '')}"
            data = synthetic(out / "data" / name, "rigid", frames=args.frames, size=(w, h), seed=seed,
                             appearance=parse_appearance(look, seed))
            r = attribute_sequence(data, args.step, args.set)
            for key, e in r["errors"].items():
                pooled.setdefault(key, []).extend(e)
            epe_med += r["epe_median_px"]
            epe_1 += r["epe_over_1px"]
            for start, e in r["epe_from_start_px"].items():
                from_start[start] += e
        for key, e in pooled.items():
            rows.append({"appearance": look, "variant": key, **summarise(e),
                         "dis_epe_median_px": float(np.median(epe_med)) if epe_med else None,
                         "dis_epe_over_1px": float(np.mean(epe_1)) if epe_1 else None,
                         "dis_epe_from_start_px": {k: [float(np.nanmedian(v)), float(np.nanmax(v))]
                                                   for k, v in from_start.items() if v}})
    lines = ["| appearance | depth / flow / weights | mean mm | p95 mm | max mm | pairs > 1 mm | failed |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['appearance']} | {r['variant']} | {r['mean']:.3f} | {r['p95']:.3f} | {r['max']:.3f} "
                     f"| {r['over_1mm']}/{r['pairs']} | {r['failed']} |")
    lines += ["", "| appearance | DIS end-point error, w2D-weighted median px | share above 1 px |", "|---|---|---|"]
    for look in args.appearances:
        r = next(x for x in rows if x["appearance"] == look)
        lines.append(f"| {look} | {r['dis_epe_median_px']:.3f} | {r['dis_epe_over_1px']:.3f} |")
    lines += ["", "| appearance | DIS end-point error from each start: median of the pairs' medians px (worst pair) |",
              "|---|---|"]
    for look in args.appearances:
        r = next(x for x in rows if x["appearance"] == look)
        lines.append(f"| {look} | " + ", ".join(f"{k} {m:.2f} ({w:.2f})" for k, (m, w) in r["dis_epe_from_start_px"].items())
                     + " |")
    table = "\n".join(lines)
    write_report(out, "error_attribution", table, rows)


if __name__ == "__main__":
    main()
