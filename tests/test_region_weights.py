"""tools/region_weights.py: the ideal per-region weight and its moving-tissue ratio."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

TOOL = Path(__file__).resolve().parents[1] / "tools" / "region_weights.py"


def load_tool():
    spec = importlib.util.spec_from_file_location("region_weights", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_region_ratio_by_hand():
    tool = load_tool()
    # 4 pixels, 2 frames: pixel 0 never moves, 1 a little, 2 and 3 breathe (peaks 1.0 and 2.0 mm)
    nonrigid = np.array([[[0.0, 0.1, 0.2, 0.4]], [[0.0, 0.3, 1.0, 2.0]]])
    tissue = np.ones_like(nonrigid, bool)
    # keep half: pixels 0 and 1 weigh 1; displaced (> 0.5 mm): (2, t1), (3, t1) -> mean 0;
    # the others: 0 and 1 in both frames (weight 1) and 2, 3 in frame 0 (weight 0) -> 4 / 6
    assert tool.region_ratio(nonrigid, tissue, 0.5) == 0.0
    # keep 3 of 4 (peak <= 1.0): displaced (2, t1) weight 1, (3, t1) 0 -> 0.5; the others 5 of 6
    assert np.isclose(tool.region_ratio(nonrigid, tissue, 0.75), 0.5 / (5 / 6))
    # instrument over pixel 3 in frame 1: that displaced sample no longer counts
    tissue[1, 0, 3] = False
    assert np.isclose(tool.region_ratio(nonrigid, tissue, 1.0), 1.0)
    assert tool.region_ratio(np.zeros_like(nonrigid), np.ones_like(tissue), 0.5) is None  # nothing displaced


def test_on_a_generated_sequence(tmp_path, synth_dir):
    data = synth_dir("breathing", frames=30, size=(64, 48), seed=3)
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, str(TOOL), str(data), "--keep", "0.5", "1.0", "--out", str(out)],
                         capture_output=True, text=True, check=True)
    rows = json.loads((out / "region_weights.json").read_text())
    assert "ratio, keep 0.5 of the view kept" in run.stdout
    assert 0.1 < rows[0]["displaced_share"] < 0.9
    assert rows[0]["keep 1"] == 1.0  # weight 1 everywhere: ratio 1
    assert rows[0]["keep 0.5"] < 0.5  # the stiller half of the view holds little displaced tissue
