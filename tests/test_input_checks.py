"""The input layer's checks (issue 48): a calibration made for another image size is refused when
the sequence opens, in every layout and calibration format, and one made at an exact integer
multiple of the frames' size is scaled. Sequences of 3 frames at 160x128 (``synth_dir``), the
calibrations written here."""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from slam.io.calibration import RawStereoCalibration, read_stereomis_ini
from slam.io.datasets import open_dataset
from slam.io.datasets.config import DataConfig
from slam.errors import DataError
from tests.test_calibration import write_ini, write_scared_yaml

SIZE = (160, 128)
FORMATS = ("ini", "scared yaml", "opencv yaml", "plain yaml", "json")
#: the calibration file each format has in a sequence folder that names it itself
FILE_NAMES = {"ini": "StereoCalibration.ini", "scared yaml": "endoscope_calibration.yaml",
              "opencv yaml": "endoscope_calibration.yaml", "plain yaml": "calibration.yaml", "json": "calibration.json"}
#: (layout, calibration format): each layout with every format it reads
LAYOUT_FORMATS = ([("stereomis", "ini"), ("stereomis_raw", "ini"), ("scared", "scared yaml"), ("scared", "opencv yaml"),
                   ("plain", "plain yaml")] + [("frames", f) for f in FORMATS] + [("video", f) for f in FORMATS])


def native(**kw) -> DataConfig:
    """The frames at their own size (DataConfig's default resizes them)."""
    return DataConfig(width=0, height=0, **kw)


def calibration_at(calib: RawStereoCalibration, size: tuple[int, int]) -> RawStereoCalibration:
    """``calib`` (made for ``SIZE``) as made for images of ``size``: intrinsics resampled with the
    pixel-centre convention (``c' + 0.5 = s (c + 0.5)``)."""
    sx, sy = size[0] / SIZE[0], size[1] / SIZE[1]
    Ks = []
    for K in (calib.K1, calib.K2):
        K = K.copy()
        K[0, 0], K[1, 1] = K[0, 0] * sx, K[1, 1] * sy
        K[0, 2], K[1, 2] = (K[0, 2] + 0.5) * sx - 0.5, (K[1, 2] + 0.5) * sy - 0.5
        Ks.append(K)
    return RawStereoCalibration(Ks[0], calib.D1, Ks[1], calib.D2, calib.R, calib.T, size)


def write_calibration(fmt: str, path: Path, calib: RawStereoCalibration) -> Path:
    """``calib`` written to ``path`` in format ``fmt`` (the SCARED yaml without its image size,
    the plain yaml as the rectified camera of the left view)."""
    c = calib
    if fmt == "ini":
        return write_ini(path, c.K1, c.D1, c.K2, c.D2, c.R, c.T, c.image_size)
    if fmt in ("scared yaml", "opencv yaml"):
        return write_scared_yaml(path, c.K1, c.D1, c.K2, c.D2, c.R, c.T,
                                 size=c.image_size if fmt == "opencv yaml" else None)
    if fmt == "plain yaml":
        fx, fy, cx, cy = (float(v) for v in (c.K1[0, 0], c.K1[1, 1], c.K1[0, 2], c.K1[1, 2]))
        path.write_text(f"fx: {fx!r}\nfy: {fy!r}\ncx: {cx!r}\ncy: {cy!r}\nbaseline_mm: {abs(float(c.T[0]))!r}\n"
                        f"width: {c.image_size[0]}\nheight: {c.image_size[1]}\n")
        return path
    data = {"left": {"K": c.K1.tolist(), "D": c.D1.tolist()}, "right": {"K": c.K2.tolist(), "D": c.D2.tolist()},
            "R": c.R.tolist(), "T": c.T.tolist(), "image_size": list(c.image_size)}
    path.write_text(json.dumps(data))
    return path


def copy_pngs(src: Path, left_dir: Path, right_dir: Path) -> None:
    """The StereoMIS frames of ``src`` into two folders, named by frame number."""
    left_dir.mkdir(parents=True)
    right_dir.mkdir(parents=True)
    for png in sorted((src / "video_frames").glob("*.png")):
        side = left_dir if png.stem.endswith("l") else right_dir
        shutil.copy(png, side / f"{png.stem[:-1]}.png")


def make_sequence(layout: str, fmt: str, root: Path, rigid: Path, raw: Path, size: tuple[int, int]
                  ) -> tuple[Path, DataConfig, Path]:
    """A ``layout`` sequence in ``root`` whose calibration (format ``fmt``) was made for images of
    ``size``; returns what to open, the config to open it with and the calibration file."""
    src = raw if layout in ("stereomis_raw", "scared", "video") else rigid
    calib = calibration_at(read_stereomis_ini(src / "StereoCalibration.ini"), size)
    video = next(raw.glob("*.mp4"))
    root.mkdir(parents=True)
    config = native()
    data = root
    if layout == "stereomis":
        shutil.copytree(rigid / "video_frames", root / "video_frames")
    elif layout == "stereomis_raw":
        shutil.copy(video, root / video.name)
    elif layout == "scared":
        (root / "data").mkdir()
        shutil.copy(video, root / "data" / "rgb.mp4")
    elif layout == "plain":
        copy_pngs(rigid, root / "left", root / "right")
    elif layout == "frames":
        copy_pngs(rigid, root / "left_image", root / "right_image")
    else:                                       # the video given as a file, its calibration named
        data = root / video.name
        shutil.copy(video, data)
    if layout == "video":
        calib_path = write_calibration(fmt, root / ("rig" + Path(FILE_NAMES[fmt]).suffix), calib)
        config = native(calibration=str(calib_path))
    else:
        calib_path = write_calibration(fmt, root / FILE_NAMES[fmt], calib)
    return data, config, calib_path


@pytest.fixture(scope="module")
def sources(synth_dir) -> tuple[Path, Path]:
    """A rectified sequence (StereoMIS layout) and a raw one (one top-bottom mp4), 3 frames each."""
    return synth_dir("rigid", 3, SIZE, seed=3), synth_dir("rigid", 3, SIZE, seed=3, raw=True)


@pytest.mark.parametrize("layout, fmt", LAYOUT_FORMATS)
def test_a_calibration_at_twice_the_size_is_scaled(sources, tmp_path, caplog, layout, fmt):
    """Made at 2x the frames' size: the intrinsics are halved (and the log says so), the camera is
    the one of the calibration made for the frames."""
    rigid, raw = sources
    # (the raw video taken as rectified by a plain calibration keeps 1.1 px of vertical disparity,
    # which opening refuses: test_cli_contract's da Vinci case; here only the sizes are at stake)
    check_rows = (layout, fmt) != ("video", "plain yaml")
    data, config, _ = make_sequence(layout, fmt, tmp_path / "at1", rigid, raw, SIZE)
    ref = open_dataset(data, config, check_rows=check_rows)
    assert ref.layout == layout
    data, config, calib_path = make_sequence(layout, fmt, tmp_path / "at2", rigid, raw, (2 * SIZE[0], 2 * SIZE[1]))
    with caplog.at_level(logging.INFO, logger="slam"):
        ds = open_dataset(data, config, check_rows=check_rows)
    assert ds.layout == layout
    np.testing.assert_allclose(ds.camera.K, ref.camera.K, atol=1e-6)
    assert ds.camera.baseline_mm == pytest.approx(ref.camera.baseline_mm)
    assert f"{calib_path}: calibration made at 2x the frames' size: intrinsics scaled by 0.5" in caplog.text
    assert ds.frame(0).left.shape == (SIZE[1], SIZE[0], 3)
    ref.close()
    ds.close()


@pytest.mark.parametrize("size", [(240, 192), (1000, 1000)], ids=["1.5x", "1000x1000"])
@pytest.mark.parametrize("layout, fmt", LAYOUT_FORMATS)
def test_a_calibration_for_another_size_is_refused_on_opening(sources, tmp_path, layout, fmt, size):
    """Neither the frames' size nor an integer multiple of it: a one-line DataError naming the
    calibration file when the sequence opens, before any frame is tracked."""
    rigid, raw = sources
    data, config, calib_path = make_sequence(layout, fmt, tmp_path / "seq", rigid, raw, size)
    with pytest.raises(DataError) as err:
        open_dataset(data, config)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{calib_path}: ")
    assert "does not fit" in message or "fits no calibration size" in message


def test_the_issue_s_run_stops_before_the_first_frame(sources, tmp_path, capsys):
    """``slam run`` on a StereoMIS folder whose .ini says 1000x1000: exit 2 with one line, where it
    used to track, fail every frame and exit 0."""
    from slam.app.cli import main

    rigid, _ = sources
    seq = tmp_path / "seq"
    shutil.copytree(rigid, seq)
    ini = seq / "StereoCalibration.ini"
    ini.write_text("\n".join("res_x = 1000" if line.startswith("res_x") else "res_y = 1000" if line.startswith("res_y")
                             else line for line in ini.read_text().splitlines()) + "\n")
    assert main(["run", str(seq), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"slam run: error: {ini}: calibration for 1000x1000 images does not fit frames of 160x128 " \
                  "(neither equal nor an integer multiple or fraction of them; frames cropped from the calibrated " \
                  "images need the calibration of the crop: the crop's size, and each principal point less the " \
                  "crop's offset)"


@pytest.mark.parametrize("layout", ["stereomis", "plain"])
def test_the_frame_size_comes_from_the_first_readable_frame(sources, tmp_path, layout):
    """An unreadable first PNG: the size comes from the next readable one (a calibration that does
    not fit is still refused); the sequence opens and its bad frames fail one by one when read, as
    they do when none of the first frames reads."""
    rigid, raw = sources
    data, config, _ = make_sequence(layout, "ini" if layout == "stereomis" else "plain yaml", tmp_path / "seq",
                                    rigid, raw, SIZE)
    name = "video_frames/{:06d}l.png" if layout == "stereomis" else "left/{:06d}.png"
    (data / name.format(0)).write_bytes(b"not a png")
    ds = open_dataset(data, config)
    with pytest.raises(DataError, match="cannot read image"):
        ds.frame(0)
    assert ds.frame(1).left.shape == (SIZE[1], SIZE[0], 3)
    for k in (1, 2):
        (data / name.format(k)).write_bytes(b"")
    assert open_dataset(data, config).num_frames_total == 3        # none reads: opens all the same
    bad, _, calib_path = make_sequence(layout, "ini" if layout == "stereomis" else "plain yaml", tmp_path / "bad",
                                       rigid, raw, (1000, 1000))
    (bad / name.format(0)).write_bytes(b"not a png")
    with pytest.raises(DataError, match=f"{calib_path}: calibration for 1000x1000 images does not fit"):
        open_dataset(bad, config)


@pytest.mark.parametrize("layout, fmt", LAYOUT_FORMATS)
def test_an_empty_calibration_file_says_so_in_every_layout(sources, tmp_path, layout, fmt):
    rigid, raw = sources
    data, config, calib_path = make_sequence(layout, fmt, tmp_path / "seq", rigid, raw, SIZE)
    calib_path.write_bytes(b"")
    with pytest.raises(DataError) as err:
        open_dataset(data, config)
    assert str(err.value) == f"{calib_path}: empty calibration file"


def calibration_warnings(caplog) -> list[str]:
    """The warnings logged since the last call but the frame rate's (these frames have no timestamps)."""
    lines = [r.getMessage() for r in caplog.records if r.name == "slam" and r.levelno >= logging.WARNING
             and "no timestamps" not in r.getMessage()]
    caplog.clear()
    return lines


def test_a_lone_calibration_candidate_is_taken_and_named(sources, tmp_path, caplog):
    """A video (folder, or file) or frame folders without --calibration and without a known
    calibration name take the only .ini/.json/.yaml beside them, and one warning says which; a
    known name or --calibration take theirs silently."""
    rigid, raw = sources
    caplog.set_level(logging.INFO, logger="slam")
    calib = read_stereomis_ini(raw / "StereoCalibration.ini")
    video = next(raw.glob("*.mp4"))
    folder = tmp_path / "video"
    folder.mkdir()
    shutil.copy(video, folder / video.name)
    rig = write_calibration("json", folder / "rig.json", calib)
    expected = f"using calibration {rig} (the only calibration file beside the video; --calibration FILE to choose)"
    for data in (folder, folder / video.name):
        ds = open_dataset(data, native())
        assert ds.layout == "video" and ds.calibration_path == rig       # an mp4 without its .ini: not StereoMIS raw
        assert calibration_warnings(caplog) == [expected]
    open_dataset(folder / video.name, native(calibration=str(rig)))
    assert calibration_warnings(caplog) == []
    rig.rename(folder / "calibration.json")
    open_dataset(folder, native())
    assert calibration_warnings(caplog) == []
    frames = tmp_path / "frames"
    copy_pngs(rigid, frames / "left", frames / "right")
    cam = write_calibration("plain yaml", frames / "camera.yaml", calibration_at(read_stereomis_ini(
        rigid / "StereoCalibration.ini"), SIZE))
    ds = open_dataset(frames, native())           # left/ right/ without calibration.yaml: not a plain folder
    assert ds.layout == "frames" and ds.calibration_path == cam
    assert calibration_warnings(caplog) == [f"using calibration {cam} (the only calibration file beside the frames; "
                                            "--calibration FILE to choose)"]


def test_a_lone_file_that_is_no_calibration_is_an_error_suggesting_the_option(sources, tmp_path, capsys):
    rigid, raw = sources
    video = next(raw.glob("*.mp4"))
    folder = tmp_path / "video"
    folder.mkdir()
    shutil.copy(video, folder / video.name)
    meta = folder / "metadata.json"
    meta.write_text(json.dumps({"device": "endoscope", "fps": 25}))
    expected = (f"{meta}: not a calibration file (missing 'R'); it was taken as the only .ini/.json/.yaml/.yml/.xml file "
                "beside the video: name the calibration with --calibration FILE")
    for data in (folder, folder / video.name):
        with pytest.raises(DataError) as err:
            open_dataset(data, native())
        assert str(err.value) == expected
    from slam.app.cli import main

    assert main(["inspect", str(folder / video.name), "--out", str(tmp_path / "insp")]) == 2
    assert capsys.readouterr().err.strip() == f"slam inspect: error: {expected}"
    frames = tmp_path / "frames"
    copy_pngs(rigid, frames / "left_image", frames / "right_image")
    (frames / "notes.yaml").write_text("operator: someone\n")
    with pytest.raises(DataError, match=r"notes.yaml: not a calibration file \(missing key 'fx'\); .* beside the "
                                        "frames: name the calibration with --calibration FILE"):
        open_dataset(frames, native())


@pytest.mark.parametrize("size, expected", [((0, 0), "taken as rectified, not resized"),
                                            ((80, 64), "taken as rectified, resized from 160x128")])
def test_inspect_says_whether_rectified_frames_were_resized(sources, tmp_path, capsys, size, expected):
    """It said "resized only" for frames it did not resize."""
    from slam.config import load_config
    from slam.app.inspect import inspect

    rigid, _ = sources
    config = load_config(None, [f"data.width={size[0]}", f"data.height={size[1]}"])
    report = inspect(rigid, config, tmp_path / "insp")
    assert report["rectified"] == expected
    assert report["output_size"] == (f"{size[0]}x{size[1]}" if size[0] else "160x128")
    printed = [line.split(None, 1) for line in capsys.readouterr().out.splitlines()]
    assert ["rectified", expected] in printed


def test_the_likely_cause_of_views_that_give_no_depth(sources):
    """What ``slam run`` says once when its frames fail, read off one frame: masks that leave
    nothing, left and right swapped, views of different times, a baseline in metres, nothing."""
    from slam.io.stereo_check import likely_cause

    rigid, _ = sources
    ds = open_dataset(rigid, native())
    first, other = ds.frame(0), ds.frame(2)
    cam, near_far = ds.camera, (20.0, 250.0)
    valid = np.ones(first.mask.shape, bool)
    assert likely_cause(first.left, first.right, valid, cam.fx, cam.baseline_mm, near_far) == ""
    assert likely_cause(first.left, first.right, ~valid, cam.fx, cam.baseline_mm, near_far).startswith(
        "only 0.0 % of the frame's pixels are valid: are its masks empty")
    assert likely_cause(first.right, first.left, valid, cam.fx, cam.baseline_mm, near_far).endswith(
        "of the stereo matches have a negative disparity: are the left and right views swapped?")
    assert likely_cause(first.left, other.right, valid, cam.fx, cam.baseline_mm, near_far).endswith(
        "px apart vertically (median): are the views mispaired (frames of different times), or the calibration "
        "not theirs?")
    assert likely_cause(first.left, first.right, valid, cam.fx, cam.baseline_mm / 1000, near_far).endswith(
        f"nearer than the 20 mm tracked: is the calibration's baseline ({cam.baseline_mm / 1000:.3g}) in metres? "
        "calibrations are in mm")
    assert "farther than the 250 mm tracked" in likely_cause(first.left, first.right, valid, cam.fx,
                                                             cam.baseline_mm * 1000, near_far)
