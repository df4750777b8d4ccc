"""``slam`` as a user or a scheduler meets it: real processes, real signals, output redirected
to files. Signals go out once a file shows how far the run is (rows in ``trajectory.txt``),
never after a sleep."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from slam.io.tum import read_tum

SLAM = [sys.executable, "-m", "slam"]
FRAMES = 10


@pytest.fixture(scope="module")
def sequence(synth_dir) -> Path:
    return synth_dir("rigid", FRAMES, (160, 128))


def start(*args) -> subprocess.Popen:
    # the default SIGINT action even when the tests run as a background job (started with SIGINT ignored)
    return subprocess.Popen([*SLAM, *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def rows(path: Path) -> int:
    if not path.is_file():
        return 0
    return len([line for line in path.read_text().splitlines() if line and not line.startswith("#")])


def wait_for_rows(proc: subprocess.Popen, path: Path, k: int, timeout_s: float = 180) -> None:
    deadline = time.time() + timeout_s
    while rows(path) < k:
        assert proc.poll() is None, f"the run ended before {k} rows: {proc.communicate()}"
        assert time.time() < deadline, f"no {k} rows in {path} after {timeout_s} s"
        time.sleep(0.02)


def slow_run(sequence: Path, out: Path, *extra) -> subprocess.Popen:
    """frame2model with L-BFGS: slow enough per frame for a signal to land mid-run."""
    return start("run", sequence, "--mode", "frame2model", "--weights", "constant", "--out", out,
                 "--set", "solver.method=lbfgs", *extra)


def test_sigterm_is_taken_as_ctrl_c(sequence, tmp_path):
    out = tmp_path / "run"
    proc = slow_run(sequence, out, "--quiet")
    wait_for_rows(proc, out / "trajectory.txt", 3)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr
    assert "Traceback" not in stderr
    metrics = json.loads((out / "metrics.json").read_text())
    done = rows(out / "trajectory.txt")
    assert metrics["interrupted"] is True and 3 <= done < FRAMES and metrics["frames"] == done
    assert metrics["stopped_before_frame"] == done and "skipped_outputs" not in metrics
    assert (out / "map.ply").is_file() and (out / "trajectory.png").is_file()
    assert f"interrupted after {done} frames" in stdout


def test_a_second_signal_skips_the_slow_outputs(sequence, tmp_path):
    """Ctrl-C, then another signal before the map is written: metrics.json, the trajectory and
    tracking.csv are there and whole; the map, mesh, plot and the recording's end are skipped
    and listed; exit 130, no traceback. (SIGINT and SIGTERM are sent together: two signals of
    one kind may merge into one, two kinds never do.)"""
    out = tmp_path / "run"
    proc = slow_run(sequence, out, "--mesh", "--rerun", out / "run.rrd", "--quiet")
    wait_for_rows(proc, out / "trajectory.txt", 3)
    proc.send_signal(signal.SIGINT)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr
    metrics = json.loads((out / "metrics.json").read_text())
    done = rows(out / "trajectory.txt")
    assert metrics["skipped_outputs"] == ["map", "mesh", "plot", "recording"]
    assert metrics["interrupted"] is True and metrics["frames"] == done == rows(out / "tracking.csv") - 1
    assert not (out / "map.ply").exists() and not (out / "mesh.ply").exists()
    assert not (out / "trajectory.png").exists() and not list(out.glob(".*partial*"))
    stamps, poses = read_tum(out / "trajectory.txt")
    assert len(stamps) == done
    assert "skipped: map, mesh, plot, recording" in stdout


def test_compare_stops_on_ctrl_c(sequence, tmp_path):
    """Ctrl-C in the first mode stops the command: the second mode never starts and the table
    marks the run that was cut short."""
    out = tmp_path / "cmp"
    proc = start("compare", sequence, "--weights", "constant", "--out", out, "--set", "solver.method=lbfgs",
                 "--quiet")
    wait_for_rows(proc, out / "frame2frame" / "trajectory.txt", 3)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    done = rows(out / "frame2frame" / "trajectory.txt")
    assert not (out / "frame2model").exists()
    table = (out / "comparison.md").read_text()
    assert f"| frame2frame (interrupted: {done} of {FRAMES} frames) | {done} |" in table
    assert "frame2model" not in table


def test_logs_redirected_to_a_file_read_as_lines(sequence, tmp_path):
    """Off a terminal: no carriage returns, no bar; warnings on lines of their own; progress a
    line now and then; the failed run is not a result (exit 3)."""
    import shutil

    data = tmp_path / "seq"
    shutil.copytree(sequence, data)
    for k in (1, 2, 4, 5, 7, 8):
        (data / "video_frames" / f"{k:06d}l.png").write_bytes(b"not a png")
    out = tmp_path / "run"
    proc = subprocess.run([*SLAM, "run", str(data), "--weights", "constant", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 3, proc.stderr
    assert "\r" not in proc.stderr and "%|" not in proc.stderr
    lines = proc.stderr.splitlines()
    warnings = [line for line in lines if "WARNING" in line]
    assert len(warnings) == 6 and all(line.startswith("WARNING slam: frame ") for line in warnings)
    progress = [line for line in lines if line.startswith("track: ")]
    assert 1 <= len(progress) <= FRAMES and progress[-1].startswith(f"track: {FRAMES}/{FRAMES} frames")
    assert "not a result: 6 of 10 frames failed" in proc.stdout
    log = (out / "run.log").read_text()
    assert log.count("WARNING slam: frame ") == 6


def test_quiet_synth_prints_no_progress(tmp_path):
    proc = subprocess.run([*SLAM, "synth", str(tmp_path / "s"), "--scenario", "rigid", "--frames", "3", "--size",
                           "64x48", "--quiet"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert (tmp_path / "s" / "groundtruth.txt").is_file()
