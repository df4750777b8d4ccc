"""Running a batch of tasks: the executor chosen from the options, one progress bar over the
tasks with the frames per second summed over the workers, a line per task as it ends, and
Ctrl-C handled so that what finished is kept.

``run_batch`` returns each task's outcome by index; a task that never started (Ctrl-C before its
turn) has none.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass
from typing import Callable, Optional

from slam.batch.executors import Finished, Frames, LocalExecutor, RayExecutor, Started, ray_available
from slam.batch.worker import execute
from slam.errors import ConfigError


@dataclass
class BatchOptions:
    """How a batch runs.

    Attributes:
        executor: ``auto`` (Ray when it is installed, else local processes), ``ray`` or ``local``.
        address: a Ray cluster's address (``auto``, ``HOST:PORT``, ``ray://HOST:PORT``); None: this
            machine.
        workers: tasks at once on this machine (0: its cores over ``cpus_per_task``).
        cpus_per_task: CPUs each task gets (Ray's ``num_cpus``); a run's ``threads`` when its
            config leaves them at 0.
        timeout_s: a task running longer is interrupted (and killed if it does not stop); None: no
            limit.
        force: run tasks whose results are there already too.
        progress: show the progress bar.
    """

    executor: str = "auto"
    address: Optional[str] = None
    workers: int = 0
    cpus_per_task: int = 1
    timeout_s: Optional[float] = None
    force: bool = False
    progress: bool = True

    def validate(self) -> None:
        if self.executor not in ("auto", "ray", "local"):
            raise ConfigError(f"--executor {self.executor}: expected auto, ray or local")
        if self.cpus_per_task < 1:
            raise ConfigError(f"--cpus-per-task {self.cpus_per_task}: must be >= 1")
        if self.workers < 0:
            raise ConfigError(f"--workers {self.workers}: must be >= 0 (0: the cores over --cpus-per-task)")
        if self.timeout_s is not None and self.timeout_s <= 0:
            raise ConfigError(f"--timeout {self.timeout_s:g}: must be positive (seconds)")
        if self.address and self.executor == "local":
            raise ConfigError("--address needs --executor ray (or auto)")

    def local_workers(self) -> int:
        if self.workers:
            return self.workers
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        return max(1, cores // self.cpus_per_task)

    def kind(self) -> str:
        """The executor that runs: ``ray`` or ``local``."""
        if self.executor == "ray" or self.address:
            if not ray_available():
                raise ConfigError("Ray is not installed: pip install 'endoslam[cluster]' (or --executor local)")
            return "ray"
        if self.executor == "auto" and ray_available():
            return "ray"
        return "local"


def thread_env(threads: int) -> dict:
    """The environment a worker gets: every library's thread pool at ``threads`` (Ray sets
    ``OMP_NUM_THREADS`` from ``num_cpus``; a local worker gets the same)."""
    return {name: str(threads) for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                            "NUMBA_NUM_THREADS")}


def make_executor(options: BatchOptions):
    env = thread_env(options.cpus_per_task)
    if options.kind() == "ray":
        return RayExecutor(options.address, options.local_workers(), options.cpus_per_task, env, options.timeout_s)
    return LocalExecutor(options.local_workers(), env, options.timeout_s)


class _Progress:
    """One bar over the tasks; frames per second summed over the running and finished tasks."""

    def __init__(self, total: int, enabled: bool):
        from tqdm import tqdm

        self.bar = tqdm(total=total, unit="task", disable=not enabled, dynamic_ncols=True, leave=False,
                        file=sys.stderr)
        self.t0 = time.perf_counter()
        self.frames: dict[int, int] = {}
        self.running: set[int] = set()

    def update(self, event) -> None:
        if isinstance(event, Started):
            self.running.add(event.index)
        elif isinstance(event, Frames):
            self.frames[event.index] = event.frames
        elif isinstance(event, Finished):
            self.running.discard(event.index)
            if "frames" in event.outcome:
                self.frames[event.index] = int(event.outcome["frames"])
            self.bar.update(1)
        elapsed = max(time.perf_counter() - self.t0, 1e-9)
        self.bar.set_postfix(running=len(self.running), fps=f"{sum(self.frames.values()) / elapsed:.1f}",
                             refresh=False)

    def write(self, line: str) -> None:
        self.bar.write(line, file=sys.stdout)
        sys.stdout.flush()

    def close(self) -> None:
        self.bar.close()


def run_batch(tasks: list, options: BatchOptions,
              describe: Callable[[int, dict], str]) -> tuple[dict[int, dict], bool, dict]:
    """Run ``tasks`` (longest first is the caller's order) on the executor the options give.

    Args:
        describe: the line printed when task ``index`` ends with ``outcome``.

    Returns:
        the outcomes by task index, whether the batch was interrupted (Ctrl-C), and the
        executor's description with the wall time (``wall_s``).
    """
    outcomes: dict[int, dict] = {}
    started: set[int] = set()
    info: dict = {}
    if not tasks:
        return outcomes, False, {"executor": "none", "wall_s": 0.0}
    executor = make_executor(options)
    info = executor.describe()
    progress = _Progress(len(tasks), options.progress)
    t0 = time.perf_counter()
    interrupted = False

    def handle(event) -> None:
        if isinstance(event, Started):
            started.add(event.index)
        progress.update(event)
        if isinstance(event, Finished) and (event.index in started or event.outcome.get("status") != "interrupted"):
            outcomes[event.index] = event.outcome
            progress.write(f"[{len(outcomes)}/{len(tasks)}] {describe(event.index, event.outcome)}")

    try:
        try:
            for event in executor.run(execute, tasks):
                handle(event)
        except KeyboardInterrupt:
            interrupted = True
            progress.write("interrupted: the running tasks write what they have (Ctrl-C again to stop at once)")
            try:
                for event in executor.interrupt():
                    handle(event)
            except KeyboardInterrupt:
                pass
    finally:
        progress.close()
        executor.close()
    info["wall_s"] = time.perf_counter() - t0
    return outcomes, interrupted, info
