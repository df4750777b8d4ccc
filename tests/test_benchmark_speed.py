"""benchmarks/benchmark_speed.py end to end on a tiny sequence: the runs' table and the map-cost table."""
from __future__ import annotations

import json
import sys

import numpy as np

from benchmarks import benchmark_speed as B
from slam.io.tum import read_tum


def test_speed_benchmark_reports_runs_and_the_map_cost(tmp_path, monkeypatch, capsys):
    out = tmp_path / "speed"
    monkeypatch.setattr(sys, "argv", ["benchmark_speed.py", "--frames", "8", "--sizes", "160x128",
                                      "--map-surfels", "20000", "--map-sizes", "160x128", "--out", str(out)])
    B.main()
    data = json.loads((out / "speed.json").read_text())
    runs = {r["mode"]: r for r in data["runs"]}
    assert set(runs) == {"frame2frame", "frame2model"}
    for r in runs.values():
        assert r["failed"] == 0 and r["fps"] > 0 and 0 < r["ate_rmse_mm"] < 1.0
    assert runs["frame2model"]["render_ms"] > 0 and runs["frame2model"]["fusion_ms"] > 0
    assert runs["frame2frame"]["render_ms"] is None
    for r in runs.values():     # the CPU time of each pipeline thread, and of the process (its pools too)
        assert r["cpu_main_ms"] > 0 and r["cpu_reader_ms"] > 0
        assert r["cpu_process_ms"] >= 0.9 * (r["cpu_main_ms"] + r["cpu_reader_ms"] + (r["cpu_mapping_ms"] or 0.0))
        assert r["pools"]["torch"] >= 1 and r["pools"]["opencv"] >= 1
    (cost,) = data["map_cost"]
    assert cost["size"] == "160x128" and cost["surfels"] >= 20000 and 0 < cost["visible"] < cost["surfels"]
    assert 0 < cost["fuse"] < cost["total_rgb"] and cost["render_rgb"] > 0
    table = (out / "speed.md").read_text()
    assert runs["frame2model"]["cpu_mapping_ms"] > 0 and runs["frame2frame"]["cpu_mapping_ms"] is None
    assert "| scanning | 160x128 | frame2model |" in table and "thread pools: " in table
    assert f"| 160x128 | {cost['surfels']} | {int(cost['visible'])} | {cost['fuse']:.1f} |" in table
    assert table in capsys.readouterr().out


def test_speed_benchmark_compares_checkouts_run_by_run(tmp_path, capsys):
    """Two checkouts (here the same one twice), alternating, twice each: median rows with their
    fps range and the ratio table; both ran the same sequence, so their poses agree."""
    from pathlib import Path

    root = str(Path(B.__file__).resolve().parents[1])
    out = tmp_path / "cmp"
    B.main(["--frames", "6", "--sizes", "160x128", "--modes", "frame2frame", "--repeat", "2",
            "--repo", f"base={root}", "--repo", f"new={root}", "--map-surfels", "0", "--out", str(out)])
    data = json.loads((out / "speed.json").read_text())
    assert [(r["repo"], r["rep"]) for r in data["runs"]] == [("base", 0), ("new", 0), ("base", 1), ("new", 1)]
    rows = {r["repo"]: r for r in data["rows"]}
    assert set(rows) == {"base", "new"}
    for name, row in rows.items():
        fps = sorted(r["fps"] for r in data["runs"] if r["repo"] == name)
        assert row["fps"] == (fps[0] + fps[1]) / 2 and row["fps_range"] == f"{fps[0]:.2f}-{fps[1]:.2f}"
    assert rows["base"]["ate_rmse_mm"] == rows["new"]["ate_rmse_mm"]
    table = (out / "speed.md").read_text()
    ratio = rows["new"]["fps"] / rows["base"]["fps"]
    assert "median fps over base's:" in table and f"| scanning | 160x128 | frame2frame | {ratio:.2f}x |" in table


def test_the_real_sequence_is_run_from_a_folder_of_links_carrying_its_reference(tmp_path):
    from benchmarks.accuracy_panel import REAL_TRAJECTORY

    real = tmp_path / "scared"
    for name in ("left_image", "right_image"):
        (real / name).mkdir(parents=True)
    (real / "calibration.json").write_text("{}")
    data = B.real_sequence(tmp_path / "out", str(real))
    (stamps, poses), (ref_stamps, ref_poses) = read_tum(data / "groundtruth.txt"), read_tum(REAL_TRAJECTORY)
    np.testing.assert_allclose(stamps, ref_stamps)
    np.testing.assert_allclose(poses, ref_poses, atol=1e-6)      # the reference as it is (not moved)
    assert (data / "left_image").resolve() == (real / "left_image").resolve()
    assert (data / "calibration.json").is_symlink()
