"""Batch runs (slam.batch): provenance, the executors' fault isolation, and `slam evaluate` /
`slam synth` end to end on a folder of synthetic sequences, locally and on a local Ray runtime."""
from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from slam.batch.executors import Finished, Frames, LocalExecutor, Started
from slam.app.cli import main
from slam.config import load_config
from slam.app.provenance import checkpoint_files, config_digest, provenance
from tests import batch_work

REPO = Path(__file__).resolve().parents[1]
SLAM = [sys.executable, "-m", "slam"]
SEQUENCES = (("a_rigid", "rigid", 11), ("b_breathing", "breathing", 12), ("c_scanning", "scanning", 13))
FRAMES = 10


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """Three small synthetic sequences (10 frames, 160x128) in one folder."""
    from slam.synth import generate

    root = tmp_path_factory.mktemp("batch") / "sequences"
    for name, scenario, seed in SEQUENCES:
        generate(root / name, scenario, frames=FRAMES, size=(160, 128), seed=seed)
    return root


def read_summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def rows_by_run(summary: dict) -> dict:
    return {(r["sweep"], r["sequence"], r["mode"]): r for r in summary["rows"]}


# ------------------------------------------------------------------------------------------------
# provenance
def test_provenance_follows_what_changes_results(tmp_path):
    base = load_config(None, ["threads=1"])
    shown = load_config(None, ["threads=1"])
    other = load_config(None, ["threads=1", "solver.max_iters=3"])
    assert config_digest(base) == config_digest(shown)          # the same config, loaded again
    assert config_digest(base) != config_digest(other)
    assert config_digest(base) != config_digest(load_config(None, ["threads=2"]))
    files = checkpoint_files(base)
    # the still camera's filtered networks, the moving camera's, the model view's: three files
    assert {p.name for p in files.values()} == {"weights_2d3d_filtered.pt", "weights_2d3d.pt", "weights_2d3d_model.pt"}
    assert checkpoint_files(load_config(None, ["weights.mode=constant"])) == {}
    mine = tmp_path / "mine.pt"
    mine.write_bytes(b"a")
    named = checkpoint_files(load_config(None, [f"weights.checkpoint={mine}"]))
    assert named["weights_filtered"] == named["weights_stereo"] == named["weights_model"] == mine
    before = provenance(load_config(None, [f"weights.checkpoint={mine}"]), "0:5")
    mine.write_bytes(b"b")
    after = provenance(load_config(None, [f"weights.checkpoint={mine}"]), "0:5")
    assert before["checkpoints"] != after["checkpoints"] and before["frames"] == "0:5"
    assert provenance(base)["frames"] == "all" and provenance(base)["version"].startswith("0.")


# ------------------------------------------------------------------------------------------------
# executors
def collect(executor, payloads):
    events = list(executor.run(batch_work.work, payloads))
    executor.close()
    return events


def test_local_executor_isolates_a_crash_and_times_out():
    ex = LocalExecutor(2, env={"OMP_NUM_THREADS": "1"}, timeout_s=1.0, grace_s=5.0)
    payloads = [("ok", 1), ("crash", 0), ("raise", 0), ("sleep", 60), ("ok", 2), ("ok", 3)]
    t0 = time.perf_counter()
    events = collect(ex, payloads)
    ends = {e.index: e.outcome for e in events if isinstance(e, Finished)}
    assert sorted(ends) == list(range(len(payloads)))       # every task ends once
    assert [ends[i]["value"] for i in (0, 4, 5)] == [1, 2, 3] and ends[0]["omp"] == "1"
    assert ends[1]["status"] == "error" and "SIGSEGV" in ends[1]["message"]   # reported, not re-run
    assert ends[2]["status"] == "error" and ends[2]["message"] == "ValueError: a bad sequence"
    assert ends[3]["status"] == "timeout" and 5 <= ends[3]["frames"] <= 20   # stopped, with what it did
    assert any(isinstance(e, Frames) and e.index == 3 for e in events)
    assert sum(isinstance(e, Started) for e in events) == len(payloads)
    assert time.perf_counter() - t0 < 30


def test_local_executor_interrupt_keeps_what_finished():
    ex = LocalExecutor(1, timeout_s=None, grace_s=5.0)
    events = []
    gen = ex.run(batch_work.work, [("ok", 1), ("sleep", 100), ("ok", 2)])
    for event in gen:
        events.append(event)
        if isinstance(event, Frames) and event.frames >= 3:
            break
    events += list(ex.interrupt())
    ex.close()
    ends = {e.index: e.outcome for e in events if isinstance(e, Finished)}
    assert ends[0]["status"] == "ok" and ends[1]["status"] == "interrupted" and ends[1]["frames"] >= 3
    assert 2 not in ends      # never started


@pytest.fixture
def short_tmp():
    """A folder with a short path (Ray's socket paths live under its temp folder)."""
    folder = Path(tempfile.mkdtemp(prefix="ray", dir="/tmp"))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def test_ray_executor_isolates_a_crash(monkeypatch, short_tmp):
    """Also: the local runtime is its own, even where Ray's address file names another cluster (one
    started with ``ray start`` earlier, here a dead one): Ray would join that one without being told
    ``local``, and refuse the CPU count. Its tasks run at the driver's priority."""
    pytest.importorskip("ray", reason="Ray is the optional extra endoslam[cluster]")
    from slam.batch.executors import RayExecutor

    monkeypatch.setenv("PYTHONPATH", str(REPO))    # the runtime's workers find tests.batch_work
    (short_tmp / "ray").mkdir()
    (short_tmp / "ray" / "ray_current_cluster").write_text("127.0.0.1:9")
    monkeypatch.setenv("RAY_TMPDIR", str(short_tmp))      # Ray's files in RAY_TMPDIR/ray
    ex = RayExecutor(None, workers=2, cpus_per_task=1, env={"OMP_NUM_THREADS": "1"}, timeout_s=3.0, grace_s=10.0)
    events = collect(ex, [("ok", 1), ("crash", 0), ("sleep", 100), ("ok", 2)])
    ends = {e.index: e.outcome for e in events if isinstance(e, Finished)}
    assert sorted(ends) == [0, 1, 2, 3]
    assert ends[0]["value"] == 1 and ends[3]["value"] == 2 and ends[0]["omp"] == "1"
    assert ends[0]["nice"] == os.nice(0)      # the driver's priority, not Ray's 15 for workers
    assert ends[1]["status"] == "error" and "worker died" in ends[1]["message"]
    assert ends[2]["status"] == "timeout" and ends[2]["frames"] >= 5


# ------------------------------------------------------------------------------------------------
# slam evaluate
@pytest.fixture(scope="module")
def local_eval(folder, tmp_path_factory):
    """`slam evaluate` of the folder, both modes, on 2 local worker processes (1 CPU each)."""
    out = tmp_path_factory.mktemp("eval") / "local"
    rc = main(["evaluate", str(folder), "--executor", "local", "--workers", "2", "--out", str(out), "--quiet"])
    assert rc == 0
    return out


def test_evaluate_table_matches_separate_runs(folder, local_eval, tmp_path):
    summary = read_summary(local_eval)
    rows = rows_by_run(summary)
    assert len(rows) == 6 and summary["errors"] == 0 and summary["batch"]["executor"] == "local"
    for name, scenario, _ in SEQUENCES:
        for mode in ("frame2frame", "frame2model"):
            r = rows[("", name, mode)]
            assert r["status"] == "ok" and r["scenario"] == scenario and r["frames"] == FRAMES, r
            assert 0 < r["ate_rmse_mm"] < 1.0
            assert (Path(r["out"]) / "trajectory.txt").is_file() and (Path(r["out"]) / "run.log").is_file()
    # each ATE equals a separate `slam run` at the same threads
    for name, mode in (("a_rigid", "frame2model"), ("c_scanning", "frame2frame")):
        out = tmp_path / f"{name}_{mode}"
        assert main(["run", str(folder / name), "--mode", mode, "--set", "threads=1", "--out", str(out), "--quiet"]) == 0
        alone = json.loads((out / "metrics.json").read_text())
        assert alone["ate_rmse_mm"] == pytest.approx(rows[("", name, mode)]["ate_rmse_mm"], rel=1e-9, abs=1e-12)
    # the tables: per scenario, micro and macro; CSV, Markdown, plot
    table = summary["tables"]["scenarios"]
    for mode in ("frame2frame", "frame2model"):
        ates = [rows[("", n, mode)]["ate_rmse_mm"] for n, _, _ in SEQUENCES]
        assert table[mode]["micro"]["mean"] == pytest.approx(np.mean(ates))
        assert table[mode]["macro"]["mean"] == pytest.approx(np.mean(ates))   # one sequence per scenario
        assert table[mode]["rigid"]["n"] == 1
    with open(local_eval / "evaluation.csv") as fh:
        lines = list(csv.DictReader(fh))
    assert len(lines) == 6 and {ln["mode"] for ln in lines} == {"frame2frame", "frame2model"}
    md = (local_eval / "evaluation.md").read_text()
    assert "micro avg." in md and "| frame2model |" in md
    assert (local_eval / "evaluation.png").stat().st_size > 10_000


def test_evaluate_resumes_only_what_is_missing(folder, local_eval, capsys):
    # a finished evaluation runs nothing again
    capsys.readouterr()
    assert main(["evaluate", str(folder), "--executor", "local", "--out", str(local_eval), "--quiet"]) == 0
    assert "6 task(s): 6 done before, 0 to run" in capsys.readouterr().out
    summary = read_summary(local_eval)
    assert summary["resumed"] == 6 and all(r["resumed"] for r in summary["rows"])
    # a run that was interrupted, one with another config and a missing one run again; the others not
    rows = rows_by_run(summary)
    interrupted = Path(rows[("", "a_rigid", "frame2frame")]["out"]) / "metrics.json"
    m = json.loads(interrupted.read_text())
    interrupted.write_text(json.dumps({**m, "interrupted": True}))
    other = Path(rows[("", "b_breathing", "frame2frame")]["out"]) / "metrics.json"
    m = json.loads(other.read_text())
    other.write_text(json.dumps({**m, "provenance": {**m["provenance"], "config_sha256": "0" * 64}}))
    (Path(rows[("", "c_scanning", "frame2model")]["out"]) / "metrics.json").unlink()
    assert main(["evaluate", str(folder), "--executor", "local", "--out", str(local_eval), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "6 task(s): 3 done before, 3 to run" in out
    ran = {line.split(":")[0].split("] ")[1] for line in out.splitlines() if line.startswith("[")}
    assert ran == {"a_rigid frame2frame", "b_breathing frame2frame", "c_scanning frame2model"}
    assert read_summary(local_eval)["errors"] == 0


def test_evaluate_killed_half_way_then_restarted(folder, tmp_path):
    out = tmp_path / "killed"
    cmd = [*SLAM, "evaluate", str(folder), "--executor", "local", "--workers", "1", "--modes", "frame2frame",
           "--out", str(out), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.time() + 180
    while time.time() < deadline and not list(out.glob("runs/*/frame2frame/metrics.json")):
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)       # the driver dies without a word; its worker follows it
    proc.communicate(timeout=30)
    finished = {p.parent.parent.name for p in out.glob("runs/*/frame2frame/metrics.json")}
    assert 1 <= len(finished) < 3
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert f"3 task(s): {len(finished)} done before, {3 - len(finished)} to run" in res.stdout
    ran = {line.split("] ")[1].split(" ")[0] for line in res.stdout.splitlines() if line.startswith("[")}
    assert ran == {n for n, _, _ in SEQUENCES} - finished
    summary = read_summary(out)
    assert summary["errors"] == 0 and len(summary["rows"]) == 3


def finished_runs(out: Path) -> list[Path]:
    """Run folders whose run has ended: its summary is the last line of its run.log (metrics.json
    comes earlier, before the map and the plot)."""
    return [p.parent for p in out.glob("runs/*/frame2frame/run.log") if "INFO slam: processed " in p.read_text()]


def test_evaluate_ctrl_c_keeps_what_finished(folder, tmp_path):
    out = tmp_path / "interrupted"
    # the default SIGINT action even when the tests run as a background job (started with SIGINT ignored)
    proc = subprocess.Popen([*SLAM, "evaluate", str(folder), "--executor", "local", "--workers", "1", "--modes",
                             "frame2frame", "--out", str(out), "--quiet"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 180
    while time.time() < deadline and not finished_runs(out):
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    summary = read_summary(out)
    assert summary["interrupted"] is True and summary["not_run"]
    done = [r for r in summary["rows"] if r["status"] == "ok"]
    assert done and all(r["frames"] == FRAMES and r["ate_rmse_mm"] > 0 for r in done)
    assert len(summary["rows"]) + len(summary["not_run"]) == 3
    assert "INTERRUPTED" in (out / "evaluation.md").read_text()


def test_evaluate_error_row_for_a_broken_sequence(folder, tmp_path):
    import shutil

    root = tmp_path / "root"
    shutil.copytree(folder / "a_rigid", root / "a_rigid")
    shutil.copytree(folder / "b_breathing", root / "broken")
    (root / "broken" / "StereoCalibration.ini").write_text("[StereoLeft]\nres_x = banana\n")
    (root / "notes").mkdir()
    out = tmp_path / "out"
    # a failed task: the table with the good rows, and a non-zero exit a batch script can see
    assert main(["evaluate", str(root), "--executor", "local", "--modes", "frame2frame", "--frames", "6",
                 "--out", str(out), "--quiet"]) == 1
    summary = read_summary(out)
    rows = rows_by_run(summary)
    assert summary["errors"] == 1 and len(rows) == 2
    bad = rows[("", "broken", "frame2frame")]
    assert bad["status"] == "error" and "StereoCalibration.ini" in bad["message"] and "\n" not in bad["message"]
    assert rows[("", "a_rigid", "frame2frame")]["status"] == "ok" and rows[("", "a_rigid", "frame2frame")]["frames"] == 6
    assert any("notes" in n for n in summary["notes"])
    assert "| broken | 6 | breathing | frame2frame | error |" in (out / "evaluation.md").read_text()


def test_evaluate_sweep(folder, tmp_path):
    out = tmp_path / "sweep"
    assert main(["evaluate", str(folder), "--executor", "local", "--modes", "frame2frame", "--frames", "6",
                 "--sweep", "weights.mode=learned,constant", "--out", str(out), "--quiet"]) == 0
    summary = read_summary(out)
    assert len(summary["rows"]) == 6 and summary["errors"] == 0
    table = summary["tables"]["scenarios"]
    assert set(table) == {"weights.mode=learned frame2frame", "weights.mode=constant frame2frame"}
    learned = rows_by_run(summary)[("weights.mode=learned", "a_rigid", "frame2frame")]
    constant = rows_by_run(summary)[("weights.mode=constant", "a_rigid", "frame2frame")]
    assert learned["ate_rmse_mm"] != constant["ate_rmse_mm"]
    assert (out / "runs" / "weights.mode=constant" / "a_rigid" / "frame2frame" / "metrics.json").is_file()
    cfg = (out / "runs" / "weights.mode=constant" / "a_rigid" / "frame2frame" / "config.yaml").read_text()
    assert "mode: constant" in cfg and "threads: 1" in cfg


@pytest.mark.parametrize("args, needle", [
    (["--sweep", "weights.mode=learned,bogus"], "weights.mode=bogus"),
    (["--sweep", "solver.max_itres=3"], "solver.max_itres"),
    (["--sweep", "solver.max_iters"], "KEY=V1,V2"),
    (["--frames", "1:a"], "--frames 1:a"),
    (["--cpus-per-task", "0"], "--cpus-per-task"),
    (["--modes", "frame2nothing"], "--modes"),
])
def test_evaluate_bad_options_fail_before_running(folder, tmp_path, args, needle):
    res = subprocess.run([*SLAM, "evaluate", str(folder), "--out", str(tmp_path / "o"), *args], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], res.stderr
    assert not (tmp_path / "o" / "runs").exists()


def test_evaluate_on_local_ray(folder, local_eval, tmp_path):
    """A local Ray runtime with 2 CPUs (one per task) gives the same table as the local workers."""
    pytest.importorskip("ray", reason="Ray is the optional extra endoslam[cluster]")
    out = tmp_path / "ray"
    assert main(["evaluate", str(folder), "--executor", "ray", "--workers", "2", "--out", str(out), "--quiet"]) == 0
    summary = read_summary(out)
    assert summary["batch"]["executor"] == "ray" and summary["errors"] == 0
    ray_rows, local_rows = rows_by_run(summary), rows_by_run(read_summary(local_eval))
    assert set(ray_rows) == set(local_rows)
    for key, r in ray_rows.items():
        assert r["ate_rmse_mm"] == pytest.approx(local_rows[key]["ate_rmse_mm"], rel=1e-9, abs=1e-12), key
    assert summary["tables"]["scenarios"]["frame2model"]["macro"]["mean"] == pytest.approx(
        read_summary(local_eval)["tables"]["scenarios"]["frame2model"]["macro"]["mean"])


# ------------------------------------------------------------------------------------------------
# slam synth of many sequences
def test_synth_many_sequences(tmp_path, capsys):
    out = tmp_path / "train"
    args = ["synth", str(out), "--scenario", "rigid", "breathing", "--seed", "3-4", "--frames", "4", "--size", "64x48",
            "--executor", "local", "--workers", "2", "--quiet"]
    assert main(args) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["breathing_s3", "breathing_s4", "rigid_s3", "rigid_s4"]
    assert (out / "rigid_s4" / "synth.log").is_file()
    # the same sequence as `slam synth` of one
    single = tmp_path / "single"
    assert main(["synth", str(single), "--scenario", "rigid", "--seed", "4", "--frames", "4", "--size", "64x48"]) == 0
    assert (single / "groundtruth.txt").read_text() == (out / "rigid_s4" / "groundtruth.txt").read_text()
    assert (single / "video_frames" / "000003l.png").read_bytes() == \
        (out / "rigid_s4" / "video_frames" / "000003l.png").read_bytes()
    capsys.readouterr()
    assert main(args) == 0            # nothing to render again
    assert "4 there already" in capsys.readouterr().out
    assert main(["synth", str(out), "--scenario", "rigid", "--seed", "4-3"]) == 2


def test_executor_choice_without_ray(monkeypatch):
    from slam.batch import runner
    from slam.errors import ConfigError

    monkeypatch.setattr(runner, "ray_available", lambda: False)
    assert runner.BatchOptions().kind() == "local"
    for options in (runner.BatchOptions(executor="ray"), runner.BatchOptions(address="auto")):
        with pytest.raises(ConfigError, match="endoslam\\[cluster\\]"):
            options.kind()
    monkeypatch.setattr(runner, "ray_available", lambda: True)
    assert runner.BatchOptions().kind() == "ray" and runner.BatchOptions(executor="local").kind() == "local"
    with pytest.raises(ConfigError, match="--address"):
        runner.BatchOptions(executor="local", address="auto").validate()
