"""The generator's folders read back through the dataset readers, and the raw (unrectified,
distorted) layout tracked end to end, which exercises rectification and the R1 convention."""
import json

import numpy as np

from slam.app.cli import main
from slam.io.datasets import DataConfig, open_dataset
from slam.io.tum import read_tum


def test_synth_deforming_reads_back(tmp_path):
    out = tmp_path / "deforming"
    assert main(["synth", str(out), "--scenario", "deforming", "--frames", "20", "--size", "160x128", "--seed", "3"]) == 0
    ds = open_dataset(out, DataConfig())
    assert ds.layout == "stereomis" and len(ds) == 20
    assert ds.gt_poses is not None and ds.gt_poses.shape == (20, 4, 4)
    frames = list(ds)
    assert all(f.left.shape == (128, 160, 3) for f in frames)
    instrument_pixels = [int((~f.mask).sum()) for f in frames]
    assert max(instrument_pixels) > 100  # instrument masks are combined into the valid mask
    assert all(f.gt_depth is not None and np.nanmax(f.gt_depth) > 20 for f in frames)
    assert "nonrigid_mm" in frames[-1].extras and frames[-1].extras["nonrigid_mm"].max() > 0.5


def test_raw_layout_is_rectified_and_tracked(synth_dir, tmp_path):
    raw = synth_dir("rigid", 12, (320, 256), seed=5, raw=True)
    ds = open_dataset(raw, DataConfig())
    assert ds.layout == "stereomis_raw" and len(ds) == 12
    assert not np.allclose(ds.R1, np.eye(3))  # the right camera is rotated: rectification rotates the left
    out = tmp_path / "run"
    assert main(["run", str(raw), "--weights", "constant", "--out", str(out), "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    _, gt = read_tum(raw / "groundtruth.txt")
    spread = np.sqrt(((gt[:, :3, 3] - gt[:, :3, 3].mean(0)) ** 2).sum(1).mean())
    assert m["failed_frames"] == [] and m["ate_rmse_mm"] < 0.3 * spread
    # the reported orientation is the original (unrectified) left camera's: reporting the
    # rectified camera instead would be off by the rectifying rotation R1 from the first step on
    _, est = read_tum(out / "trajectory.txt")
    r1_angle = np.degrees(np.arccos(np.clip((np.trace(ds.R1) - 1) / 2, -1, 1)))
    for k in (1, 2):
        R_err = est[k, :3, :3].T @ gt[k, :3, :3]
        angle = np.degrees(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1)))
        assert angle < 0.5 * r1_angle, (k, angle, r1_angle)
