"""Executors: run a batch's tasks in worker processes, on this machine or on a Ray cluster.

Both take a worker function ``function(payload, report) -> dict`` (importable by name: worker
processes import it) and the payloads, and yield the same events as tasks start, report frames
and end. ``report(kind, value)`` sends ``("frames", n)`` from inside a task to the driver.

* :class:`RayExecutor` (``pip install endoslam[cluster]``): one Ray task per payload with an
  explicit ``num_cpus``, ``max_retries=0`` (a task whose worker dies is reported, not re-run),
  submitted in the given order (the driver puts the longest first). Locally it starts a Ray
  runtime with ``workers * cpus_per_task`` CPUs; with an address it joins a cluster
  (``auto``, ``HOST:PORT`` or ``ray://HOST:PORT``). Progress comes back through a small actor.
* :class:`LocalExecutor`: the same tasks in ``workers`` processes started with ``spawn`` (torch,
  OpenCV and numba threads do not survive ``fork``), each kept for task after task so that the
  imports and the networks' loading are paid once per worker. A worker that dies (a segfault, the
  OOM killer) ends its task with an error; a new worker takes the next task.

A task that runs longer than ``timeout_s`` is interrupted (``KeyboardInterrupt`` in the task: a
run then writes its trajectory so far and a ``metrics.json`` marked ``interrupted``), and killed
``grace_s`` later if it has not returned. :meth:`interrupt` does the same for every running task
(Ctrl-C in the driver) and yields their ends.

Each worker process gets the environment ``env`` (e.g. ``OMP_NUM_THREADS``) before a task imports
anything.
"""
from __future__ import annotations

import collections
import os
import signal
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Optional

from slam.errors import ConfigError, one_line

WorkerFunction = Callable[[Any, Callable[[str, Any], None]], dict]
POLL_S = 0.5


@dataclass
class Started:
    """Task ``index`` started."""

    index: int


@dataclass
class Frames:
    """Task ``index`` has processed ``frames`` frames."""

    index: int
    frames: int


@dataclass
class Finished:
    """Task ``index`` ended: ``outcome`` is the worker function's dict, or one made here
    (``status`` ``error`` | ``timeout`` | ``interrupted`` and a one-line ``message``) when the
    task could not return one."""

    index: int
    outcome: dict


Event = Started | Frames | Finished


def failure(status: str, message: str, seconds: float = float("nan")) -> dict:
    return {"status": status, "message": message, "seconds": seconds}


def signal_name(exitcode: Optional[int]) -> str:
    if exitcode is None or exitcode >= 0:
        return f"exit code {exitcode}"
    try:
        return signal.Signals(-exitcode).name
    except ValueError:
        return f"signal {-exitcode}"


@dataclass
class _Running:
    index: int
    started: float
    stopping_since: Optional[float] = None   # when it was asked to stop
    reason: str = ""                          # timeout | interrupted


def _stop_outcome(running: _Running, outcome: dict, timeout_s: Optional[float]) -> dict:
    """The outcome of a task that was asked to stop: its own (a run's partial results), marked
    with why it stopped."""
    if running.stopping_since is None or outcome.get("status") not in ("ok", "interrupted"):
        return outcome
    out = dict(outcome)
    out["status"] = running.reason
    if running.reason == "timeout":
        out["message"] = f"stopped at the timeout ({timeout_s:g} s)"
    else:
        out["message"] = "interrupted"
    return out


# ------------------------------------------------------------------------------------------------
# local worker processes
def _watch_parent(parent: int) -> None:
    """End this worker when the driver is gone (killed without a chance to stop its workers)."""
    while True:
        if os.getppid() != parent:
            os._exit(3)
        time.sleep(1.0)


def serve(conn, env: dict, parent: int) -> None:
    """A local worker's loop: receive ``(index, function, payload)``, run it, send its events;
    ``None`` or a closed pipe ends it. Runs in its own process group, so a Ctrl-C in the driver's
    terminal reaches the driver only, which stops tasks itself."""
    os.setpgrp()
    os.environ.update(env)
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        except KeyboardInterrupt:
            continue
        if message is None:
            return
        index, function, payload = message

        def report(kind: str, value: Any, index: int = index) -> None:
            conn.send((kind, index, value))

        t0 = time.perf_counter()
        try:
            signal.signal(signal.SIGINT, signal.default_int_handler)
            conn.send(("started", index, None))
            outcome = function(payload, report)
        except KeyboardInterrupt:
            outcome = failure("interrupted", "interrupted", time.perf_counter() - t0)
        except Exception as err:  # noqa: BLE001 - the driver gets a row, the worker goes on
            outcome = failure("error", one_line(err), time.perf_counter() - t0)
        finally:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            conn.send(("finished", index, outcome))
        except (EOFError, OSError):
            return


class LocalExecutor:
    """Tasks in ``workers`` spawned processes on this machine (see the module docstring)."""

    kind = "local"

    def __init__(self, workers: int, env: Optional[dict] = None, timeout_s: Optional[float] = None,
                 grace_s: float = 20.0):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = workers
        self.env = {k: str(v) for k, v in (env or {}).items()}
        self.timeout_s = timeout_s
        self.grace_s = grace_s
        self._procs: list = []                     # [process, connection]
        self._running: dict[int, _Running] = {}    # slot -> running task
        self._pending: collections.deque = collections.deque()
        self._function: Optional[WorkerFunction] = None
        self._payloads: list = []

    def describe(self) -> dict:
        return {"executor": "local", "workers": self.workers}

    def _start(self, slot: int) -> None:
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        here, there = ctx.Pipe(duplex=True)
        proc = ctx.Process(target=serve, args=(there, self.env, os.getpid()), daemon=True,
                           name=f"slam-worker-{slot}")
        proc.start()
        there.close()
        if slot < len(self._procs):
            self._procs[slot] = [proc, here]
        else:
            self._procs.append([proc, here])

    def _dispatch(self, slot: int) -> None:
        index = self._pending.popleft()
        message = (index, self._function, self._payloads[index])
        try:
            self._procs[slot][1].send(message)
        except (BrokenPipeError, EOFError, OSError):   # the idle worker had died: a new one
            self._start(slot)
            self._procs[slot][1].send(message)
        self._running[slot] = _Running(index, time.perf_counter())

    def run(self, function: WorkerFunction, payloads: list) -> Iterator[Event]:
        """Run every payload; yield events as they come (see the module docstring)."""
        self._function, self._payloads = function, list(payloads)
        self._pending = collections.deque(range(len(self._payloads)))
        for slot in range(min(self.workers, len(self._payloads))):
            self._start(slot)
            self._dispatch(slot)
        while self._running:
            yield from self._poll()
            for slot in range(len(self._procs)):
                if slot not in self._running and self._pending:
                    if not self._procs[slot][0].is_alive():
                        self._start(slot)
                    self._dispatch(slot)

    def _poll(self, timeout: float = POLL_S) -> Iterator[Event]:
        from multiprocessing.connection import wait

        waitables = {}
        for slot in self._running:
            proc, conn = self._procs[slot]
            waitables[conn] = slot
            waitables[proc.sentinel] = slot
        for ready in wait(list(waitables), timeout=timeout):
            slot = waitables[ready]
            if slot not in self._running:
                continue
            proc, conn = self._procs[slot]
            if ready is conn or conn.poll():
                yield from self._receive(slot)
            elif not proc.is_alive():
                yield from self._died(slot)
        yield from self._check_timeouts()

    def _receive(self, slot: int) -> Iterator[Event]:
        proc, conn = self._procs[slot]
        while slot in self._running and conn.poll():
            try:
                kind, index, value = conn.recv()
            except (EOFError, OSError):
                yield from self._died(slot)
                return
            if kind == "started":
                yield Started(index)
            elif kind == "frames":
                yield Frames(index, int(value))
            elif kind == "finished":
                running = self._running.pop(slot)
                yield Finished(index, _stop_outcome(running, value, self.timeout_s))

    def _died(self, slot: int) -> Iterator[Event]:
        proc, conn = self._procs[slot]
        proc.join(timeout=5)
        running = self._running.pop(slot)
        seconds = time.perf_counter() - running.started
        if running.stopping_since is not None and running.reason == "timeout":
            outcome = failure("timeout", f"killed {self.grace_s:g} s after the timeout ({self.timeout_s:g} s)", seconds)
        elif running.stopping_since is not None:
            outcome = failure("interrupted", "interrupted (worker killed)", seconds)
        else:
            outcome = failure("error", f"worker died ({signal_name(proc.exitcode)}); its log has what it printed",
                              seconds)
        conn.close()
        yield Finished(running.index, outcome)

    def _ask_to_stop(self, slot: int, reason: str) -> None:
        running = self._running[slot]
        if running.stopping_since is not None:
            return
        running.stopping_since, running.reason = time.perf_counter(), reason
        try:
            os.kill(self._procs[slot][0].pid, signal.SIGINT)
        except ProcessLookupError:
            pass

    def _check_timeouts(self) -> Iterator[Event]:
        now = time.perf_counter()
        for slot, running in list(self._running.items()):
            if running.stopping_since is None and self.timeout_s and now - running.started > self.timeout_s:
                self._ask_to_stop(slot, "timeout")
            elif running.stopping_since is not None and now - running.stopping_since > self.grace_s:
                self._procs[slot][0].kill()
                yield from self._died(slot)

    def interrupt(self) -> Iterator[Event]:
        """Stop: nothing more starts, running tasks are interrupted; yields their ends."""
        self._pending.clear()
        for slot in list(self._running):
            self._ask_to_stop(slot, "interrupted")
        while self._running:
            yield from self._poll()

    def close(self) -> None:
        """End the worker processes."""
        for proc, conn in self._procs:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
        deadline = time.perf_counter() + 10.0
        for proc, conn in self._procs:
            proc.join(timeout=max(0.1, deadline - time.perf_counter()))
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=5)
            conn.close()
        self._procs.clear()


# ------------------------------------------------------------------------------------------------
# Ray
class _Inbox:
    """A Ray actor (no CPU) that keeps the tasks' reports until the driver takes them."""

    def __init__(self):
        self.items: list = []

    def put(self, item) -> None:
        self.items.append(item)

    def take(self) -> list:
        items, self.items = self.items, []
        return items


def _ray_task(function: WorkerFunction, payload: Any, index: int, inbox, env: dict) -> dict:
    """What a Ray worker runs: the worker function, with ``report`` sending to the driver's inbox.

    ``env`` is set in the worker before the task imports anything heavy (a Ray worker starts
    with none of numpy, torch, OpenCV: measured), which a ``runtime_env`` would do too but with a
    worker started for it, a second or two later. A report is sent without waiting for it: a task
    that waits on another (``ray.get``) lends its CPU to the next task, which would run more tasks
    at once than there are CPUs."""
    os.environ.update(env)

    def report(kind: str, value: Any) -> None:
        try:
            inbox.put.remote((kind, index, value))
        except Exception:  # noqa: BLE001 - progress is best effort; the task goes on
            pass

    t0 = time.perf_counter()
    report("started", None)
    try:
        return function(payload, report)
    except KeyboardInterrupt:
        return failure("interrupted", "interrupted", time.perf_counter() - t0)
    except Exception as err:  # noqa: BLE001
        return failure("error", one_line(err), time.perf_counter() - t0)


@dataclass
class _RayState:
    refs: dict = field(default_factory=dict)        # ref -> index
    started: dict = field(default_factory=dict)     # index -> _Running


class RayExecutor:
    """Tasks on Ray (see the module docstring).

    Args:
        address: None: a local Ray runtime with ``workers * cpus_per_task`` CPUs; else the
            cluster's address (``auto``, ``HOST:PORT``, ``ray://HOST:PORT``).
        workers: local runtime only: how many tasks run at once.
        cpus_per_task: each task's ``num_cpus``.
        env: environment variables of every task's worker, set before the task imports anything.
    """

    kind = "ray"

    def __init__(self, address: Optional[str], workers: int, cpus_per_task: int, env: Optional[dict] = None,
                 timeout_s: Optional[float] = None, grace_s: float = 20.0):
        import ray  # noqa: F401 - fail here, before anything starts, without the extra

        self.address = address
        self.workers = workers
        self.cpus_per_task = cpus_per_task
        self.env = {k: str(v) for k, v in (env or {}).items()}
        self.timeout_s = timeout_s
        self.grace_s = grace_s
        self._state = _RayState()
        self._inbox = None
        self._started_runtime = False

    def describe(self) -> dict:
        out = {"executor": "ray", "address": self.address or "local", "cpus_per_task": self.cpus_per_task}
        if self.address is None:
            out["workers"] = self.workers
        return out

    def _init(self) -> None:
        import logging

        import ray

        if ray.is_initialized():
            return
        options = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
        try:
            if self.address is None:
                # "local": a runtime of our own, even when another is running or Ray's address file
                # names one (Ray would join that one and refuse the CPU count). Niceness 0: Ray runs
                # its workers at 15, so any other process on the machine took their CPU (one busy
                # loop made the 12 runs of tools/benchmark_evaluate.py 84 s instead of 65).
                ray.init(address="local", num_cpus=self.workers * self.cpus_per_task,
                         object_store_memory=128 * 1024 * 1024, _system_config={"worker_niceness": 0}, **options)
            else:
                ray.init(address=self.address, **options)
        except Exception as err:  # noqa: BLE001 - Ray raises several kinds; the user needs one line
            where = f"the Ray cluster at {self.address}" if self.address else "a local Ray runtime"
            raise ConfigError(f"cannot start or reach {where}: {one_line(err)}") from None
        self._started_runtime = True

    def run(self, function: WorkerFunction, payloads: list) -> Iterator[Event]:
        import ray

        self._init()
        self._inbox = ray.remote(_Inbox).options(num_cpus=0).remote()
        remote = ray.remote(_ray_task).options(num_cpus=self.cpus_per_task, max_retries=0)
        self._state = _RayState()
        for index, payload in enumerate(payloads):
            self._state.refs[remote.remote(function, payload, index, self._inbox, self.env)] = index
        while self._state.refs:
            yield from self._poll()

    def _drain_inbox(self) -> Iterator[Event]:
        import ray

        try:
            messages = ray.get(self._inbox.take.remote(), timeout=10)
        except ray.exceptions.RayError:   # progress is best effort
            messages = []
        for kind, index, value in messages:
            if kind == "started":
                self._state.started.setdefault(index, _Running(index, time.perf_counter()))
                yield Started(index)
            elif kind == "frames":
                yield Frames(index, int(value))

    def _poll(self, timeout: float = POLL_S) -> Iterator[Event]:
        import ray

        ready, _ = ray.wait(list(self._state.refs), num_returns=1, timeout=timeout)
        yield from self._drain_inbox()
        for ref in ready:
            yield self._collect(ref)
        self._check_timeouts()

    def _collect(self, ref) -> Finished:
        import ray

        index = self._state.refs.pop(ref)
        running = self._state.started.pop(index, None)
        seconds = time.perf_counter() - running.started if running else float("nan")
        try:
            outcome = ray.get(ref)
            if running is not None:
                outcome = _stop_outcome(running, outcome, self.timeout_s)
        except ray.exceptions.TaskCancelledError:
            if running is not None and running.reason == "timeout":
                outcome = failure("timeout", f"cancelled after the timeout ({self.timeout_s:g} s)", seconds)
            else:
                outcome = failure("interrupted", "interrupted", seconds)
        except ray.exceptions.WorkerCrashedError:
            outcome = failure("error", "worker died (crashed or killed); its log has what it printed", seconds)
        except ray.exceptions.RayError as err:
            outcome = failure("error", one_line(err), seconds)
        return Finished(index, outcome)

    def _check_timeouts(self) -> None:
        import ray

        now = time.perf_counter()
        for ref, index in list(self._state.refs.items()):
            running = self._state.started.get(index)
            if running is None:
                continue
            if running.stopping_since is None and self.timeout_s and now - running.started > self.timeout_s:
                running.stopping_since, running.reason = now, "timeout"
                ray.cancel(ref)
            elif running.stopping_since is not None and now - running.stopping_since > self.grace_s:
                ray.cancel(ref, force=True)

    def interrupt(self) -> Iterator[Event]:
        """Stop: tasks not started are cancelled, running ones interrupted; yields every task's end
        (a task cancelled before it started ends ``interrupted`` without a ``Started``)."""
        import ray

        now = time.perf_counter()
        yield from self._drain_inbox()
        for ref, index in list(self._state.refs.items()):
            running = self._state.started.get(index)
            if running is not None and running.stopping_since is None:
                running.stopping_since, running.reason = now, "interrupted"
            ray.cancel(ref)
        while self._state.refs:
            yield from self._poll()

    def close(self) -> None:
        import ray

        if self._inbox is not None:
            try:
                ray.kill(self._inbox)
            except Exception:  # noqa: BLE001 - the runtime may be gone already
                pass
            self._inbox = None
        if self._started_runtime and ray.is_initialized():
            ray.shutdown()
        self._started_runtime = False


def ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True
