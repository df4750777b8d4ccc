"""StereoMIS evaluation protocol of Hayoz et al. 2023 (paper Tables 1 and 2) for our pipeline.

    .venv/bin/python tools/evaluate_stereomis.py STEREOMIS_ROOT [--csv configs/stereomis_protocol.csv]
        [--out runs/eval_stereomis] [--modes frame2frame [frame2model]] [--config FILE]
        [--set key=value ...] [--align auto|se3|first] [--split test]
    .venv/bin/python tools/evaluate_stereomis.py --synthetic DIR [--synthetic-frames 24]
        [--synthetic-size 320x256] [...]       # synthetic stand-in, written into DIR and evaluated

What it reads
-------------
``STEREOMIS_ROOT`` holds one folder per sequence (``P2_0``, ``P2_1``, ``H2_0`` ...) in either
StereoMIS layout ``slam.datasets.open_dataset`` reads (docs/inputs.md):
pre-processed (``video_frames/%06dl.png`` + ``%06dr.png``, ``StereoCalibration.ini``,
``groundtruth.txt``, optional ``masks/``) or raw (one ``*.mp4`` holding the left view over the
right view, ``StereoCalibration.ini``, ``groundtruth.txt``). Ground truth is required.

The CSV (``--csv``; default ``configs/stereomis_protocol.csv``, a TEMPLATE: replace it with the
official clip list of the paper's supplementary material) has the columns
``sequence,start,end,scenario,split``; ``#`` lines are comments:

* ``sequence``: folder name under the root;
* ``start``, ``end``: 0-based frame positions in the sequence's sorted frame list, ``end``
  exclusive (``slam run --frames start:end``); empty = from the first / to the last frame
  (``full`` rows usually leave both empty);
* ``scenario``: ``breathing`` | ``scanning`` | ``deforming`` (150-frame clips, Table 1) or
  ``full`` (a whole test sequence, Table 2);
* ``split``: ``test`` (rows of another split than ``--split`` are skipped).

A structurally bad CSV (missing column, non-integer frame, unknown scenario, ``end <= start``)
stops before any run with a one-line error naming the line. A row whose data fails (missing
sequence, range beyond the sequence, no ground truth, a failure inside the pipeline) becomes an
error row in the tables; the evaluation goes on.

What it computes
----------------
Every row is run with our pipeline (``slam.runner.run_from_config``) in each ``--modes`` mode
(default ``frame2frame``, as the paper on StereoMIS; ``frame2model`` can be added), with the config
``--config`` (default ``configs/stereomis_frame2frame.yaml``: 640x512, the paper's half
resolution) and ``--set`` overrides, and evaluated with ``slam.evaluation.evaluate``: ATE-RMSE (mm,
after a rigid SE(3) alignment; ``--align auto`` = first-pose alignment on static-camera clips, as
``slam run``), RPE-trans (mm) and RPE-rot (deg) between consecutive frames (mean and std).

* Table 1 style (scenario clips): ATE-RMSE mean ± std per scenario, micro average (over clips)
  and macro average (over the scenario means), one row per mode.
* Table 2 style (``full`` rows): per sequence ATE-RMSE, RPE-trans and RPE-rot (mean ± std), the
  average over sequences, per-subject means (subject = the name before ``_``: H2, P2, ...) and
  their macro average (the paper's Table 2 columns).
* A listing of every run (with its error message where it failed).

Outputs in ``--out``: ``stereomis_eval.md`` (the tables, also printed), ``stereomis_eval.json``
(every row and the aggregates), ``runs/<sequence>_<start>-<end>_<scenario>/<mode>/`` (the usual
``slam run`` files: ``trajectory.txt``, ``metrics.json``, ...).

``--synthetic DIR`` writes a stand-in with ``slam.synth.generate`` (StereoMIS pre-processed layout):
``DIR/P2_0`` (scanning), ``DIR/P2_1`` (breathing), ``DIR/P3_0`` (deforming), and
``DIR/protocol.csv`` (each sequence split into two scenario clips + one ``full`` row), and runs the
protocol on it at native size (``data.width=0``, ``data.height=0`` before your ``--set``). Results go
to ``DIR/results`` unless ``--out`` is given. Already generated sequences are reused.
"""
from __future__ import annotations

import argparse
import copy
import csv
import io
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # running from a checkout without an installed package
    sys.path.insert(0, str(REPO))

from slam.errors import ConfigError, DataError, SlamError  # noqa: E402

DEFAULT_CSV = REPO / "configs" / "stereomis_protocol.csv"
DEFAULT_CONFIG = REPO / "configs" / "stereomis_frame2frame.yaml"
MODES = ("frame2frame", "frame2model")
CLIP_SCENARIOS = ("breathing", "scanning", "deforming")
SCENARIOS = (*CLIP_SCENARIOS, "full")
COLUMNS = ("sequence", "start", "end", "scenario", "split")
METRICS = ("ate_rmse_mm", "rpe_trans_mm", "rpe_trans_std_mm", "rpe_rot_deg", "rpe_rot_std_deg")
# synthetic stand-in: (folder, generator scenario, seed); seeds disjoint from training (1000+),
# the baseline comparison (7001+) and the scenario benchmark (9001+)
SYNTHETIC_SEQUENCES = (("P2_0", "scanning", 8201), ("P2_1", "breathing", 8202), ("P3_0", "deforming", 8203))


# ------------------------------------------------------------------------------------------------
# shared with tools/evaluate_scared.py
class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line (no usage dump, no traceback)."""

    def error(self, message: str):  # noqa: D401 - argparse API
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    if not isinstance(err, SlamError):
        text = f"{type(err).__name__}: {text}"
    return text[:300]


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--synthetic-size {text}: expected WIDTHxHEIGHT, e.g. 320x256") from None
    if w < 32 or h < 32:
        raise ConfigError(f"--synthetic-size {text}: at least 32x32")
    return w, h


def load_mode_configs(config_path, overrides: list[str], modes: list[str]) -> dict:
    """One resolved ``SlamConfig`` per mode (``tracking.mode`` set last); config errors surface here,
    before any run."""
    from slam.config import load_config

    if config_path and not Path(config_path).is_file():
        raise ConfigError(f"{config_path}: config file not found")
    return {mode: load_config(config_path, [*overrides, f"tracking.mode={mode}"]) for mode in modes}


def run_one(data: Path, config, out_dir: Path, start: int | None = None, end: int | None = None,
            align: str = "auto") -> dict:
    """Run our pipeline on frames ``start:end`` of ``data`` and evaluate it against the ground truth.

    Returns a row: ``status`` (``ok`` | ``error`` | ``interrupted``), ``message`` (one line, errors),
    ``frames``, ``failed``, the metrics of ``slam.evaluation.evaluate`` (mm, deg), ``alignment``,
    ``fps``, ``seconds``, ``out`` and the run's ``result`` (``RunResult``, not serialised).
    """
    from slam.datasets import open_dataset
    from slam.evaluation import evaluate
    from slam.runner import run_from_config

    t0 = time.perf_counter()
    row: dict = {"status": "ok", "out": str(out_dir)}
    try:
        dataset = open_dataset(data, config.data)
        try:
            n = len(dataset)
            s = 0 if start is None else int(start)
            e = n if end is None else int(end)
            if s >= n:
                raise DataError(f"{data}: start frame {s} is beyond its {n} frames")
            if e > n:
                raise DataError(f"{data}: frames {s}:{e} end beyond its {n} frames")
            if e - s < 2:
                raise DataError(f"{data}: frames {s}:{e} select fewer than 2 frames")
            gt = dataset.select(f"{s}:{e}").gt_poses
            if gt is None:
                raise DataError(f"{data}: no ground-truth poses")
        finally:
            dataset.close()
        result = run_from_config(data, config, out_dir, f"{s}:{e}", print_summary=False)
        est = np.stack([r.pose for r in result.records]) if result.records else np.zeros((0, 4, 4))
        row.update(frames=len(result.records), failed=len(result.metrics.get("failed_frames", [])),
                   fps=float(result.metrics.get("fps", 0.0)), result=result)
        if result.interrupted:
            row.update(status="interrupted", message=f"interrupted after {len(est)} of {e - s} frames")
        if len(est) >= 2:
            metrics = evaluate(gt[: len(est)], est, align)
            row.update({k: float(metrics[k]) for k in METRICS}, alignment=metrics["alignment"])
            if not all(math.isfinite(row[k]) for k in METRICS):
                raise DataError("non-finite metrics")
    except KeyboardInterrupt:  # outside the pipeline's own handling (e.g. while opening the data)
        row.update(status="interrupted", message="interrupted")
    except Exception as err:  # noqa: BLE001 - one bad row must not stop the evaluation
        row.update(status="error", message=one_line(err))
    row["seconds"] = time.perf_counter() - t0
    return row


def mean_std(values) -> tuple[float | None, float | None]:
    vals = [float(v) for v in values if v is not None]
    if not vals:
        return None, None
    return float(np.mean(vals)), float(np.std(vals))


def fmt(v, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def fmt_ms(mean, std, digits: int = 2) -> str:
    return "-" if mean is None else f"{mean:.{digits}f} ± {std:.{digits}f}"


def progress_line(k: int, total: int, label: str, mode: str, row: dict) -> str:
    head = f"[{k}/{total}] {label} {mode}:"
    if row["status"] == "error":
        return f"{head} ERROR {row['message']}"
    text = (f"{head} ATE {fmt(row.get('ate_rmse_mm'), 3)} mm, RPE {fmt(row.get('rpe_trans_mm'), 3)} mm "
            f"{fmt(row.get('rpe_rot_deg'), 4)} deg ({row.get('frames', 0)} frames, {row.get('failed', 0)} failed, "
            f"{row['seconds']:.1f} s)")
    return text + (f" {row['message']}" if row["status"] == "interrupted" else "")


def public(row: dict) -> dict:
    """A row without the non-serialisable run result."""
    return {k: v for k, v in row.items() if k != "result"}


# ------------------------------------------------------------------------------------------------
# the protocol CSV
def read_protocol(path: Path) -> list[dict]:
    """Rows of the protocol CSV (see the module docstring); ConfigError naming ``file:line``."""
    if not path.is_file():
        raise ConfigError(f"{path}: protocol CSV not found")
    lines = path.read_text().splitlines()
    body = [(i + 1, line) for i, line in enumerate(lines) if line.strip() and not line.lstrip().startswith("#")]
    if not body:
        raise ConfigError(f"{path}: no header line ({','.join(COLUMNS)})")
    header_no, header = body[0]
    names = [c.strip().lower() for c in next(csv.reader([header]))]
    missing = [c for c in COLUMNS if c not in names]
    if missing:
        raise ConfigError(f"{path}:{header_no}: header lacks column(s) {', '.join(missing)} "
                          f"(expected {','.join(COLUMNS)})")
    rows = []
    for lineno, line in body[1:]:
        values = [v.strip() for v in next(csv.reader(io.StringIO(line)))]
        if len(values) != len(names):
            raise ConfigError(f"{path}:{lineno}: {len(values)} values, the header has {len(names)}")
        rec = dict(zip(names, values))
        where = f"{path}:{lineno}"
        if not rec["sequence"]:
            raise ConfigError(f"{where}: empty sequence name")
        bounds = {}
        for key in ("start", "end"):
            text = rec[key]
            if text == "":
                bounds[key] = None
                continue
            try:
                bounds[key] = int(text)
            except ValueError:
                raise ConfigError(f"{where}: {key} '{text}' is not an integer frame number") from None
            if bounds[key] < 0:
                raise ConfigError(f"{where}: {key} {bounds[key]} is negative")
        if bounds["start"] is not None and bounds["end"] is not None and bounds["end"] <= bounds["start"]:
            raise ConfigError(f"{where}: end {bounds['end']} <= start {bounds['start']}")
        scenario = rec["scenario"].lower()
        if scenario not in SCENARIOS:
            raise ConfigError(f"{where}: scenario '{rec['scenario']}' is not one of {', '.join(SCENARIOS)}")
        rows.append({"sequence": rec["sequence"], "start": bounds["start"], "end": bounds["end"],
                     "scenario": scenario, "split": rec["split"].lower() or "test", "line": lineno})
    if not rows:
        raise ConfigError(f"{path}: no rows after the header")
    return rows


def range_text(rec: dict) -> str:
    """``start:end`` of a row (``all`` for a whole sequence)."""
    if rec["start"] is None and rec["end"] is None:
        return "all"
    return f"{'' if rec['start'] is None else rec['start']}:{'' if rec['end'] is None else rec['end']}"


def row_label(rec: dict) -> str:
    return f"{rec['sequence']} {range_text(rec)} {rec['scenario']}"


def run_dir_name(rec: dict) -> str:
    s = "start" if rec["start"] is None else str(rec["start"])
    e = "end" if rec["end"] is None else str(rec["end"])
    return f"{rec['sequence']}_{s}-{e}_{rec['scenario']}"


# ------------------------------------------------------------------------------------------------
# synthetic stand-in
def make_synthetic(folder: Path, frames: int, size: tuple[int, int]) -> Path:
    """Generate (or reuse) the stand-in sequences in ``folder`` and write ``folder/protocol.csv``."""
    from slam.synth import generate

    if frames < 4:
        raise ConfigError(f"--synthetic-frames {frames}: need at least 4 (two clips of 2 frames)")
    folder.mkdir(parents=True, exist_ok=True)
    half = frames // 2
    lines = ["# Synthetic stand-in for the StereoMIS protocol (tools/evaluate_stereomis.py --synthetic).",
             "# Each sequence holds one generator scenario; two clips per sequence + the full sequence.",
             ",".join(COLUMNS)]
    for name, scenario, seed in SYNTHETIC_SEQUENCES:
        path = folder / name
        meta = {}
        if (path / "synth.json").is_file():
            try:
                meta = json.loads((path / "synth.json").read_text())
            except ValueError:
                meta = {}
        wanted = {"scenario": scenario, "seed": seed, "frames": frames, "size": list(size)}
        if any(meta.get(k) != v for k, v in wanted.items()) or not (path / "groundtruth.txt").is_file():
            print(f"generating synthetic {name} ({scenario}, {frames} frames, {size[0]}x{size[1]}) ...", flush=True)
            generate(path, scenario, frames=frames, size=size, seed=seed)
        lines += [f"{name},0,{half},{scenario},test", f"{name},{half},{frames},{scenario},test", f"{name},,,full,test"]
    (folder / "protocol.csv").write_text("\n".join(lines) + "\n")
    return folder / "protocol.csv"


# ------------------------------------------------------------------------------------------------
# tables
def table1(rows: list[dict], modes: list[str]) -> dict:
    """Per mode: ATE mean/std/n per clip scenario, micro (over clips) and macro (over scenario means)."""
    out = {}
    for mode in modes:
        mine = [r for r in rows if r["mode"] == mode and r["scenario"] in CLIP_SCENARIOS]
        agg: dict = {}
        means = []
        for sc in CLIP_SCENARIOS:
            vals = [r["ate_rmse_mm"] for r in mine if r["scenario"] == sc and r["status"] == "ok"]
            m, s = mean_std(vals)
            agg[sc] = {"mean": m, "std": s, "n": len(vals),
                       "errors": sum(r["scenario"] == sc and r["status"] != "ok" for r in mine)}
            if m is not None:
                means.append(m)
        all_ok = [r["ate_rmse_mm"] for r in mine if r["status"] == "ok"]
        m, s = mean_std(all_ok)
        agg["micro"] = {"mean": m, "std": s, "n": len(all_ok)}
        m, s = mean_std(means)
        agg["macro"] = {"mean": m, "std": s, "n": len(means)}
        out[mode] = agg
    return out


def subject_of(sequence: str) -> str:
    return sequence.split("_")[0]


def table2(rows: list[dict], modes: list[str]) -> dict:
    """Per mode: the full-sequence rows, their average, per-subject means and the macro average."""
    out = {}
    for mode in modes:
        mine = [r for r in rows if r["mode"] == mode and r["scenario"] == "full"]
        ok = [r for r in mine if r["status"] == "ok"]
        avg = {}
        for key in ("ate_rmse_mm", "rpe_trans_mm", "rpe_rot_deg"):
            m, s = mean_std(r[key] for r in ok)
            avg[key] = {"mean": m, "std": s}
        avg["n"] = len(ok)
        subjects = {}
        for subj in sorted({subject_of(r["sequence"]) for r in ok}):
            sub = [r for r in ok if subject_of(r["sequence"]) == subj]
            subjects[subj] = {key: mean_std(r[key] for r in sub)[0] for key in ("ate_rmse_mm", "rpe_trans_mm", "rpe_rot_deg")}
            subjects[subj]["n"] = len(sub)
        macro = {}
        for key in ("ate_rmse_mm", "rpe_trans_mm", "rpe_rot_deg"):
            m, s = mean_std(v[key] for v in subjects.values())
            macro[key] = {"mean": m, "std": s}
        macro["n"] = len(subjects)
        out[mode] = {"sequences": [public(r) for r in mine], "average": avg, "subjects": subjects, "macro": macro,
                     "errors": len(mine) - len(ok)}
    return out


def cell(agg: dict) -> str:
    text = fmt_ms(agg["mean"], agg["std"])
    if agg.get("errors"):
        text += f" ({agg['errors']} failed)"
    return text


def format_report(rows: list[dict], modes: list[str], t1: dict, t2: dict, notes: list[str]) -> str:
    lines = []
    clips = [r for r in rows if r["scenario"] in CLIP_SCENARIOS]
    if clips:
        first = modes[0]
        counts = [sum(r["scenario"] == sc and r["mode"] == first for r in clips) for sc in CLIP_SCENARIOS]
        lines += ["### Table 1 style: ATE-RMSE (mean ± std, mm) per surgical scenario", "",
                  "| method | breathing | scanning | deforming | micro avg. | macro avg. |",
                  "|---|---|---|---|---|---|",
                  "| # clips | " + " | ".join(map(str, counts)) + " | | |"]
        for mode in modes:
            a = t1[mode]
            lines.append(f"| ours ({mode}) | " + " | ".join(cell(a[sc]) for sc in CLIP_SCENARIOS)
                         + f" | {cell(a['micro'])} | {cell(a['macro'])} |")
        lines.append("")
    fulls = [r for r in rows if r["scenario"] == "full"]
    if fulls:
        lines += ["### Table 2 style: full test sequences", ""]
        for mode in modes:
            t = t2[mode]
            lines += [f"**ours ({mode})**", "",
                      "| sequence | frames | failed frames | ATE-RMSE mm | RPE-trans mm | RPE-rot deg |",
                      "|---|---|---|---|---|---|"]
            for r in t["sequences"]:
                if r["status"] == "error":
                    lines.append(f"| {r['sequence']} | error: {r['message']} | | | | |")
                    continue
                lines.append(f"| {r['sequence']} | {r.get('frames', 0)} | {r.get('failed', 0)} | "
                             f"{fmt(r.get('ate_rmse_mm'))} | {fmt_ms(r.get('rpe_trans_mm'), r.get('rpe_trans_std_mm'))} | "
                             f"{fmt_ms(r.get('rpe_rot_deg'), r.get('rpe_rot_std_deg'), 3)} |")
            a = t["average"]
            lines.append(f"| **average ({a['n']} sequences)** | | | {fmt_ms(a['ate_rmse_mm']['mean'], a['ate_rmse_mm']['std'])} | "
                         f"{fmt_ms(a['rpe_trans_mm']['mean'], a['rpe_trans_mm']['std'])} | "
                         f"{fmt_ms(a['rpe_rot_deg']['mean'], a['rpe_rot_deg']['std'], 3)} |")
            for subj, v in t["subjects"].items():
                lines.append(f"| {subj} (subject mean, {v['n']}) | | | {fmt(v['ate_rmse_mm'])} | {fmt(v['rpe_trans_mm'])} | "
                             f"{fmt(v['rpe_rot_deg'], 3)} |")
            mac = t["macro"]
            lines.append(f"| **macro avg. ({mac['n']} subjects)** | | | "
                         f"{fmt_ms(mac['ate_rmse_mm']['mean'], mac['ate_rmse_mm']['std'])} | "
                         f"{fmt_ms(mac['rpe_trans_mm']['mean'], mac['rpe_trans_mm']['std'])} | "
                         f"{fmt_ms(mac['rpe_rot_deg']['mean'], mac['rpe_rot_deg']['std'], 3)} |")
            lines.append("")
    lines += ["### Every run", "",
              "| sequence | frames | scenario | mode | ATE-RMSE mm | RPE-trans mm | RPE-rot deg | failed | alignment | note |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        rng = range_text(r)
        if r["status"] == "error":
            lines.append(f"| {r['sequence']} | {rng} | {r['scenario']} | {r['mode']} | error | | | | | {r['message']} |")
            continue
        lines.append(f"| {r['sequence']} | {rng} | {r['scenario']} | {r['mode']} | {fmt(r.get('ate_rmse_mm'), 3)} | "
                     f"{fmt(r.get('rpe_trans_mm'), 3)} | {fmt(r.get('rpe_rot_deg'), 4)} | "
                     f"{r.get('failed', 0)}/{r.get('frames', 0)} | {r.get('alignment', '-')} | {r.get('message', '')} |")
    if notes:
        lines += ["", *[f"- {n}" for n in notes]]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    ap = OneLineParser(prog="evaluate_stereomis.py", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", nargs="?", help="StereoMIS root folder (one sub-folder per sequence)")
    ap.add_argument("--csv", help=f"protocol CSV (default {DEFAULT_CSV.relative_to(REPO)}; with --synthetic "
                                  "the generated DIR/protocol.csv)")
    ap.add_argument("--out", help="output folder (default runs/eval_stereomis; with --synthetic DIR/results)")
    ap.add_argument("--modes", nargs="+", default=["frame2frame"], choices=MODES, help="tracking modes to run")
    ap.add_argument("--config", default=str(DEFAULT_CONFIG), help="YAML config (default %(default)s)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override (repeatable)")
    ap.add_argument("--align", default="auto", choices=["auto", "se3", "first"],
                    help="trajectory alignment before ATE (auto: first-pose on static-camera clips, else SE(3))")
    ap.add_argument("--split", default="test", help="evaluate the CSV rows of this split (default test)")
    ap.add_argument("--synthetic", metavar="DIR", help="generate a synthetic stand-in in DIR and evaluate it")
    ap.add_argument("--synthetic-frames", type=int, default=24, help="frames per stand-in sequence (default 24)")
    ap.add_argument("--synthetic-size", default="320x256", help="stand-in image size WxH (default 320x256)")
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    try:
        return evaluate_protocol(args)
    except (SlamError, ValueError, OSError) as err:
        print(f"{ap.prog}: error: {one_line(err) if not isinstance(err, SlamError) else err}", file=sys.stderr)
        return 2


def evaluate_protocol(args) -> int:
    overrides = list(args.set)
    notes = []
    if args.synthetic:
        if args.root:
            raise ConfigError("give STEREOMIS_ROOT or --synthetic DIR, not both")
        folder = Path(args.synthetic)
        csv_path = make_synthetic(folder, args.synthetic_frames, parse_size(args.synthetic_size))
        root = folder
        csv_path = Path(args.csv) if args.csv else csv_path
        out = Path(args.out) if args.out else folder / "results"
        overrides = ["data.width=0", "data.height=0", *overrides]
        notes.append("SYNTHETIC stand-in (slam.synth), not StereoMIS: native size (data.width=data.height=0).")
    else:
        if not args.root:
            raise ConfigError("give the StereoMIS root folder (or --synthetic DIR)")
        root = Path(args.root)
        if not root.is_dir():
            raise DataError(f"{root}: no such folder (the StereoMIS root)")
        csv_path = Path(args.csv) if args.csv else DEFAULT_CSV
        out = Path(args.out) if args.out else Path("runs") / "eval_stereomis"
    if not sys.stderr.isatty():
        overrides = ["logging.progress=false", *overrides]
    configs = load_mode_configs(args.config, overrides, args.modes)
    protocol = read_protocol(csv_path)
    todo = [r for r in protocol if r["split"] == args.split.lower()]
    skipped = len(protocol) - len(todo)
    if not todo:
        raise ConfigError(f"{csv_path}: no rows of split '{args.split}'")
    if csv_path.resolve() == DEFAULT_CSV.resolve():
        notes.append(f"{DEFAULT_CSV.relative_to(REPO)} is a TEMPLATE, not the paper's clip list: "
                     "replace it with the official split (paper, supplementary material).")
    notes.append(f"config {args.config}" + (f", overrides {' '.join(overrides)}" if overrides else "")
                 + f"; ATE alignment: {args.align}.")
    if skipped:
        notes.append(f"{skipped} CSV row(s) of other splits skipped.")
    out.mkdir(parents=True, exist_ok=True)

    rows: list[dict] = []
    total = len(todo) * len(args.modes)
    k = 0
    interrupted = False
    print(f"{total} run(s): {len(todo)} CSV row(s) x {len(args.modes)} mode(s); results in {out}", flush=True)
    for rec in todo:
        for mode in args.modes:
            k += 1
            row = run_one(root / rec["sequence"], copy.deepcopy(configs[mode]), out / "runs" / run_dir_name(rec) / mode,
                          rec["start"], rec["end"], args.align)
            row.update({key: rec[key] for key in ("sequence", "start", "end", "scenario", "split", "line")}, mode=mode)
            print(progress_line(k, total, row_label(rec), mode, row), flush=True)
            rows.append(public(row))
            if row["status"] == "interrupted":
                interrupted = True
                break
        if interrupted:
            notes.append("INTERRUPTED: the tables hold the runs finished so far.")
            break

    t1, t2 = table1(rows, args.modes), table2(rows, args.modes)
    report = format_report(rows, args.modes, t1, t2, notes)
    print()
    print(report)
    (out / "stereomis_eval.md").write_text(report + "\n")
    payload = {"protocol": "StereoMIS, Hayoz et al. 2023 Tables 1-2", "root": str(root), "csv": str(csv_path),
               "config": args.config, "overrides": overrides, "modes": args.modes, "align": args.align,
               "split": args.split, "notes": notes, "rows": rows, "table1": t1, "table2": t2,
               "errors": sum(r["status"] == "error" for r in rows), "interrupted": interrupted}
    (out / "stereomis_eval.json").write_text(json.dumps(payload, indent=2, default=str))
    print(f"\nwrote {out / 'stereomis_eval.md'} and {out / 'stereomis_eval.json'}")
    return 130 if interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
