"""Trajectory figures are written as real images, with and without ground truth."""
from __future__ import annotations

import os
import subprocess
import sys

import matplotlib.image as mpimg
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.app import plots


def _traj(rng, n=50, offset=None):
    s = np.linspace(0, 1, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.stack([40 * np.cos(2 * np.pi * s), 25 * np.sin(2 * np.pi * s), 5 * s], axis=1)
    poses[:, :3, :3] = Rotation.from_rotvec(np.outer(s, [0, 0.5, 0])).as_matrix()
    if offset is not None:
        poses = offset @ poses
    poses[:, :3, 3] += rng.normal(size=(n, 3)) * 0.5
    return poses


def _check_png(path, min_side=300):
    assert path.is_file() and path.stat().st_size > 10_000
    img = mpimg.imread(path)
    assert img.ndim == 3 and min(img.shape[:2]) >= min_side
    assert img[..., :3].std() > 0.01  # not a blank canvas


def test_plot_trajectory_with_gt(tmp_path):
    rng = np.random.default_rng(0)
    gt = _traj(rng)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [20, -10, 30], degrees=True).as_matrix()
    T[:3, 3] = [100, -50, 20]
    est = _traj(rng, offset=T)
    out = tmp_path / "sub" / "traj.png"
    plots.plot_trajectory(out, est, gt=gt, timestamps=np.arange(50) / 30.0, title="test")
    _check_png(out)


def test_plot_trajectory_without_gt_and_static(tmp_path):
    rng = np.random.default_rng(1)
    plots.plot_trajectory(tmp_path / "a.png", _traj(rng))
    _check_png(tmp_path / "a.png")
    static = np.tile(np.eye(4), (20, 1, 1))
    static[:, :3, 3] += rng.normal(size=(20, 3)) * 0.1
    plots.plot_trajectory(tmp_path / "b.png", static.copy(), gt=static)
    _check_png(tmp_path / "b.png")


def test_plot_comparison(tmp_path):
    rng = np.random.default_rng(2)
    gt = _traj(rng)
    ests = {"frame2frame": _traj(rng), "frame2model": _traj(rng)}
    plots.plot_comparison(tmp_path / "cmp.png", gt, ests, title="modes")
    _check_png(tmp_path / "cmp.png")
    plots.plot_comparison(tmp_path / "cmp_nogt.png", None, {"a": _traj(rng, 30), "b": _traj(rng, 40)})
    _check_png(tmp_path / "cmp_nogt.png")


def test_plot_rejects_bad_input(tmp_path):
    rng = np.random.default_rng(3)
    gt = _traj(rng)
    bad = gt.copy()
    bad[3, 1, 3] = np.inf
    with pytest.raises(ValueError):
        plots.plot_trajectory(tmp_path / "x.png", bad, gt=gt)
    with pytest.raises(ValueError):
        plots.plot_trajectory(tmp_path / "x.png", gt[:10], gt=gt)
    with pytest.raises(ValueError):
        plots.plot_comparison(tmp_path / "x.png", gt, {})
    assert not (tmp_path / "x.png").exists()


def test_never_uses_pyplot(tmp_path):
    # drawing happens on an Agg canvas: pyplot (and with it any GUI backend) is never imported
    code = (
        "import sys, numpy as np\n"
        "from slam.app import plots\n"
        "plots.plot_trajectory(sys.argv[1], np.tile(np.eye(4), (3, 1, 1)))\n"
        "assert 'matplotlib.pyplot' not in sys.modules\n"
    )
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path / "p.png")], capture_output=True, text=True,
                         env={**os.environ, "MPLBACKEND": "TkAgg"}, timeout=60)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "p.png").is_file()
