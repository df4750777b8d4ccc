"""The frame prefetcher returns what a synchronous read would, errors included, in any order of gets."""
from __future__ import annotations

import os
import threading

import pytest

from slam.app.prefetch import Prefetcher


def test_prefetcher_reads_ahead_in_one_thread_and_reraises():
    threads, calls = set(), []

    def read(k):
        threads.add(threading.get_ident())
        calls.append(k)
        if k == 3:
            raise ValueError(f"frame {k} unreadable")
        return k * 10

    with Prefetcher(read, 6) as reader:
        assert [reader.get(k) for k in range(3)] == [0, 10, 20]
        with pytest.raises(ValueError, match="frame 3"):
            reader.get(3)
        assert reader.get(5) == 50          # skipping ahead works too
    assert len(threads) == 1 and threading.get_ident() not in threads
    assert {0, 1, 2, 3, 5} <= set(calls) <= set(range(6))   # never past the end (4 may be cancelled)


def test_prefetcher_disabled_reads_synchronously():
    seen = []
    reader = Prefetcher(lambda k: seen.append(threading.get_ident()) or k, 3, enabled=False)
    assert [reader.get(k) for k in range(3)] == [0, 1, 2]
    assert set(seen) == {threading.get_ident()}
    reader.close()


def test_read_ahead_gives_the_same_run_in_another_thread(synth_dir, tmp_path):
    """The next frame's stereo depth is made in the read-ahead thread; the trajectory is the same
    bit for bit as with every view made in the main thread, the thread count of torch is
    restored after the run, and ``threads: 0`` leaves one core to that thread."""
    import numpy as np
    import torch

    from slam.app.pipeline import Pipeline
    from slam.config import load_config
    from slam.io.datasets import open_dataset

    data = synth_dir("rigid", 6, (160, 128))
    before = torch.get_num_threads()
    poses, stereo_threads = {}, {}
    for ahead in (True, False):
        cfg = load_config(None, ["tracking.mode=frame2model", "threads=1"])
        pipe = Pipeline(cfg, open_dataset(data, cfg.data), tmp_path / str(ahead))
        if not ahead:
            pipe._read_ahead = lambda: False
        make_view = pipe.odometry.make_view
        seen = set()

        def spy(*args, **kwargs):
            seen.add(threading.get_ident())
            return make_view(*args, **kwargs)

        pipe.odometry.make_view = spy
        result = pipe.run(progress=False)
        assert not any(r.failed for r in result.records)
        poses[ahead] = np.stack([r.pose for r in result.records])
        stereo_threads[ahead] = seen
        assert torch.get_num_threads() == before
    np.testing.assert_array_equal(poses[True], poses[False])
    assert stereo_threads[False] == {threading.get_ident()}
    assert threading.get_ident() not in stereo_threads[True]
    cfg = load_config(None, [])
    pipe = Pipeline(cfg, open_dataset(data, cfg.data), tmp_path / "auto")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    from slam.app.thread_use import ThreadBudget
    assert ThreadBudget.of(cfg.threads, pipe._read_ahead()).torch == max(1, cores - 1)


@pytest.mark.parametrize("mode, slow", [("frame2frame", "track"), ("frame2model", "track"), ("frame2frame", "stereo")])
def test_flow_ahead_gives_the_same_run_and_goes_to_the_idle_thread(synth_dir, tmp_path, mode, slow):
    """The read-ahead thread also computes each frame's temporal flow against the previous
    frame, with its own estimator, unless the main thread already waits for that frame; the
    trajectory is the same bit for bit as with every flow computed where it is needed. With
    tracking the slower stage the flows go to the read-ahead thread (all but the first pair's:
    frame 0 is not tracked, so the main thread waits for frame 1); with stereo the slower one they
    stay in the main thread. Frame2model's cross-check (its estimate against the last frame) takes
    them too."""
    import time

    import numpy as np

    from slam.app.pipeline import Pipeline
    from slam.config import load_config
    from slam.io.datasets import open_dataset

    data = synth_dir("rigid", 6, (160, 128))
    poses, main_pairs, ahead_pairs = {}, {}, {}
    for ahead in (True, False):
        cfg = load_config(None, [f"tracking.mode={mode}", "threads=1", "tracking.keyframe_gap=1"])
        pipe = Pipeline(cfg, open_dataset(data, cfg.data), tmp_path / f"{mode}_{slow}_{ahead}")
        if not ahead:
            pipe._flow_ahead = lambda: False
        odo = pipe.odometry
        pair_flow, slowed = odo._pair_flow, getattr(odo, "track" if slow == "track" else "make_view")
        calls = []

        def spy_pairs(estimator, cur, against, *args):
            if not against.from_model:          # (frame2model's flows against the model view: no frame pairs)
                calls.append(threading.get_ident())
            return pair_flow(estimator, cur, against, *args)

        def spy_slow(*args, **kwargs):
            time.sleep(0.3)
            return slowed(*args, **kwargs)

        odo._pair_flow = spy_pairs
        setattr(odo, "track" if slow == "track" else "make_view", spy_slow)
        result = pipe.run(progress=False)
        assert not any(r.failed for r in result.records)
        poses[ahead] = np.stack([r.pose for r in result.records])
        main_pairs[ahead] = calls.count(threading.get_ident())
        ahead_pairs[ahead] = len(pipe.timings.get("flow_ahead", []))
    np.testing.assert_array_equal(poses[True], poses[False])
    assert main_pairs[False] == 5 and ahead_pairs[False] == 0
    assert main_pairs[True] + ahead_pairs[True] == 5
    if slow == "track":
        # frame 1's flow is the main thread's when it waits for frame 1, the read-ahead thread's
        # when a loaded machine delays the main thread until frame 1 is ready: 1 or 0
        assert main_pairs[True] <= 1 and ahead_pairs[True] >= 4
    else:
        assert (main_pairs[True], ahead_pairs[True]) == (5, 0)


def test_flow_ahead_is_taken_only_against_the_view_it_was_computed_for(synth_dir):
    """A view whose look-ahead flow went against another view than its reference (the previous
    frame failed) computes its flow anew: the same pose as without any look-ahead; a view with
    its depth filtered is still the view the flow was computed against."""
    import dataclasses

    import numpy as np

    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from vo.odometry import StereoOdometry

    data = synth_dir("rigid", 6, (160, 128))
    cfg = load_config(None, [])
    dataset = open_dataset(data, cfg.data)
    odo = StereoOdometry(dataset.camera, cfg.vo())
    frames = [dataset.frame(k) for k in range(3)]
    a, b, c = (odo.make_view(f.left, f.right, f.mask, specular=f.specular) for f in frames)
    plain = odo.track(c, a).relative
    to_b = odo.flow_ahead(c, b)
    assert not to_b.serves(a) and to_b.serves(b)
    assert to_b.serves(dataclasses.replace(b, depth=b.depth * 2, stereo_depth=b.depth, base=b))
    np.testing.assert_array_equal(odo.track(c, a, ahead=to_b).relative, plain)
    to_a = odo.flow_ahead(c, a)
    assert odo.correspondences(c, a, ahead=to_a) is to_a.corr
    np.testing.assert_array_equal(odo.track(c, a, ahead=to_a).relative, plain)
