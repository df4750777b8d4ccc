"""What a worker process does with one task (``slam.batch.tasks``): run it with its threads as
the task says (a run writes its own ``run.log``; what else the task prints is added to it) and
return its outcome.

The outcome is a small dict (``status`` ``ok`` | ``interrupted`` | ``error`` | ``not a result``, a one-line
``message`` for errors, ``seconds``, ``frames``); the results themselves are the files the task
writes into its folder, which the driver reads.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Callable, Iterator

from slam.app.run_folder import write_text_atomically
from slam.batch.tasks import MAP_ACCURACY, METRICS, RUN_LOG, RunTask, SynthTask

#: what a task prints outside the project's logging, appended to ``run.log`` when it ends
STRAY_LOG = ".task_output.log"
from slam.errors import DataError, one_line

Report = Callable[[str, Any], None]


@contextlib.contextmanager
def captured_output(path: Path) -> Iterator[None]:
    """Send this process's standard output and error, at the file-descriptor level (so what
    native libraries print lands there too), to ``path`` for the duration; warnings logged by
    the project go there as well."""
    path.parent.mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    root = logging.getLogger()
    handler = None
    with open(path, "w") as log:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        if not root.handlers:
            handler = logging.StreamHandler(sys.stderr)
            handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
            root.addHandler(handler)
            root.setLevel(logging.WARNING)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            if handler is not None:
                root.removeHandler(handler)
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def _throttled(report: Report, every_s: float = 1.0) -> Callable[[int], None]:
    last = [0.0]

    def on_frame(done: int) -> None:
        now = time.perf_counter()
        if now - last[0] >= every_s:
            last[0] = now
            report("frames", done)

    return on_frame


def check_sequence(task: RunTask) -> None:
    """The protocol's demands on the sequence, before the run: the frames it names exist and it
    has ground-truth poses (DataError naming the sequence otherwise)."""
    from slam.io.datasets import open_dataset

    dataset = open_dataset(Path(task.data), task.config.data)
    try:
        n = len(dataset)
        if task.bounds is not None:
            start, end = task.bounds
            start = 0 if start is None else int(start)
            end = n if end is None else int(end)
            if start >= n:
                raise DataError(f"{task.data}: start frame {start} is beyond its {n} frames")
            if end > n:
                raise DataError(f"{task.data}: frames {start}:{end} end beyond its {n} frames")
            if end - start < 2:
                raise DataError(f"{task.data}: frames {start}:{end} select fewer than 2 frames")
        if task.require_groundtruth:
            selected = dataset.select(task.frames) if task.frames else dataset
            if selected.gt_poses is None:
                raise DataError(f"{task.data}: no ground-truth poses")
    finally:
        dataset.close()


def run_task(task: RunTask, report: Report) -> dict:
    """Track ``task``'s sequence into its run folder (see ``slam.batch.tasks.RunTask``); the run
    writes its own ``run.log``, to which an error's traceback is added."""
    import cv2

    from slam.batch.map_accuracy import keyframe_map_accuracy
    from slam.app.runner import exit_status, run_from_config

    out = Path(task.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name in (METRICS, MAP_ACCURACY):   # a stale result must not pass for this run's
        (out / name).unlink(missing_ok=True)
    threads = max(1, task.config.threads)
    cv2.setNumThreads(threads)
    quiet_console()
    t0 = time.perf_counter()
    stray = out / STRAY_LOG
    try:
        with captured_output(stray):    # what native code prints; the run's own log is run.log
            check_sequence(task)
            result = run_from_config(task.data, task.config, out, task.frames, print_summary=False,
                                     on_frame=_throttled(report), overwrite=True, progress=False)
    except KeyboardInterrupt:
        return {"status": "interrupted", "message": "interrupted", "seconds": time.perf_counter() - t0}
    except Exception as err:  # noqa: BLE001 - one bad sequence is one error row
        with open(stray, "a") as fh:
            fh.write(f"{task.label}: {task.data} -> {out} (threads {threads}, pid {os.getpid()})\n")
            fh.write(traceback.format_exc())
        return {"status": "error", "message": one_line(err), "seconds": time.perf_counter() - t0}
    finally:
        append_stray_output(stray, out / RUN_LOG)
    report("frames", len(result.records))
    if task.map_accuracy is not None and not result.interrupted and result.records:
        acc = keyframe_map_accuracy(Path(task.data), out, result.records[0].pose, task.map_accuracy.gt_depth,
                                    task.map_accuracy.png_scale_mm)
        write_text_atomically(out / MAP_ACCURACY, json.dumps(acc, indent=2))
    status = {0: "ok", 3: "not a result"}.get(exit_status(result), "interrupted")
    outcome = {"status": status, "frames": len(result.records), "seconds": time.perf_counter() - t0}
    if status == "not a result":
        outcome["message"] = result.metrics["status"]
    return outcome


def append_stray_output(stray: Path, log: Path) -> None:
    """Add what the task printed outside the project's logging (native libraries, a traceback)
    to the end of the run's ``run.log``, and remove ``stray``."""
    if not stray.is_file():
        return
    text = stray.read_text(errors="replace")
    if text.strip():
        with open(log, "a") as fh:
            fh.write("--- printed by the task outside the run's log ---\n" + text)
    stray.unlink()


def quiet_console() -> None:
    """A worker's log records go to its run's ``run.log`` only: without a handler of its own the
    root logger would print warnings on the driver's terminal (Python's last resort)."""
    root = logging.getLogger()
    if not root.handlers:
        root.addHandler(logging.NullHandler())


def synth_task(task: SynthTask, report: Report) -> dict:
    """Render ``task``'s synthetic sequence; its log ends up as ``synth.log`` in the folder."""
    from slam.synth import generate

    out = Path(task.out_dir)
    log = out.parent / f".{out.name}.log"
    t0 = time.perf_counter()
    with captured_output(log):
        try:
            generate(out, task.scenario, frames=task.frames, size=tuple(task.size), seed=task.seed, raw=task.raw,
                     codec=task.codec, breathing_follows_tissue=task.breathing_follows_tissue,
                     camera_speed=task.camera_speed, appearance=task.look())
        except KeyboardInterrupt:
            return {"status": "interrupted", "message": "interrupted", "seconds": time.perf_counter() - t0}
        except Exception as err:  # noqa: BLE001
            traceback.print_exc()
            return {"status": "error", "message": one_line(err), "seconds": time.perf_counter() - t0,
                    "log": str(log)}
    os.replace(log, out / "synth.log")
    report("frames", task.frames)
    return {"status": "ok", "frames": task.frames, "seconds": time.perf_counter() - t0}


def execute(task: RunTask | SynthTask, report: Report) -> dict:
    """The worker function of every batch (``slam.batch.executors``)."""
    if isinstance(task, SynthTask):
        return synth_task(task, report)
    return run_task(task, report)
