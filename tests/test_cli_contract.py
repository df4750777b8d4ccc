"""What a run promises whatever the input: a broken input is one line and exit 2 with nothing
written; a finished run keeps every row and says, by its exit code and its metrics, whether it
is a result. A table of broken inputs walked through ``slam``'s own ``main`` (signals and
terminals are tested with real processes in ``test_cli_signals.py``)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
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


def _rolled_right_views(data: Path, by: int = 5) -> None:
    """A plain folder whose right view k is that of frame k + ``by``: every name pairs, no view."""
    _as_plain(data)
    right = sorted((data / "right").iterdir())
    for path in right:
        path.rename(path.with_suffix(".tmp"))
    for k, path in enumerate(right):
        right[(k + by) % len(right)].with_suffix(".tmp").rename(path)


def _swapped_views(data: Path) -> None:
    _as_plain(data)
    (data / "left").rename(data / "was_left")
    (data / "right").rename(data / "left")
    (data / "was_left").rename(data / "right")


def _baseline_in_metres(data: Path) -> None:
    ini = data / "StereoCalibration.ini"
    ini.write_text(ini.read_text().replace("T_0 = -4.5", "T_0 = -0.0045"))


def _empty_masks(data: Path) -> None:
    (data / "masks").mkdir()
    for k in range(FRAMES):
        cv2.imwrite(str(data / "masks" / f"{k:06d}l.png"), np.zeros((128, 160), np.uint8))


def _tiny_frames(data: Path, size=(10, 8)) -> None:
    """A plain folder of ``size`` frames with its calibration for them."""
    _as_plain(data)
    for png in [*(data / "left").iterdir(), *(data / "right").iterdir()]:
        cv2.imwrite(str(png), cv2.resize(cv2.imread(str(png)), size, interpolation=cv2.INTER_AREA))
    calib = data / "calibration.yaml"
    values = dict(line.split(": ") for line in calib.read_text().splitlines())
    scale = size[0] / 160
    values.update(fx=float(values["fx"]) * scale, fy=float(values["fy"]) * scale,
                  cx=(float(values["cx"]) + 0.5) * scale - 0.5, cy=(float(values["cy"]) + 0.5) * scale - 0.5,
                  width=size[0], height=size[1])
    calib.write_text("".join(f"{k}: {v}\n" for k, v in values.items()))


def _frame_folders(data: Path, stamps_scale: float) -> None:
    """The copy as frame folders (``left_image/``, ``right_image/`` beside its .ini) with a
    ``timestamps.txt`` of the ground truth's times times ``stamps_scale`` (1000: milliseconds)."""
    for side, folder in (("l", "left_image"), ("r", "right_image")):
        (data / folder).mkdir()
        for k in range(FRAMES):
            (data / "video_frames" / f"{k:06d}{side}.png").rename(data / folder / f"{k:06d}.png")
    shutil.rmtree(data / "video_frames")
    stamps, _ = read_tum(data / "groundtruth.txt")
    (data / "timestamps.txt").write_text("".join(f"{t * stamps_scale:.6f}\n" for t in stamps))


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
    "mispaired views": (_rolled_right_views, [], 2, "calibration.yaml: the first frame's views keep a vertical "
                                                    "disparity of 4.6 px taken as rectified (median over 73 matches"),
    "left and right swapped": (_swapped_views, [], 2, "calibration.yaml: 100 % of the first frame's stereo matches "
                                                      "have a negative disparity taken as rectified: the left and "
                                                      "right views are swapped"),
    "frames resized under 12 px": (lambda d: None, ["--set", "data.width=7", "--set", "data.height=5"], 2,
                                   "config: data.width and data.height must be at least 12 px (the optical flow's "
                                   "smallest image), got 7x5"),
    "frames of 10x8": (_tiny_frames, [], 2, "seq: frames of 10x8 px are too small to track (at least 12x12: the "
                                            "optical flow's smallest image)"),
    "timestamps.txt in milliseconds": (lambda d: _frame_folders(d, 1000.0), [], 0, None),
    "timestamps.txt 2 apart": (lambda d: _frame_folders(d, 50.0), [], 0, None),
    # ... and what they still cannot be told from before the frames fail: the likely cause, said once
    "baseline in metres": (_baseline_in_metres, [], 3, "the stereo depth is 0.0752 mm (median), nearer than the 20 "
                                                      "mm tracked: is the calibration's baseline (0.0045) in metres? "
                                                      "calibrations are in mm"),
    "all-zero masks": (_empty_masks, [], 3, "only 0.0 % of the frame's pixels are valid: are its masks empty "
                                            "(non-zero = tissue), or the frame dark or saturated?"),
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
    captured = capsys.readouterr()
    err = captured.err
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
    causes = [line for line in captured.out.splitlines() if line.startswith("likely cause: ")]
    assert causes == ([] if word is None else [f"likely cause: {word}"])       # said once, where there is one
    assert metrics.get("likely_cause") == word


# ------------------------------------------------------------------------------------------------
# a da Vinci rig: an OpenCV XML calibration (M_l M_r D_l D_r R T) made for 1920x1080 images, frames
# cropped to 1280x960 (here a fifth of both: 384x216 calibrated, 256x192 cropped at (128, 24))
CALIBRATED, CROP, OFFSET = (384, 216), (256, 192), (128, 24)


@pytest.fixture(scope="module")
def davinci(tmp_path_factory) -> tuple[Path, "RawStereoCalibration"]:
    """``left/`` and ``right/`` cropped from a raw synthetic rig (distorted, the right camera
    rotated by 1.7 degrees) rendered at :data:`CALIBRATED`, its ground truth, and its calibration."""
    import cv2

    from slam.synth import generate

    root = tmp_path_factory.mktemp("davinci")
    raw = generate(root / "raw", "rigid", frames=FRAMES, size=CALIBRATED, seed=0, raw=True, codec="ffv1")
    seq = root / "seq"
    (x0, y0), (w, h) = OFFSET, CROP
    video = cv2.VideoCapture(str(next(raw.glob("*.avi"))))
    for k in range(FRAMES):
        ok, both = video.read()
        assert ok
        for side, view in (("left", both[:CALIBRATED[1]]), ("right", both[CALIBRATED[1]:])):
            (seq / side).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(seq / side / f"{k:04d}.png"), view[y0:y0 + h, x0:x0 + w])
    video.release()
    shutil.copy(raw / "groundtruth.txt", seq / "groundtruth.txt")
    return seq, read_stereomis_ini(raw / "StereoCalibration.ini")


def davinci_xml(path: Path, calib, size=None, moved=(0.0, 0.0), R=None) -> Path:
    """``calib`` as the da Vinci's OpenCV XML: ``M_l M_r D_l D_r R T``, its principal points moved
    by ``-moved`` (px), ``width``/``height`` when ``size`` is given."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for name, K in (("M_l", calib.K1), ("M_r", calib.K2)):
        K = K.copy()
        K[:2, 2] -= moved
        fs.write(name, K)
    fs.write("D_l", calib.D1[None, :5])
    fs.write("D_r", calib.D2[None, :5])
    fs.write("R", calib.R if R is None else R)
    fs.write("T", calib.T.reshape(3, 1))
    if size is not None:
        fs.write("width", size[0])
        fs.write("height", size[1])
    fs.release()
    return path


def _not_orthonormal(calib, deviation: float):
    """``calib.R`` scaled so that ``max |R R^T - I|`` is ``deviation``."""
    return calib.R * np.sqrt(1.0 + deviation)


DAVINCI = {
    # name: (the XML's arguments, exit code, the one line's end or what the run reports)
    "calibrated size": (dict(size=CALIBRATED), 2,
                        "calibration for 384x216 images does not fit frames of 256x192 (neither equal nor an integer "
                        "multiple or fraction of them; frames cropped from the calibrated images need the calibration "
                        "of the crop: the crop's size, and each principal point less the crop's offset)"),
    "no size": (dict(), 2, "its principal point (191, 106) fits no calibration size for frames of 256x192"),
    "labelled with the crop's size": (dict(size=CROP), 2,
                                      "the first frame's views keep a vertical disparity of 1.4 px after "
                                      "rectification (median over 127 matches; a calibration of these frames leaves "
                                      "at most 1 px): the calibration does not fit them"),
    "principal point outside": (dict(size=CROP, moved=(-200.0, 0.0)), 2,
                                "the left principal point (389.9, 106.4) lies outside the 256x192 frames"),
    "R far from orthonormal": (dict(size=CROP, moved=OFFSET, R=0.05), 2,
                               "stereo rotation R is not a rotation matrix (max |R R^T - I| = 0.05, det 1.08; up "
                               "to 0.02 is taken for a rotation written with few digits)"),
    "the crop's calibration": (dict(size=CROP, moved=OFFSET), 0, None),
    "R 1.9e-3 from orthonormal": (dict(size=CROP, moved=OFFSET, R=1.9e-3), 0,
                                  "stereo rotation R is 1.9e-03 from orthonormal (max |R R^T - I|): taken as the "
                                  "nearest rotation"),
}


@pytest.mark.parametrize("name", list(DAVINCI))
def test_a_davinci_calibration_of_cropped_frames(davinci, tmp_path, capsys, name):
    """``--calibration`` beside ``left/ right/`` is the frames' calibration (frame folders), its
    OpenCV names read; a calibration that does not fit the crop is one line (its size, its principal
    point, the rectified views' vertical disparity, its rotation), never a run of flagged frames;
    the crop's calibration runs, a rotation written with few digits with a warning."""
    seq, calib = davinci
    kwargs, code, line = DAVINCI[name]
    kwargs = dict(kwargs)
    if "R" in kwargs:
        kwargs["R"] = _not_orthonormal(calib, kwargs["R"])
    xml = davinci_xml(tmp_path / "davinci.xml", calib, **kwargs)
    out = tmp_path / "out"
    assert main(["run", str(seq), "--calibration", str(xml), "--weights", "constant", "--out", str(out),
                 "--quiet"]) == code
    err = capsys.readouterr().err
    if code == 2:
        assert err == f"slam run: error: {xml}: {line}\n" or (err.startswith(f"slam run: error: {xml}: {line}")
                                                              and err.count("\n") == 1), err
        assert not out.exists()
        return
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "ok" and metrics["ate_rmse_mm"] < 0.5 and not metrics["flagged_frames"]
    assert rows(out / "trajectory.txt") == FRAMES
    warnings = [w for w in err.splitlines() if w]
    assert warnings == ([] if line is None else [f"WARNING slam: {xml}: {line}"])


@pytest.mark.parametrize("scale, warning", [
    (1000.0, "{data}/timestamps.txt: steps of 40 (median) read as milliseconds (25 fps); the trajectory's "
             "timestamps are in seconds"),
    (50.0, "{data}: the frames' timestamps step by 2 (median), not 1-1000 frames a second: the frames are taken at "
           "25 fps (the default; --fps to give the rate)")])
def test_timestamps_in_another_unit(sequence, tmp_path, capsys, scale, warning):
    """``timestamps.txt`` in milliseconds: read as such, said once, the rate read off them and the
    trajectory in seconds, which ``slam eval`` matches with the ground truth (in seconds); steps
    that fit no unit: the rate falls back, said once (it fell back without a word)."""
    data = copy_of(sequence, tmp_path)
    _frame_folders(data, scale)
    out = tmp_path / "out"
    assert main(["run", str(data), "--weights", "constant", "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert [line for line in err.splitlines() if "timestamps" in line] == [f"WARNING slam: {warning.format(data=data)}"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frame_rate"] == 25.0
    stamps, _ = read_tum(out / "trajectory.txt")
    gt_stamps, _ = read_tum(data / "groundtruth.txt")
    np.testing.assert_allclose(stamps, gt_stamps * (1.0 if scale == 1000.0 else scale), atol=1e-6)
    if scale == 1000.0:
        assert main(["eval", str(data / "groundtruth.txt"), str(out / "trajectory.txt"), "--quiet"]) == 0
        assert "ATE-RMSE" in capsys.readouterr().out


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


@pytest.mark.parametrize("which", ["estimate", "ground truth"])
def test_eval_refuses_repeated_timestamps(sequence, tmp_path, capsys, which):
    """A timestamp that repeats an earlier row's in either file is one line naming both rows (it
    was associated with the wrong pose: ATE 0.14 -> 2.11 mm), exit 2, nothing written."""
    gt = sequence / "groundtruth.txt"
    stamps, poses = read_tum(gt)
    doubled = tmp_path / "doubled.txt"
    write_tum(doubled, np.insert(stamps, 4, stamps[3]), np.insert(poses, 4, poses[7], axis=0))
    args = [str(gt), str(doubled)] if which == "estimate" else [str(doubled), str(gt)]
    report = tmp_path / "metrics.json"
    assert main(["eval", *args, "--json", str(report), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err == (f"slam eval: error: {doubled}:6: timestamp {stamps[3]:.9g} repeats line 5's (1 repeated timestamp; "
                   "a trajectory has one pose per time)\n")
    assert not report.exists()


def test_threads_beyond_the_cores_are_capped(sequence, tmp_path, capsys):
    """``threads=999`` on a machine of fewer cores: capped to them, said once (it ran 6.5x slower
    without a word)."""
    from slam.app.thread_use import available_cores

    cores = available_cores()
    out = tmp_path / "out"
    assert main(["run", str(sequence), "--weights", "constant", "--frames", "3", "--out", str(out), "--quiet",
                 "--set", "threads=999"]) == 0
    assert capsys.readouterr().err.splitlines() == [f"WARNING slam: threads=999, but this process may use {cores} "
                                                    f"cores: using {cores}"]
    pools = json.loads((out / "metrics.json").read_text())["thread_pools"]
    assert pools["opencv"] == cores and pools["torch"] <= cores


@pytest.fixture
def small_disk(tmp_path):
    """A folder on a 64 kB file system: a tmpfs mounted for the test where it may mount one, else
    a file size limit of 64 kB on this process (RLIMIT_FSIZE, its signal ignored: a write beyond
    it fails with EFBIG) while the test runs."""
    import resource
    import signal
    import subprocess

    folder = tmp_path / "small"
    folder.mkdir()
    try:
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(folder)],
                                 capture_output=True).returncode == 0
    except OSError:         # no mount command
        mounted = False
    if mounted:
        yield folder
        # (lazily: open3d keeps the files it failed to write open, deleted, until the process ends)
        subprocess.run(["umount", "--lazy", str(folder)], check=True)
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, hard))
    try:
        yield folder
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, handler)


def test_a_full_disk_during_the_outputs(sequence, small_disk, capfd):
    """The map, the mesh and the plot do not fit: each is named in the one error line (exit 2),
    none is left half written (nor its temporary file), metrics.json lists them and keeps the
    run's true status, the rows and the other outputs are there; open3d's writer prints nothing
    (it printed a line per element it could not write, and left a truncated map.ply)."""
    out = small_disk / "out"
    assert main(["run", str(sequence), "--weights", "constant", "--frames", "5", "--export-map", "--mesh",
                 "--out", str(out), "--quiet"]) == 2
    captured = capfd.readouterr()
    metrics = json.loads((out / "metrics.json").read_text())
    failed = metrics["output_errors"]
    assert set(failed) == {"map", "mesh", "plot"} and metrics["skipped_outputs"] == ["map", "mesh", "plot"]
    files = {"map": "map.ply", "mesh": "mesh.ply", "plot": "trajectory.png"}
    for name, why in failed.items():
        assert why.startswith(f"{out / files[name]}: ") and "\n" not in why
        assert not (out / files[name]).exists()
    assert captured.err == f"slam run: error: {'; '.join(failed.values())} (not written, no partial file left; " \
                           "the other outputs are, and metrics.json lists these under skipped_outputs)\n"
    assert metrics["status"] == "ok" and metrics["frames"] == 5 and rows(out / "trajectory.txt") == 5
    assert sorted(p.name for p in out.iterdir()) == ["config.yaml", "metrics.json", "run.log", "tracking.csv",
                                                     "trajectory.txt"]
    assert "skipped: map, mesh, plot" in captured.out


def test_a_full_disk_during_the_frames(sequence, tmp_path, capsys, monkeypatch):
    """A write of tracking.csv's that fails part way (as on a disk filling up): one line naming
    the file, exit 2; the rows written before are whole (the half row taken back), no metrics.json."""
    import errno
    import os

    import slam.io.row_file as row_file

    room = {"left": 700}           # the bytes tracking.csv still gets: its header and a few rows
    real_write = os.write

    def filling_write(fd, data):
        if not os.readlink(f"/proc/self/fd/{fd}").endswith("tracking.csv"):
            return real_write(fd, data)
        if room["left"] <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        done = real_write(fd, data[:room["left"]])
        room["left"] -= done
        return done

    monkeypatch.setattr(row_file.os, "write", filling_write)
    out = tmp_path / "out"
    assert main(["run", str(sequence), "--weights", "constant", "--out", str(out), "--quiet"]) == 2
    assert capsys.readouterr().err == f"slam run: error: {out / 'tracking.csv'}: No space left on device\n"
    text = (out / "tracking.csv").read_text()
    assert text.endswith("\n") and 1 < len(text.splitlines()) < FRAMES + 1 and len(text) <= 700
    assert rows(out / "trajectory.txt") == len(text.splitlines())      # the frame that failed wrote its pose
    assert not (out / "metrics.json").exists()


def test_a_run_log_that_cannot_be_written(sequence, tmp_path, capsys):
    """run.log on a device that is always full: the run goes on, the log is named in the one
    error line and listed in metrics.json (logging printed a traceback per record)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "run.log").symlink_to("/dev/full")
    assert main(["run", str(sequence), "--weights", "constant", "--frames", "3", "--out", str(out), "--quiet"]) == 2
    captured = capsys.readouterr()
    err = captured.err
    assert "skipped: log" in captured.out and "log=" not in captured.out.splitlines()[-1]
    assert err == f"slam run: error: {out / 'run.log'}: No space left on device (not written, no partial file left; " \
                  "the other outputs are, and metrics.json lists these under skipped_outputs)\n"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["skipped_outputs"] == ["log"] and list(metrics["output_errors"]) == ["log"]
    assert metrics["status"] == "ok" and rows(out / "trajectory.txt") == 3 and (out / "trajectory.png").is_file()


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
    from slam.app.status import MAX_FAILED_SHARE, MAX_FLAGGED_SHARE, is_result, run_status

    assert MAX_FAILED_SHARE == 0.5 == MAX_FLAGGED_SHARE
    assert run_status(10, 5) == "ok" and run_status(10, 6) == "not a result: 6 of 10 frames failed"
    assert run_status(0, 0) == "ok"
    assert run_status(10, 0, 5) == "ok" and run_status(10, 0, 6) == "untrusted: 6 of 10 frames flagged"
    assert run_status(10, 6, 4) == "not a result: 6 of 10 frames failed"
    assert is_result("ok") and is_result("untrusted: 6 of 10 frames flagged")
    assert not is_result("not a result: 6 of 10 frames failed")


def test_a_run_of_mostly_flagged_frames_is_untrusted(sequence, tmp_path, capsys):
    """Over half the frames flagged (here by a ``health.flag_mm`` no pose's spread meets): the
    status says so, the ATE stays, marked in the summary, ``slam compare`` names it in its table;
    the exit code stays 0 (flagged frames are results)."""
    out = tmp_path / "out"
    tight = ["--set", "health.flag_mm=0.001"]
    assert main(["run", str(sequence), "--weights", "constant", "--out", str(out), "--quiet", *tight]) == 0
    printed = capsys.readouterr().out.splitlines()
    metrics = json.loads((out / "metrics.json").read_text())
    flagged = len(metrics["flagged_frames"])
    assert flagged > FRAMES / 2 and metrics["status"] == f"untrusted: {flagged} of {FRAMES} frames flagged"
    assert metrics["ate_rmse_mm"] < 1.0 and "not_trusted" not in metrics and "likely_cause" not in metrics
    assert f"untrusted: {flagged} of {FRAMES} frames flagged: their poses are reported, not trusted (tracking.csv " \
           "says why)" in printed
    assert [line.startswith(f"ATE-RMSE {metrics['ate_rmse_mm']:.3f} mm (untrusted) | ") for line in printed].count(True) == 1
    cmp_ = tmp_path / "cmp"
    assert main(["compare", str(sequence), "--weights", "constant", "--frames", "4", "--out", str(cmp_), "--quiet",
                 *tight]) == 0
    rows_ = json.loads((cmp_ / "comparison.json").read_text())
    table = (cmp_ / "comparison.md").read_text()
    for mode, m in rows_.items():
        assert m["status"].startswith("untrusted: ") and f"| {mode} ({m['status']}) | 4 | {m['ate_rmse_mm']:.3f} |" in table
