"""``slam run``: claim the output folder, open the dataset, build the pipeline and logger, run,
log to ``run.log``, print a summary; the exit code of a run."""
from __future__ import annotations

import contextlib
import logging
import signal
import sys
from pathlib import Path
from typing import Callable, Iterator

from slam.config import SlamConfig
from slam.errors import SlamError
from slam.app.interrupts import exit_code
from slam.app.pipeline import Pipeline, RunResult
from slam.app.status import is_result
from slam.app.run_folder import check_out_dir, clear_run_files

log = logging.getLogger("slam")

RUN_LOG = "run.log"
#: the loggers whose records ``run.log`` keeps
PROJECT_LOGGERS = ("slam", "vo", "mapping")
#: the exit code of a finished run that is not a result (``slam.app.status``)
NOT_A_RESULT = 3


def default_out_dir(data: str | Path, mode: str) -> Path:
    path = Path(data).resolve()
    return Path("runs") / f"{path.stem if path.is_file() else path.name}_{mode}"


def make_logger(config: SlamConfig, dataset, spawn: bool = False):
    """A rerun logger when a recording or the viewer (``spawn``) is asked for, else None (rerun
    is then not imported at all)."""
    if not (config.logging.rerun or spawn):
        return None
    from slam.app.rerun_log import RerunLogger

    return RerunLogger(config.logging, dataset.camera, name=dataset.path.name,
                       gt_poses=dataset.gt_poses, R1=dataset.R1, spawn=spawn)


def run_from_config(data: str | Path, config: SlamConfig, out: str | Path | None = None,
                    frames: str | None = None, print_summary: bool = True,
                    on_frame: Callable[[int], None] | None = None, overwrite: bool = False,
                    progress: bool = True, spawn: bool = False) -> RunResult:
    """Run one sequence end to end with a resolved config; ``metrics.json`` records the run's
    provenance (``slam.app.provenance``) and ``run.log`` what the run logged. ``on_frame``: see
    ``Pipeline.run``. A folder holding an earlier run is refused unless ``overwrite``, which
    removes that run's files once the data is open (``slam.app.run_folder``). ``progress``:
    show it (``slam.app.progress``); ``spawn``: open the rerun viewer."""
    from slam.io.datasets import open_dataset
    from slam.app.provenance import provenance

    out_dir = Path(out) if out else default_out_dir(data, config.tracking.mode)
    check_out_dir(out_dir, overwrite)
    dataset = open_dataset(Path(data), config.data)
    if frames:
        dataset = dataset.select(frames)
    out_dir.mkdir(parents=True, exist_ok=True)
    clear_run_files(out_dir)
    with run_log(out_dir / RUN_LOG) as run_log_file:
        log.info("slam run %s -> %s (%s, %d frames)", dataset.path, out_dir, config.tracking.mode, len(dataset))
        logger = make_logger(config, dataset, spawn)
        pipeline = Pipeline(config, dataset, out_dir, logger=logger, provenance=provenance(config, frames))
        result = pipeline.run(progress=progress, on_frame=on_frame)
        result.files["log"] = str(out_dir / RUN_LOG)
        summary = summary_text(result)
        log.info("%s", summary)
    if run_log_file.error is not None:
        record_output_error(result, "log", run_log_file.error)
        summary = summary_text(result)
    if print_summary:
        print(summary)
    if result.output_errors:
        raise SlamError(f"{'; '.join(result.output_errors.values())} (not written, no partial file left; the other "
                        "outputs are, and metrics.json lists these under skipped_outputs)")
    return result


def record_output_error(result: RunResult, name: str, error: str) -> None:
    """An output the runner writes (``run.log``) that could not be written: in ``result`` and its
    ``metrics.json`` as the pipeline's own are."""
    from slam.app.run_folder import write_json_atomically

    result.output_errors[name] = error
    result.files.pop(name, None)
    result.metrics["skipped_outputs"] = [*result.metrics.get("skipped_outputs", []), name]
    result.metrics["output_errors"] = result.output_errors
    write_json_atomically(result.out_dir / "metrics.json", result.metrics)


class RunLogHandler(logging.FileHandler):
    """``run.log``'s handler: a record it cannot write (a full disk) stops it, the first error
    kept in ``error`` (one line naming the file), where logging would print a traceback per record."""

    error = None

    def handleError(self, record: logging.LogRecord) -> None:  # noqa: N802 - logging's API
        if self.error is None:
            err = sys.exc_info()[1]
            self.error = f"{self.baseFilename}: {getattr(err, 'strerror', None) or err}"
        self.setLevel(logging.CRITICAL + 1)


@contextlib.contextmanager
def run_log(path: Path) -> Iterator[RunLogHandler]:
    """What the project logs (info and above, with times) goes to ``path`` as well while the
    block runs; the console keeps its own level. Yields the handler (its ``error``: why the file
    could not be written, or None)."""
    handler = RunLogHandler(path, mode="a", encoding="utf-8")
    handler.setLevel(logging.INFO)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    loggers = [logging.getLogger(name) for name in PROJECT_LOGGERS]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.addHandler(handler)
        if lg.getEffectiveLevel() > logging.INFO:
            lg.setLevel(logging.INFO)
    try:
        yield handler
    finally:
        for lg, level in zip(loggers, levels):
            lg.removeHandler(handler)
            lg.setLevel(level)
        try:
            handler.close()         # (flushes what it still holds)
        except OSError as err:
            handler.error = handler.error or f"{path}: {err.strerror or err}"


def exit_status(result: RunResult) -> int:
    """``slam run``'s exit code: 128 + the signal when it was stopped (130 Ctrl-C, 143
    SIGTERM), 3 when it is not a result (too many frames failed), else 0 (an untrusted run too:
    its flagged frames are results)."""
    if result.interrupted:
        return exit_code(result.signum or signal.SIGINT)
    return 0 if is_result(result.metrics.get("status", "ok")) else NOT_A_RESULT


def summary_text(result: RunResult) -> str:
    m = result.metrics
    done = m["frames"]
    lines = [f"{'interrupted after' if result.interrupted else 'processed'} {done} frames "
             f"({m.get('mode')}), {len(m['failed_frames'])} failed, {len(m.get('flagged_frames', []))} flagged, "
             f"{m['fps']:.1f} fps (tracked frames)"]
    status = m.get("status", "ok")
    if not is_result(status):
        lines.append(f"{status}: their poses are carried over, not tracked")
    elif status != "ok":
        lines.append(f"{status}: their poses are reported, not trusted (tracking.csv says why)")
    if m.get("likely_cause"):
        lines.append(f"likely cause: {m['likely_cause']}")
    if is_result(status) and "ate_rmse_mm" in m:
        over = (f" over {m['evaluated_frames']} frames with ground truth"
                if m.get("evaluated_frames", done) != done else "")
        mark = "" if status == "ok" else f" ({status.split(':')[0]})"
        lines.append(f"ATE-RMSE {m['ate_rmse_mm']:.3f} mm{mark} | RPE-trans {m['rpe_trans_mm']:.3f} ± "
                     f"{m['rpe_trans_std_mm']:.3f} mm | RPE-rot {m['rpe_rot_deg']:.4f} ± {m['rpe_rot_std_deg']:.4f} deg"
                     f"{over}")
    if m.get("map_points"):
        lines.append(f"map: {m['map_points']} points")
    if m.get("skipped_outputs"):
        lines.append("skipped: " + ", ".join(m["skipped_outputs"]))
    lines.append("outputs: " + ", ".join(f"{k}={v}" for k, v in result.files.items()))
    return "\n".join(lines)
