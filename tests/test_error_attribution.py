"""benchmarks/error_attribution.py: the exact rigid flow and the variants it tracks with."""
from __future__ import annotations


import numpy as np
import pytest

from benchmarks.error_attribution import attribute_sequence, exact_flow
from slam.synth import generate
from slam.synth.appearance import Appearance


def test_exact_flow_of_a_plane_under_a_known_motion():
    K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    depth = np.full((48, 64), 50.0, np.float32)
    T = np.eye(4)
    T[0, 3] = 1.0  # the reference camera sees the points 1 mm further along +x
    flow, seen = exact_flow(depth, depth, K, T)
    # a fronto-parallel plane at 50 mm moved 1 mm: 100 * 1 / 50 = 2 px to the right
    np.testing.assert_allclose(flow[0][seen], 2.0, atol=1e-5)
    np.testing.assert_allclose(flow[1][seen], 0.0, atol=1e-5)
    assert not seen[:, -2:].any() and seen[:, :-3].all()   # the last columns leave the view


def test_exact_depth_and_flow_recover_every_relative_pose(tmp_path):
    data = generate(tmp_path / "rigid", "rigid", frames=4, size=(96, 80), seed=9501,
                    appearance=Appearance(texture=0.0, highlights=1.0))
    result = attribute_sequence(data, 1, ["analysis.fb_check_px=0"])
    exact = np.asarray(result["errors"]["exact/exact/constant"])
    assert exact.shape == (3,) and np.all(exact < 2e-3)
    stereo = np.asarray(result["errors"]["stereo/dis/learned"])
    assert np.all(np.isfinite(stereo)) and np.all(stereo < 1.0) and stereo.mean() > exact.mean()
    assert len(result["epe_median_px"]) == 3


@pytest.mark.parametrize("depth_shift", [0.0, 5.0])
def test_occluded_pixels_are_not_seen(depth_shift):
    K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    depth = np.full((48, 64), 50.0, np.float32)
    ref = depth + np.float32(depth_shift)       # something else in front of (or at) the points
    _, seen = exact_flow(depth, ref, K, np.eye(4))
    assert seen.all() == (depth_shift == 0.0) and (seen.any() == (depth_shift == 0.0))
