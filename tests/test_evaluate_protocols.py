"""The paper's evaluation protocols (`slam evaluate --protocol stereomis|scared`, through their
wrappers benchmarks/evaluate_stereomis.py and benchmarks/evaluate_scared.py that make synthetic
stand-ins in the StereoMIS and SCARED layouts) end to end, run from the command line."""
from __future__ import annotations

import json
import math
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
THREADS = ["--set", "threads=1", "--executor", "local"]


def run_tool(name: str, *args, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -m benchmarks.NAME ARGS`` (``name`` with or without ``.py``)."""
    module = f"benchmarks.{name.removesuffix('.py')}"
    return subprocess.run([sys.executable, "-m", module, *map(str, args)], capture_output=True, text=True,
                          env=ENV, cwd=REPO, timeout=timeout)


def finite(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def assert_one_line_error(res: subprocess.CompletedProcess, *needles: str) -> None:
    assert res.returncode == 2, res.stdout + res.stderr
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert "error:" in lines[0]
    for n in needles:
        assert n in lines[0], lines[0]


# ------------------------------------------------------------------------------------------------
# StereoMIS
@pytest.fixture(scope="module")
def stereomis(tmp_path_factory):
    """The StereoMIS stand-in (3 sequences x 12 frames, 160x128) and its evaluation, run once."""
    folder = tmp_path_factory.mktemp("stereomis") / "standin"
    res = run_tool("evaluate_stereomis.py", "--synthetic", folder, "--synthetic-frames", 12,
                   "--synthetic-size", "160x128", *THREADS)
    assert res.returncode == 0, res.stdout + res.stderr
    return folder, res


def test_stereomis_standin_end_to_end(stereomis):
    folder, res = stereomis
    out = folder / "results"
    md = (out / "evaluation.md").read_text()
    assert "Table 1 style" in md and "Table 2 style" in md and "Table 1 style" in res.stdout
    report = json.loads((out / "summary.json").read_text())
    rows = report["rows"]
    assert len(rows) == 9  # 3 sequences x (2 clips + full), frame2frame
    for r in rows:
        assert r["status"] == "ok", r
        assert r["frames"] == (12 if r["scenario"] == "full" else 6)
        for key in ("ate_rmse_mm", "rpe_trans_mm", "rpe_trans_std_mm", "rpe_rot_deg", "rpe_rot_std_deg"):
            assert finite(r[key]) and r[key] >= 0, (key, r)
        assert r["ate_rmse_mm"] < 3.0 and r["rpe_trans_mm"] < 1.0 and r["rpe_rot_deg"] < 1.0, r
        assert (Path(r["out"]) / "trajectory.txt").is_file()
    t1 = report["tables"]["table1"]["frame2frame"]
    for sc in ("breathing", "scanning", "deforming"):
        assert t1[sc]["n"] == 2 and finite(t1[sc]["mean"]) and t1[sc]["mean"] < 3.0
    assert t1["micro"]["n"] == 6 and finite(t1["micro"]["mean"])
    assert t1["macro"]["n"] == 3 and finite(t1["macro"]["mean"])
    t2 = report["tables"]["table2"]["frame2frame"]
    assert t2["average"]["n"] == 3 and finite(t2["average"]["ate_rmse_mm"]["mean"])
    assert set(t2["subjects"]) == {"P2", "P3"} and t2["macro"]["n"] == 2
    p2 = [r["ate_rmse_mm"] for r in rows if r["scenario"] == "full" and r["group"] == "P2"]
    assert t2["subjects"]["P2"]["ate_rmse_mm"] == pytest.approx(np.mean(p2))
    assert report["errors"] == 0


def test_stereomis_bad_rows_are_error_rows(stereomis, tmp_path):
    folder, _ = stereomis
    csv = tmp_path / "protocol.csv"
    csv.write_text("# a protocol with failing rows\n"
                   "sequence,start,end,scenario,split\n"
                   "P2_0,0,4,scanning,test\n"
                   "P9_9,0,6,breathing,test\n"       # missing sequence
                   "P2_0,0,500,scanning,test\n"      # beyond the sequence
                   "P9_9,,,full,test\n"
                   "P2_0,0,6,scanning,train\n")      # other split: skipped
    out = tmp_path / "out"
    res = run_tool("evaluate_stereomis.py", folder, "--csv", csv, "--out", out, *THREADS,
                   "--set", "data.width=0", "--set", "data.height=0")
    assert res.returncode == 1, res.stdout + res.stderr   # failed tasks: the table, and a non-zero exit
    assert "Traceback" not in res.stderr
    report = json.loads((out / "summary.json").read_text())
    rows = {(r["sequence"], r["selection"]): r for r in report["rows"]}
    assert len(rows) == 4
    assert rows[("P2_0", "0:4")]["status"] == "ok" and finite(rows[("P2_0", "0:4")]["ate_rmse_mm"])
    assert rows[("P9_9", "0:6")]["status"] == "error" and "P9_9" in rows[("P9_9", "0:6")]["message"]
    assert "no such folder" in rows[("P9_9", "0:6")]["message"]
    assert rows[("P2_0", "0:500")]["status"] == "error" and "beyond" in rows[("P2_0", "0:500")]["message"]
    assert rows[("P9_9", "")]["status"] == "error"
    assert all("\n" not in r.get("message", "") for r in rows.values())
    assert report["errors"] == 3
    assert report["tables"]["table1"]["frame2frame"]["breathing"]["errors"] == 1
    assert report["tables"]["table2"]["frame2frame"]["errors"] == 1
    assert any("other splits skipped" in n for n in report["notes"])
    md = (out / "evaluation.md").read_text()
    assert "| P9_9 | error: " in md


def test_stereomis_bad_arguments(tmp_path):
    assert_one_line_error(run_tool("evaluate_stereomis.py", tmp_path, "--bogus"), "unrecognized")
    assert_one_line_error(run_tool("evaluate_stereomis.py"), "root")
    assert_one_line_error(run_tool("evaluate_stereomis.py", tmp_path / "missing"), "no such folder")
    assert_one_line_error(run_tool("evaluate_stereomis.py", tmp_path, "--set", "tracking.mdoe=x"), "tracking.mdoe")
    assert_one_line_error(run_tool("evaluate_stereomis.py", tmp_path, "--modes", "frame2nothing"), "--modes")
    bad = tmp_path / "bad.csv"
    bad.write_text("sequence,start,end,scenario,split\nP2_0,0,150,walking,test\n")
    assert_one_line_error(run_tool("evaluate_stereomis.py", tmp_path, "--csv", bad), "bad.csv:2", "walking")
    bad.write_text("sequence,start,end,scenario,split\nP2_0,0,150,scanning,test\nP2_0,0,150,scanning,test\n")
    assert_one_line_error(run_tool("evaluate_stereomis.py", tmp_path, "--csv", bad), "bad.csv:3", "same clip")
    bad.write_text("sequence,start,scenario\nP2_0,0,full\n")
    assert_one_line_error(run_tool("evaluate_stereomis.py", tmp_path, "--csv", bad), "end")
    assert_one_line_error(run_tool("evaluate_stereomis.py", tmp_path, "--csv", tmp_path / "none.csv"), "none.csv")


def test_default_protocol_csv_parses():
    from slam.batch.protocols import CONFIGS, read_stereomis_csv

    rows = read_stereomis_csv(CONFIGS / "stereomis_protocol.csv")
    assert rows and {r["scenario"] for r in rows} <= {"breathing", "scanning", "deforming", "full"}
    assert "TEMPLATE" in (CONFIGS / "stereomis_protocol.csv").read_text()


# ------------------------------------------------------------------------------------------------
# SCARED
@pytest.fixture(scope="module")
def scared(tmp_path_factory):
    """The SCARED stand-in (d1_k2, d8_k1; 12 frames, 320x256) and its evaluation, run once."""
    folder = tmp_path_factory.mktemp("scared") / "standin"
    res = run_tool("evaluate_scared.py", "--synthetic", folder, "--datasets", 1, 8, "--synthetic-frames", 12,
                   "--synthetic-size", "320x256", *THREADS)
    assert res.returncode == 0, res.stdout + res.stderr
    return folder, res


def test_scared_standin_layout(scared):
    from slam.io.datasets import DataConfig, detect_layout, open_dataset

    folder, _ = scared
    kf = folder / "dataset_1" / "keyframe_2"
    for name in ("endoscope_calibration.yaml", "data/rgb.mp4", "data/frame_data/frame_data000000.json",
                 "left_depth_map.tiff", "Left_Image.png"):
        assert (kf / name).is_file(), name
    assert detect_layout(kf) == "scared"
    ds = open_dataset(kf, DataConfig(rectify_mode="pseudo"))
    assert len(ds) == 12 and ds.camera.width == 320
    np.testing.assert_allclose(ds.gt_poses[0], np.eye(4), atol=1e-9)  # world = the keyframe's camera
    assert np.linalg.norm(ds.gt_poses[-1][:3, 3]) > 1.0  # the camera moves
    ds.close()


def test_scared_standin_end_to_end(scared):
    folder, res = scared
    out = folder / "results"
    md = (out / "evaluation.md").read_text()
    assert "Table 3 style" in md and "Map accuracy" in md and "Table 3 style" in res.stdout
    report = json.loads((out / "summary.json").read_text())
    rows = report["rows"]
    assert [r["sequence"] for r in rows] == ["d1_k2", "d8_k1"]
    for r in rows:
        assert r["status"] == "ok" and r["mode"] == "frame2model", r
        assert r["frames"] == 12 and r["failed"] == 0
        for key in ("ate_rmse_mm", "rpe_trans_mm", "rpe_rot_deg", "map_median_mm", "map_mean_mm", "map_coverage"):
            assert finite(r[key]), (key, r)
        assert r["ate_rmse_mm"] < 2.0 and r["rpe_trans_mm"] < 1.0, r
        assert r["map_median_mm"] < 1.0 and r["map_mean_mm"] < 2.0, r
        assert 0.05 < r["map_coverage"] <= 1.0 and r["map_points"] > 1000 and r["gt_pixels"] > 0.5 * 320 * 256
    s = report["tables"]["table3"]["frame2model"]
    assert s["n"] == 2 and finite(s["ate_rmse_mm"]["mean"]) and s["paper_avg_ate_mm"]["n"] == 2
    assert s["map_median_mm"]["mean"] == pytest.approx(np.mean([r["map_median_mm"] for r in rows]))
    assert report["errors"] == 0


def test_scared_missing_keyframes_are_error_rows(scared, tmp_path):
    folder, _ = scared
    root = tmp_path / "scared"
    (root / "dataset_9" / "keyframe_3").mkdir(parents=True)
    shutil.copytree(folder / "dataset_1", root / "dataset_1")
    shutil.copy(folder / "dataset_1" / "keyframe_2" / "endoscope_calibration.yaml", root / "dataset_9" / "keyframe_3")
    out = tmp_path / "out"
    res = run_tool("evaluate_scared.py", root, "--keyframes", "d1_k2", "d8_k1", "d9_k3", "--frames", 4,
                   "--modes", "frame2frame", "--no-map", "--out", out, *THREADS,
                   "--set", "data.width=0", "--set", "data.height=0")
    assert res.returncode == 1, res.stdout + res.stderr   # failed tasks: the table, and a non-zero exit
    assert "Traceback" not in res.stderr
    report = json.loads((out / "summary.json").read_text())
    status = {r["sequence"]: r for r in report["rows"]}
    assert status["d1_k2"]["status"] == "ok" and status["d1_k2"]["frames"] == 4
    assert "map_median_mm" not in status["d1_k2"]
    assert status["d8_k1"]["status"] == "error" and "not found" in status["d8_k1"]["message"]
    assert status["d9_k3"]["status"] == "error" and "rgb.mp4" in status["d9_k3"]["message"]
    assert report["errors"] == 2
    line = next(ln for ln in (out / "evaluation.md").read_text().splitlines() if ln.startswith("| d9_k3 |"))
    assert "| error |" in line and "rgb.mp4" in line


def test_scared_bad_arguments(tmp_path):
    assert_one_line_error(run_tool("evaluate_scared.py", tmp_path, "--bogus"), "unrecognized")
    assert_one_line_error(run_tool("evaluate_scared.py"), "root")
    assert_one_line_error(run_tool("evaluate_scared.py", tmp_path / "missing"), "no such folder")
    assert_one_line_error(run_tool("evaluate_scared.py", tmp_path, "--datasets", "one"), "--datasets")
    assert_one_line_error(run_tool("evaluate_scared.py", tmp_path, "--keyframes", "k2"), "--keyframes")
    assert_one_line_error(run_tool("evaluate_scared.py", tmp_path, "--frames", "1:a"), "--frames")
    assert_one_line_error(run_tool("evaluate_scared.py", tmp_path, "--config", tmp_path / "no.yaml"), "no.yaml")


def test_gt_depth_files(tmp_path):
    """left_depth_map.tiff stores x, y, z in file order; the loaders read back z; npy and png work."""
    import cv2

    from slam.synth.scared_layout import read_xyz_tiff, write_xyz_tiff

    from slam.batch.map_accuracy import load_gt_depth

    xyz = np.zeros((4, 5, 3), np.float32)
    xyz[..., 0], xyz[..., 1], xyz[..., 2] = 1.5, 2.5, 80.0
    xyz[0, 0] = 0.0  # unknown pixel
    write_xyz_tiff(tmp_path / "left_depth_map.tiff", xyz)
    np.testing.assert_array_equal(read_xyz_tiff(tmp_path / "left_depth_map.tiff"), xyz)
    raw = (tmp_path / "left_depth_map.tiff").read_bytes()
    assert struct.pack("<fff", 1.5, 2.5, 80.0) in raw  # x y z per pixel, as SCARED / tifffile
    z, path = load_gt_depth(tmp_path)
    assert path.name == "left_depth_map.tiff" and np.isnan(z[0, 0]) and np.all(z.flat[1:] == 80.0)
    np.save(tmp_path / "d.npy", xyz[..., 2])
    z, _ = load_gt_depth(tmp_path, "d.npy")
    assert np.isnan(z[0, 0]) and z[1, 1] == 80.0
    cv2.imwrite(str(tmp_path / "d.png"), (xyz[..., 2] / 0.01).astype(np.uint16))
    z, _ = load_gt_depth(tmp_path, "d.png", 0.01)
    assert np.isnan(z[0, 0]) and z[1, 1] == pytest.approx(80.0)
    assert load_gt_depth(tmp_path / "nothing") == (None, None)
