"""tools/stereo_noise.py: the stereo depth's error and its frame-to-frame change against the generator."""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import stereo_noise as tool  # noqa: E402


def test_stereo_noise_against_the_generators_depth(synth_dir):
    data = synth_dir("breathing", 8)
    stereo = tool.sequence_noise(data, [], start=2, frames=6)
    exact = tool.sequence_noise(data, ["analysis.depth_source=groundtruth"], start=2, frames=6)
    assert stereo["frames"] == 6 and stereo["median_nonrigid_motion_mm"] is not None
    # stereo: a real error, below a millimetre at these depths; a part of it changes between frames
    assert 0.02 < stereo["median_abs_error_mm"] < 1.0
    assert 0.0 < stereo["median_change_mm"] < 2 * stereo["p90_change_mm"]
    assert 0.0 < stereo["median_abs_error_px"] < 0.5
    # the generator's own depth: no error at all
    assert exact["median_abs_error_mm"] == 0.0 and exact["median_change_mm"] == 0.0
    assert "| " + data.name + " |" in tool.format_row(stereo)
