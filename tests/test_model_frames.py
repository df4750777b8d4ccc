"""Model frames (tracking.model_every): frame2model registers against the map on some frames and
carries the chain of frame-to-frame estimates between them (slam.tracking.model_frames)."""
from __future__ import annotations

import numpy as np
import pytest

from slam.app.pipeline import Pipeline
from slam.config import load_config
from slam.evaluation.chain import silent_summary
from slam.io.datasets import open_dataset
from slam.tracking.model_frames import EveryFrame, ModelFrameSchedule


class _Acceptance:
    def __init__(self, confirmed=True, P=0.01):
        self.chain_confirmed = confirmed
        self.cross_check = type("C", (), {"P": np.eye(6) * P})()


class _Estimate:
    def __init__(self, var):
        self.estimate = type("E", (), {"covariance": np.eye(6) * var})()


def test_the_schedule_calls_a_model_frame_at_the_gap_on_an_unconfirmed_chain_and_an_uncertain_one():
    schedule = ModelFrameSchedule(every=3, flag_mm=1.5)
    ok = _Estimate(0.001)
    assert not schedule.between(0, ok, _Acceptance())          # no model frame yet
    schedule.model_frame(0)
    assert schedule.between(1, ok, _Acceptance()) and schedule.between(2, ok, _Acceptance())
    assert not schedule.between(3, ok, _Acceptance())          # the largest gap
    assert not schedule.between(1, None, _Acceptance())        # the frame's own estimate failed
    assert not schedule.between(1, ok, _Acceptance(confirmed=False))
    assert not schedule.between(1, _Estimate(0.1), _Acceptance(P=0.1))   # sqrt(3 * 0.2) = 0.77 > 0.75
    assert not EveryFrame().between(5, ok, _Acceptance())


@pytest.fixture(scope="module")
def rigid(tmp_path_factory):
    from slam.synth import generate

    return generate(tmp_path_factory.mktemp("model_frames") / "rigid", "rigid", frames=40, size=(320, 256), seed=5)


def _run(data, out, every):
    cfg = load_config(None, ["tracking.mode=frame2model", "threads=1", f"tracking.model_every={every}"])
    pipe = Pipeline(cfg, open_dataset(data, cfg.data), out)
    result = pipe.run(progress=False)
    return pipe, result


def test_model_frames_track_as_well_as_every_frame_and_the_frames_between_are_corrected(rigid, tmp_path):
    _, every = _run(rigid, tmp_path / "every", 1)
    pipe, some = _run(rigid, tmp_path / "some", 3)
    refs = [r.reference for r in some.records]
    model = [k for k, ref in enumerate(refs) if ref == "model"]
    assert model[:4] == [1, 4, 7, 10]          # every third frame is registered against the map
    assert refs[2] == refs[3] == "previous_frame"
    assert all(r.trust in ("confirmed", "tracked") for r in some.records)
    assert some.metrics["ate_rmse_mm"] < max(1.25 * every.metrics["ate_rmse_mm"], 0.15)
    truth = pipe.dataset.gt_poses
    poses = np.stack([r.pose for r in some.records])
    flags = np.zeros(len(poses), bool)
    assert silent_summary(poses, truth, flags, flags)["silent_over"] == 0
    online = (tmp_path / "some" / "trajectory_online.txt").read_text().splitlines()
    final = (tmp_path / "some" / "trajectory.txt").read_text().splitlines()
    assert len(online) == len(final) == 40 and online != final      # the frames between corrected
