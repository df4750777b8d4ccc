"""benchmarks/benchmark_loop_map.py end to end on a tiny loop, and the map error it rests on."""
from __future__ import annotations

import json
import sys

import numpy as np

from benchmarks import benchmark_loop_map as B
from slam.evaluation.map_error import depth_errors_mm


def test_depth_errors_of_points_on_a_plane_and_behind_it():
    """A camera 50 mm above a plane (identity pose and rectification): points on it err by 0,
    points 1 mm behind by +1, points 8 mm behind are occluded, points out of view unseen."""
    K = np.array([[100.0, 0, 80], [0, 100.0, 64], [0, 0, 1]])
    gt = np.full((128, 160), 50.0)
    pts = np.array([[0, 0, 50.0], [5, 5, 51.0], [0, 0, 58.0], [500, 0, 50.0], [0, 0, -5.0]])
    seen, err = depth_errors_mm(pts, np.eye(4), K, np.eye(3), gt)
    assert seen.tolist() == [True, True, False, False, False]
    assert np.allclose(err, [0.0, 1.0])


def test_benchmark_reports_the_map_where_the_loop_closes(tmp_path, monkeypatch, capsys):
    out = tmp_path / "bench"
    monkeypatch.setattr(sys, "argv", ["benchmark_loop_map.py", "--seeds", "5", "--frames", "30", "--size", "160x128",
                                      "--methods", "rendered", "--workers", "1", "--out", str(out)])
    B.main()
    (row,) = json.loads((out / "loop_map.json").read_text())
    assert row["sequence"] == "loop s5" and row["method"] == "rendered" and row["loops"] is None
    # the camera ends where it started: the first and the last view overlap
    assert row["points"] > 5000 and row["overlap_points"] > 1000
    assert 0 < row["median_mm"] < 1.0 and row["doubled_share"] < 0.05
    table = (out / "loop_map.md").read_text()
    assert f"| loop s5 | rendered | {row['ate_rmse_mm']:.3f} |" in table
    assert table.splitlines()[0] in capsys.readouterr().out
