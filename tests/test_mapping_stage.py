"""The mapping stage (``slam.tracking.mapping_stage``): the fusion in its own thread changes no pose
and no map, and every use of the map waits for the fusion in flight."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from slam.tracking.mapping_stage import BackgroundMapping, InlineMapping


def _run(data, out, inline: bool, monkeypatch, mode: str = "frame2model"):
    import slam.tracking.tracker as tracker
    from slam.app.runner import run_from_config
    from slam.config import load_config

    with monkeypatch.context() as m:
        if inline:
            m.setattr(tracker, "make_mapping", InlineMapping)
        cfg = load_config(None, [f"tracking.mode={mode}", "threads=1"])
        res = run_from_config(data, cfg, out, print_summary=False)
    return res, (out / "trajectory.txt").read_bytes()


def test_the_mapping_thread_gives_the_same_poses_and_map_bit_for_bit(synth_dir, tmp_path, monkeypatch):
    """Frame2model at 160x128 (where float rounding shows most): the fusion in the mapping thread
    against the fusion in the tracking thread, and two runs with the thread: byte-identical
    trajectories and the same map."""
    data = synth_dir("scanning", 14, seed=5)
    a, traj_a = _run(data, tmp_path / "a", False, monkeypatch)
    b, traj_b = _run(data, tmp_path / "b", False, monkeypatch)
    c, traj_c = _run(data, tmp_path / "c", True, monkeypatch)
    assert traj_a == traj_b == traj_c
    assert (tmp_path / "a" / "map.ply").read_bytes() == (tmp_path / "c" / "map.ply").read_bytes()
    assert a.metrics["frames"] == 14 and not a.metrics["failed_frames"]
    # the mapping thread's work is reported: its fusions and CPU time, and what tracking waited
    timings = a.metrics["timings_ms"]
    assert timings["fusion"] > 0 and "map_wait" in timings and "map_wait" not in c.metrics["timings_ms"]
    assert a.metrics["thread_cpu_ms"]["mapping"] > 0 and "mapping" not in c.metrics["thread_cpu_ms"]


class _SlowFusion:
    """A fusion that takes ``seconds`` and records which thread ran it; its map counts fusions."""

    def __init__(self, seconds: float, fail_at: int = -1):
        self.seconds, self.fail_at = seconds, fail_at
        self.map = _CountingMap()
        self.threads: list[str] = []

    def fuse(self, view, w3d, pose, position, active_from):
        time.sleep(self.seconds)
        if position == self.fail_at:
            raise RuntimeError(f"fusion failed at {position}")
        self.threads.append(threading.current_thread().name)
        self.map.fused.append(position)
        return [("fusion", self.seconds * 1000.0)]


class _CountingMap:
    def __init__(self):
        self.fused: list[int] = []

    def __len__(self):
        return len(self.fused)

    def positions(self):
        return list(self.fused)


def test_every_use_of_the_map_waits_for_the_fusion_in_flight():
    fusion = _SlowFusion(0.2)
    stage = BackgroundMapping(fusion)
    try:
        t0 = time.perf_counter()
        stage.fuse(None, None, np.eye(4), 0, None)
        assert time.perf_counter() - t0 < 0.1              # handed over, not waited for
        assert stage.map.positions() == [0]                 # a method of the map waits first
        stage.fuse(None, None, np.eye(4), 1, None)
        assert len(stage.map) == 2                          # so does len()
        stage.fuse(None, None, np.eye(4), 2, None)
        stage.fuse(None, None, np.eye(4), 3, None)          # one in flight: the next waits for it
        stage.settle()
        assert fusion.map.fused == [0, 1, 2, 3]
        assert set(fusion.threads) == {n for n in fusion.threads if n.startswith("mapping")}
        timings, cpu_ms = stage.finished()
        assert [s for s, _ in timings].count("fusion") == 4 and cpu_ms >= 0.0
        assert stage.finished() == ([], 0.0)                # handed over once
    finally:
        stage.close()


def test_a_failed_fusion_surfaces_at_the_next_use_of_the_map():
    stage = BackgroundMapping(_SlowFusion(0.01, fail_at=1))
    try:
        stage.fuse(None, None, np.eye(4), 0, None)
        stage.fuse(None, None, np.eye(4), 1, None)
        with pytest.raises(RuntimeError, match="fusion failed at 1"):
            len(stage.map)
    finally:
        stage.close()


def test_inline_mapping_fuses_at_once():
    fusion = _SlowFusion(0.0)
    stage = InlineMapping(fusion)
    stage.fuse(None, None, np.eye(4), 0, None)
    assert fusion.map.fused == [0] and fusion.threads == [threading.current_thread().name]
    assert stage.finished() == ([("fusion", 0.0)], 0.0)
