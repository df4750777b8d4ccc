"""The frame prefetcher returns what a synchronous read would, errors included, in any order of gets."""
from __future__ import annotations

import os
import threading

import pytest

from slam.prefetch import Prefetcher


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


def test_stereo_ahead_gives_the_same_run_in_another_thread(synth_dir, tmp_path):
    """``tracking.stereo_ahead``: the next frame's stereo depth is made in the read-ahead thread;
    the trajectory is the same bit for bit, the thread count of torch is restored after the run,
    and ``threads: 0`` leaves one core to that thread."""
    import numpy as np
    import torch

    from slam.config import load_config
    from slam.datasets import open_dataset
    from slam.pipeline import Pipeline

    data = synth_dir("rigid", 6, (160, 128))
    before = torch.get_num_threads()
    poses, stereo_threads = {}, {}
    for ahead in (True, False):
        cfg = load_config(None, ["tracking.mode=frame2model", f"tracking.stereo_ahead={str(ahead).lower()}",
                                 "threads=1"])
        pipe = Pipeline(cfg, open_dataset(data, cfg.data), tmp_path / str(ahead))
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
    assert pipe._torch_threads() == max(1, cores - 1)
