"""What a run promises whatever the input: a broken input is one line and exit 2 with nothing
written; a finished run keeps every row and says, by its exit code and its metrics, whether it
is a result. A table of broken inputs walked through ``slam``'s own ``main`` (signals and
terminals are tested with real processes in ``test_cli_signals.py``)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from slam.app.cli import main
from slam.io.calibration import read_stereomis_ini
from slam.io.tum import read_tum, write_tum

FRAMES = 10


@pytest.fixture(scope="module")
def sequence(synth_dir) -> Path:
    return synth_dir("rigid", FRAMES, (160, 128))


def copy_of(sequence: Path, tmp_path: Path) -> Path:
    data = tmp_path / "seq"
    shutil.copytree(sequence, data)
    return data


def rows(path: Path) -> int:
    return len([line for line in path.read_text().splitlines() if line and not line.startswith("#")])


# ------------------------------------------------------------------------------------------------
# the table: how to break a copy of the sequence, the arguments, the exit code, a word of the message
def _calibration_size(data: Path, w: int, h: int) -> None:
    ini = data / "StereoCalibration.ini"
    ini.write_text(ini.read_text().replace("res_x = 160", f"res_x = {w}").replace("res_y = 128", f"res_y = {h}"))


def _unreadable(data: Path, keep_every: int) -> None:
    for k in range(FRAMES):
        if k % keep_every:
            (data / "video_frames" / f"{k:06d}l.png").write_bytes(b"not a png")


def _truncated_png(data: Path) -> None:
    png = data / "video_frames" / "000004l.png"
    png.write_bytes(png.read_bytes()[: png.stat().st_size // 2])


def _short_groundtruth(data: Path) -> None:
    stamps, poses = read_tum(data / "groundtruth.txt")
    write_tum(data / "groundtruth.txt", stamps[:5], poses[:5])


def _as_plain(data: Path, left: str = "{:04d}", right: str = "{:04d}", first: int = 5) -> None:
    """The copy as a plain folder: ``left/`` and ``right/`` named ``left.format(number)``,
    ``right.format(number)`` from ``first`` on (5 .. 14: as text, 10 sorts before 5), beside a
    ``calibration.yaml`` of the rectified rig."""
    calib = read_stereomis_ini(data / "StereoCalibration.ini")
    for side, folder, name in (("l", "left", left), ("r", "right", right)):
        (data / folder).mkdir()
        for k in range(FRAMES):
            (data / "video_frames" / f"{k:06d}{side}.png").rename(data / folder / f"{name.format(k + first)}.png")
    shutil.rmtree(data / "video_frames")
    (data / "StereoCalibration.ini").unlink()
    K = calib.K1
    (data / "calibration.yaml").write_text(f"fx: {K[0, 0]}\nfy: {K[1, 1]}\ncx: {K[0, 2]}\ncy: {K[1, 2]}\n"
                                           f"baseline_mm: {calib.baseline_mm}\nwidth: 160\nheight: 128\n")


def _plain_with_a_gap(data: Path) -> None:
    """Unpadded right names, one of them one number off: no pairing by name, none by order."""
    _as_plain(data, right="{}")
    (data / "right" / "14.png").rename(data / "right" / "15.png")


BROKEN = {
    # name: (break the copy, extra arguments, exit code, word in the one error line or None)
    "missing folder": (lambda d: shutil.rmtree(d), [], 2, "no such folder"),
    "empty folder": (lambda d: [shutil.rmtree(d), d.mkdir()], [], 2, "empty folder"),
    "no calibration": (lambda d: (d / "StereoCalibration.ini").unlink(), [], 2, "StereoCalibration.ini"),
    "empty calibration": (lambda d: (d / "StereoCalibration.ini").write_text(""), [], 2, "empty calibration file"),
    "calibration for 1000x1000": (lambda d: _calibration_size(d, 1000, 1000), [], 2, "does not fit"),
    "calibration for 240x192": (lambda d: _calibration_size(d, 240, 192), [], 2, "does not fit"),
    "a right view missing": (lambda d: (d / "video_frames" / "000009r.png").unlink(), [], 2, "right"),
    "ground truth not TUM": (lambda d: (d / "groundtruth.txt").write_text("1 2 3\n"), [], 2, "groundtruth.txt"),
    "frames beyond the sequence": (lambda d: None, ["--frames", "20:30"], 2, "frames"),
    "negative threads": (lambda d: None, ["--set", "threads=-3"], 2, "threads"),
    "unknown key": (lambda d: None, ["--set", "tracking.modes=frame2model"], 2, "did you mean"),
    "one corrupt frame": (lambda d: (d / "video_frames" / "000003l.png").write_bytes(b"x"), [], 0, None),
    "one truncated frame": (_truncated_png, [], 0, None),
    "ground truth for half the frames": (_short_groundtruth, [], 0, None),
    "two thirds unreadable": (lambda d: _unreadable(d, 3), [], 3, None),
    # issue 62: what people's folders look like
    "plain, unpadded names": (lambda d: _as_plain(d, "{}", "{}"), [], 0, None),
    "plain, unpadded names in right/ only": (lambda d: _as_plain(d, right="{}"), [], 0, None),
    "plain, names that do not pair": (_plain_with_a_gap, [], 2, "right: the frames do not pair: 1 left frames "
                                                               "without a right one (first 0014.png)"),
    "all but the first unreadable": (lambda d: _unreadable(d, FRAMES), [], 3, None),
}


@pytest.mark.parametrize("name", list(BROKEN))
def test_broken_inputs(sequence, tmp_path, capsys, name):
    """No traceback; a one-line error and nothing written (exit 2), or every row kept with an
    exit code that says whether the run is a result (0 or 3)."""
    breaks, extra, code, word = BROKEN[name]
    data = copy_of(sequence, tmp_path)
    breaks(data)
    out = tmp_path / "out"
    assert main(["run", str(data), "--weights", "constant", "--out", str(out), "--quiet", *extra]) == code
    err = capsys.readouterr().err
    assert "Traceback" not in err and "UserWarning" not in err
    if code == 2:
        assert err.count("\n") == 1 and err.startswith("slam run: error: ") and word in err, err
        assert not out.exists() or not any(out.iterdir())
        return
    metrics = json.loads((out / "metrics.json").read_text())
    assert rows(out / "trajectory.txt") == metrics["frames"] == FRAMES       # every row kept
    assert rows(out / "tracking.csv") == FRAMES + 1                          # its header and a row a frame
    failed = len(metrics["failed_frames"])
    assert metrics["tracked_frames"] == FRAMES - failed
    if code == 3:
        assert metrics["status"] == f"not a result: {failed} of {FRAMES} frames failed" and failed > FRAMES / 2
        assert "ate_rmse_mm" not in metrics and "ate_rmse_mm" in metrics["not_trusted"]
    else:
        assert metrics["status"] == "ok" and metrics["ate_rmse_mm"] < 1.0


def test_ground_truth_shorter_than_the_frames(sequence, tmp_path, capsys):
    """Frames tracked stay the run's ``frames``; the evaluation's count is ``evaluated_frames``;
    the warning is one log line."""
    data = copy_of(sequence, tmp_path)
    _short_groundtruth(data)
    out = tmp_path / "out"
    assert main(["run", str(data), "--weights", "constant", "--out", str(out), "--quiet"]) == 0
    captured = capsys.readouterr()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == FRAMES and metrics["evaluated_frames"] == 5
    assert metrics["frames_without_groundtruth"] == FRAMES - 5
    assert f"processed {FRAMES} frames" in captured.out and "over 5 frames with ground truth" in captured.out
    warnings = [line for line in captured.err.splitlines() if "ground-truth pose" in line]
    assert len(warnings) == 1 and warnings[0].startswith("WARNING slam: ")


def test_a_run_owns_its_folder(sequence, tmp_path, capsys):
    """A folder holding an earlier run is refused (one line, nothing touched); --overwrite
    removes the earlier run's files first, so no map of another mode stays beside the new run."""
    out = tmp_path / "out"
    assert main(["run", str(sequence), "--mode", "frame2model", "--weights", "constant", "--frames", "4", "--mesh",
                 "--out", str(out), "--quiet"]) == 0
    first = (out / "trajectory.txt").read_text()
    assert (out / "map.ply").is_file() and (out / "mesh.ply").is_file()
    capsys.readouterr()
    assert main(["run", str(sequence), "--weights", "constant", "--frames", "6", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "holds an earlier run" in err and "--overwrite" in err
    assert (out / "trajectory.txt").read_text() == first
    assert main(["run", str(sequence), "--weights", "constant", "--frames", "6", "--out", str(out), "--quiet",
                 "--overwrite"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["mode"] == "frame2frame" and rows(out / "trajectory.txt") == 6
    assert not (out / "map.ply").exists() and not (out / "mesh.ply").exists()


def test_out_that_is_a_file(sequence, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("in the way")
    assert main(["run", str(sequence), "--out", str(blocker), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err == f"slam run: error: {blocker}: is a file, not a folder (--out names the run's folder)\n"


def test_outputs_line_run_log_and_metrics_status(sequence, tmp_path, capsys):
    out = tmp_path / "out"
    rrd = out / "run.rrd"
    assert main(["run", str(sequence), "--weights", "constant", "--frames", "4", "--out", str(out), "--quiet",
                 "--rerun", str(rrd)]) == 0
    printed = capsys.readouterr().out
    outputs = printed.splitlines()[-1]
    for name in ("trajectory.txt", "tracking.csv", "metrics.json", "config.yaml", "trajectory.png", "run.rrd",
                 "run.log"):
        assert name in outputs, outputs
    log = (out / "run.log").read_text()
    assert "INFO slam: slam run" in log and "INFO slam: processed 4 frames" in log
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "ok" and metrics["selected_frames"] == 4
    assert not list(out.glob(".*partial*"))


def test_usage_errors_share_one_format(sequence, tmp_path, capsys):
    """Every command: ``slam COMMAND: error: ...`` on one line, exit 2."""
    cases = [
        ["eval", str(sequence / "groundtruth.txt"), str(tmp_path / "missing.txt")],
        ["run", str(tmp_path / "nowhere")],
        ["compare", str(tmp_path / "nowhere")],
        ["inspect", str(tmp_path / "nowhere")],
        ["synth", str(tmp_path / "s"), "--scenario", "rigid", "--size", "64by48"],
        ["train", "--config", str(tmp_path / "missing.yaml")],
        ["evaluate", str(tmp_path / "nowhere"), "--executor", "local"],
    ]
    for argv in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith(f"slam {argv[0]}: error: ") and err.count("\n") == 1, err
    with pytest.raises(SystemExit) as exit_:
        main(["run", str(sequence), "--mode", "sideways"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("slam run: error: ") and err.count("\n") == 1


def test_compare_help_names_its_own_out_default(capsys):
    with pytest.raises(SystemExit):
        main(["compare", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "runs/<sequence>_compare" in text and "runs/<sequence>_<mode>" not in text


def test_compare_records_one_file_per_mode(sequence, tmp_path, capsys):
    out = tmp_path / "cmp"
    rrd = tmp_path / "x.rrd"
    assert main(["compare", str(sequence), "--weights", "constant", "--frames", "4", "--out", str(out),
                 "--rerun", str(rrd), "--quiet"]) == 0
    assert (tmp_path / "x_frame2frame.rrd").stat().st_size > 1000
    assert (tmp_path / "x_frame2model.rrd").stat().st_size > 1000 and not rrd.exists()
    table = (out / "comparison.md").read_text()
    assert "| frame2frame | 4 |" in table and "| frame2model | 4 |" in table
    capsys.readouterr()
    assert main(["compare", str(sequence), "--weights", "constant", "--frames", "4", "--out", str(out),
                 "--quiet"]) == 2      # the same folder again: refused before anything runs
    assert "holds an earlier run" in capsys.readouterr().err


def test_evaluate_exits_non_zero_when_a_run_is_not_a_result(sequence, tmp_path, capsys):
    root = tmp_path / "root"
    shutil.copytree(sequence, root / "good")
    shutil.copytree(sequence, root / "blind")
    _unreadable(root / "blind", 3)
    out = tmp_path / "eval"
    assert main(["evaluate", str(root), "--executor", "local", "--workers", "1", "--modes", "frame2frame",
                 "--out", str(out), "--quiet", "--set", "weights.mode=constant"]) == 1
    captured = capsys.readouterr()
    summary = json.loads((out / "summary.json").read_text())
    status = {r["sequence"]: r["status"] for r in summary["rows"]}
    assert status == {"good": "ok", "blind": "not a result"} and summary["errors"] == 1
    assert "did not give a result" in captured.err
    assert "not a result: 6 of 10 frames failed" in (out / "evaluation.md").read_text()
    log = (out / "runs" / "blind" / "frame2frame" / "run.log").read_text()
    assert "not a result" in log


def test_failed_share_threshold():
    from slam.app.pipeline import MAX_FAILED_SHARE, run_status

    assert MAX_FAILED_SHARE == 0.5
    assert run_status(10, 5) == "ok" and run_status(10, 6) == "not a result: 6 of 10 frames failed"
    assert run_status(0, 0) == "ok"
