"""Helpers of ``benchmarks/compare_baselines.py``: the shared stereo-depth cache, the Open3D baselines
(RGB-D odometry frame-to-frame, dense TSDF SLAM frame-to-model), our pipeline as a job, and a
runner that executes one job in its own process so that a crash inside a native library
(Open3D 0.20's dense SLAM was seen to segfault) is reported instead of killing the comparison.

Run as a module it executes one job: ``python -m benchmarks.baselines_open3d JOB.json RESULT.json``.

Units. Our depth is in millimetres; Open3D's pipelines work in metres: the odometry gets float32
millimetres with ``depth_scale = 1000``, the dense SLAM the cache's uint16 (0.01 mm) with
``depth_scale = 100000`` (its integration kernel takes uint16 depth with uint8 colour), and every
Open3D length (depth limits, depth difference thresholds, voxel size) is given in metres.
Estimated translations come back in metres and are converted to millimetres.

Poses. Every baseline tracks the *rectified* left camera; its trajectory starts at identity and is
anchored like our pipeline's: ``T_wc_rect,k = G_0 @ R1^T @ T_0k`` and ``T_wc,k = T_wc_rect,k @ R1``
(``G_0`` the first ground-truth pose, ``R1`` the rectifying rotation as a 4x4; identity on the
synthetic rectified data).
"""
from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

DEPTH_UNIT_MM = 0.01  # the cache stores depth as uint16 in units of 0.01 mm (max 655 mm)
CACHE_VERSION = 1

# Options of the baselines, chosen on training-like sequences (seeds 1000-1004), never on the
# evaluation data; the evidence is in compare_baselines.py's docstring (Tuning).
ODOMETRY_DEFAULTS = {
    "iterations": [20, 10, 5],  # Gauss-Newton iterations per pyramid level, coarsest level first
    "depth_diff_max_mm": {"color": 10.0, "hybrid": 2.0},  # per Jacobian
}
SLAM_DEFAULTS = {
    "voxel_mm": 0.125,  # about one pixel's footprint at 640x512 (75 mm / fx 554); finer was better
    "depth_diff_mm": 2.0,
    "trunc_voxel_multiplier": 8.0,
    "block_count": 10000,  # initial capacity of the block hash map (it grows as needed)
    "method": "PointToPlane",  # Hybrid diverged on the moving-camera tuning sequences
    "iterations": [6, 3, 1],  # per pyramid level, coarsest first (Open3D's dense_slam.py default)
}


# ------------------------------------------------------------------------------------------------
# data and depth
def data_overrides(size: tuple[int, int] | None) -> list[str]:
    """Config overrides that resize frames to ``size`` (None keeps the native size)."""
    return [] if not size else [f"data.width={int(size[0])}", f"data.height={int(size[1])}"]


def open_sequence(data: str | Path, overrides: list[str], frames: int | str | None):
    """The dataset as our pipeline reads it (same rectification, resizing, masks, frames)."""
    from slam.config import load_config
    from slam.io.datasets import open_dataset

    cfg = load_config(None, list(overrides))
    dataset = open_dataset(Path(data), cfg.data)
    if frames:
        dataset = dataset.select(frames)
    return dataset


def depth_cache_key(data: str | Path, overrides: list[str], frames) -> str:
    """A short hash of what the cached depth depends on."""
    from slam.config import load_config

    cfg = load_config(None, list(overrides))
    gt = Path(data) / "groundtruth.txt"
    stamp = gt.stat().st_mtime_ns if gt.is_file() else 0
    text = json.dumps({"v": CACHE_VERSION, "data": str(Path(data).resolve()), "stamp": stamp, "frames": str(frames),
                       "data_cfg": vars(cfg.data), "corr": vars(cfg.correspondence), "depth": vars(cfg.depth)},
                      sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:10]


def compute_depth_cache(data: str | Path, path: str | Path, overrides: list[str], frames=None,
                        progress: bool = False) -> Path:
    """Our stereo depth of every selected frame, computed once with ``StereoOdometry.make_view``
    (constant weights: the weights do not touch the depth) and saved to ``path`` (.npz):

    ``depth_cmm`` ``(N, H, W)`` uint16 depth in 0.01 mm (0 = invalid: no stereo match, out of
    [min_depth_mm, max_depth_mm], instrument or specular mask), ``stereo_ms`` ``(N,)`` time of
    ``make_view`` per frame, ``indices``, ``timestamps``.
    """
    import torch

    from slam.config import load_config
    from vo.odometry import StereoOdometry

    path = Path(path)
    if path.is_file():
        return path
    cfg = load_config(None, [*overrides, "weights.mode=constant"])
    dataset = open_sequence(data, overrides, frames)
    odometry = StereoOdometry(dataset.camera, cfg.vo())
    n, H, W = len(dataset), dataset.camera.height, dataset.camera.width
    depth = np.zeros((n, H, W), np.uint16)
    stereo_ms = np.zeros(n)
    for k in range(n):
        frame = dataset.frame(k)
        t0 = time.perf_counter()
        with torch.inference_mode():
            view = odometry.make_view(frame.left, frame.right, frame.mask, specular=frame.specular)
        stereo_ms[k] = (time.perf_counter() - t0) * 1000.0
        d = view.depth[0, 0].cpu().numpy().astype(np.float64)
        d[~frame.mask] = 0.0
        depth[k] = np.clip(np.rint(d / DEPTH_UNIT_MM), 0, 65535).astype(np.uint16)
        if progress:
            print(f"\r  stereo depth {k + 1}/{n}", end="", file=sys.stderr, flush=True)
    if progress:
        print(file=sys.stderr)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, depth_cmm=depth, stereo_ms=stereo_ms, indices=np.asarray(dataset.indices),
                        timestamps=np.asarray(dataset.timestamps), K=dataset.camera.K)
    os.replace(tmp, path)
    return path


def load_depth_mm(path: str | Path) -> tuple[np.ndarray, dict]:
    """``(N, H, W)`` float32 depth in mm (0 invalid) and the cache's other arrays."""
    with np.load(path) as z:
        depth = z["depth_cmm"].astype(np.float32) * np.float32(DEPTH_UNIT_MM)
        rest = {k: z[k] for k in z.files if k != "depth_cmm"}
    return depth, rest


def anchor(relative_poses: np.ndarray, gt0: np.ndarray | None, R1: np.ndarray) -> np.ndarray:
    """Poses ``T_0k`` of the rectified camera (first = identity, mm) -> ``T_wc`` of the original
    left camera in the ground truth's world (see the module docstring)."""
    R = np.eye(4)
    R[:3, :3] = R1
    start = (np.eye(4) if gt0 is None else gt0) @ R.T
    return np.stack([start @ T @ R for T in relative_poses])


# ------------------------------------------------------------------------------------------------
# Open3D RGB-D odometry, frame to frame
def run_rgbd_odometry(data: str, depth_cache: str, overrides: list[str], frames=None, jacobian: str = "color",
                      iterations=None, depth_diff_max_mm: float | None = None) -> dict:
    """Frame-to-frame ``open3d.pipelines.odometry.compute_rgbd_odometry`` on our stereo depth.

    Args:
        jacobian: ``color`` (RGBDOdometryJacobianFromColorTerm, photometric) or ``hybrid``
            (RGBDOdometryJacobianFromHybridTerm, photometric + depth).
        iterations: Gauss-Newton iterations per pyramid level (Open3D's order).
        depth_diff_max_mm: correspondences whose depths differ more are rejected (default: per
            Jacobian, ``ODOMETRY_DEFAULTS``).

    A failed step (``success`` False or a non-finite motion) keeps the previous pose; the next frame
    is tracked against the last successfully tracked one. Timing: building the Open3D images and
    the odometry call, per tracked frame (no file reading, no stereo depth).
    """
    import open3d as o3d

    iterations = list(iterations or ODOMETRY_DEFAULTS["iterations"])
    diff = ODOMETRY_DEFAULTS["depth_diff_max_mm"][jacobian] if depth_diff_max_mm is None else float(depth_diff_max_mm)
    dataset = open_sequence(data, overrides, frames)
    depth, _ = load_depth_mm(depth_cache)
    cfg_depth = _depth_limits(overrides)
    cam = dataset.camera
    intr = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    odo = o3d.pipelines.odometry
    jac = {"color": odo.RGBDOdometryJacobianFromColorTerm, "hybrid": odo.RGBDOdometryJacobianFromHybridTerm}[jacobian]()
    option = odo.OdometryOption(o3d.utility.IntVector(iterations), diff / 1000.0,
                                cfg_depth[0] / 1000.0, cfg_depth[1] / 1000.0)
    n = len(dataset)
    poses = [np.eye(4)]
    failed: list[int] = []
    track_s = 0.0
    target = None
    for k in range(n):
        left = np.ascontiguousarray(dataset.frame(k).left)
        t0 = time.perf_counter()
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(left), o3d.geometry.Image(np.ascontiguousarray(depth[k])),
            depth_scale=1000.0, depth_trunc=cfg_depth[1] / 1000.0, convert_rgb_to_intensity=True)
        if target is None:
            target = rgbd
            track_s += time.perf_counter() - t0
            continue
        ok, T, _ = odo.compute_rgbd_odometry(rgbd, target, intr, np.eye(4), jac, option)
        track_s += time.perf_counter() - t0
        if ok and np.isfinite(T).all():
            T = T.copy()
            T[:3, 3] *= 1000.0
            poses.append(poses[-1] @ T)
            target = rgbd
        else:
            poses.append(poses[-1].copy())
            failed.append(int(dataset.indices[k]))
    est = anchor(np.stack(poses), None if dataset.gt_poses is None else dataset.gt_poses[0], dataset.R1)
    return {"poses": est.tolist(), "failed_frames": failed, "track_s": track_s, "frames": n,
            "params": {"jacobian": jacobian, "iterations": iterations, "depth_diff_max_mm": diff,
                       "depth_min_mm": cfg_depth[0], "depth_max_mm": cfg_depth[1]}}


def _open3d_message(err: Exception) -> str:
    """Open3D's error text without terminal colours and source locations."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(err)).strip()
    return (text.split(": ")[-1] if "Open3D Error" in text else text)[:200] or type(err).__name__


def _depth_limits(overrides: list[str]) -> tuple[float, float]:
    from slam.config import load_config

    cfg = load_config(None, list(overrides))
    return float(cfg.depth.min_depth_mm), float(cfg.depth.max_depth_mm)


# ------------------------------------------------------------------------------------------------
# Open3D dense SLAM (TSDF voxel blocks, frame to model)
def run_dense_slam(data: str, depth_cache: str, overrides: list[str], frames=None, voxel_mm: float | None = None,
                   depth_diff_mm: float | None = None, trunc_voxel_multiplier: float | None = None,
                   block_count: int | None = None, method: str | None = None, iterations=None) -> dict:
    """``open3d.t.pipelines.slam.Model`` as Open3D's ``dense_slam.py``: track the frame against
    the model's ray-cast view, integrate it at the tracked pose, ray-cast the model there.

    A tracking exception (or a non-finite pose) is a failure: the previous pose is kept and the
    frame is not integrated. Timing: the whole per-frame Open3D work (Open3D images, tracking,
    integration, ray casting), no file reading, no stereo depth.
    """
    import open3d as o3d
    import open3d.core as o3c

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    p = {**SLAM_DEFAULTS}
    for key, value in (("voxel_mm", voxel_mm), ("depth_diff_mm", depth_diff_mm),
                       ("trunc_voxel_multiplier", trunc_voxel_multiplier), ("block_count", block_count),
                       ("method", method), ("iterations", iterations)):
        if value is not None:
            p[key] = value
    dataset = open_sequence(data, overrides, frames)
    with np.load(depth_cache) as z:  # uint16 depth (the integration kernel takes uint16 + uint8 colour)
        depth = z["depth_cmm"]
    scale = 1000.0 / DEPTH_UNIT_MM  # depth units per metre
    dmin, dmax = (v / 1000.0 for v in _depth_limits(overrides))
    cam = dataset.camera
    device = o3c.Device("CPU:0")
    K = o3c.Tensor(np.asarray(cam.K, dtype=np.float64))
    T = o3c.Tensor(np.eye(4))
    model = o3d.t.pipelines.slam.Model(float(p["voxel_mm"]) / 1000.0, 16, int(p["block_count"]), T, device)
    input_frame = o3d.t.pipelines.slam.Frame(cam.height, cam.width, K, device)
    raycast_frame = o3d.t.pipelines.slam.Frame(cam.height, cam.width, K, device)
    tmethod = getattr(o3d.t.pipelines.odometry.Method, p["method"])
    criteria = [o3d.t.pipelines.odometry.OdometryConvergenceCriteria(int(i)) for i in p["iterations"]]
    use_color = p["method"] != "PointToPlane"
    n = len(dataset)
    poses, failed, reasons = [], [], {}
    track_s = 0.0
    for k in range(n):
        left = np.ascontiguousarray(dataset.frame(k).left)
        t0 = time.perf_counter()
        input_frame.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth[k][..., None]))))
        input_frame.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(left)))
        ok = True
        if k > 0:
            try:
                result = model.track_frame_to_model(input_frame, raycast_frame, scale, dmax,
                                                    float(p["depth_diff_mm"]) / 1000.0, tmethod, criteria)
                rel = result.transformation.cpu().numpy()
                if not np.isfinite(rel).all():
                    raise RuntimeError("non-finite pose")
                T = T @ o3c.Tensor(rel)
            except RuntimeError as err:  # Open3D raises RuntimeError on a tracking failure
                ok = False
                failed.append(int(dataset.indices[k]))
                reasons[str(int(dataset.indices[k]))] = _open3d_message(err)
        poses.append(T.cpu().numpy().copy())
        if ok:
            model.update_frame_pose(k, T)
            model.integrate(input_frame, scale, dmax, float(p["trunc_voxel_multiplier"]))
            model.synthesize_model_frame(raycast_frame, scale, dmin, dmax, float(p["trunc_voxel_multiplier"]), use_color)
        track_s += time.perf_counter() - t0
    rel_mm = np.stack(poses)
    rel_mm[:, :3, 3] *= 1000.0
    est = anchor(rel_mm, None if dataset.gt_poses is None else dataset.gt_poses[0], dataset.R1)
    return {"poses": est.tolist(), "failed_frames": failed, "failures": reasons, "track_s": track_s, "frames": n,
            "params": p}


# ------------------------------------------------------------------------------------------------
# our pipeline
# the pipeline's per-frame times that are not tracking work: reading and stereo depth (the
# read-ahead thread's), the logging, the main thread's wall time per frame, and its wait for the
# mapping thread (whose fusion is counted as its own stage)
NOT_TRACKING = ("read", "stereo", "logging", "total", "map_wait")


def tracking_ms(timings: dict) -> float:
    """Our tracking work per frame (ms) from the pipeline's per-stage means (``metrics.json``'s
    ``timings_ms``): the sum of the stages that track and map, on whichever thread they ran (the
    flow computed ahead, the mapping thread's fusion), without reading and stereo depth.
    (The main thread's wall time minus the read-ahead thread's reading and stereo is not that:
    they overlap, and it comes out near zero or negative.)"""
    return float(sum(ms for stage, ms in timings.items() if stage not in NOT_TRACKING))


def run_ours(data: str, overrides: list[str], out: str, frames=None, mode: str = "frame2frame") -> dict:
    """Our pipeline (``run_from_config``) with ``tracking.mode=mode``. Timing: the pipeline's
    per-stage means; ``track_s`` is the tracking work without reading frames and the stereo depth
    (:func:`tracking_ms`, comparable with the baselines)."""
    from slam.config import load_config
    from slam.app.runner import run_from_config

    cfg = load_config(None, [*overrides, f"tracking.mode={mode}"])
    result = run_from_config(data, cfg, out, frames, print_summary=False, overwrite=True)
    m = result.metrics
    n = m["frames"]
    return {"poses": [r.pose.tolist() for r in result.records], "failed_frames": m["failed_frames"],
            "failures": m.get("failures", {}), "track_s": tracking_ms(m.get("timings_ms", {})) * n / 1000.0, "frames": n,
            "pipeline_fps": m["fps"], "params": {"mode": mode, "weights": cfg.weights.mode}}


# ------------------------------------------------------------------------------------------------
# one job per process
def run_job(job: dict) -> dict:
    """Run one job in this process. ``job["kind"]``: ``odometry``, ``dense_slam``, ``ours`` (keyword
    arguments in ``job["args"]``) or ``call`` (``job["file"]``'s ``job["function"](**args)``)."""
    kind, args = job["kind"], dict(job.get("args", {}))
    if kind == "odometry":
        return run_rgbd_odometry(**args)
    if kind == "dense_slam":
        return run_dense_slam(**args)
    if kind == "ours":
        return run_ours(**args)
    if kind == "call":
        spec = importlib.util.spec_from_file_location("_baseline_job", job["file"])
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return getattr(module, job["function"])(**args)
    raise ValueError(f"unknown job kind '{kind}'")


def run_isolated(job: dict, log_path: str | Path | None = None, timeout: float | None = None) -> dict:
    """Run ``job`` in a fresh Python process; never raises for what happens in the child.

    Returns:
        ``{"status": "ok", "result": {...}}`` or ``{"status": "crash" | "error" | "timeout",
        "returncode": int | None, "signal": name | None, "message": str}``: ``crash`` = the child
        died (signal, e.g. SIGSEGV/SIGABRT, or a non-zero exit without a Python error), ``error`` =
        the job raised a Python exception, ``timeout`` = it ran longer than ``timeout`` seconds.
    """
    with tempfile.TemporaryDirectory(prefix="baseline_job_") as tmp:
        job_file, result_file = Path(tmp) / "job.json", Path(tmp) / "result.json"
        job_file.write_text(json.dumps(job))
        log = open(log_path, "a") if log_path else subprocess.DEVNULL
        try:
            cmd = [sys.executable, "-m", "benchmarks.baselines_open3d", str(job_file), str(result_file)]
            proc = subprocess.run(cmd, stdout=log, stderr=log, timeout=timeout, cwd=str(ROOT))
        except subprocess.TimeoutExpired:
            return {"status": "timeout", "returncode": None, "signal": None, "message": f"timed out after {timeout} s"}
        finally:
            if log_path:
                log.close()
        rc = proc.returncode
        payload = json.loads(result_file.read_text()) if result_file.is_file() else None
        if rc == 0 and payload is not None and "result" in payload:
            return {"status": "ok", "result": payload["result"], "returncode": 0, "signal": None, "message": ""}
        if payload is not None and "error" in payload:
            return {"status": "error", "returncode": rc, "signal": None, "message": payload["error"]}
        sig = None
        if rc < 0:
            try:
                sig = signal.Signals(-rc).name
            except ValueError:
                sig = str(-rc)
        return {"status": "crash", "returncode": rc, "signal": sig,
                "message": f"child died ({sig or f'exit code {rc}'})"}


def main(argv: list[str] | None = None) -> int:
    """Run the job of ``JOB.json`` and write its result (or its error) to ``RESULT.json``."""
    import faulthandler
    import traceback

    job_file, result_file = sys.argv[1:] if argv is None else argv
    faulthandler.enable()  # a native crash prints the Python stack to the log
    job = json.loads(Path(job_file).read_text())
    try:
        result = run_job(job)
    except Exception as err:  # reported to the parent as an error, not a crash
        traceback.print_exc()
        Path(result_file).write_text(json.dumps({"error": f"{type(err).__name__}: {err}"}))
        return 1
    Path(result_file).write_text(json.dumps({"result": result}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
