"""Map accuracy of `slam run`'s exported map.ply against the generator's ground-truth surface.

The exported points (metres, world frame of trajectory.txt) are projected into several frames with
the ground-truth poses; where they land on a pixel with ground-truth depth, the difference between
the point's depth and the surface's depth is its distance to the surface along the ray (the
surface is smooth at this scale, so this is within a few percent of the normal distance).
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from slam.app.cli import main
from slam.io.datasets import open_dataset
from slam.evaluation.map_error import depth_errors_mm as map_depth_errors
from slam.io.tum import read_tum


def depth_errors_mm(ply, data, frame_ids) -> np.ndarray:
    """``(M,)`` absolute depth differences (mm) of the map's points seen in ``frame_ids``."""
    import open3d as o3d

    pts_mm = np.asarray(o3d.io.read_point_cloud(str(ply)).points) * 1000.0
    assert len(pts_mm) > 1000, f"{ply}: only {len(pts_mm)} points"
    ds = open_dataset(data)
    K, R1 = ds.camera.K, ds.R1
    errors = []
    for i in frame_ids:
        _, err = map_depth_errors(pts_mm, ds.gt_poses[i], K, R1, ds.frame(i).gt_depth)
        errors.append(np.abs(err))
    return np.concatenate(errors)


@pytest.mark.parametrize("scenario,seed", [("rigid", 8101), ("scanning", 8102)])
def test_map_fused_with_groundtruth_poses_within_half_a_millimetre(synth_dir, tmp_path, scenario, seed):
    data = synth_dir(scenario, 40, (320, 256), seed=seed)
    out = tmp_path / "gt_poses"
    assert main(["run", str(data), "--mode", "frame2model", "--out", str(out), "--quiet",
                 "--set", "analysis.poses=groundtruth"]) == 0
    # the trajectory written is the ground truth itself
    _, est = read_tum(out / "trajectory.txt")
    _, gt = read_tum(data / "groundtruth.txt")
    assert np.allclose(est, gt, atol=1e-6)
    err = depth_errors_mm(out / "map.ply", data, [0, 13, 26, 39])
    assert len(err) > 20_000
    assert np.median(err) < 0.5, f"median {np.median(err):.3f} mm"


def test_map_of_a_frame2model_run_within_one_millimetre(synth_dir, tmp_path):
    data = synth_dir("rigid", 60, (320, 256), seed=8103)
    out = tmp_path / "f2m"
    assert main(["run", str(data), "--mode", "frame2model", "--out", str(out), "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["failed_frames"] == []
    err = depth_errors_mm(out / "map.ply", data, [0, 20, 40, 59])
    assert len(err) > 20_000
    assert np.median(err) < 1.0, f"median {np.median(err):.3f} mm (ATE {m['ate_rmse_mm']:.3f} mm)"


def test_groundtruth_poses_without_groundtruth_is_a_clear_error(synth_dir, tmp_path, capsys):
    data = synth_dir("rigid", 6, (160, 128), seed=8104)
    bare = tmp_path / "bare"
    import shutil

    shutil.copytree(data, bare)
    (bare / "groundtruth.txt").unlink()
    code = main(["run", str(bare), "--mode", "frame2model", "--out", str(tmp_path / "o"), "--quiet",
                 "--set", "analysis.poses=groundtruth"])
    assert code != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err and "ground" in err[-1].lower()
