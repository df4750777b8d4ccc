"""The left-right stereo check (``correspondence.lr_check_px``, on by default) and the
pipeline's constant-velocity start (``solver.init``)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from slam.config import load_config
from slam.io.datasets import open_dataset
from vo.odometry import StereoOdometry


def _stereo_views(data, lr_check_px: float, frame: int = 1):
    cfg = load_config(None, [f"correspondence.lr_check_px={lr_check_px}", "weights.mode=constant"])
    ds = open_dataset(data, cfg.data)
    fr = ds.frame(frame)
    view = StereoOdometry(ds.camera, cfg.vo()).make_view(fr.left, fr.right, fr.mask, None)
    return view, torch.from_numpy(fr.gt_depth)[None, None]


@pytest.mark.parametrize("scenario", ["rigid", "deforming"])
def test_left_right_check_removes_the_bad_depths(synth_dir, scenario):
    """Measured at 320x256: the check drops 5-8 % of the valid pixels, whose median depth error
    is 3-4 mm against 0.3 mm on the pixels it keeps (occlusion borders, mismatches)."""
    data = synth_dir(scenario, 3, (320, 256), seed=3)
    plain, gt = _stereo_views(data, 0.0)
    checked, _ = _stereo_views(data, 1.0)
    assert torch.equal(checked.valid, plain.valid & checked.valid)       # it only removes pixels
    assert torch.all(checked.depth[~checked.valid] == 0)
    removed = plain.valid & ~checked.valid
    share = float(removed.sum() / plain.valid.sum())
    assert 0.01 < share < 0.15
    err = (plain.depth - gt).abs()
    assert float(err[removed].median()) > 5 * float(err[checked.valid].median())
    # the tail of the depth error the residuals and the map see shrinks
    assert float(err[checked.valid].quantile(0.95)) < 0.7 * float(err[plain.valid].quantile(0.95))


def test_pipeline_starts_the_solver_from_the_last_motion(synth_dir, tmp_path):
    """``solver.init: constant_velocity``: each frame's solve starts from the previous frame's
    tracked motion (was ignored by ``slam run``); ``identity`` starts from no motion."""
    from slam.app.pipeline import Pipeline

    data = synth_dir("rigid", 6, (160, 128))
    for init in ("constant_velocity", "identity"):
        # every frame against the previous one (a keyframe's start: tests/test_keyframes.py)
        cfg = load_config(None, ["weights.mode=constant", "tracking.keyframe_gap=1"])
        cfg.solver.init = init          # (fixed for users: identity)
        pipe = Pipeline(cfg, open_dataset(data, cfg.data), tmp_path / init)
        starts, motions = [], []
        track = pipe.odometry.track

        def spy(cur, ref, init=None, filter_against=None, ahead=None):
            starts.append(None if init is None else np.array(init))
            result = track(cur, ref, init, filter_against, ahead)
            motions.append(result.relative)
            return result

        pipe.odometry.track = spy
        pipe.run(progress=False)
        assert len(starts) == 5
        if init == "identity":
            assert all(s is None for s in starts)
        else:
            assert np.allclose(starts[0], np.eye(4))
            for k in range(1, 5):
                assert np.allclose(starts[k], motions[k - 1])
            assert np.linalg.norm(motions[-1][:3, 3]) > 0.05      # the camera moves: a real start


def test_the_flow_back_preset_follows_the_working_resolution():
    """``auto``: DIS ``fast`` where its quarter-size working image is >= 128 px wide (640x512:
    within 1 % of ``medium``'s ATE), ``medium`` below (320x256: ``fast`` made the check less
    selective); an explicit preset is kept."""
    from vo.config import CorrespondenceConfig, lr_check_preset
    from vo.correspondence import DisFlow, make_lr_check_flow

    assert lr_check_preset("auto", 640) == "fast"
    assert lr_check_preset("auto", 512) == "fast"
    assert lr_check_preset("auto", 320) == "medium"
    assert lr_check_preset("medium", 1280) == "medium"
    stereo = DisFlow("medium")
    cfg = CorrespondenceConfig()
    assert cfg.dis_lr_check_preset == "auto"
    assert make_lr_check_flow(cfg, stereo, 320) is stereo
    back = make_lr_check_flow(cfg, stereo, 640)
    assert back is not stereo and back.preset == "fast"
