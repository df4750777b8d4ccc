"""benchmarks/compare_baselines.py: the Open3D baselines on our stereo depth, crash isolation, tables."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks import baselines_open3d as B
from benchmarks import compare_baselines as C


@pytest.fixture(scope="module")
def rigid(synth_dir, tmp_path_factory):
    """A tiny rigid sequence and its cached stereo depth."""
    data = synth_dir("rigid", 20, (160, 128))
    cache = B.compute_depth_cache(data, tmp_path_factory.mktemp("depth") / "rigid.npz", [], None)
    return data, cache


def _spread(gt: np.ndarray) -> float:
    """ATE of a camera that never moves (SE(3) alignment cannot do better than the centroid)."""
    return float(np.sqrt(((gt[:, :3, 3] - gt[:, :3, 3].mean(0)) ** 2).sum(1).mean()))


def test_depth_cache_is_our_stereo_depth(rigid):
    import torch

    from slam.io.datasets import DataConfig, open_dataset
    from vo.config import VOConfig
    from vo.odometry import StereoOdometry
    from vo.config import WeightsConfig

    data, cache = rigid
    depth, rest = B.load_depth_mm(cache)
    ds = open_dataset(data, DataConfig())
    assert depth.shape == (20, ds.camera.height, ds.camera.width) and len(rest["stereo_ms"]) == 20
    frame = ds.frame(3)
    with torch.inference_mode():
        view = StereoOdometry(ds.camera, VOConfig(weights=WeightsConfig(mode="constant"))).make_view(
            frame.left, frame.right, frame.mask, specular=frame.specular)
    ours = view.depth[0, 0].numpy()
    assert np.array_equal(ours > 0, depth[3] > 0)
    assert np.abs(ours - depth[3]).max() <= B.DEPTH_UNIT_MM  # quantisation only
    assert (depth[3][~frame.mask] == 0).all()


def test_open3d_odometry_recovers_rigid_trajectory(rigid):
    from slam.io.datasets import DataConfig, open_dataset
    from slam.evaluation.metrics import evaluate

    data, cache = rigid
    gt = open_dataset(data, DataConfig()).gt_poses
    for jacobian in ("color", "hybrid"):
        result = B.run_rgbd_odometry(str(data), str(cache), [], None, jacobian=jacobian)
        est = np.asarray(result["poses"])
        assert est.shape == (20, 4, 4) and result["failed_frames"] == []
        assert np.allclose(est[0], gt[0])  # anchored at the first ground-truth pose
        ate = evaluate(gt, est)["ate_rmse_mm"]
        # The colour-only term follows the highlights, which ride with the light on this tiny
        # sequence: on seeds 0-2 it scored 1.0-3.0 mm (spreads 2.3-3.6) with either version of
        # our stereo depth, the hybrid one 0.5-2.0; it must still beat a camera that never moves.
        bound = 0.4 if jacobian == "hybrid" else 0.6
        assert ate < bound * _spread(gt), (jacobian, ate, _spread(gt))
        assert result["track_s"] > 0


def test_anchor_handles_rectification():
    from scipy.spatial.transform import Rotation

    R1 = Rotation.from_euler("xyz", [2, -1, 3], degrees=True).as_matrix()
    gt0 = np.eye(4)
    gt0[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    gt0[:3, 3] = [1, 2, 3]
    step = np.eye(4)
    step[:3, 3] = [0, 0, 5]  # 5 mm along the rectified optical axis
    est = B.anchor(np.stack([np.eye(4), step]), gt0, R1)
    assert np.allclose(est[0], gt0)
    M = np.eye(4)
    M[:3, :3] = R1
    assert np.allclose(est[1], gt0 @ M.T @ step @ M)
    # the original camera moved along the rectified z axis expressed in the world
    assert np.allclose(est[1][:3, 3] - gt0[:3, 3], (gt0[:3, :3] @ R1.T) @ [0, 0, 5])


def _write_module(path: Path) -> Path:
    path.write_text(
        "import os\n"
        "def boom():\n    os.abort()\n"
        "def fail():\n    raise ValueError('bad input')\n"
        "def fine(x):\n    return {'twice': 2 * x}\n")
    return path


def test_runner_isolates_a_crash(tmp_path):
    module = _write_module(tmp_path / "jobs.py")
    crash = B.run_isolated({"kind": "call", "file": str(module), "function": "boom"}, log_path=tmp_path / "log.txt")
    assert crash["status"] == "crash" and crash["signal"] == "SIGABRT"
    error = B.run_isolated({"kind": "call", "file": str(module), "function": "fail"})
    assert error["status"] == "error" and "bad input" in error["message"]
    ok = B.run_isolated({"kind": "call", "file": str(module), "function": "fine", "args": {"x": 21}})
    assert ok["status"] == "ok" and ok["result"] == {"twice": 42}


def _seq(n=5):
    gt = np.repeat(np.eye(4)[None], n, axis=0)
    gt[:, 0, 3] = np.arange(n)
    return {"name": "seq", "data": "unused", "frames": None, "depth": "unused", "stereo_ms": np.full(n, 10.0),
            "gt": gt, "timestamps": np.arange(n) / 25.0, "size": "16x16", "n": n}


def test_dense_slam_retries_with_coarser_voxels_then_reports_crash(tmp_path):
    seq = _seq()
    calls = []

    def crashes_once(job, log_path=None, timeout=None):
        calls.append(job["args"]["voxel_mm"])
        if len(calls) == 1:
            return {"status": "crash", "returncode": -11, "signal": "SIGSEGV", "message": "child died (SIGSEGV)"}
        return {"status": "ok", "result": {"poses": seq["gt"].tolist(), "failed_frames": [], "track_s": 0.5,
                                           "frames": 5, "params": {}}}

    row = C.run_method("o3d_slam", seq, [], [], tmp_path, runner=crashes_once)
    v = B.SLAM_DEFAULTS["voxel_mm"]
    assert calls == [v, 2 * v] and row["status"] == "ok" and row["ate_rmse_mm"] < 1e-9
    assert row["fps"] == pytest.approx(10.0) and "after 1 failed" in row["notes"][0]

    def always_crashes(job, log_path=None, timeout=None):
        return {"status": "crash", "returncode": -11, "signal": "SIGSEGV", "message": "child died (SIGSEGV)"}

    row = C.run_method("o3d_slam", seq, [], [], tmp_path, runner=always_crashes)
    assert row["status"] == "crash" and len(row["attempts"]) == len(C.SLAM_VOXEL_FACTORS)
    table = C.format_tables([row], ["o3d_slam"], ["seq"])
    assert "crash" in table.split("### Average")[0]


def test_table_has_every_row():
    methods = list(C.METHODS)
    sequences = ["a", "b"]
    rows = []
    for s in sequences:
        for i, m in enumerate(methods):
            if s == "b" and m == "o3d_slam":
                rows.append({"sequence": s, "method": m, "status": "crash", "message": "child died (SIGSEGV)"})
                continue
            rows.append({"sequence": s, "method": m, "status": "ok", "ate_rmse_mm": 1.0 + i, "rpe_trans_mm": 0.1,
                         "rpe_rot_deg": 0.01, "fps": 10.0, "fps_with_depth": 5.0, "failed": 0, "frames": 5,
                         "notes": []})
    table = C.format_tables(rows, methods, sequences, notes=["a note"])
    ate, avg, every = table.split("###")[1:]
    for m in methods:
        label = C.METHODS[m]
        assert sum(line.startswith(f"| {label} |") for line in ate.splitlines()) == 1
        assert sum(line.startswith(f"| {label} |") for line in avg.splitlines()) == 1
        assert sum(f"| {label} |" in line for line in every.splitlines()) == 2
    slam_line = next(line for line in ate.splitlines() if line.startswith(f"| {C.METHODS['o3d_slam']} |"))
    assert "crash" in slam_line and "(1/2)" in slam_line
    assert "b not finished" in avg and "- a note" in table
    averages = {a["method"]: a for a in C.average_rows(rows, methods, sequences)}
    assert averages["o3d_color"]["ate_rmse_mm"] == pytest.approx(1.0) and averages["o3d_slam"]["n"] == 1


def test_compare_baselines_end_to_end(rigid, tmp_path):
    data, _ = rigid
    out = tmp_path / "cmp"
    assert C.main([str(data), "--out", str(out), "--frames", "12", "--methods", "o3d_hybrid", "o3d_slam", "static"]) == 0
    report = json.loads((out / "baselines.json").read_text())
    rows = {r["method"]: r for r in report["rows"]}
    assert set(rows) == {"o3d_hybrid", "o3d_slam", "static"}
    assert all(r["status"] == "ok" and r["frames"] == 12 for r in rows.values())
    assert rows["o3d_hybrid"]["ate_rmse_mm"] < rows["static"]["ate_rmse_mm"]
    assert (out / "runs" / data.name / "o3d_hybrid" / "trajectory.txt").is_file()
    assert "Open3D dense SLAM" in (out / "baselines.md").read_text()


def test_our_tracking_time_counts_the_work_of_every_thread_but_reading_and_stereo():
    """The read-ahead thread reads and computes stereo depth while the main thread tracks: the
    main thread's time per frame minus theirs was near zero or negative (fps in the thousands or
    none); the tracking time is the sum of the tracking and mapping stages wherever they ran."""
    # per-stage means of a 640x512 frame2frame run with the read-ahead thread (metrics.json)
    f2f = {"read": 120.7, "stereo": 356.9, "logging": 0.0, "total": 446.8, "flow": 92.8, "flow_back": 0.0,
           "weights": 146.8, "solve": 70.1, "flow_ahead": 80.5}
    assert f2f["total"] - f2f["read"] - f2f["stereo"] < 0
    assert B.tracking_ms(f2f) == pytest.approx(92.8 + 146.8 + 70.1 + 80.5)
    # frame2model: the mapping thread's fusion counts, the main thread's wait for it does not
    f2m = {"read": 8.9, "stereo": 394.4, "logging": 0.1, "total": 861.4, "cross_check": 189.7, "render": 263.2,
           "flow": 143.6, "flow_back": 0.0, "weights": 80.0, "solve": 22.8, "verify": 9.5, "fusion": 275.1,
           "map_wait": 87.4, "flow_ahead": 83.1}
    assert B.tracking_ms(f2m) == pytest.approx(189.7 + 263.2 + 143.6 + 80.0 + 22.8 + 9.5 + 275.1 + 83.1)
