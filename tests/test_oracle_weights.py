"""The odometry's weight hook and the oracle tool built on it (tools/oracle_weights.py)."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import torch

TOOL = Path(__file__).resolve().parents[1] / "tools" / "oracle_weights.py"


def load_tool():
    spec = importlib.util.spec_from_file_location("oracle_weights", TOOL)
    module = importlib.util.module_from_spec(spec)
    sys.modules["oracle_weights"] = module
    spec.loader.exec_module(module)
    return module


def test_weight_hook_sees_every_solve_and_a_common_scale_leaves_the_pose(synth_dir):
    from slam.io.datasets import DataConfig, open_dataset
    from vo.config import SolverConfig, WeightsConfig
    from vo.config import VOConfig
    from vo.odometry import StereoOdometry

    ds = open_dataset(synth_dir("rigid", 4), DataConfig())
    calls = []

    def triple(cur, ref, flow, w2, w3):
        calls.append((tuple(w2.shape), tuple(w3.shape), tuple(flow.shape)))
        return 3.0 * w2, 3.0 * w3

    # the plain objective (no robust step, whose second solve stops 0.3 um apart on this pair)
    cfg = VOConfig(weights=WeightsConfig(mode="constant"), solver=SolverConfig(robust_3d_mm=0.0))
    plain, hooked = StereoOdometry(ds.camera, cfg), StereoOdometry(ds.camera, cfg, weight_hook=triple)
    a, b = (ds.frame(k) for k in (0, 2))
    va, vb = plain.make_view(a.left, a.right, a.mask), plain.make_view(b.left, b.right, b.mask)
    T_plain = plain.track(vb, va).relative
    T_hooked = hooked.track(vb, va).relative
    H, W = ds.camera.height, ds.camera.width
    assert calls == [((1, 1, H, W), (1, 1, H, W), (1, 2, H, W))]
    assert np.linalg.norm(T_plain[:3, 3]) > 0.05                  # the camera moved
    np.testing.assert_allclose(T_hooked, T_plain, atol=2e-4)      # the optimum ignores a common scale


def test_pair_motion_follows_the_flow():
    from vo.geometry import change_along_flow

    ref = torch.zeros(1, 1, 8, 10)
    ref[..., 3:5, 6] = 2.0
    cur = torch.zeros(1, 1, 8, 10)
    cur[..., 3:5, 4] = 2.5                                        # the same tissue, 2 px to the left
    flow = torch.zeros(1, 2, 8, 10)
    flow[:, 0] = 2.0                                               # current -> reference: +2 px in x
    motion = change_along_flow(cur, ref, flow)
    assert torch.allclose(motion[..., 3:5, 4], torch.tensor(0.5))
    assert motion[..., :, :7].sum() == motion[..., 3:5, 4].sum()   # nothing else moved (inside the image)


def test_oracle_tool_masks_moving_tissue_on_a_breathing_sequence(synth_dir):
    tool = load_tool()
    data = synth_dir("breathing", 8)
    rows = tool.run_sequence(data, ["weights.mode=constant"], gaps=[1], thresholds=[0.005])
    by_mask = {r["mask"]: r for r in rows}
    assert set(by_mask) == {"none", "w3D", "w2D & w3D"}
    none = by_mask["none"]
    # breathing tissue moves between frames: some pixels are masked, so the poses change
    assert 0.0 < none["share_pair>0.005"] < 1.0
    assert by_mask["w2D & w3D"]["pair_error_mm"] != none["pair_error_mm"]
    for r in rows:
        assert np.isfinite(r["pair_error_mm"]) and r["chained_ate_mm"] is not None
    # constant weights: w3D is the same on moving and still pixels
    assert abs(none["w3d_ratio_pair>0.005"] - 1.0) < 1e-6


def test_detector_ratio_of_an_ideal_motion_detector():
    tool = load_tool()
    # 4 pixels displaced from rest (> 0.5 mm), 4 not; per-pair motion decides what the detector keeps
    rest = np.array([1.0, 1.0, 1.0, 1.0, 0.1, 0.1, 0.1, 0.1])
    motion = np.array([0.05, 0.05, 0.05, 0.0, 0.0, 0.0, 0.0, 0.05])
    out = tool.detector_ratios(motion, rest, [0.01, 0.1])
    assert out["detector_ratio_pair<=0.01"] == 0.25 / 0.75         # keeps 1 of 4 displaced, 3 of 4 others
    assert out["detector_ratio_pair<=0.1"] == 1.0                  # keeps everything
    assert tool.detector_ratios(motion, np.zeros(8), [0.01]) == {} # nothing displaced: no ratio


def test_masking_moving_tissue_helps_the_3d_residual_only_on_exact_depth(synth_dir):
    """The physics behind the w3D check (docs/experiments.md, "What hides moving tissue"):
    with the generator's depth, zeroing w3D where the tissue moved between the frames lowers the
    3D-only pose error per pair several times; with stereo depth, whose error changes between
    frames by more than the tissue moves, it does not lower it."""
    tool = load_tool()
    data = synth_dir("breathing", 10, seed=1)
    common = ["weights.mode=constant", "weights.residuals=3d", "solver.robust_3d_mm=0", "depth.temporal_gain=1"]
    errors = {}
    for source in ("groundtruth", "stereo"):
        rows = tool.run_sequence(data, [*common, f"analysis.depth_source={source}"], gaps=[1], thresholds=[0.005])
        by_mask = {r["mask"]: r["pair_error_mm"] for r in rows}
        errors[source] = (by_mask["none"], by_mask["w3D"])
    exact, stereo = errors["groundtruth"], errors["stereo"]
    assert exact[1] < 0.5 * exact[0]            # 0.055 -> 0.016 mm when written
    assert stereo[1] > 0.9 * stereo[0]          # 0.79 -> 1.15 mm when written
    assert exact[0] < 0.2 * stereo[0]           # and exact depth tracks far better to begin with


def test_oracle_tool_scales_w3d_on_tissue_displaced_from_rest(synth_dir):
    """The rows that meet the w3D check by construction: w3D times a factor where the tissue
    is displaced from its rest shape by more than 0.5 mm, as it is, with the frame's total w3D
    kept (moved onto the other pixels), or with w2D scaled too. Factor 1 changes nothing; factor 0
    changes the poses."""
    tool = load_tool()
    data = synth_dir("breathing", 8)
    rows = tool.run_sequence(data, ["weights.mode=constant"], gaps=[1], thresholds=[0.005], rest_scales=[1.0, 0.0])
    by = {(r["mask"], r["threshold_mm"]): r["pair_error_mm"] for r in rows}
    none = next(r for r in rows if r["mask"] == "none")
    assert 0.0 < none["share_rest>0.5"] < 1.0          # some of the view is displaced, some not
    assert by[("w3D rest", 1.0)] == by[("none", 0.0)] == by[("w3D rest, same total", 1.0)]
    assert by[("w3D rest", 0.0)] != by[("none", 0.0)] != by[("w3D rest, same total", 0.0)]
    assert by[("w3D rest", 0.0)] != by[("w3D rest, same total", 0.0)]
    assert by[("w2D & w3D rest", 1.0)] == by[("none", 0.0)] != by[("w2D & w3D rest", 0.0)] != by[("w3D rest", 0.0)]
    assert "displaced from rest > 0.5 mm, same total" in tool.format_row(rows[-2])
    assert tool.format_row(rows[-1]).startswith("| breathing") and "w2D and w3D x 0 where displaced" in tool.format_row(rows[-1])
