"""How a run uses the machine's threads: the CPU time each of the pipeline's threads spends per
frame (``time.thread_time``: what the thread computed, not what it waited for) and the sizes of
the thread pools the libraries run inside those threads (torch, OpenCV, numba).

Wall-clock stage times (``timings_ms``) overlap across threads and include waiting for a core;
the CPU time per thread says which thread bounds the frame rate.
"""
from __future__ import annotations

import logging
import os
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import numpy as np

log = logging.getLogger("slam")


class ThreadClock:
    """CPU milliseconds per frame of each named pipeline thread (``main``, ``reader``, ``mapping``),
    and of the whole process (those threads plus the libraries' pool workers) from :meth:`start` on."""

    def __init__(self) -> None:
        self._ms: dict[str, list[float]] = {}
        self._process_start = self._process_end = time.process_time()

    def start(self) -> None:
        """The frames start now (the process's CPU time counts from here)."""
        self._process_start = time.process_time()

    def stop(self) -> None:
        """The frames are done (the final trajectory, map and files are not counted)."""
        self._process_end = time.process_time()

    @contextmanager
    def measure(self, thread: str) -> Iterator[None]:
        """Add the calling thread's CPU time inside the block to ``thread``'s frames."""
        t0 = time.thread_time()
        try:
            yield
        finally:
            self.add(thread, (time.thread_time() - t0) * 1000.0)

    def add(self, thread: str, ms: float) -> None:
        """One frame's ``ms`` of CPU time of ``thread``."""
        self._ms.setdefault(thread, []).append(ms)

    def reader_name(self) -> str | None:
        """``reader`` when called outside the main thread; None in the main thread (whose frames
        ``main`` already counts)."""
        return None if threading.current_thread() is threading.main_thread() else "reader"

    def summary(self, frames: int) -> dict[str, float]:
        """CPU milliseconds per frame of each thread measured (its total over ``frames``), and ``process``: the
        process's CPU time from :meth:`start` to :meth:`stop` over ``frames`` (pool workers
        included)."""
        out = {name: float(np.sum(ms)) / max(frames, 1) for name, ms in self._ms.items() if ms}
        if frames > 0:
            out["process"] = (self._process_end - self._process_start) * 1000.0 / frames
        return out


def pool_sizes() -> dict[str, int | None]:
    """Threads of each library's pool as set now: torch's intra-op pool, OpenCV's ``parallel_for``
    pool and the threads numba's pool would have (None where numba was not loaded: a run that never
    compiled a kernel).

    numba's is read from its configuration, not from ``numba.get_num_threads()``: that call
    launches the pool (an OpenMP team, none of our kernels being parallel), whose workers then spin
    beside the tracking: 2.5 instead of 3.4 fps in frame2model at 640x512 on two cores."""
    import cv2
    import torch
    numba = sys.modules.get("numba")
    return {"torch": torch.get_num_threads(), "opencv": cv2.getNumThreads(),
            "numba": int(numba.config.NUMBA_NUM_THREADS) if numba is not None else None}


def available_cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@dataclass(frozen=True)
class ThreadBudget:
    """The pools a run's ``threads`` (the cores it may use; 0: all; more than this process has:
    capped to them, with a warning) gives the libraries.

    - torch: every core but the read-ahead thread's (which computes the next frame's stereo and
      flow beside the tracking), at least one; all of them without a read-ahead thread;
    - OpenCV: all of them: its ``parallel_for`` workers take whichever core the other threads leave
      idle (at 640x512 on two cores frame2frame ran 7.7 fps with two against 7.1 with one; the
      mapping thread and numba start no pool: none of our compiled kernels is parallel).
    """

    torch: int
    opencv: int

    @staticmethod
    def of(threads: int, read_ahead: bool) -> "ThreadBudget":
        available = available_cores()
        if threads > available:      # more threads than cores only wait for them (6.5x slower at 999 on 2)
            log.warning("threads=%d, but this process may use %d cores: using %d", threads, available, available)
        cores = min(threads, available) if threads > 0 else available
        return ThreadBudget(torch=max(1, cores - 1) if read_ahead else cores, opencv=cores)

    @contextmanager
    def applied(self) -> Iterator[None]:
        """Set the pools for the block (new threads inherit torch's) and restore them after."""
        import cv2
        import torch
        before = torch.get_num_threads(), cv2.getNumThreads()
        torch.set_num_threads(self.torch)
        cv2.setNumThreads(self.opencv)
        try:
            yield
        finally:
            torch.set_num_threads(before[0])
            cv2.setNumThreads(before[1])
