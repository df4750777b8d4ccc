"""The mapping stage: a tracked frame's fusion runs in its own thread while the next frame's
map-free work goes on (its estimate against the last frame: the cross-check's flow, weights and
solve), the way ORB-SLAM3 hands keyframes from tracking to local mapping.

Determinism: at most one fusion is in flight (a queue of one), and every use of the map waits
for it first: the map is reached only through :class:`SettledMap`, whose every attribute waits
for the fusion in flight, so the next frame's render, the cross-check's rebuild
(``forget_view``), the loop closure's ``move_surfels`` / ``reactivate_view``, logging and export
all see the map exactly as a run fusing in the tracking thread would. Nothing uses a result "if it
is ready": poses depend on the input and the configuration only.

Variants chosen once per run: :class:`BackgroundMapping` (a fusing run with the read-ahead
thread's cores to share) or :class:`InlineMapping` (the fusion in the calling thread). Both give
the same maps and poses bit for bit (``tests/test_mapping_stage.py``).
"""
from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Optional


class Handover:
    """What the mapping stage reports back to the tracking thread: the ``(stage, ms)`` wall times
    of the fusions that finished since the last handover and the mapping thread's CPU time (ms)."""

    def __init__(self) -> None:
        self.timings: list[tuple[str, float]] = []
        self.cpu_ms = 0.0

    def take(self) -> tuple[list, float]:
        timings, cpu = self.timings, self.cpu_ms
        self.timings, self.cpu_ms = [], 0.0
        return timings, cpu


class SettledMap:
    """The surfel map as the tracking thread sees it: every attribute (``render``,
    ``forget_view``, ``save_ply``, ...) first waits for the fusion in flight."""

    def __init__(self, surfel_map, settle: Callable[[], None]):
        object.__setattr__(self, "_map", surfel_map)
        object.__setattr__(self, "_settle", settle)

    def __getattr__(self, name: str):
        self._settle()
        return getattr(self._map, name)

    def __setattr__(self, name: str, value) -> None:
        self._settle()
        setattr(self._map, name, value)

    def __len__(self) -> int:
        self._settle()
        return len(self._map)


class InlineMapping:
    """The fusion in the calling thread (a run without a map, or without a core to spare).

    Args:
        fusion: :class:`slam.tracking.map_fusion.SurfelFusion` or ``NoFusion``.
    """

    threaded = False

    def __init__(self, fusion):
        self.fusion = fusion
        self.handover = Handover()

    @property
    def map(self):
        return self.fusion.map

    def fuse(self, view, w3d, pose, position: int, active_from: Optional[int], scale: float = 1.0) -> None:
        """Fuse ``view`` at ``pose`` (as :meth:`SurfelFusion.fuse`) now."""
        self.handover.timings += self.fusion.fuse(view, w3d, pose, position, active_from, scale)

    def settle(self) -> None:
        """(Nothing in flight.)"""

    def finished(self) -> tuple[list, float]:
        """The ``(stage, ms)`` of the fusions since the last call and the mapping thread's CPU
        ms (0: the fusion's CPU time is the calling thread's)."""
        return self.handover.take()[0], 0.0

    def close(self) -> None:
        """(No thread.)"""


class BackgroundMapping(InlineMapping):
    """The fusion in a mapping thread, one frame in flight.

    The thread starts with the run's torch thread count (``torch.set_num_threads`` is
    inherited by new threads): the same numerics as the tracking thread's.

    Args:
        fusion: :class:`slam.tracking.map_fusion.SurfelFusion`.
    """

    threaded = True

    def __init__(self, fusion):
        super().__init__(fusion)
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mapping")
        self._in_flight: Optional[Future] = None
        self._map = SettledMap(fusion.map, self.settle)

    @property
    def map(self):
        return self._map

    def fuse(self, view, w3d, pose, position: int, active_from: Optional[int], scale: float = 1.0) -> None:
        """Start fusing ``view`` at ``pose`` in the mapping thread (after the fusion in flight)."""
        self.settle()
        self._in_flight = self._pool.submit(self._fuse, view, w3d, pose, position, active_from, scale)

    def _fuse(self, view, w3d, pose, position: int, active_from: Optional[int], scale: float = 1.0) -> tuple[list, float]:
        t_cpu = time.thread_time()
        timings = self.fusion.fuse(view, w3d, pose, position, active_from, scale)
        return timings, (time.thread_time() - t_cpu) * 1000.0

    def settle(self) -> None:
        """Wait for the fusion in flight (raises what it raised)."""
        future, self._in_flight = self._in_flight, None
        if future is None:
            return
        t0 = time.perf_counter()
        timings, cpu_ms = future.result()
        self.handover.timings += timings
        self.handover.timings.append(("map_wait", (time.perf_counter() - t0) * 1000.0))
        self.handover.cpu_ms += cpu_ms

    def finished(self) -> tuple[list, float]:
        return self.handover.take()

    def close(self) -> None:
        """Finish the fusion in flight and stop the thread."""
        try:
            self.settle()
        finally:
            self._pool.shutdown(wait=True)
