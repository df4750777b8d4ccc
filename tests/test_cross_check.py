"""Frame2model's cross-check against the last frame: flagging, the pose kept, not fusing, rebuilding."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from mapping import SurfelMap
from mapping.config import MapConfig
from slam.tracking.acceptance import REBUILD_AFTER


def test_forget_view_removes_the_surfels_a_view_sees():
    H, W = 48, 64
    K = torch.tensor([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    m = SurfelMap(MapConfig())
    depth = torch.full((H, W), 80.0)
    colour = torch.full((3, H, W), 0.5)
    for i in range(3):
        m.fuse(depth, colour, K, torch.eye(4), i)
    n = len(m)
    T_side = torch.eye(4)
    T_side[0, 3] = 40.0     # a view that sees the left part of the plane only
    seen = int(m.render(K, T_side, H, W, colour=False).valid.sum())
    removed = m.forget_view(K, T_side, H, W)
    assert 0 < removed < n and len(m) == n - removed
    assert int(m.render(K, T_side, H, W, colour=False).valid.sum()) < 0.05 * seen
    assert m.render(K, torch.eye(4), H, W, colour=False).valid.float().mean() > 0.3    # the rest stays


def _run(data, tmp_path, name, cross_check: float, corrupt: range | None = None, shift_map_at: int | None = None):
    """Frame2model over ``data``. The flows against the model view of the frames in ``corrupt``
    are pushed 4 px sideways (confident but wrong, as on weak texture); at frame
    ``shift_map_at`` every surfel is moved 2 mm along the last view's optical axis (a wrong map)."""
    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from slam.app.pipeline import Pipeline

    cfg = load_config(None, ["tracking.mode=frame2model", f"health.cross_check={cross_check}", "threads=1"])
    pipe = Pipeline(cfg, open_dataset(data, cfg.data), tmp_path / name)
    odo, tracker = pipe.odometry, pipe.tracker
    flow, track = odo.correspondences, tracker.track

    def corrupted(cur, against, round_trip=None, ahead=None, motion=None):
        corr = flow(cur, against, round_trip, ahead, motion)
        if corrupt is not None and against.from_model and tracker.state.position + 1 in corrupt:
            shifted = corr.flow.clone()
            shifted[:, 0] += 4.0
            corr = corr._replace(flow=shifted)
        return corr

    def shifting(position, view, ahead=None):
        if position == shift_map_at:
            st = tracker.map.store
            axis = torch.as_tensor(tracker.pose[:3, 2], dtype=st.pos.dtype)
            st.pos[: st.n] += 2.0 * axis
        return track(position, view, ahead)

    odo.correspondences, tracker.track = corrupted, shifting
    res = pipe.run(progress=False)
    return res, json.loads((tmp_path / name / "metrics.json").read_text())


@pytest.fixture(scope="module")
def rigid(synth_dir):
    return synth_dir("rigid", 30, size=(160, 128), seed=9901)


@pytest.fixture(scope="module")
def clean_ate(rigid, tmp_path_factory):
    res, _ = _run(rigid, tmp_path_factory.mktemp("clean"), "clean", 0.0)
    return res.metrics["ate_rmse_mm"]


def test_the_cross_check_flags_a_wrong_model_estimate_and_recovers(rigid, clean_ate, tmp_path):
    from slam.app.tracking_csv import read_tracking_csv

    broken, _ = _run(rigid, tmp_path, "broken", 0.0, range(12, 16))
    checked, metrics = _run(rigid, tmp_path, "checked", 22.5, range(12, 16))
    assert broken.metrics["ate_rmse_mm"] > 3 * clean_ate          # 4 px on 160 px: millimetres, fused into the map
    assert checked.metrics["ate_rmse_mm"] < 1.5 * clean_ate + 0.05
    assert len(metrics["flagged_frames"]) <= 5 and not metrics["failed_frames"]
    rows = read_tracking_csv(tmp_path / "checked" / "tracking.csv")
    flagged = rows["flagged"] == 1
    # a wrong frame is flagged; one tracked against the previous frame (the model view no longer
    # covers what the last frame saw when the frames before it were not fused) is unconfirmed:
    # flagged too, until the map agrees again or re-anchors
    assert np.all(flagged[12:16]) and np.all(rows["trust"][flagged] != "confirmed")
    disagree = np.array(["last frame's estimate kept" in r for r in rows["reason"]])
    unconfirmed = rows["trust"] == "unconfirmed"
    assert disagree[12] and np.all(disagree[flagged] | unconfirmed[flagged])
    assert all(r.startswith("unconfirmed since frame 12") for r in rows["reason"][unconfirmed])
    assert np.all(rows["cross_check_d2"][disagree] > 22.5)
    assert np.all(rows["trust"][~flagged] == "confirmed")
    on_model = (rows["reference"] == "model") & ~flagged
    assert np.all(rows["cross_check_d2"][on_model] <= 22.5)
    assert metrics["timings_ms"]["cross_check"] > 0


def test_a_wrong_map_is_rebuilt_around_the_view(rigid, clean_ate, tmp_path):
    """The map is moved 2 mm at frame 10: the frames after it disagree with the last frame's
    estimate, report that one, and after ten of them the model around the view is rebuilt;
    the frames after the rebuild agree again. Without the cross-check the map pulls the poses."""
    broken, _ = _run(rigid, tmp_path, "broken", 0.0, shift_map_at=10)
    checked, metrics = _run(rigid, tmp_path, "checked", 22.5, shift_map_at=10)
    assert broken.metrics["ate_rmse_mm"] > 2 * clean_ate
    # the model is rebuilt around the view after REBUILD_AFTER disagreements, or the map re-anchors
    # sooner where the unfused frames leave the view uncovered: either way once, and the frames
    # after it are confirmed again
    assert metrics["model_rebuilds"] + metrics["map_reanchors"] == 1
    flagged = metrics["flagged_frames"]
    assert flagged[:2] == [10, 11] and len(flagged) <= REBUILD_AFTER and flagged == list(range(10, max(flagged) + 1))
    assert metrics["trust"]["confirmed"] == metrics["frames"] - len(flagged)
    assert checked.metrics["ate_rmse_mm"] < 1.5 * clean_ate + 0.05


def _translation(x_mm: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x_mm
    return T


def test_agreeing_estimates_are_combined_by_their_covariances():
    from slam.tracking.cross_check import CrossCheck, Estimate

    check = CrossCheck(limit_d2=22.5, limit_mm=1e9)
    cov = np.diag([0.01] * 3 + [1e-6] * 3)
    out = check.check(Estimate(_translation(1.0), cov), Estimate(_translation(1.2), cov))
    assert out.agree and out.kept == "combined"
    assert out.relative[0, 3] == pytest.approx(1.1, abs=1e-9)      # equal covariances: half way
    np.testing.assert_allclose(out.covariance, cov / 2, rtol=1e-9)
    assert out.d2 == pytest.approx(0.2 ** 2 / 0.02, rel=1e-6) and out.distance_mm == pytest.approx(0.2)
    # the last pose's uncertainty against the map makes the last frame's estimate count less
    out = check.check(Estimate(_translation(1.0), cov), Estimate(_translation(1.2), cov))
    assert 1.0 < out.relative[0, 3] < 1.1


def test_a_disagreement_keeps_the_better_estimate_and_widens_the_gate():
    from slam.tracking.cross_check import CrossCheck, Estimate

    check = CrossCheck(limit_d2=22.5, limit_mm=1e9)
    frame_cov = np.diag([0.01] * 3 + [1e-6] * 3)
    model_cov = 4 * frame_cov
    kept = []
    for _ in range(40):     # the model view sits 2 mm off the last frame's chain every frame
        out = check.check(Estimate(_translation(2.0), model_cov), Estimate(np.eye(4), frame_cov))
        kept.append(out.kept)
    assert kept[0] == "frame"       # d2 = 2^2 / (0.2^2 + 0.1^2) = 80
    first = kept.index("combined")  # the chain's own uncertainty grew until the model agrees: 4 / (0.05 + 0.01 n) <= 22.5
    assert first == 13 and kept[:first] == ["frame"] * first
    # the model is the better-supported one: it is kept
    check.reset()
    out = check.check(Estimate(_translation(1.0), frame_cov / 4), Estimate(np.eye(4), frame_cov))
    assert out.kept == "model" and out.relative[0, 3] == pytest.approx(1.0)
    # a distance beyond limit_mm disagrees whatever the covariances
    loose = CrossCheck(limit_d2=1e9, limit_mm=0.5)
    assert loose.check(Estimate(_translation(1.0), model_cov), Estimate(np.eye(4), frame_cov)).kept == "frame"


def test_an_uncertain_pose_is_flagged_in_frame2frame(tmp_path):
    from slam.config import load_config
    from slam.app.runner import run_from_config
    from slam.synth import generate
    from slam.app.tracking_csv import read_tracking_csv

    data = generate(tmp_path / "seq", "rigid", frames=6, size=(96, 80), seed=9602)
    runs = {}
    for name, bar in (("loose", 1.5), ("tight", 1e-4)):
        cfg = load_config(None, ["tracking.mode=frame2frame", f"health.flag_mm={bar}", "threads=1"])
        runs[name] = run_from_config(data, cfg, tmp_path / name, print_summary=False)
    assert runs["loose"].metrics["flagged_frames"] == []
    assert runs["tight"].metrics["flagged_frames"] == [1, 2, 3, 4, 5]      # frame 0 is the start
    rows = read_tracking_csv(tmp_path / "tight" / "tracking.csv")
    assert all(r.startswith("uncertain pose (sigma_t") for r in rows["reason"][1:])
    assert np.all(rows["sigma_t_mm"][1:] > 1e-4)
    # a flag does not change a frame2frame pose
    np.testing.assert_array_equal(np.stack([r.pose for r in runs["loose"].records]),
                                  np.stack([r.pose for r in runs["tight"].records]))
