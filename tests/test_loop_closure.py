"""Loop closure end to end (slam.tracking.loop_closure through the pipeline): a synthetic loop whose
camera returns to tissue it saw 80 frames before."""
from __future__ import annotations

import json

import numpy as np
import pytest

from slam.config import load_config
from slam.io.datasets import open_dataset
from slam.tracking.loop_closure import LoopClosure
from slam.app.pipeline import Pipeline
from slam.io.tum import read_tum

# a 60 mm loop at 160x128: the start's surfels are inactive after 30 frames and back in view
# from frame ~90 on
LOOP_SETTINGS = ["tracking.mode=frame2model", "graph.loop_closure=true", "graph.inactive_after=30",
                 "graph.keyframe_mm=3", "threads=1"]


def _run(data, out, extra=()):
    cfg = load_config(None, [*LOOP_SETTINGS, *extra])
    return Pipeline(cfg, open_dataset(data, cfg.data), out).run(progress=False)


@pytest.fixture(scope="module")
def loop_data(tmp_path_factory):
    from slam.synth import generate

    return generate(tmp_path_factory.mktemp("loop") / "loop", "loop", frames=120, size=(160, 128), seed=3)


def test_a_loop_is_closed_and_both_trajectories_are_written(loop_data, tmp_path):
    result = _run(loop_data, tmp_path / "run")
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    lc = m["loop_closure"]
    assert lc["accepted"] >= 1 and lc["keyframes"] > 10 and lc["ms_per_frame"] > 0
    event = next(e for e in lc["events"] if e["accepted"])
    assert event["position"] > 60 and event["anchor_position"] < 40 and event["d2"] < 22.5
    stamps, optimised = read_tum(tmp_path / "run" / "trajectory.txt")
    stamps_online, online = read_tum(tmp_path / "run" / "trajectory_online.txt")
    assert len(optimised) == len(online) == 120 and np.array_equal(stamps, stamps_online)
    assert np.isclose(m["ate_rmse_mm"], result.metrics["ate_rmse_mm"]) and "online" in m
    # the loop edge brings the frame it was found at back to the tissue it saw before
    _, gt = read_tum(loop_data / "groundtruth.txt")
    k = event["position"]
    err_online = np.linalg.norm(online[k][:3, 3] - gt[k][:3, 3])
    err_optimised = np.linalg.norm(optimised[k][:3, 3] - gt[k][:3, 3])
    assert err_optimised < 0.5 * err_online
    # the optimised trajectory as a whole: no worse than 1.2x the poses as tracked
    assert m["ate_rmse_mm"] < 1.2 * m["online"]["ate_rmse_mm"]
    assert m["ate_rmse_mm"] < 0.6


def test_a_wrong_loop_with_a_confident_covariance_is_rejected(loop_data, tmp_path, monkeypatch):
    """Every registration against the inactive model moved 4 mm aside and made 100x more
    confident: the graph rejects it and the trajectory stays the one tracked."""
    propose = LoopClosure.propose

    def wrong(self, position, anchor_frame, relative, covariance, reason="", coverage=float("nan"), rendered_at=None):
        shifted = relative.copy()
        shifted[:3, 3] += [4.0, 0.0, 0.0]
        confident = None if covariance is None else covariance / 100.0
        return propose(self, position, anchor_frame, shifted, confident, reason, coverage, rendered_at)

    monkeypatch.setattr(LoopClosure, "propose", wrong)
    _run(loop_data, tmp_path / "wrong")
    m = json.loads((tmp_path / "wrong" / "metrics.json").read_text())
    lc = m["loop_closure"]
    assert lc["candidates"] >= 1 and lc["accepted"] == 0
    assert any("odometry" in e["reason"] or "GNC" in e["reason"] for e in lc["events"])     # the graph's doing
    _, optimised = read_tum(tmp_path / "wrong" / "trajectory.txt")
    _, online = read_tum(tmp_path / "wrong" / "trajectory_online.txt")
    assert np.abs(optimised - online).max() < 1e-6


def test_relocalised_after_frames_that_could_not_be_read(tmp_path):
    """Frames 50-89 of a 320x256 loop unreadable (the camera moves 20 mm meanwhile): frame 90 is
    relocalised against a keyframe (ORB and PnP, then the dense registration against the model)
    instead of tracked from a pose 10 mm off (which leaves frame2model 11 mm off: measured)."""
    from slam.synth import generate

    data = generate(tmp_path / "loop", "loop", frames=120, size=(320, 256), seed=3)
    for k in range(50, 90):
        (data / "video_frames" / f"{k:06d}l.png").write_bytes(b"lost")
    _run(data, tmp_path / "run")
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["failed_frames"] == list(range(50, 90))
    rows = (tmp_path / "run" / "tracking.csv").read_text().splitlines()
    assert any(r.startswith("90,") and "relocalised" in r for r in rows[1:])
    _, online = read_tum(tmp_path / "run" / "trajectory_online.txt")
    _, gt = read_tum(data / "groundtruth.txt")
    err = np.linalg.norm(online[:, :3, 3] - gt[:, :3, 3], axis=1)
    assert np.linalg.norm(online[49][:3, 3] - gt[90][:3, 3]) > 8.0     # where the last pose left it
    assert err[90] < 0.6 and err[91:].max() < 1.0
