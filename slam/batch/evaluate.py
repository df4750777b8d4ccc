"""``slam evaluate``: many sequences, both modes, config sweeps: one task per sequence, mode and
swept value, run on Ray or local worker processes, gathered into one table.

Outputs in ``OUT``:

* ``runs/[SWEEP/]RUN/MODE/``: each task's ``slam run`` folder (``trajectory.txt``,
  ``metrics.json`` with its provenance, ...) and ``run.log``, what the task printed;
* ``evaluation.md``: the protocol's tables (``slam.batch.reports``), also printed;
* ``evaluation.csv``: one line per run;
* ``evaluation.png``: ATE per run and per scenario, a bar per method;
* ``summary.json``: the options, the executor, the rows and the tables' figures.

A task whose run folder already holds its result (``slam.batch.tasks.RunTask.is_done``) is not
run again unless ``--force``: an evaluation stopped half way (Ctrl-C, a lost machine) and started
again runs only what is missing.
"""
from __future__ import annotations

import copy
import itertools
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from slam.app.run_folder import replaced_atomically, write_text_atomically
from slam.app.status import is_result
from slam.batch import protocols
from slam.batch.reports import REPORTS
from slam.batch.runner import BatchOptions, run_batch
from slam.batch.tables import METRIC_KEYS, fmt, plot, scenarios_of, write_csv
from slam.batch.tasks import MAP_ACCURACY, METRICS, MapAccuracySpec, RunTask, read_json
from slam.config import SlamConfig, load_config, with_overrides
from slam.errors import ConfigError

DEFAULT_CONFIGS = {"folder": None, "stereomis": protocols.CONFIGS / "stereomis_frame2frame.yaml",
                   "scared": protocols.CONFIGS / "scared_frame2model.yaml"}
#: config values that name files: made absolute before they travel to a worker
PATH_KEYS = (("weights", "checkpoint"), ("weights", "checkpoint_model"), ("correspondence", "raft_checkpoint"),
             ("data", "calibration"))
DEFAULT_MODES = {"folder": ["frame2frame", "frame2model"], "stereomis": ["frame2frame"], "scared": ["frame2model"]}


@dataclass
class EvaluateRequest:
    """What ``slam evaluate`` was asked (the command line's options, typed)."""

    root: Path
    protocol: str = "folder"
    modes: list = field(default_factory=list)
    config: Optional[str] = None
    overrides: list = field(default_factory=list)
    sweeps: list = field(default_factory=list)
    frames: Optional[str] = None
    out: Optional[Path] = None
    csv: Optional[Path] = None
    split: str = "test"
    datasets: list = field(default_factory=lambda: list(protocols.SCARED_DATASETS))
    keyframes: Optional[list] = None
    gt_depth: str = ""
    gt_depth_scale_mm: float = 0.01
    no_map: bool = False
    batch: BatchOptions = field(default_factory=BatchOptions)


# ------------------------------------------------------------------------------------------------
# sweeps
def parse_sweeps(specs: list[str]) -> list[list[str]]:
    """``KEY=V1,V2,...`` specs -> one list of overrides per combination (their product, in the
    order given); ``[[]]`` without sweeps."""
    axes = []
    keys = set()
    for spec in specs:
        key, sep, values = spec.partition("=")
        key = key.strip()
        items = [v.strip() for v in values.split(",")]
        if not sep or not key or not all(items):
            raise ConfigError(f"--sweep {spec}: expected KEY=V1,V2,... (e.g. solver.max_iters=5,10)")
        if key in keys:
            raise ConfigError(f"--sweep {spec}: {key} is swept twice")
        keys.add(key)
        axes.append([f"{key}={v}" for v in items])
    return [list(combo) for combo in itertools.product(*axes)]


def sweep_label(overrides: list[str]) -> str:
    return " ".join(overrides)


def sweep_folder(overrides: list[str]) -> str:
    """The run folder level of a swept combination (safe as a file name)."""
    return "_".join(re.sub(r"[^A-Za-z0-9._=+-]", "-", o) for o in overrides)


def method_config(base: SlamConfig, sweep: list[str], mode: str, cpus_per_task: int) -> SlamConfig:
    """The resolved config of one swept combination and mode: the base with the swept values and
    the mode, ``threads`` made explicit (the CPUs a task gets when the config leaves them at 0)."""
    try:
        config = with_overrides(base, [*sweep, f"tracking.mode={mode}"], source="--sweep")
    except ConfigError as err:
        raise ConfigError(f"--sweep {' '.join(sweep)}: {str(err).removeprefix('--sweep: ')}" if sweep
                          else str(err)) from None
    for section, key in PATH_KEYS:       # a worker elsewhere, or in another folder, finds them too
        part = getattr(config, section)
        if getattr(part, key):
            setattr(part, key, str(Path(getattr(part, key)).expanduser().resolve()))
    if config.threads == 0:
        config.threads = cpus_per_task
    return config


def task_config(method: SlamConfig, out_dir: Path) -> SlamConfig:
    """A task's config: its method's, with a rerun recording (when asked for) in its own folder."""
    if not method.logging.rerun:
        return method
    config = copy.deepcopy(method)
    config.logging.rerun = str(out_dir / "run.rrd")
    return config


# ------------------------------------------------------------------------------------------------
def entries_of(req: EvaluateRequest, out: Path) -> tuple[list[protocols.Entry], list[str]]:
    if req.protocol == "folder":
        return protocols.folder_entries(req.root, req.frames, exclude=(out,))
    if req.protocol == "stereomis":
        csv_path = req.csv or protocols.CONFIGS / "stereomis_protocol.csv"
        return protocols.stereomis_entries(req.root, Path(csv_path), req.split)
    return protocols.scared_entries(req.root, req.datasets, req.keyframes, req.frames), []


def estimated_cost(entry: protocols.Entry, config: SlamConfig, cache: dict) -> float:
    """Frames x pixels of a task (frame2model counted double; 0 when the sequence cannot be
    opened: it fails fast)."""
    key = (str(entry.path), entry.frames, config.data.width, config.data.height, config.data.layout)
    if key not in cache:
        from slam.io.datasets import open_dataset

        try:
            dataset = open_dataset(entry.path, config.data)
            try:
                n = len(dataset.select(entry.frames)) if entry.frames else len(dataset)
                w, h = dataset.camera.width, dataset.camera.height
            finally:
                dataset.close()
            cache[key] = float(n) * w * h
        except Exception:  # noqa: BLE001 - the worker reports it as the row's error
            cache[key] = 0.0
    return cache[key] * (2.0 if config.tracking.mode == "frame2model" else 1.0)


def build_tasks(req: EvaluateRequest, out: Path) -> tuple[list[RunTask], list[dict], list[str]]:
    """The tasks (one per swept combination, entry and mode), the error rows of entries that could
    not be found, and notes. Every config is resolved and checked here, before anything runs."""
    modes = req.modes or DEFAULT_MODES[req.protocol]
    bad = [m for m in modes if m not in protocols.MODES]
    if bad:
        raise ConfigError(f"--modes {' '.join(bad)}: expected {' or '.join(protocols.MODES)}")
    config_path = req.config or DEFAULT_CONFIGS[req.protocol]
    overrides = list(req.overrides)
    if req.protocol == "scared" and not req.no_map:
        overrides = ["logging.export_map=true", *overrides]
    base = load_config(config_path, overrides)
    sweeps = parse_sweeps(req.sweeps)
    if req.frames:
        from slam.io.datasets.selection import parse_frames

        try:
            parse_frames(req.frames, 10**6)
        except ConfigError as err:
            raise ConfigError(f"--frames {req.frames}: {str(err).removeprefix('frames: ')}") from None
    entries, notes = entries_of(req, out)
    map_spec = None
    if req.protocol == "scared" and not req.no_map:
        first = (req.frames or "").split(":")[0].strip() if req.frames and ":" in req.frames else ""
        if first not in ("", "0"):
            notes.append("map accuracy skipped: --frames does not start at the keyframe (frame 0).")
        else:
            map_spec = MapAccuracySpec(req.gt_depth, req.gt_depth_scale_mm)
    strict = req.protocol in ("stereomis", "scared")
    tasks, error_rows = [], []
    sizes: dict = {}
    for sweep in sweeps:
        label = sweep_label(sweep)
        level = out / "runs" / sweep_folder(sweep) if sweep else out / "runs"
        methods = {mode: method_config(base, sweep, mode, req.batch.cpus_per_task) for mode in modes}
        for entry in entries:
            for mode in modes:
                run_dir = level / entry.name / mode
                config = task_config(methods[mode], run_dir)
                if entry.error:
                    error_rows.append({"sweep": label, "sequence": entry.sequence, "selection": entry.frames or "",
                                       "scenario": entry.scenario, "group": entry.group, "mode": mode,
                                       "status": "error", "message": entry.error, "out": str(run_dir)})
                    continue
                task = RunTask(data=str(entry.path), out_dir=str(run_dir), config=config, frames=entry.frames,
                               sequence=entry.sequence, mode=mode, scenario=entry.scenario, group=entry.group,
                               sweep=label, bounds=entry.bounds, require_groundtruth=strict, map_accuracy=map_spec)
                task.cost = estimated_cost(entry, config, sizes)
                tasks.append(task)
    notes.append(f"config {config_path or '(defaults)'}" + (f", overrides {' '.join(overrides)}" if overrides else ""))
    return tasks, error_rows, notes


def row_of(task: RunTask, outcome: Optional[dict], resumed: bool) -> dict:
    """The table row of a task: what it was, how it ended, and its run's figures."""
    row = {"sweep": task.sweep, "sequence": task.sequence, "selection": task.frames or "", "scenario": task.scenario,
           "group": task.group, "mode": task.mode, "out": task.out_dir, "resumed": resumed,
           "status": "ok" if resumed else outcome.get("status", "error"),
           "message": "" if resumed else outcome.get("message", "")}
    if outcome is not None and outcome.get("seconds") is not None:
        row["seconds"] = outcome["seconds"]
    metrics = read_json(Path(task.out_dir) / METRICS)
    if metrics is None and row["status"] == "ok":
        row.update(status="error", message=f"{task.out_dir}: the run ended but its metrics.json is not here: OUT must "
                                           "be a folder every node mounts at the same path (docs/evaluation.md)")
    if metrics is not None and row["status"] != "error":
        row.update(frames=metrics.get("frames"), failed=len(metrics.get("failed_frames", [])),
                   flagged=len(metrics.get("flagged_frames", [])), fps=metrics.get("fps"))
        row.update({k: metrics[k] for k in METRIC_KEYS if k in metrics})
        if row["status"] == "ok" and not is_result(metrics.get("status", "ok")):    # too many frames failed
            row.update(status="not a result", message=metrics["status"])
        elif row["status"] == "ok" and metrics.get("status", "ok") != "ok":       # untrusted: scored, marked
            row.update(message=metrics["status"])
        if task.require_groundtruth and row["status"] == "ok" and "ate_rmse_mm" not in metrics:
            row.update(status="error", message="too few frames with ground truth to evaluate")
    accuracy = read_json(Path(task.out_dir) / MAP_ACCURACY)
    if accuracy:
        row.update(accuracy)
    return row


def describe(task: RunTask, outcome: dict) -> str:
    """The line printed when a task ends."""
    head = f"{task.label}:"
    status = outcome.get("status")
    if status == "error":
        return f"{head} ERROR {outcome.get('message', '')}"
    row = row_of(task, outcome, resumed=False)
    text = (f"{head} ATE {fmt(row.get('ate_rmse_mm'))} mm, RPE {fmt(row.get('rpe_trans_mm'))} mm "
            f"{fmt(row.get('rpe_rot_deg'), 4)} deg ({row.get('frames', 0)} frames, {row.get('failed', 0)} failed, "
            f"{fmt(outcome.get('seconds'), 1)} s)")
    if row.get("map_median_mm") is not None:
        text += f", map median {fmt(row['map_median_mm'])} mm"
    return text + (f" {status.upper()}: {outcome.get('message', '')}" if status != "ok" else "")


def evaluate(req: EvaluateRequest) -> int:
    """Run the evaluation; write its tables. Exit code: 130 when interrupted, 1 when a task
    failed, timed out or its run is not a result (the tables hold the good rows), else 0."""
    if req.protocol not in protocols.PROTOCOLS:
        raise ConfigError(f"--protocol {req.protocol}: expected one of {', '.join(protocols.PROTOCOLS)}")
    req.batch.validate()
    req.root = Path(req.root).expanduser().resolve()
    out = (Path(req.out) if req.out else Path("runs") / f"evaluate_{req.root.name}").expanduser().resolve()
    tasks, error_rows, notes = build_tasks(req, out)
    done = set() if req.batch.force else {i for i, t in enumerate(tasks) if t.is_done()}
    order = sorted((i for i in range(len(tasks)) if i not in done), key=lambda i: -tasks[i].cost)
    kind = req.batch.kind() if order else "none"
    print(f"{len(tasks) + len(error_rows)} task(s): {len(done)} done before, {len(order)} to run"
          + (f" on {kind} ({req.batch.address or 'this machine'})" if order else "")
          + (f", {len(error_rows)} not found" if error_rows else "") + f"; results in {out}", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    outcomes, interrupted, info = run_batch([tasks[i] for i in order], req.batch,
                                            lambda k, outcome: describe(tasks[order[k]], outcome))
    by_task = {order[k]: outcome for k, outcome in outcomes.items()}
    rows = list(error_rows)
    not_run = []
    for i, task in enumerate(tasks):
        if i in done:
            rows.append(row_of(task, None, resumed=True))
        elif i in by_task:
            rows.append(row_of(task, by_task[i], resumed=False))
        else:
            not_run.append(task.label)
    rows.sort(key=lambda r: (r["sweep"], r["sequence"], r["selection"], r["mode"]))
    if interrupted:
        notes.append(f"INTERRUPTED: {len(not_run)} task(s) did not run; the tables hold the runs finished so far "
                     "(run the same command again to run the rest).")
    return write_report(req, out, rows, notes, info, interrupted, not_run, len(done))


def write_report(req: EvaluateRequest, out: Path, rows: list[dict], notes: list[str], info: dict,
                 interrupted: bool, not_run: list[str], resumed: int) -> int:
    if not rows:
        print("no runs finished; nothing to report", file=sys.stderr)
        return status_of(rows, interrupted)
    sections, figures = REPORTS[req.protocol](rows)
    report = "\n\n".join([*sections, *([("\n".join(f"- {n}" for n in notes))] if notes else [])])
    print()
    print(report)
    write_text_atomically(out / "evaluation.md", report + "\n")
    with replaced_atomically(out / "evaluation.csv") as tmp:
        write_csv(rows, tmp)
    with replaced_atomically(out / "evaluation.png") as tmp:
        plot(rows, scenarios_of(rows) or [""], tmp, f"slam evaluate {Path(req.root).name}")
    summary = {"protocol": req.protocol, "root": str(req.root), "out": str(out), "config": req.config,
               "overrides": req.overrides, "modes": req.modes or DEFAULT_MODES[req.protocol], "sweep": req.sweeps,
               "frames": req.frames, "batch": {**info, "cpus_per_task": req.batch.cpus_per_task,
                                               "timeout_s": req.batch.timeout_s},
               "tasks": len(rows) + len(not_run), "resumed": resumed,
               "errors": sum(r["status"] != "ok" for r in rows),
               "not_run": not_run, "interrupted": interrupted, "notes": notes, "tables": figures, "rows": rows}
    write_text_atomically(out / "summary.json", json.dumps(summary, indent=2, default=str))
    print(f"\nwrote {out / 'evaluation.md'}, evaluation.csv, evaluation.png and summary.json")
    return status_of(rows, interrupted)


def status_of(rows: list[dict], interrupted: bool) -> int:
    """``slam evaluate``'s exit code (see :func:`evaluate`)."""
    if interrupted:
        return 130
    bad = [r for r in rows if r["status"] != "ok"]
    if bad:
        print(f"{len(bad)} of {len(rows)} task(s) did not give a result: "
              + "; ".join(f"{r['sequence']} {r['mode']}: {r['status']}" for r in bad[:5])
              + (" ..." if len(bad) > 5 else ""), file=sys.stderr)
    return 1 if bad else 0
