"""Long runs, kept out of CI (`pytest -m slow`): memory stays bounded over thousands of frames,
and the paper-resolution accuracy target."""
import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow


def _run(data, out, *extra):
    subprocess.run([sys.executable, "-m", "slam", "run", str(data), "--out", str(out), "--quiet", *extra],
                   check=True, capture_output=True)
    return json.loads((out / "metrics.json").read_text())


def test_memory_bounded_on_long_frame2model_runs(tmp_path):
    from slam.synth import generate

    data = generate(tmp_path / "long", "scanning", frames=2000, size=(320, 256), seed=4321)
    short = _run(data, tmp_path / "r500", "--mode", "frame2model", "--frames", "500")
    long = _run(data, tmp_path / "r2000", "--mode", "frame2model")
    assert long["frames"] == 2000
    assert long["peak_rss_mb"] <= 1.5 * short["peak_rss_mb"], (short["peak_rss_mb"], long["peak_rss_mb"])


def test_rigid_640x512_frame2frame_constant_below_1mm(tmp_path):
    from slam.synth import generate

    data = generate(tmp_path / "rigid", "rigid", frames=150, size=(640, 512), seed=9001)
    m = _run(data, tmp_path / "run", "--weights", "constant")
    assert m["failed_frames"] == [] and m["ate_rmse_mm"] < 1.0
