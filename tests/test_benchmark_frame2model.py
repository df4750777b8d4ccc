"""benchmarks/benchmark_frame2model.py end to end on a tiny sequence: table, ratios and JSON."""
from __future__ import annotations

import json
import sys

import pytest

from benchmarks import benchmark_frame2model as B


def test_benchmark_writes_ate_and_ratio_per_sequence(tmp_path, monkeypatch, capsys):
    out = tmp_path / "bench"
    monkeypatch.setattr(sys, "argv", ["benchmark_frame2model.py", "--scenarios", "rigid", "--seeds", "3",
                                      "--frames", "rigid=16", "--size", "160x128", "--workers", "1",
                                      "--methods", "frame2frame", "rendered", "--out", str(out)])
    B.main()
    data = json.loads((out / "frame2model.json").read_text())
    rows = {r["method"]: r for r in data["results"]}
    assert set(rows) == {"frame2frame", "rendered"}
    assert data["settings"]["frames"]["rigid"] == 16
    for r in rows.values():
        assert r["frames"] == 16 and r["failed"] == 0 and 0 < r["ate_rmse_mm"] < 2.0
        # the run's own outputs are there to inspect
        assert (out / "runs" / f"rigid_s3_{r['method']}" / "trajectory.txt").is_file()
    table = (out / "frame2model.md").read_text()
    ratio = rows["rendered"]["ate_rmse_mm"] / rows["frame2frame"]["ate_rmse_mm"]
    assert f"| rigid s3 | {rows['frame2frame']['ate_rmse_mm']:.3f} | {rows['rendered']['ate_rmse_mm']:.3f} | {ratio:.2f} |" in table
    assert "frames tracked against the previous frame" in table
    assert table.splitlines()[0] in capsys.readouterr().out


def test_frames_option_is_scenario_equals_count():
    assert B.parse_frames(["loop=120"]) == {"rigid": 150, "loop": 120}
    with pytest.raises(SystemExit):
        B.parse_frames(["120"])
