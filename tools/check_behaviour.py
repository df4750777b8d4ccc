"""Same input, same config, same outputs: this checkout against another commit, byte for byte.

A maintainer's check for a change that must not change behaviour (a redesign): each case runs
``slam run`` with ``threads=1`` in a git worktree of the base commit and in this checkout, one
after the other, and compares ``trajectory.txt``, ``tracking.csv``, ``metrics.json`` (without
timings, speed, memory and provenance; its accuracy figures to 1e-9, as evo computes them) and
``map.ply`` byte for byte. Prints a Markdown table;
exit code 1 when a file differs.

    .venv/bin/python tools/check_behaviour.py --base COMMIT [--cases default paper ...] [--out DIR]

The sequences are rendered once into ``OUT/data`` by this checkout's ``slam synth``. A case
whose options the new code names differently carries them as ``new`` (a removed key, a moved
analysis switch).
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks.checkout import run_slam

ROOT = Path(__file__).resolve().parents[1]
#: metrics.json keys that measure the machine, not the result
VOLATILE = ("fps", "timings_ms", "thread_cpu_ms", "peak_rss_mb", "provenance", "data")
FILES = ("trajectory.txt", "tracking.csv", "metrics.json", "map.ply")


@dataclass
class Sequence:
    name: str
    synth: list          # slam synth's options
    unreadable: tuple = ()   # frames whose left PNG is made unreadable (frames that could not be read)


@dataclass
class Case:
    name: str
    sequence: str
    args: list                     # slam run's options for both versions
    new: list = field(default_factory=list)   # replaces ``args`` for this checkout when not empty


SEQUENCES = {s.name: s for s in [
    Sequence("scanning", ["--scenario", "scanning", "--frames", "40", "--size", "320x256", "--seed", "4242"]),
    Sequence("still", ["--scenario", "breathing", "--frames", "30", "--size", "320x256", "--seed", "4243"]),
    Sequence("weak", ["--scenario", "rigid", "--frames", "40", "--size", "320x256", "--seed", "9801",
                      "--appearance", "texture=0,highlights=1,haze=0.3"]),
    Sequence("loop_gap", ["--scenario", "loop", "--frames", "160", "--size", "320x256", "--seed", "8001"],
             unreadable=tuple(range(90, 97))),
]}

CASES = {c.name: c for c in [
    Case("default-f2f", "scanning", ["--mode", "frame2frame"]),
    Case("default-f2m", "scanning", ["--mode", "frame2model"]),
    Case("keyframes", "still", ["--mode", "frame2frame"]),
    Case("keyframes-f2m", "still", ["--mode", "frame2model"]),
    Case("refine", "scanning", ["--mode", "frame2model", "--set", "tracking.refine_passes=1"]),
    Case("flags-rebuild", "weak", ["--mode", "frame2model", "--set", "health.cross_check=2"]),
    Case("loop-reloc", "loop_gap", ["--mode", "frame2model", "--set", "graph.loop_closure=true"]),
    Case("paper", "scanning", ["--config", str(ROOT / "configs" / "paper.yaml")]),
    Case("residuals-2d", "scanning", ["--residuals", "2d"]),
    Case("residuals-3d", "scanning", ["--residuals", "3d"]),
    Case("constant", "scanning", ["--weights", "constant"]),
    Case("groundtruth-poses", "scanning", ["--set", "tracking.poses=groundtruth"],
         new=["--set", "analysis.poses=groundtruth"]),
]}


def render(out: Path) -> dict[str, Path]:
    data = {}
    for seq in SEQUENCES.values():
        path = out / "data" / seq.name
        if not (path / "groundtruth.txt").is_file():
            run_slam(ROOT, "synth", path, *seq.synth, "--quiet", check=True)
            for k in seq.unreadable:
                (path / "video_frames" / f"{k:06d}l.png").write_bytes(b"not a png")
        data[seq.name] = path
    return data


def run(tree: Path, data: Path, out: Path, args: list) -> tuple[int, str]:
    shutil.rmtree(out, ignore_errors=True)
    proc = run_slam(tree, "run", data, "--out", out, "--quiet", "--set", "threads=1", *args,
                    capture_output=True, text=True)
    return proc.returncode, (proc.stderr.strip().splitlines() or [""])[-1]


def read_metrics(path: Path) -> dict:
    metrics = json.loads(path.read_text())
    for key in VOLATILE:
        metrics.pop(key, None)
    metrics.get("loop_closure", {}).pop("ms_per_frame", None)      # (the detection's time)
    return metrics


def close(a, b, rtol: float = 1e-9, atol: float = 1e-12) -> bool:
    """Equal, floats within ``rtol`` or ``atol`` (the accuracy figures in mm and degrees: evo sums
    in another order; a zero error, as at known poses, is rounding noise of 1e-15)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(close(a[k], b[k], rtol, atol) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(close(x, y, rtol, atol) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float):
        return a == b or abs(a - b) <= max(rtol * max(abs(a), abs(b)), atol)
    return a == b


def compare(a: Path, b: Path) -> str:
    """``same`` (byte for byte; metrics.json: without timings, and ``same to 1e-9`` where its
    figures differ in the last digits), ``**differs**``, or ``-`` where neither run wrote it."""
    if not a.is_file() and not b.is_file():
        return "-"
    if not (a.is_file() and b.is_file()):
        return "**differs**"
    if a.name != "metrics.json":
        return "same" if a.read_bytes() == b.read_bytes() else "**differs**"
    ma, mb = read_metrics(a), read_metrics(b)
    return "same" if ma == mb else ("same to 1e-9" if close(ma, mb) else "**differs**")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", required=True, help="the commit to compare with")
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "check_behaviour")
    args = ap.parse_args()
    out = args.out.resolve()
    base = out / "base_tree"
    if not (base / "slam").is_dir():
        subprocess.run(["git", "worktree", "add", "--detach", "--force", str(base), args.base], check=True, cwd=ROOT)
    else:
        subprocess.run(["git", "checkout", "--detach", "--quiet", args.base], check=True, cwd=base)
    data = render(out)
    print("| case | sequence | " + " | ".join(FILES) + " | note |")
    print("|---|---|" + "---|" * len(FILES) + "---|")
    differ = False
    for name in args.cases:
        case = CASES[name]
        runs = {}
        notes = []
        for label, tree, options in (("base", base, case.args), ("new", ROOT, case.new or case.args)):
            code, last = run(tree, data[case.sequence], out / "runs" / name / label, options)
            runs[label] = out / "runs" / name / label
            if code != 0:
                notes.append(f"{label} exit {code}: {last}")
        cells = [compare(runs["base"] / f, runs["new"] / f) for f in FILES]
        differ |= "**differs**" in cells
        print(f"| {name} | {case.sequence} | " + " | ".join(cells) + f" | {'; '.join(notes)} |", flush=True)
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
