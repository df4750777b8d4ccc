"""The accuracy gate: this working tree against a base commit, on real video and the generator, with
each case's own run-to-run spread. One command, one table, one verdict.

    .venv/bin/python tools/check_accuracy.py --base COMMIT [--new COMMIT] [--quick] [--runs 3]
        [--real DIR] [--cases GLOB ...] [--workers 2] [--out runs/check_accuracy] [--list]

Both sides run ``slam run`` (``threads=1``) in a checkout of their own (the base, and ``--new
COMMIT`` in place of the working tree, in git worktrees under ``OUT/trees``), on data the working
tree makes once (``OUT/data``). Each case runs ``K``
times (``--runs``) on copies of its sequence whose world frame is moved rigidly
(:mod:`benchmarks.accuracy_panel`): the spread of the ``K`` results is what rounding alone does.
Per case and side, on the poses known at the time (``trajectory_online.txt`` where a run corrected
its poses afterwards, whose ATE is given besides): the ATE (mm, SE(3)-aligned, as ``slam run``),
the map's error against the
reference points (the real sequence in frame2model: each point's distance to the nearest map
point, median and the share within 1 mm), silent frames along the chain of trusted poses (a frame
neither flagged nor failed whose position errs by more than 1 mm against the last such frame
before it, :mod:`slam.evaluation.chain`), the largest error of a trusted frame's motion from the
frame before it, flagged and failed frames, fps (under the gate's own load: compare sides, not
runs of another time).

A case regressed where ``median_new - median_base > max(range_base, range_new, floor)`` for its
ATE or its map's median error (floor: 1 % of the base's median or 0.005 mm, whichever is larger)
or its count of silent frames (floor 0); an improvement by as much is listed, not failed. The
verdict fails too where a case's ``K`` runs wrote the same trajectory (the perturbation did not
reach them) or where a run of the new side did not finish. Results are cached by the content of
the code a run depends on (``slam/``, ``vo/``, ``mapping/``, ``configs/`` of a commit or of the
working tree: a run of the working tree is reused once it is committed, and a commit that changes
only docs, tests or tools reuses the runs of the one before), so a second gate against the same
base runs only this side, and an interrupted gate resumes.
"""
from __future__ import annotations

import argparse
import csv
import fnmatch
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.accuracy_panel import (REAL_POINTS, REAL_TRAJECTORY, ROOT, Case, moved_copy, panel, real_folder,
                                       render, world_move)
from benchmarks.checkout import run_slam

#: the folders whose content a run's results depend on (the cache's key)
RUN_CODE = ("slam", "vo", "mapping", "configs")
#: a run's exit codes that mean it finished (3: a run that is not a result still wrote every pose)
FINISHED = (0, 3)
#: the gated figures: (key, label, floor of the spread as a function of the base's median)
GATED = (("ate_mm", "ATE", lambda m: max(0.01 * abs(m), 0.005)),
         ("map_median_mm", "map error", lambda m: max(0.01 * abs(m), 0.005)),
         ("silent_over", "silent frames", lambda m: 0.0))


# ------------------------------------------------------------------------------------------ trees
def git(*args: str, env: dict | None = None) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, check=True, capture_output=True, text=True,
                          env={**os.environ, **(env or {})}).stdout.strip()


def code_key(tree: str) -> str:
    """What a run's results depend on in the git tree ``tree`` (a commit or a tree hash): the
    hash of its code and configs (``RUN_CODE``), not of its docs, tests or tools, so that a commit
    that changes only those reuses the runs of the one before."""
    names = [git("rev-parse", f"{tree}:{folder}") for folder in RUN_CODE]
    return hashlib.sha1(" ".join(names).encode()).hexdigest()


def working_tree_key() -> str:
    """:func:`code_key` of the working tree's content (tracked and untracked files, ignored ones
    aside): equal to the commit's once that content is committed."""
    with tempfile.TemporaryDirectory() as tmp:
        index = Path(tmp) / "index"
        git_dir = Path(git("rev-parse", "--absolute-git-dir"))
        if (git_dir / "index").is_file():
            index.write_bytes((git_dir / "index").read_bytes())
        env = {"GIT_INDEX_FILE": str(index)}
        git("add", "-A", ".", env=env)
        return code_key(git("write-tree", env=env))


def checkout(commit: str, out: Path) -> tuple[Path, str]:
    """A worktree of ``commit`` under ``out/trees`` and its :func:`code_key`."""
    sha = git("rev-parse", "--verify", f"{commit}^{{commit}}")
    tree = out / "trees" / sha[:12]
    if not (tree / "slam").is_dir():
        git("worktree", "add", "--detach", "--force", str(tree), sha)
    return tree, code_key(sha)


def known_keys(tree: Path) -> set[str]:
    """The config keys (``section.key``) a checkout knows, from its ``configs/default.yaml``."""
    import yaml

    config = yaml.safe_load((tree / "configs" / "default.yaml").read_text()) or {}
    keys = set()
    for key, value in config.items():
        keys |= {f"{key}.{k}" for k in value} if isinstance(value, dict) else {key}
    return keys


def options_for(tree: Path, options: list[str]) -> tuple[list[str], list[str]]:
    """``options`` without the ``--set`` keys the checkout ``tree`` lacks, and those dropped."""
    keys, kept, dropped = known_keys(tree), [], []
    given = iter(options)
    for option in given:
        if option != "--set":
            kept.append(option)
            continue
        value = next(given)
        if value.split("=", 1)[0] in keys:
            kept += [option, value]
        else:
            dropped.append(value)
    return kept, dropped


# ------------------------------------------------------------------------------------------- runs
@dataclass
class Side:
    """One version under test: its checkout, its cache key and label."""

    label: str
    tree: Path
    key: str


@dataclass
class Job:
    side: Side
    case: Case
    k: int
    data: Path
    folder: Path          # OUT/cache/KEY/CASE/kK

    @property
    def run_dir(self) -> Path:
        return self.folder / "run"


def data_fingerprint(data: Path) -> str:
    """What identifies a sequence's content for the cache: its ground truth and generator record."""
    h = hashlib.sha1()
    for name in ("groundtruth.txt", "synth.json"):
        if (data / name).is_file():
            h.update((data / name).read_bytes())
    return h.hexdigest()[:16]


def job_args(job: Job) -> tuple[list[str], list[str]]:
    options = ["--mode", job.case.mode, "--set", "threads=1", *job.case.options]
    return options_for(job.side.tree, options)


def run_job(job: Job) -> dict:
    """``slam run`` of the job's side (unless its cache holds it); returns its ``done.json``."""
    options, dropped = job_args(job)
    stamp = {"args": options, "data": data_fingerprint(job.data)}
    done = job.folder / "done.json"
    if done.is_file():
        record = json.loads(done.read_text())
        if {k: record.get(k) for k in stamp} == stamp:
            return record
    job.folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    proc = run_slam(job.side.tree, "run", job.data, "--out", job.run_dir, "--overwrite", "--quiet", *options,
                    capture_output=True, text=True)
    record = {**stamp, "dropped": dropped, "exit": proc.returncode, "seconds": round(time.perf_counter() - t0, 1),
              "error": "" if proc.returncode in FINISHED else (proc.stderr.strip().splitlines() or [""])[-1]}
    done.write_text(json.dumps(record, indent=1))
    return record


# ---------------------------------------------------------------------------------------- figures
def read_flags(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``tracking.csv``'s flagged and failed columns (any version's)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return (np.array([r["flagged"] == "1" for r in rows], bool), np.array([r["failed"] == "1" for r in rows], bool))


def figures(run: Path, truth_file: Path, k: int, points_mm: np.ndarray | None) -> dict:
    """A finished run's figures against its (moved) ground truth; the map's against the reference
    points (``points_mm``, in the unmoved reference frame) where given."""
    from slam.evaluation.chain import silent_summary
    from slam.evaluation.map_error import read_points_mm, reference_point_errors
    from slam.evaluation.metrics import align, alignment_transform, associate, ate_rmse, default_max_diff
    from slam.io.tum import read_tum

    online = run / "trajectory_online.txt"
    stamps, poses = read_tum(online if online.is_file() else run / "trajectory.txt")
    gt_stamps, gt = read_tum(truth_file)
    flagged, failed = read_flags(run / "tracking.csv")
    gi, ei = associate(gt_stamps, stamps, default_max_diff(gt_stamps))
    truth, est = gt[gi], poses[ei]
    aligned, _ = align(truth, est, "auto")
    out = {"ate_mm": ate_rmse(truth, aligned), "frames": int(len(stamps)),
           "flagged": int(flagged.sum()), "failed": int(failed.sum()),
           **silent_summary(est, truth, flagged[ei], failed[ei])}
    if online.is_file():        # (the run corrected its poses afterwards: the result's ATE besides)
        _, final = read_tum(run / "trajectory.txt")
        corrected, _ = align(truth, final[ei], "auto")
        out["ate_corrected_mm"] = ate_rmse(truth, corrected)
        est, aligned = final[ei], corrected
    metrics = run / "metrics.json"
    out["fps"] = json.loads(metrics.read_text()).get("fps") if metrics.is_file() else None
    if points_mm is not None and (run / "map.ply").is_file():
        move = np.linalg.inv(world_move(k)) @ alignment_transform(est, aligned)    # run's world -> reference's
        cloud = read_points_mm(run / "map.ply")
        errors = reference_point_errors(points_mm, cloud @ move[:3, :3].T + move[:3, 3])
        out.update(map_median_mm=errors["median_mm"], map_within_1mm=errors["within"])
    return out


# ---------------------------------------------------------------------------------------- verdict
def spread(values: list[float]) -> float:
    return float(max(values) - min(values)) if values else 0.0


def judge(base: list[float], new: list[float], floor) -> tuple[str, float, float]:
    """``regressed``, ``improved`` or ``same``: the medians' difference against the larger of both
    sides' ranges and ``floor(median_base)``; with the difference and that bound."""
    mb, mn = float(np.median(base)), float(np.median(new))
    bound = max(spread(base), spread(new), floor(mb))
    diff = mn - mb
    return ("regressed" if diff > bound else "improved" if -diff > bound else "same"), diff, bound


def identical(runs: list[Path]) -> bool:
    """Whether ``K > 1`` runs wrote the same trajectory byte for byte (the perturbation did not
    reach them)."""
    texts = [(r / "trajectory.txt").read_bytes() for r in runs]
    return len(texts) > 1 and all(t == texts[0] for t in texts[1:])


@dataclass
class CaseResult:
    case: Case
    figures: dict = field(default_factory=dict)          # side label -> list of per-run figures
    problems: list = field(default_factory=list)         # the new side's runs that did not finish, identical runs
    notes: list = field(default_factory=list)            # the same of the base's (they do not fail the gate)
    judged: dict = field(default_factory=dict)           # key -> (verdict, diff, bound)
    dropped: list = field(default_factory=list)


def judge_case(result: CaseResult, base: str, new: str) -> None:
    for key, label, floor in GATED:
        b = [f[key] for f in result.figures.get(base, []) if f.get(key) is not None]
        n = [f[key] for f in result.figures.get(new, []) if f.get(key) is not None]
        if b and n:
            result.judged[key] = judge(b, n, floor)


def verdict(results: list[CaseResult]) -> str:
    """The verdict line: PASS, or each regression with its size and the spread it went beyond, and
    each problem."""
    lines = []
    for r in results:
        for key, label, _ in GATED:
            if key in r.judged and r.judged[key][0] == "regressed":
                _, diff, bound = r.judged[key]
                lines.append(f"{r.case.name} {label} +{diff:.4g} beyond {bound:.4g}")
        lines += [f"{r.case.name}: {p}" for p in r.problems]
    better = [f"{r.case.name} {label}" for r in results for key, label, _ in GATED
              if r.judged.get(key, ("",))[0] == "improved"]
    tail = f" (improved: {', '.join(better)})" if better else ""
    return ("FAIL: " + "; ".join(lines) + tail) if lines else f"PASS: {len(results)} cases{tail}"


# ------------------------------------------------------------------------------------------ table
def _cell(values: list, spec: str = ".3f") -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "-"
    med = format(float(np.median(values)), spec)
    low, high = format(min(values), spec), format(max(values), spec)
    return med if low == high else f"{med} [{low}-{high}]"


def table(results: list[CaseResult], base: str, new: str) -> str:
    cols = ["case", f"ATE mm {base}", f"ATE mm {new}", "change", "ATE corrected mm", f"map mm {base}", f"map mm {new}",
            "silent >1 mm", "largest silent mm", "largest unflagged step mm", "flagged", "failed", "fps", "verdict"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in results:
        fb, fn = r.figures.get(base, []), r.figures.get(new, [])

        def both(key, spec=".3f"):
            return f"{_cell([f.get(key) for f in fb], spec)} / {_cell([f.get(key) for f in fn], spec)}"

        def mapcell(fs):
            if not any(f.get("map_median_mm") is not None for f in fs):
                return "-"
            share = np.median([f["map_within_1mm"] for f in fs if f.get("map_within_1mm") is not None])
            return f"{_cell([f.get('map_median_mm') for f in fs])} ({100 * share:.0f} % < 1 mm)"

        ate = r.judged.get("ate_mm")
        change = f"{100 * ate[1] / np.median([f['ate_mm'] for f in fb]):+.1f} %" if ate and fb else "-"
        states = [r.judged[k][0] for k, _, _ in GATED if k in r.judged]
        word = ("**error**" if r.problems else "**regressed**" if "regressed" in states
                else "improved" if "improved" in states else "same")
        lines.append("| " + " | ".join([
            r.case.name, _cell([f.get("ate_mm") for f in fb]), _cell([f.get("ate_mm") for f in fn]), change,
            both("ate_corrected_mm") if any("ate_corrected_mm" in f for f in fb + fn) else "-", mapcell(fb), mapcell(fn), both("silent_over", ".0f"), both("silent_max_mm", ".2f"),
            both("unflagged_step_max_mm", ".2f"), both("flagged", ".0f"), both("failed", ".0f"),
            both("fps", ".2f"), word]) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------- main
def run_all(jobs: list[Job], workers: int) -> dict[Path, dict]:
    """Every job's ``done.json`` record by its folder, ``workers`` runs at once."""
    records = {}
    with ThreadPoolExecutor(max(1, workers)) as pool:
        futures = {pool.submit(run_job, job): job for job in jobs}
        for n, future in enumerate(as_completed(futures), 1):
            job = futures[future]
            records[job.folder] = record = future.result()
            print(f"[{n}/{len(jobs)}] {job.side.label} {job.case.name} k{job.k}: exit {record['exit']}, "
                  f"{record['seconds']} s", file=sys.stderr, flush=True)
    return records


def collect(result: CaseResult, label: str, jobs: list[Job], records: dict, points: np.ndarray | None,
            fails: bool) -> None:
    """One side's runs of a case into ``result``: their figures, and the runs that did not finish
    and runs that all wrote the same trajectory, as problems where the side ``fails`` the gate
    (the new one), else as notes. A run that stopped with an error after writing every row (an
    older commit's failing metrics) is measured all the same."""
    said = result.problems if fails else result.notes
    finished = []
    for job in jobs:
        record = records[job.folder]
        result.dropped = sorted(set(result.dropped) | set(record.get("dropped", [])))
        if record["exit"] not in FINISHED:
            said.append(f"{label} run k{job.k} exit {record['exit']}: {record['error']}")
        try:
            figures_k = figures(job.run_dir, job.data / "groundtruth.txt", job.k,
                                points if job.case.map_error else None)
        except Exception as err:       # (what the run left cannot be read: said, not measured)
            said.append(f"{label} run k{job.k} not measured: {err}")
            continue
        result.figures.setdefault(label, []).append(figures_k)
        finished.append(job.run_dir)
    if identical(finished):
        said.append(f"{label}: its {len(finished)} runs wrote the same trajectory "
                    "(the moved world frame did not reach them)")


def select(cases: list[Case], quick: bool, patterns: list[str] | None) -> list[Case]:
    chosen = [c for c in cases if c.quick or not quick]
    if patterns:
        chosen = [c for c in chosen if any(fnmatch.fnmatch(c.name, p) for p in patterns)]
    return chosen


def _render(job: tuple) -> Path:
    return render(*job)


def prepare(cases: list[Case], out: Path, real: Path | None, runs: int, workers: int) -> dict[tuple[str, int], Path]:
    """The moved copies of every sequence the cases track, by (sequence name, k); the synthetic
    ones rendered first, ``workers`` at once."""
    from benchmarks.runs import run_in_workers

    sequences = sorted({c.sequence for c in cases}, key=lambda s: s.name)
    synthetic = [s for s in sequences if not s.real]
    originals = dict(zip([s.name for s in synthetic],
                         run_in_workers(_render, [(s, out / "data" / s.name) for s in synthetic], workers)))
    copies = {}
    for seq in sequences:
        original = real if seq.real else originals[seq.name]
        truth = REAL_TRAJECTORY if seq.real else original / "groundtruth.txt"
        for k in range(runs):
            copies[(seq.name, k)] = moved_copy(original, truth, k, out / "data" / "moved" / f"{seq.name}_k{k}")
    return copies


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", required=True, help="the commit to compare the working tree with")
    ap.add_argument("--new", help="a commit to run in its own worktree instead of the working tree (a gate that "
                                  "runs while the working tree changes)")
    ap.add_argument("--quick", action="store_true", help="the quick panel (the real sequence always in it)")
    ap.add_argument("--runs", type=int, default=3, help="runs per case, each in its own moved world frame (K)")
    ap.add_argument("--real", help="the real sequence's folder (default $ENDOSLAM_REAL or ~/.cache/endoslam-real/scared_640)")
    ap.add_argument("--cases", nargs="+", metavar="GLOB", help="only the cases whose names match")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="runs at once")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "check_accuracy")
    ap.add_argument("--list", action="store_true", help="list the panel's cases and stop")
    args = ap.parse_args(argv)
    cases = select(panel(), args.quick, args.cases)
    if args.list:
        print("\n".join(f"{c.name}{'  (quick)' if c.quick else ''}" for c in cases))
        return 0
    if args.runs < 2:
        raise SystemExit("check_accuracy: error: --runs must be at least 2: one run per case has no spread")
    if not cases:
        raise SystemExit("check_accuracy: error: no case matches --cases")
    t0 = time.time()
    out = args.out.resolve()
    real = real_folder(args.real) if any(c.sequence.real for c in cases) else None
    base_tree, base_key = checkout(args.base, out)
    base = Side(f"base {args.base}", base_tree, base_key)
    if args.new:
        new_tree, new_key = checkout(args.new, out)
        new = Side(f"new {args.new}", new_tree, new_key)
    else:
        new = Side("new", ROOT, working_tree_key())
    copies = prepare(cases, out, real, args.runs, max(1, args.workers))
    from slam.evaluation.map_error import read_points_mm

    points = read_points_mm(REAL_POINTS) if any(c.map_error for c in cases) else None

    def folder(side: Side, case: Case, k: int) -> Path:
        return out / "cache" / side.key[:12] / case.name / f"k{k}"

    jobs = {}              # one run per folder: a side whose tree equals the other's shares its runs
    for case in cases:
        for k in range(args.runs):
            for side in (base, new):
                jobs.setdefault(folder(side, case, k), Job(side, case, k, copies[(case.sequence.name, k)],
                                                           folder(side, case, k)))
    records = run_all(list(jobs.values()), args.workers)
    results = []
    for case in cases:
        result = CaseResult(case)
        for side in (base, new):
            collect(result, side.label, [jobs[folder(side, case, k)] for k in range(args.runs)], records, points,
                    fails=side is new)
        judge_case(result, base.label, new.label)
        results.append(result)

    text = table(results, base.label, new.label)
    dropped = sorted({d for r in results for d in r.dropped})
    notes = [f"K = {args.runs} runs per case (median [min-max]); {len(cases)} cases; "
             f"{(time.time() - t0) / 60:.1f} min"]
    if dropped:
        notes.append(f"options the base lacks, not passed to it: {', '.join(dropped)}")
    notes += [f"{r.case.name}: {n}" for r in results for n in r.notes]
    line = verdict(results)
    report = "\n".join([text, "", *notes, "", line])
    print(report)
    (out / "reports").mkdir(parents=True, exist_ok=True)
    name = f"{base_key[:12]}_vs_{new.key[:12]}{'_quick' if args.quick else ''}"
    (out / "reports" / f"{name}.md").write_text(report + "\n")
    (out / "reports" / f"{name}.json").write_text(json.dumps(
        {"base": args.base, "verdict": line, "cases": [
            {"case": r.case.name, "figures": r.figures, "problems": r.problems, "notes": r.notes,
             "judged": {k: list(v) for k, v in r.judged.items()}} for r in results]}, indent=1))
    return 0 if line.startswith("PASS") else 1
