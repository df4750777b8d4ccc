"""SCARED evaluation protocol of Hayoz et al. 2023 (paper Table 3) for our pipeline, plus map accuracy.

    .venv/bin/python tools/evaluate_scared.py SCARED_ROOT [--datasets 1 8 9] [--keyframes d1_k2 ...]
        [--out runs/eval_scared] [--modes frame2model [frame2frame]] [--config FILE]
        [--set key=value ...] [--frames N | A:B] [--align auto|se3|first]
        [--gt-depth FILE] [--gt-depth-scale-mm 0.01] [--no-map]
    .venv/bin/python tools/evaluate_scared.py --synthetic DIR [--synthetic-frames 30]
        [--synthetic-size 320x256] [...]       # synthetic stand-in, written into DIR and evaluated

What it reads
-------------
``SCARED_ROOT/dataset_<d>/keyframe_<k>/`` (also ``dataset<d>/keyframe<k>`` or flat
``SCARED_ROOT/d<d>_k<k>/``) for the test datasets ``--datasets`` (default 1 8 9: the paper's test
split; d4 and d5 are excluded for bad calibrations, d2 d3 d6 d7 are training data). Each keyframe
folder is in the SCARED keyframe layout ``slam.datasets`` reads (docs/inputs.md;
``slam/datasets/scared.py``): ``endoscope_calibration.yaml``, ``data/rgb.mp4`` (left over right),
``data/frame_data/*.json`` or ``data/frame_data.tar.gz`` (``camera-pose``, converted to our ``T_wc``
as documented in ``slam/datasets/scared.py``; the world frame is the keyframe's left camera).
Keyframes are named ``d<d>_k<k>`` in the tables; ``--keyframes`` restricts the evaluation to some.

Ground-truth depth for the map accuracy (optional; the first file found, or ``--gt-depth FILE``):

* ``left_depth_map.tiff``: H x W x 3 float32, x y z (mm) of the surface seen by each pixel of the
  keyframe's original (unrectified, distorted) left image, in that left camera's frame, 0 or NaN
  where unknown (as SCARED ships it; channel order x, y, z as ``tifffile`` reads the file). A
  single-channel float TIFF is read as z.
* ``left_depth.npy``: H x W z (mm) or H x W x 3 x y z (mm), same camera and pixels; 0 / NaN = unknown.
* ``left_depth.png``: uint16 z in units of ``--gt-depth-scale-mm`` (default 0.01 mm, the unit of
  ``slam synth``'s ``depth/`` PNGs); 0 = unknown.

The keyframe is frame 0 of ``data/rgb.mp4`` (``--frames A:B`` with A > 0 disables the map accuracy).

What it computes
----------------
Each keyframe sequence is run with our pipeline (``slam.runner.run_from_config``) in each ``--modes``
mode (default ``frame2model``, as the paper on SCARED) with ``--config`` (default
``configs/scared_frame2model.yaml``: 640x512, full rectification) and ``--set`` overrides, and
evaluated with ``slam.evaluation.evaluate``: ATE-RMSE (mm, SE(3)-aligned; ``--align auto``:
first-pose alignment for a static camera), RPE-trans (mm) and RPE-rot (deg), mean ± std.

Map accuracy: the exported map (``map.ply``, metres, world frame; ``tracking.export_map=true`` is set
so frame2frame exports one too) is moved into the keyframe's left camera with the first pose of the
run (which the pipeline sets to the first ground-truth pose), projected with the left intrinsics and
distortion (``M1``, ``D1``; scaled if the depth map's size differs from the calibration's) onto the
ground-truth depth map's pixels, z-buffered (nearest point per pixel), and compared with the
ground-truth z: median and mean absolute depth error (mm) over the pixels with both a ground-truth
depth and a map point, and the coverage (that pixel count / pixels with ground truth).

Tables (printed, and written to ``--out``): Table 3 style (ATE-RMSE per keyframe, "avg." over the
paper's four keyframes d1_k2 d8_k1 d9_k1 d9_k3 where evaluated, "SCARED avg." mean ± std over every
evaluated keyframe, one row per mode) and per mode a detail table (ATE, RPE, failed frames, map
accuracy, average row). A keyframe that fails (missing folder or video, no poses, a pipeline
failure) is a one-line error row; the evaluation goes on. Outputs: ``scared_eval.md``,
``scared_eval.json``, ``runs/<keyframe>/<mode>/`` (the usual ``slam run`` files).

``--synthetic DIR`` writes a stand-in with ``slam.synth.scared_layout.make_scared_standin``
(rigid synthetic scenes converted to the SCARED keyframe layout, with ``left_depth_map.tiff``):
``DIR/dataset_<d>/keyframe_<k>`` for the paper's keyframes of ``--datasets``, runs at native size
(``data.width=0``, ``data.height=0`` before your ``--set``) and writes results to ``DIR/results``
unless ``--out`` is given.
"""
from __future__ import annotations

import argparse
import copy
import json
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import evaluate_stereomis as common  # noqa: E402  (tools/ is not a package)

from slam.errors import ConfigError, DataError, SlamError  # noqa: E402

REPO = common.REPO
DEFAULT_CONFIG = REPO / "configs" / "scared_frame2model.yaml"
DEFAULT_DATASETS = (1, 8, 9)
PAPER_KEYFRAMES = ("d1_k2", "d8_k1", "d9_k1", "d9_k3")  # the paper's Table 3 columns
GT_DEPTH_FILES = ("left_depth_map.tiff", "left_depth.npy", "left_depth.png")
MODES = common.MODES
_KEYFRAME_DIR = re.compile(r"^keyframe_?(\d+)$", re.IGNORECASE)


# ------------------------------------------------------------------------------------------------
# keyframes
def discover(root: Path, datasets, wanted: list[str] | None) -> list[tuple[str, Path | None, str]]:
    """``(name, folder, error)`` per keyframe of ``datasets`` (``folder`` None with an error message
    when a dataset or a requested keyframe is missing). ``wanted``: keep only these names."""
    found: list[tuple[str, Path | None, str]] = []
    for d in datasets:
        folders: dict[int, Path] = {}
        dataset_dir = next((p for p in (root / f"dataset_{d}", root / f"dataset{d}", root / f"d{d}") if p.is_dir()), None)
        if dataset_dir is not None:
            for child in dataset_dir.iterdir():
                m = _KEYFRAME_DIR.match(child.name)
                if m and child.is_dir():
                    folders.setdefault(int(m.group(1)), child)
        flat = re.compile(rf"^d{d}_k(\d+)$", re.IGNORECASE)
        for child in root.iterdir():
            m = flat.match(child.name)
            if m and child.is_dir():
                folders.setdefault(int(m.group(1)), child)
        names = {f"d{d}_k{k}": folders[k] for k in sorted(folders)}
        if wanted is not None:
            for name in wanted:
                if name.lower().startswith(f"d{d}_") and name.lower() not in names:
                    found.append((name.lower(), None, f"{root}: keyframe {name} not found "
                                                      f"(looked for dataset_{d}/keyframe_* and d{d}_k*)"))
            names = {n: p for n, p in names.items() if n in wanted}
            if not names:
                continue
        if not names:
            where = f"dataset_{d}/keyframe_*" if dataset_dir is None else f"{dataset_dir.name}/keyframe_*"
            found.append((f"d{d}", None, f"{root}: no {where} (or d{d}_k*) folders"))
        found += [(n, p, "") for n, p in names.items()]
    return found


# ------------------------------------------------------------------------------------------------
# map accuracy
def load_gt_depth(folder: Path, name: str | None = None, png_scale_mm: float = 0.01):
    """Ground-truth z (mm, ``(H, W)`` float64, NaN = unknown) of the keyframe's left image and its
    file, or ``(None, None)`` when the folder has none (see the module docstring for the formats)."""
    import cv2

    candidates = [folder / name] if name else [folder / n for n in GT_DEPTH_FILES]
    path = next((p for p in candidates if p.is_file()), None)
    if path is None:
        if name:
            raise DataError(f"{folder / name}: ground-truth depth file not found")
        return None, None
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            arr = np.load(path)
        except (OSError, ValueError) as err:
            raise DataError(f"{path}: cannot read ({common.one_line(err)})") from None
        arr = np.asarray(arr, dtype=np.float64)
    elif suffix in (".tif", ".tiff"):
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DataError(f"{path}: cannot read TIFF")
        arr = np.asarray(img, dtype=np.float64)
        if arr.ndim == 3:
            arr = arr[..., ::-1]  # OpenCV returns the channels reversed (BGR): back to x, y, z
    elif suffix == ".png":
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None or img.ndim != 2:
            raise DataError(f"{path}: expected a single-channel (uint16) depth PNG")
        arr = img.astype(np.float64) * float(png_scale_mm)
    else:
        raise DataError(f"{path}: unsupported ground-truth depth format (tiff, npy or png)")
    if arr.ndim == 3 and arr.shape[2] == 3:
        z = arr[..., 2].copy()
    elif arr.ndim == 2:
        z = arr.copy()
    else:
        raise DataError(f"{path}: expected H x W (z) or H x W x 3 (x y z), got shape {arr.shape}")
    z[~np.isfinite(z) | (z <= 0)] = np.nan
    if not np.isfinite(z).any():
        raise DataError(f"{path}: no valid ground-truth depth")
    return z, path


def project_depth(points_c: np.ndarray, K: np.ndarray, D: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Z-buffered depth image ``(H, W)`` (mm, NaN = no point) of camera-frame points ``(N, 3)`` (mm),
    projected with intrinsics ``K`` and OpenCV distortion ``D`` (pixel centres at integers)."""
    import cv2

    w, h = size
    z = points_c[:, 2]
    keep = z > 1e-6
    p = points_c[keep]
    # points far outside the view can fold back into it through the distortion polynomial
    uv0 = p[:, :2] / p[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    inside = (uv0[:, 0] > -0.25 * w) & (uv0[:, 0] < 1.25 * w) & (uv0[:, 1] > -0.25 * h) & (uv0[:, 1] < 1.25 * h)
    p = p[inside]
    depth = np.full(h * w, np.inf)
    if len(p):
        uv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.asarray(D, dtype=np.float64))
        uv = np.rint(uv.reshape(-1, 2)).astype(np.int64)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        np.minimum.at(depth, uv[ok, 1] * w + uv[ok, 0], p[ok, 2])
    depth[~np.isfinite(depth)] = np.nan
    return depth.reshape(h, w)


def map_accuracy(ply: Path, T_wc0: np.ndarray, calib_path: Path, gt_z: np.ndarray) -> dict:
    """Depth error of the map ``ply`` (metres, world frame) against the ground-truth z map of the
    keyframe (see the module docstring). ``T_wc0``: the keyframe's left camera pose (mm)."""
    import open3d as o3d

    from slam.calibration import read_scared_yaml

    h, w = gt_z.shape
    calib = read_scared_yaml(calib_path, image_size=(w, h))
    K = calib.K1.copy()
    cw, ch = calib.image_size
    if (cw, ch) != (w, h):  # depth map at another resolution than the calibration
        sx, sy = w / cw, h / ch
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    if not ply.is_file():
        raise DataError(f"{ply}: no map exported")
    points = np.asarray(o3d.io.read_point_cloud(str(ply)).points, dtype=np.float64) * 1000.0
    gt_valid = np.isfinite(gt_z)
    out = {"map_points": int(len(points)), "gt_pixels": int(gt_valid.sum())}
    if len(points) == 0:
        return {**out, "map_pixels": 0, "map_coverage": 0.0, "map_median_mm": None, "map_mean_mm": None}
    T_cw = np.linalg.inv(T_wc0)
    pc = points @ T_cw[:3, :3].T + T_cw[:3, 3]
    depth = project_depth(pc, K, calib.D1, (w, h))
    both = gt_valid & np.isfinite(depth)
    err = np.abs(depth[both] - gt_z[both])
    out.update(map_pixels=int(both.sum()), map_coverage=float(both.sum() / max(1, gt_valid.sum())),
               map_median_mm=float(np.median(err)) if len(err) else None,
               map_mean_mm=float(np.mean(err)) if len(err) else None)
    return out


# ------------------------------------------------------------------------------------------------
# tables
def summarise(rows: list[dict], modes: list[str]) -> dict:
    out = {}
    for mode in modes:
        ok = [r for r in rows if r["mode"] == mode and r["status"] == "ok"]
        agg = {"n": len(ok), "errors": sum(r["mode"] == mode and r["status"] != "ok" for r in rows)}
        for key in ("ate_rmse_mm", "rpe_trans_mm", "rpe_rot_deg", "map_median_mm", "map_mean_mm", "map_coverage"):
            m, s = common.mean_std(r.get(key) for r in ok)
            agg[key] = {"mean": m, "std": s}
        paper = [r["ate_rmse_mm"] for r in ok if r["keyframe"] in PAPER_KEYFRAMES]
        agg["paper_avg_ate_mm"] = {"mean": common.mean_std(paper)[0], "n": len(paper)}
        out[mode] = agg
    return out


def format_report(rows: list[dict], modes: list[str], summary: dict, notes: list[str]) -> str:
    names = list(dict.fromkeys(r["keyframe"] for r in rows))
    by = {(r["keyframe"], r["mode"]): r for r in rows}
    lines = ["### Table 3 style: ATE-RMSE (mm) per SCARED keyframe sequence", "",
             "| method | " + " | ".join(names) + " | avg. | SCARED avg. |",
             "|---" * (len(names) + 3) + "|"]
    for mode in modes:
        cells = []
        for n in names:
            r = by.get((n, mode))
            cells.append("-" if r is None else ("error" if r["status"] == "error" else common.fmt(r.get("ate_rmse_mm"))))
        s = summary[mode]
        pa = s["paper_avg_ate_mm"]
        avg = "-" if pa["mean"] is None else f"{pa['mean']:.2f}" + ("" if pa["n"] == len(PAPER_KEYFRAMES) else f" ({pa['n']}/4)")
        lines.append(f"| ours ({mode}) | " + " | ".join(cells) + f" | {avg} | "
                     f"{common.fmt_ms(s['ate_rmse_mm']['mean'], s['ate_rmse_mm']['std'])} |")
    lines += ["", f"avg. = mean over the paper's keyframes {', '.join(PAPER_KEYFRAMES)} that were evaluated; "
                  "SCARED avg. = mean ± std over every evaluated keyframe.", ""]
    for mode in modes:
        lines += [f"**ours ({mode})**", "",
                  "| keyframe | frames | failed | ATE-RMSE mm | RPE-trans mm | RPE-rot deg | map median mm | "
                  "map mean mm | map coverage | map points |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for n in names:
            r = by.get((n, mode))
            if r is None:
                continue
            if r["status"] == "error":
                lines.append(f"| {n} | error: {r['message']} | | | | | | | | |")
                continue
            cov = r.get("map_coverage")
            lines.append(
                f"| {n} | {r.get('frames', 0)} | {r.get('failed', 0)} | {common.fmt(r.get('ate_rmse_mm'), 3)} | "
                f"{common.fmt_ms(r.get('rpe_trans_mm'), r.get('rpe_trans_std_mm'), 3)} | "
                f"{common.fmt_ms(r.get('rpe_rot_deg'), r.get('rpe_rot_std_deg'), 4)} | "
                f"{common.fmt(r.get('map_median_mm'), 3)} | {common.fmt(r.get('map_mean_mm'), 3)} | "
                f"{'-' if cov is None else f'{100 * cov:.1f} %'} | {r.get('map_points', '-')} |"
                + (f" {r['map_note']}" if r.get("map_note") else ""))
        s = summary[mode]

        def ms(key, d=3):
            return common.fmt_ms(s[key]["mean"], s[key]["std"], d)

        cov = s["map_coverage"]["mean"]
        lines.append(f"| **average ({s['n']} keyframes)** | | | {ms('ate_rmse_mm')} | {ms('rpe_trans_mm')} | "
                     f"{ms('rpe_rot_deg', 4)} | {ms('map_median_mm')} | {ms('map_mean_mm')} | "
                     f"{'-' if cov is None else f'{100 * cov:.1f} %'} | |")
        lines.append("")
    if notes:
        lines += [*[f"- {n}" for n in notes]]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------
def parse_frames(text: str | None) -> tuple[int | None, int | None]:
    if not text:
        return None, None
    try:
        if ":" in text:
            a, b = text.split(":")
            start, end = (int(a) if a.strip() else None), (int(b) if b.strip() else None)
        else:
            start, end = 0, int(text)
    except ValueError:
        raise ConfigError(f"--frames {text}: expected N (first N frames) or A:B") from None
    if (start is not None and start < 0) or (end is not None and end < 2) or \
            (start is not None and end is not None and end - start < 2):
        raise ConfigError(f"--frames {text}: need at least 2 frames, non-negative bounds")
    return start, end


def build_parser() -> argparse.ArgumentParser:
    ap = common.OneLineParser(prog="evaluate_scared.py", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", nargs="?", help="SCARED root folder (dataset_<d>/keyframe_<k>/ or d<d>_k<k>/)")
    ap.add_argument("--datasets", nargs="+", type=int, default=list(DEFAULT_DATASETS),
                    help="SCARED dataset numbers (default: the paper's test split 1 8 9)")
    ap.add_argument("--keyframes", nargs="+", metavar="dD_kK", help="only these keyframes, e.g. d1_k2 d9_k3")
    ap.add_argument("--out", help="output folder (default runs/eval_scared; with --synthetic DIR/results)")
    ap.add_argument("--modes", nargs="+", default=["frame2model"], choices=MODES, help="tracking modes to run")
    ap.add_argument("--config", default=str(DEFAULT_CONFIG), help="YAML config (default %(default)s)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override (repeatable)")
    ap.add_argument("--frames", help="frames of every keyframe video: N (first N) or A:B (default all)")
    ap.add_argument("--align", default="auto", choices=["auto", "se3", "first"],
                    help="trajectory alignment before ATE (auto: first-pose for a static camera, else SE(3))")
    ap.add_argument("--gt-depth", metavar="FILE", help="ground-truth depth file name in each keyframe folder "
                                                       f"(default: the first of {', '.join(GT_DEPTH_FILES)})")
    ap.add_argument("--gt-depth-scale-mm", type=float, default=0.01, help="mm per unit of a uint16 depth PNG")
    ap.add_argument("--no-map", action="store_true", help="skip the map accuracy (and the map export in frame2frame)")
    ap.add_argument("--synthetic", metavar="DIR", help="generate a synthetic stand-in in DIR and evaluate it")
    ap.add_argument("--synthetic-frames", type=int, default=30, help="frames per stand-in keyframe (default 30)")
    ap.add_argument("--synthetic-size", default="320x256", help="stand-in image size WxH (default 320x256)")
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    try:
        return evaluate_protocol(args)
    except (SlamError, ValueError, OSError) as err:
        print(f"{ap.prog}: error: {err if isinstance(err, SlamError) else common.one_line(err)}", file=sys.stderr)
        return 2


def evaluate_protocol(args) -> int:
    overrides = list(args.set)
    notes = []
    wanted = [k.lower() for k in args.keyframes] if args.keyframes else None
    if wanted:
        bad = [k for k in wanted if not re.fullmatch(r"d\d+_k\d+", k)]
        if bad:
            raise ConfigError(f"--keyframes {' '.join(bad)}: expected names like d1_k2")
    if args.gt_depth_scale_mm <= 0:
        raise ConfigError("--gt-depth-scale-mm must be positive")
    start, end = parse_frames(args.frames)
    if args.synthetic:
        if args.root:
            raise ConfigError("give SCARED_ROOT or --synthetic DIR, not both")
        if args.synthetic_frames < 2:
            raise ConfigError(f"--synthetic-frames {args.synthetic_frames}: need at least 2")
        from slam.synth.scared_layout import make_scared_standin

        root = Path(args.synthetic)
        keyframes = [(int(n[1:].split("_")[0]), int(n.split("_k")[1])) for n in PAPER_KEYFRAMES
                     if int(n[1:].split("_")[0]) in args.datasets and (wanted is None or n in wanted)]
        if not keyframes:
            raise ConfigError("--synthetic: none of the paper's keyframes (d1_k2 d8_k1 d9_k1 d9_k3) is selected")
        make_scared_standin(root, keyframes, frames=args.synthetic_frames,
                            size=common.parse_size(args.synthetic_size), progress=True)
        out = Path(args.out) if args.out else root / "results"
        overrides = ["data.width=0", "data.height=0", *overrides]
        notes.append("SYNTHETIC stand-in (slam.synth, rigid scenes in the SCARED keyframe layout), not SCARED: "
                     "native size (data.width=data.height=0).")
    else:
        if not args.root:
            raise ConfigError("give the SCARED root folder (or --synthetic DIR)")
        root = Path(args.root)
        if not root.is_dir():
            raise DataError(f"{root}: no such folder (the SCARED root)")
        out = Path(args.out) if args.out else Path("runs") / "eval_scared"
    if not args.no_map:
        overrides = ["tracking.export_map=true", *overrides]
    if not sys.stderr.isatty():
        overrides = ["logging.progress=false", *overrides]
    configs = common.load_mode_configs(args.config, overrides, args.modes)
    keyframes = discover(root, args.datasets, wanted)
    notes.append(f"config {args.config}" + (f", overrides {' '.join(overrides)}" if overrides else "")
                 + f"; ATE alignment: {args.align}; frames: {args.frames or 'all'}.")
    map_on = not args.no_map and not (start or 0) > 0
    if not args.no_map and not map_on:
        notes.append("map accuracy skipped: --frames does not start at the keyframe (frame 0).")
    out.mkdir(parents=True, exist_ok=True)

    rows: list[dict] = []
    total = sum(len(args.modes) for _, p, _ in keyframes if p is not None) + sum(p is None for _, p, _ in keyframes)
    k = 0
    interrupted = False
    print(f"{total} run(s) over {len(keyframes)} keyframe sequence(s); results in {out}", flush=True)
    for name, folder, error in keyframes:
        if folder is None:
            k += 1
            row = {"keyframe": name, "mode": args.modes[0], "status": "error", "message": error, "seconds": 0.0}
            print(common.progress_line(k, total, name, "-", row), flush=True)
            rows += [{**row, "mode": m} for m in args.modes]
            continue
        for mode in args.modes:
            k += 1
            row = common.run_one(folder, copy.deepcopy(configs[mode]), out / "runs" / name / mode, start, end, args.align)
            row.update(keyframe=name, mode=mode, path=str(folder))
            if row["status"] == "ok" and map_on:
                add_map_accuracy(row, folder, args)
            print(common.progress_line(k, total, name, mode, row)
                  + (f", map median {common.fmt(row.get('map_median_mm'), 3)} mm" if row.get("map_median_mm") is not None
                     else ""), flush=True)
            rows.append(common.public(row))
            if row["status"] == "interrupted":
                interrupted = True
                break
        if interrupted:
            notes.append("INTERRUPTED: the tables hold the runs finished so far.")
            break

    summary = summarise(rows, args.modes)
    report = format_report(rows, args.modes, summary, notes)
    print()
    print(report)
    (out / "scared_eval.md").write_text(report + "\n")
    payload = {"protocol": "SCARED, Hayoz et al. 2023 Table 3 (+ map accuracy)", "root": str(root),
               "datasets": args.datasets, "keyframes": [n for n, _, _ in keyframes], "config": args.config,
               "overrides": overrides, "modes": args.modes, "align": args.align, "frames": args.frames,
               "notes": notes, "rows": rows, "summary": summary, "paper_keyframes": list(PAPER_KEYFRAMES),
               "errors": sum(r["status"] == "error" for r in rows), "interrupted": interrupted}
    (out / "scared_eval.json").write_text(json.dumps(payload, indent=2, default=str))
    print(f"\nwrote {out / 'scared_eval.md'} and {out / 'scared_eval.json'}")
    return 130 if interrupted else 0


def add_map_accuracy(row: dict, folder: Path, args) -> None:
    """Map accuracy of a finished run (fields ``map_*``; a problem becomes ``map_note``, not an error)."""
    try:
        gt_z, gt_path = load_gt_depth(folder, args.gt_depth, args.gt_depth_scale_mm)
        if gt_z is None:
            row["map_note"] = "no ground-truth depth"
            return
        result = row["result"]
        T_wc0 = result.records[0].pose
        ply = Path(result.files.get("map", Path(row["out"]) / "map.ply"))
        row.update(map_accuracy(ply, T_wc0, folder / "endoscope_calibration.yaml", gt_z), gt_depth=str(gt_path))
    except Exception as err:  # noqa: BLE001 - the trajectory metrics stand without the map
        row["map_note"] = f"map accuracy failed: {common.one_line(err)}"


if __name__ == "__main__":
    sys.exit(main())
