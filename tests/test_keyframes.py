"""``tracking.keyframe_gap``: frame2frame against a keyframe instead of the previous frame."""
from __future__ import annotations

import dataclasses

import numpy as np

from slam.config import load_config
from slam.io.datasets import open_dataset
from slam.app.pipeline import Pipeline


def _run(data, tmp_path, name, overrides, fail_at=None, still_mm=None, init=None):
    """Run the pipeline, recording which frame each frame was tracked against (and the solver's
    start); ``fail_at``: that frame's tracking is reported failed; ``still_mm``, ``init``: the
    fixed ``tracking.keyframe_still_mm`` and ``solver.init``, set as an analysis would."""
    cfg = load_config(None, [*overrides])
    if still_mm is not None:
        cfg.tracking.keyframe_still_mm = still_mm
    if init is not None:
        cfg.solver.init = init
    pipe = Pipeline(cfg, open_dataset(data, cfg.data), tmp_path / name)
    frame_of, calls, views = {}, [], []
    track = pipe.odometry.track
    make_view = pipe._make_view

    def numbered(frame, timings):
        view = make_view(frame, timings)
        views.append(view)      # kept alive: ids of freed views are reused
        frame_of[id(view)] = len(views) - 1
        return view

    def spy(cur, ref, init=None, filter_against=None, ahead=None, seed=False):
        result = track(cur, ref, init, filter_against, ahead, seed)
        k = frame_of[id(cur.origin)]
        if not seed:        # (the tracking calls; a recovery's registrations start from a prediction)
            calls.append((k, frame_of[id(ref.origin)], None if init is None else np.array(init), result.relative))
        return dataclasses.replace(result, failed=True, reason="forced") if k == fail_at else result

    pipe._make_view = numbered
    pipe.odometry.track = spy
    return pipe.run(progress=False), calls


def test_keyframe_reference_order_and_poses(synth_dir, tmp_path):
    """Gap 3: frames 1-3 against frame 0, 4-6 against 3, ...; the poses compose from the keyframe's
    and stay as accurate as frame-to-frame on a moving camera; gap 1 is the previous frame."""
    data = synth_dir("rigid", 10, (160, 128))
    one, calls_one = _run(data, tmp_path, "gap1", ["tracking.keyframe_gap=1"])
    assert [c[1] for c in calls_one] == list(range(9))
    assert [r.reference for r in one.records] == ["first"] + ["previous_frame"] * 9
    three, calls = _run(data, tmp_path, "gap3", ["tracking.keyframe_gap=3"], still_mm=0.0)
    assert [(c[0], c[1]) for c in calls] == [(k, 3 * ((k - 1) // 3)) for k in range(1, 10)]
    assert [r.reference for r in three.records] == ["first"] + ["previous_frame", "keyframe", "keyframe"] * 3
    assert not any(r.failed for r in three.records)
    assert three.metrics["ate_rmse_mm"] < 0.3 and one.metrics["ate_rmse_mm"] < 0.3
    # each frame's pose is its keyframe's composed with the tracked relative motion
    poses = {r.index: r.pose for r in three.records}
    R1 = np.eye(4)
    R1[:3, :3] = open_dataset(data, load_config(None, []).data).R1
    for k, kf, _, rel in calls:
        expected = poses[kf] @ R1.T @ rel @ R1
        np.testing.assert_allclose(poses[k], expected, atol=1e-9)
    # by default a keyframe is kept only while the camera is still: this one moves about 0.5 mm per
    # frame, so every frame goes against the one before it
    moving, calls_moving = _run(data, tmp_path, "moving", [])
    assert load_config(None, []).tracking.keyframe_still_mm == 0.1
    assert [(c[0], c[1]) for c in calls_moving] == [(k, k - 1) for k in range(1, 10)]
    assert [r.reference for r in moving.records] == ["first"] + ["previous_frame"] * 9
    # frame2model keeps its own reference: the gap does not apply
    from slam.tracking.references import ModelViewReference

    cfg = load_config(None, ["tracking.mode=frame2model", "tracking.keyframe_gap=3"])
    tracker = Pipeline(cfg, open_dataset(data, cfg.data), tmp_path / "f2m").tracker
    assert type(tracker.references) is ModelViewReference


def test_keyframe_after_a_failure_and_the_solver_start(synth_dir, tmp_path):
    """A failed frame: the next is tracked against the last tracked frame and becomes the keyframe.
    ``solver.init: constant_velocity`` starts a frame tracked against its keyframe from the
    motion since the keyframe plus one more frame's."""
    data = synth_dir("rigid", 10, (160, 128))
    result, calls = _run(data, tmp_path, "fail", ["tracking.keyframe_gap=3"], fail_at=5, still_mm=0.0,
                         init="constant_velocity")
    assert [(c[0], c[1]) for c in calls] == [(1, 0), (2, 0), (3, 0), (4, 3), (5, 3), (6, 4), (7, 6), (8, 6), (9, 6)]
    assert [r.failed for r in result.records] == [k == 5 for k in range(10)]
    assert [r.reference for r in result.records][6:] == ["previous_frame", "previous_frame", "keyframe", "keyframe"]
    for k, kf, start, rel in calls:
        if k - kf >= 2 and k != 6:      # against an earlier keyframe: the start is close to the solved motion
            step = np.linalg.norm(calls[k - 2][3][:3, 3])     # frame k-1's tracked motion
            assert np.linalg.norm(start[:3, 3] - rel[:3, 3]) < 0.5 * max(step, 1e-3), k
    assert result.metrics["ate_rmse_mm"] < 0.3


def test_keyframes_from_the_command_on_a_raw_video_layout(synth_dir, tmp_path):
    """``slam run --set tracking.keyframe_gap=3`` on the StereoMIS raw layout (one unrectified mp4
    with lens distortion and its calibration): every frame tracked, the trajectory and the resolved
    config written, the poses recovered."""
    import json

    import yaml

    from slam.app.cli import main
    from slam.io.tum import read_tum

    raw = synth_dir("rigid", 12, (320, 256), seed=5, raw=True)
    out = tmp_path / "run"
    assert main(["run", str(raw), "--out", str(out), "--set", "tracking.keyframe_gap=3", "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == 12 and m["failed_frames"] == []
    assert yaml.safe_load((out / "config.yaml").read_text())["tracking"]["keyframe_gap"] == 3
    _, est = read_tum(out / "trajectory.txt")
    _, gt = read_tum(raw / "groundtruth.txt")
    assert len(est) == 12
    spread = np.sqrt(((gt[:, :3, 3] - gt[:, :3, 3].mean(0)) ** 2).sum(1).mean())
    assert m["ate_rmse_mm"] < 0.1 * spread and m["ate_rmse_mm"] < 0.5


def test_filtered_depth_runs_frame_to_frame_while_tracking_against_the_keyframe(synth_dir, tmp_path):
    """Gap 3 with the temporal depth filter: every frame's depth is filtered against the frame just
    before it (as the training's pair cache does), while the pose is tracked against the keyframe;
    the read-ahead thread's flow to the previous frame and a flow computed in place give the same
    poses bit for bit. On a still camera over breathing tissue the filtered depth's change over the
    gap is closer to the truth's than the stereo depth's, and the poses stay accurate."""
    data = synth_dir("breathing", 10, (160, 128))
    # one torch thread either way (threads: 0 gives the read-ahead thread a core: another rounding)
    overrides = ["tracking.keyframe_gap=3", "depth.temporal_gain=0.05", "threads=1"]
    runs = {}
    for ahead in ("true", "false"):
        cfg = load_config(None, overrides)
        pipe = Pipeline(cfg, open_dataset(data, cfg.data), tmp_path / f"ahead_{ahead}")
        if ahead == "false":        # every flow computed where it is needed
            pipe._flow_ahead = lambda: False
        frame_of, views, filtered, tracked, as_tracked = {}, [], [], [], {}
        make_view, filter_depth, track = pipe._make_view, pipe.odometry.filter_depth, pipe.odometry.track

        def numbered(frame, timings, views=views, frame_of=frame_of, make_view=make_view):
            view = make_view(frame, timings)
            views.append(view)
            frame_of[id(view)] = len(views) - 1
            return view

        def spy_filter(cur, against, corr, filtered=filtered, frame_of=frame_of, filter_depth=filter_depth,
                       as_tracked=as_tracked):
            out = filter_depth(cur, against, corr)
            k = frame_of[id(cur.origin)]
            filtered.append((k, None if against is None else frame_of[id(against.origin)], out.stereo_depth is not None))
            as_tracked[k] = out
            return out

        def spy_track(cur, ref, *args, tracked=tracked, frame_of=frame_of, track=track, **kwargs):
            tracked.append((frame_of[id(cur.origin)], frame_of[id(ref.origin)]))
            return track(cur, ref, *args, **kwargs)

        pipe._make_view, pipe.odometry.filter_depth, pipe.odometry.track = numbered, spy_filter, spy_track
        runs[ahead] = (pipe.run(progress=False), as_tracked)
        assert tracked == [(k, 3 * ((k - 1) // 3)) for k in range(1, 10)]
        assert filtered == [(k, k - 1, True) for k in range(1, 10)]
    result, views = runs["true"]
    assert not any(r.failed for r in result.records)
    assert result.metrics["ate_rmse_mm"] < 0.2
    np.testing.assert_array_equal(np.stack([r.pose for r in result.records]),
                                  np.stack([r.pose for r in runs["false"][0].records]))
    # the camera is still: at a fixed pixel, the depth's change over a gap against the true change
    dataset = open_dataset(data, load_config(None, []).data)
    truth = [dataset.frame(k).gt_depth for k in range(10)]
    inner = (slice(16, -16), slice(16, -16))

    def change_error(a, b, attr):
        da, db = (getattr(views[k], attr)[0, 0].numpy() for k in (a, b))      # (the views as tracked)
        ok = np.isfinite(da) & np.isfinite(db) & (da > 0) & (db > 0)
        return float(np.median(np.abs((db - da) - (truth[b] - truth[a]))[inner][ok[inner]]))

    for a, b in ((3, 6), (6, 9)):
        assert change_error(a, b, "depth") < 0.3 * change_error(a, b, "stereo_depth")


def test_keyframe_settings_range(tmp_path, capsys):
    """A gap below 1 is a one-line error naming the setting; the still threshold is no setting."""
    from slam.app.cli import main

    assert main(["run", str(tmp_path), "--set", "tracking.keyframe_still_mm=-0.1"]) != 0
    assert "'tracking.keyframe_still_mm' is gone" in capsys.readouterr().err
    assert main(["run", str(tmp_path), "--set", "tracking.keyframe_gap=0"]) != 0
    assert "tracking.keyframe_gap must be >= 1" in capsys.readouterr().err


def test_paper_config_is_the_papers_reference(synth_dir, tmp_path):
    """``configs/paper.yaml``: every frame against the previous one with its own stereo depth (the
    defaults keep a keyframe and filter the depth while the camera is still)."""
    from pathlib import Path

    paper = load_config(str(Path(__file__).resolve().parents[1] / "configs" / "paper.yaml"))
    assert (paper.tracking.keyframe_gap, paper.depth.temporal_gain) == (1, 1.0)
    defaults = load_config(None, [])
    assert (defaults.tracking.keyframe_gap, defaults.depth.temporal_gain, defaults.depth.temporal_still_mm) == (5, 0.05, 0.1)
    data = synth_dir("breathing", 8, (160, 128))
    pipe = Pipeline(paper, open_dataset(data, paper.data), tmp_path / "paper")
    filtered = []
    track = pipe.odometry.track

    def spy(cur, ref, *args, **kwargs):
        result = track(cur, ref, *args, **kwargs)
        filtered.append(result.view.stereo_depth is not None)
        return result

    pipe.odometry.track = spy
    result = pipe.run(progress=False)
    assert [r.reference for r in result.records] == ["first"] + ["previous_frame"] * 7
    assert filtered == [False] * 7 and pipe.odometry.networks.stereo is pipe.odometry.networks.filtered
