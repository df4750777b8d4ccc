"""``depth.temporal_gain``: each frame's stereo depth filtered along the temporal flow."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml

from vo.depth import filter_depth_along_flow


def test_filter_follows_the_flow_and_keeps_its_stereo_depth_where_it_cannot_predict():
    """``d = p + g (d_stereo - p)`` with ``p`` the reference depth where the flow lands; the stereo
    depth where the innovation exceeds the gate, the reference is invalid there, or the flow failed."""
    H, W = 6, 8
    ref = (50.0 + torch.arange(W, dtype=torch.float32)).expand(H, W).clone()[None, None]   # 50, 51, ... per column
    ref_valid = torch.ones(1, 1, H, W, dtype=torch.bool)
    ref_valid[..., 0, 6] = False
    ref[..., 0, 6] = 0.0
    flow = torch.zeros(1, 2, H, W)
    flow[:, 0] = 1.0                                  # each pixel lands one column to the right
    cur = torch.full((1, 1, H, W), 55.0)
    valid = torch.ones(1, 1, H, W, dtype=torch.bool)
    valid[..., 5, 2] = False
    cur[..., 5, 2] = 0.0
    flow_ok = torch.ones(1, 1, H, W, dtype=torch.bool)
    flow_ok[..., 3, 3] = False
    out = filter_depth_along_flow(cur, valid, ref, ref_valid, flow, flow_ok, gain=0.25, gate_mm=2.0)
    for y in range(H):
        for x in range(W):
            p = 51.0 + x                              # ref at column x + 1
            inside = x + 1 < W
            predicted = inside and not (y == 0 and x + 1 == 6) and (y, x) not in ((3, 3), (5, 2))
            if (y, x) == (5, 2):
                expected = 0.0                        # invalid stays invalid
            elif predicted and abs(55.0 - p) <= 2.0:
                expected = p + 0.25 * (55.0 - p)
            else:
                expected = 55.0                       # no prediction, or beyond the gate
            assert float(out[0, 0, y, x]) == pytest.approx(expected, abs=1e-4), (y, x)
    assert filter_depth_along_flow(cur, valid, ref, ref_valid, flow, None, gain=1.0, gate_mm=2.0) is cur


def _rigid_pairs_config(tmp_path, scenario: str):
    from slam.synth import generate

    data = generate(tmp_path / scenario, scenario, frames=10, size=(96, 80), seed=5001)
    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump({
        "residuals": "2d3d",
        "data": {"scenarios": [scenario], "seeds": [5000], "frames": 10, "width": 96, "height": 80,
                 "pairs_per_sequence": 6, "pixels_per_pair": 512, "max_gap": 1, "cache_dir": str(tmp_path / "cache")},
        "optim": {"seed": 3, "threads": 1},
    }))
    return data, path


def _residual_at_true_pose_mm(samples, max_depth_mm):
    from vo.lie import se3_exp

    res = []
    for s in samples:
        T = se3_exp(s["p_gt"][None].double())[0].float()
        moved = T[:3, :3] @ s["points_cur"] + T[:3, 3:]
        res.append((moved - s["points_ref"])[:, s["valid3"]].norm(dim=0))
    return float(torch.cat(res).median()) * max_depth_mm


@pytest.mark.parametrize("scenario", ["breathing", "rigid"])
def test_filtered_depth_cuts_the_3d_residual_at_the_true_pose(tmp_path, scenario):
    """Training pairs of consecutive frames: with the filter the 3D residual at the true pose is a
    fraction of the stereo one, on a static camera over breathing tissue and on a moving camera
    (the filter's lag is the same in both frames and cancels); gain 1 is the unfiltered cache."""
    from slam.training.trainer import build_pair_samples, load_train_config

    data, path = _rigid_pairs_config(tmp_path, scenario)
    res = {}
    for gain in (1.0, 0.1):
        cfg = load_train_config(path, [f"depth.temporal_gain={gain}"])
        samples = build_pair_samples(data, cfg)
        assert len(samples) >= 5
        res[gain] = _residual_at_true_pose_mm(samples, cfg.depth.max_depth_mm)
    assert len(list((tmp_path / "cache" / "pairs").glob("*.pt"))) == 2     # one cache each
    assert res[0.1] < 0.6 * res[1.0], res


def test_filter_from_the_command_tracks_a_moving_camera(synth_dir, tmp_path):
    """``slam run --set depth.temporal_gain=0.1`` on a moving camera filmed in the StereoMIS raw
    layout (one unrectified mp4 with lens distortion): every frame tracked, the poses recovered as
    well as without the filter (to 0.05 mm), the setting in the written config."""
    from slam.app.cli import main

    data = synth_dir("rigid", 12, (320, 256), seed=5, raw=True)
    ate = {}
    for gain in ("1.0", "0.1"):
        out = tmp_path / f"run{gain}"
        assert main(["run", str(data), "--out", str(out), "--set", f"depth.temporal_gain={gain}", "--quiet"]) == 0
        m = json.loads((out / "metrics.json").read_text())
        assert m["frames"] == 12 and m["failed_frames"] == []
        assert yaml.safe_load((out / "config.yaml").read_text())["depth"]["temporal_gain"] == float(gain)
        ate[gain] = m["ate_rmse_mm"]
    assert ate["0.1"] < 0.3 and ate["0.1"] < ate["1.0"] + 0.05, ate


def test_filter_config_range(tmp_path, capsys):
    from slam.app.cli import main

    assert main(["run", str(tmp_path), "--set", "depth.temporal_gain=0"]) != 0
    assert "depth.temporal_gain must be in (0, 1]" in capsys.readouterr().err


def test_warning_when_the_networks_saw_another_filter(caplog):
    """Networks trained on depth filtered with one gain, tracking with another: one warning naming both."""
    import logging

    from vo.weights import warn_depth_filter_mismatch

    meta = {"train_config": {"depth": {"temporal_gain": 0.05}}}
    with caplog.at_level(logging.WARNING):
        warn_depth_filter_mismatch(meta, 0.05, "")
        warn_depth_filter_mismatch({}, 1.0, "x.pt")          # checkpoints from before the filter: unfiltered
        assert not caplog.records
        warn_depth_filter_mismatch(meta, 1.0, "x.pt")
    assert len(caplog.records) == 1
    assert "x.pt" in caplog.text and "temporal_gain=0.05" in caplog.text and "uses 1" in caplog.text


@pytest.mark.parametrize("residuals", ["2d3d", "2d", "3d"])
def test_filtered_depth_selects_the_packaged_networks_trained_on_it(residuals):
    """With the filter on and no checkpoint named, 2D&3D tracking loads the packaged networks trained
    on filtered depth (their config says so) for the filtered frames; without it, and for the 2D and
    3D ablations (which ship one network each), the stereo-depth ones."""
    from slam.config import load_config
    from vo.camera import StereoCamera
    from vo.odometry import StereoOdometry

    cam = StereoCamera(K=np.array([[200.0, 0, 79.5], [0, 200.0, 63.5], [0, 0, 1]]), baseline_mm=5.0, width=160, height=128)
    for gain, expected in ((0.05, 0.05 if residuals == "2d3d" else 1.0), (1.0, 1.0)):
        cfg = load_config(None, [f"depth.temporal_gain={gain}", f"weights.residuals={residuals}"])
        odo = StereoOdometry(cam, cfg.vo())
        assert odo.networks.meta["residuals"] == residuals
        assert odo.networks.meta["train_config"]["depth"].get("temporal_gain", 1.0) == expected


@pytest.mark.parametrize("scenario, expected", [("breathing", [True] * 7), ("rigid", [True] + [False] * 6)])
def test_filter_only_while_the_camera_is_still(synth_dir, tmp_path, scenario, expected):
    """The still-camera rule (``depth.temporal_still_mm``, fixed at 0.1 mm a frame at 25 fps): a
    still camera's frames are filtered; a moving camera's first
    tracked frame is (nothing has moved yet), the later ones keep their stereo depth and are weighed
    by the networks trained on stereo depth."""
    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from slam.app.pipeline import Pipeline

    data = synth_dir(scenario, 8, (160, 128))
    cfg = load_config(None, ["depth.temporal_gain=0.05"])
    assert cfg.depth.temporal_still_mm == 0.1
    pipe = Pipeline(cfg, open_dataset(data, cfg.data), tmp_path / "run")
    odo = pipe.odometry
    assert odo.networks.stereo is not odo.networks.filtered
    filtered, nets = [], []
    track, weights = odo.track, odo.weight_maps

    def spy_weights(cur, ref, *args, **kwargs):
        nets.append(odo.networks.select(ref.from_model, cur.stereo_depth is not None))
        return weights(cur, ref, *args, **kwargs)

    def spy_track(cur, *args, **kwargs):
        result = track(cur, *args, **kwargs)
        filtered.append(result.view.stereo_depth is not None)
        return result

    odo.track, odo.weight_maps = spy_track, spy_weights
    result = pipe.run(progress=False)
    assert filtered == expected
    assert [n is odo.networks.filtered for n in nets] == expected
    assert not any(r.failed for r in result.records)


def test_pair_cache_key_ignores_the_filter_settings_that_do_not_change_the_pairs(tmp_path):
    """Off (gain 1), the filter's settings do not enter the key; ``temporal_still_mm`` never does
    (the cache filters every frame)."""
    from slam.training.trainer import _cache_key, load_train_config

    import dataclasses

    data, path = _rigid_pairs_config(tmp_path, "rigid")

    def key(*overrides, **depth):       # depth: the fixed constants, set as an analysis would
        cfg = load_train_config(path, list(overrides))
        return _cache_key(dataclasses.replace(cfg, depth=dataclasses.replace(cfg.depth, **depth)), data)

    assert key() == key(temporal_gate_mm=2.0, temporal_still_mm=0.1)
    assert key("depth.temporal_gain=0.05") == key("depth.temporal_gain=0.05", temporal_still_mm=0.1)
    assert key("depth.temporal_gain=0.05") != key("depth.temporal_gain=0.05", temporal_gate_mm=2.0)
    assert key("depth.temporal_gain=0.05") != key() != key("depth.temporal_gain=0.1")
