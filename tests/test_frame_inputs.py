"""Frame folders and stereo video files as recordings circulate (docs/inputs.md): found by name,
paired, read at any bit depth, calibrated from any file the project reads, fitted to the frames'
size, timed, and tracked from the command."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from slam.io.datasets import open_dataset
from slam.io.datasets.config import DataConfig
from slam.errors import ConfigError, DataError

SIZE = (160, 128)


@pytest.fixture(scope="module")
def rigid(tmp_path_factory) -> Path:
    """A rectified synthetic sequence (StereoMIS layout): 6 frames, ground truth at 25 fps."""
    from slam.synth import generate

    return generate(tmp_path_factory.mktemp("src") / "rigid", "rigid", frames=6, size=SIZE, seed=3, progress=False)


@pytest.fixture(scope="module")
def raw(tmp_path_factory) -> Path:
    """An unrectified synthetic sequence with lens distortion: one top-bottom mp4 and its .ini."""
    from slam.synth import generate

    return generate(tmp_path_factory.mktemp("raw") / "raw", "rigid", frames=6, size=SIZE, seed=3, raw=True,
                    progress=False)


def _rectified_json(ds, path: Path, scale: float = 1.0, size: bool = False) -> None:
    """A rectified calibration (no distortion, no rotation) in the project's JSON, optionally made at
    ``scale`` times the frames' size."""
    K = ds.camera.K.copy()
    K[:2, :2] *= scale
    K[:2, 2] = (K[:2, 2] + 0.5) * scale - 0.5
    data = {"left": {"K": K.tolist(), "D": []}, "right": {"K": K.tolist()}, "R": np.eye(3).tolist(),
            "T": [-ds.camera.baseline_mm, 0.0, 0.0]}
    if size:
        data["image_size"] = [int(SIZE[0] * scale), int(SIZE[1] * scale)]
    path.write_text(json.dumps(data))


def _write_folders(ds, out: Path, names=("left_image", "right_image"), stems=("frame_{:05d}", "frame_{:05d}"),
                   ext=".png", depth16: int | None = None) -> Path:
    out.mkdir(parents=True)
    for side, name, stem in zip((0, 1), names, stems):
        (out / name).mkdir()
        for k in range(len(ds)):
            f = ds.frame(k)
            img = cv2.cvtColor(f.left if side == 0 else f.right, cv2.COLOR_RGB2BGR)
            if depth16:
                img = np.rint(img.astype(np.float64) * ((1 << depth16) - 1) / 255).astype(np.uint16)
            assert cv2.imwrite(str(out / name / (stem.format(k) + ext)), img)
    return out


@pytest.mark.parametrize("names, stems", [
    (("left_image", "right_image"), ("frame_{:05d}", "frame_{:05d}")),
    (("Left", "Right"), ("Left_{:04d}", "Right_{:04d}")),
    (("image01", "image02"), ("{:06d}", "{:06d}")),
    (("IMAGE_0", "IMAGE_1"), ("{:06d}l", "{:06d}r")),
    (("l", "r"), ("img{}", "img{}")),
])
def test_frame_folders_are_found_by_name_and_paired(rigid, tmp_path, names, stems):
    src = open_dataset(rigid)
    out = _write_folders(src, tmp_path / "seq", names, stems)
    _rectified_json(src, out / "calibration.json")
    ds = open_dataset(out)
    assert ds.layout == "frames" and len(ds) == 6
    assert (ds.camera.width, ds.camera.height) == SIZE
    np.testing.assert_allclose(ds.camera.K, src.camera.K)
    assert ds.camera.baseline_mm == pytest.approx(src.camera.baseline_mm)
    for k in (0, 5):
        assert np.array_equal(ds.frame(k).left, src.frame(k).left)
        assert np.array_equal(ds.frame(k).right, src.frame(k).right)


@pytest.mark.parametrize("ext, depth16, tol", [(".jpg", None, 12), (".tif", None, 0), (".tiff", 12, 1), (".png", 16, 1),
                                               (".png", 10, 1)])
def test_image_kinds_and_bit_depths(rigid, tmp_path, ext, depth16, tol):
    """JPEG, TIFF and PNG, 8 or 16 bit: 16-bit frames are scaled by the data's real bit depth
    (12-bit values in 16-bit files come back at full brightness, not a sixteenth of it)."""
    src = open_dataset(rigid)
    out = _write_folders(src, tmp_path / "seq", ext=ext, depth16=depth16)
    _rectified_json(src, out / "calibration.json")
    ds = open_dataset(out)
    assert ds.bit_depth == (depth16 or 8)
    diff = np.abs(ds.frame(2).left.astype(int) - src.frame(2).left.astype(int))
    assert diff.max() <= tol if ext != ".jpg" else diff.mean() < 3


def test_every_calibration_kind_and_one_made_at_twice_the_size(rigid, tmp_path, caplog):
    """StereoMIS .ini, SCARED yaml (without an image size), plain yaml and JSON give the same
    camera; a calibration made at twice the frames' size is scaled down (and says so), with or
    without the size in the file; one that fits no integer factor is a one-line error."""
    import logging

    from slam.synth.scared_layout import _write_calibration

    src = open_dataset(rigid)
    out = _write_folders(src, tmp_path / "seq")
    calib = src.processor
    kinds = {}
    shutil.copy(rigid / "StereoCalibration.ini", tmp_path / "c.ini")
    kinds["ini"] = tmp_path / "c.ini"
    from slam.io.calibration import read_stereomis_ini

    raw = read_stereomis_ini(rigid / "StereoCalibration.ini")
    fs = cv2.FileStorage(str(tmp_path / "c.yaml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (("M1", raw.K1), ("D1", raw.D1.reshape(1, -1)), ("M2", raw.K2), ("D2", raw.D2.reshape(1, -1)),
                       ("R", raw.R), ("T", raw.T.reshape(3, 1))):
        fs.write(key, value)
    fs.release()
    kinds["scared yaml"] = tmp_path / "c.yaml"
    cam = src.camera
    (tmp_path / "plain.yaml").write_text(f"fx: {cam.fx}\nfy: {cam.fy}\ncx: {cam.K[0, 2]}\ncy: {cam.K[1, 2]}\n"
                                         f"baseline_mm: {cam.baseline_mm}\nwidth: {cam.width}\nheight: {cam.height}\n")
    kinds["plain yaml"] = tmp_path / "plain.yaml"
    _rectified_json(src, tmp_path / "c.json")
    kinds["json"] = tmp_path / "c.json"
    _rectified_json(src, tmp_path / "twice.json", scale=2.0)
    kinds["json at twice the size"] = tmp_path / "twice.json"
    _rectified_json(src, tmp_path / "twice_sized.json", scale=2.0, size=True)
    kinds["json at twice the size, sized"] = tmp_path / "twice_sized.json"
    for name, path in kinds.items():
        with caplog.at_level(logging.INFO, logger="slam"):
            caplog.clear()
            ds = open_dataset(out, DataConfig(calibration=str(path)))
        np.testing.assert_allclose(ds.camera.K, cam.K, atol=1e-6, err_msg=name)
        assert ds.camera.baseline_mm == pytest.approx(cam.baseline_mm), name
        assert ("scaled by 0.5" in caplog.text) == ("twice" in name), name
        assert np.array_equal(ds.frame(1).left, src.frame(1).left), name
    assert calib is not None
    _rectified_json(src, tmp_path / "odd.json", scale=1.6)
    with pytest.raises(DataError, match=r"odd.json: its principal point .* fits no calibration size for frames of 160x128"):
        open_dataset(out, DataConfig(calibration=str(tmp_path / "odd.json")))
    _rectified_json(src, tmp_path / "odd_sized.json", scale=1.5, size=True)
    with pytest.raises(DataError, match=r"calibration for 240x192 images does not fit frames of 160x128"):
        open_dataset(out, DataConfig(calibration=str(tmp_path / "odd_sized.json")))


def test_unrectified_frames_and_the_video_file_match_the_raw_layout(raw, tmp_path):
    """Frames taken out of an unrectified video into folders, with the video's .ini beside them, are
    rectified (distortion in the calibration) exactly as the StereoMIS raw layout rectifies the
    video; the video given as a file with --calibration, and the same frames side by side, too."""
    from slam.io.datasets.video import StackedStereoVideo

    ref = open_dataset(raw)
    assert ref.layout == "stereomis_raw"
    video = StackedStereoVideo(next(raw.glob("*.mp4")))
    out = tmp_path / "frames"
    (out / "left").mkdir(parents=True)
    (out / "right").mkdir()
    sbs = cv2.VideoWriter(str(tmp_path / "sbs.avi"), cv2.VideoWriter_fourcc(*"FFV1"), 25.0, (2 * SIZE[0], SIZE[1]))
    for k in range(len(video)):
        left, right = video.read(k)
        cv2.imwrite(str(out / "left" / f"{k:04d}.png"), cv2.cvtColor(left, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(out / "right" / f"{k:04d}.png"), cv2.cvtColor(right, cv2.COLOR_RGB2BGR))
        sbs.write(cv2.cvtColor(np.hstack([left, right]), cv2.COLOR_RGB2BGR))
    sbs.release()
    video.close()
    shutil.copy(raw / "StereoCalibration.ini", out / "StereoCalibration.ini")
    frames = open_dataset(out)
    assert frames.layout == "frames" and len(frames) == len(ref)
    ini = str(raw / "StereoCalibration.ini")
    as_file = open_dataset(next(raw.glob("*.mp4")), DataConfig(calibration=ini))
    side = open_dataset(tmp_path / "sbs.avi", DataConfig(calibration=ini))
    assert as_file.layout == side.layout == "video" and side.video.layout == "side-by-side"
    assert as_file.video.layout == "top-bottom"
    for ds in (frames, as_file, side):
        np.testing.assert_allclose(ds.camera.K, ref.camera.K)
        np.testing.assert_allclose(ds.R1, ref.R1)
        for k in (0, 5):
            assert np.array_equal(ds.frame(k).left, ref.frame(k).left)
            assert np.array_equal(ds.frame(k).right, ref.frame(k).right)
    assert not np.allclose(ref.R1, np.eye(3))          # it really rectifies


def test_bad_frame_folders_give_one_line(rigid, tmp_path):
    src = open_dataset(rigid)
    out = _write_folders(src, tmp_path / "seq", stems=("a{:02d}", "b{:02d}"))
    with pytest.raises(DataError, match=r"seq: no calibration file"):
        open_dataset(out)
    _rectified_json(src, out / "calibration.json")
    (out / "right_image" / "b05.png").unlink()
    with pytest.raises(DataError, match=r"left_image has 6 images but .*right_image has 5, and their names do not pair"):
        open_dataset(out)
    (out / "right_image" / "b04.png").rename(out / "right_image" / "a04.png")
    with pytest.raises(DataError, match=r"left_image and .*right_image: the frames do not pair"):
        open_dataset(out)
    (out / "image01").mkdir()
    (out / "image02").mkdir()
    with pytest.raises(DataError, match="several left/right folder pairs"):
        open_dataset(out)
    with pytest.raises(ConfigError, match="applies to frame folders and video files"):
        open_dataset(rigid, DataConfig(calibration=str(out / "calibration.json")))


def test_masks_pair_like_the_frames(rigid, tmp_path):
    src = open_dataset(rigid)
    out = _write_folders(src, tmp_path / "seq", stems=("Left_{:03d}", "Right_{:03d}"))
    _rectified_json(src, out / "calibration.json")
    (out / "masks").mkdir()
    mask = np.full(SIZE[::-1], 255, np.uint8)
    mask[:, :40] = 0
    cv2.imwrite(str(out / "masks" / "Mask_003.png"), mask)    # only frame 3 has one
    ds = open_dataset(out)
    assert not ds.frame(3).mask[:, :40].any() and ds.frame(2).mask[:, :40].any()


def test_timestamps_and_ground_truth_at_another_rate(rigid, tmp_path):
    """Every second frame with its timestamps.txt: ground truth at 25 fps is associated by time,
    never by index; the view's frame rate halves. Without timestamps, --fps gives them."""
    src = open_dataset(rigid)
    out = tmp_path / "seq"
    sub = src.select("0::2")
    _write_folders(sub, out)
    _rectified_json(src, out / "calibration.json")
    shutil.copy(rigid / "groundtruth.txt", out / "groundtruth.txt")
    (out / "timestamps.txt").write_text("\n".join(f"{t:.6f}" for t in sub.timestamps) + "\n")
    ds = open_dataset(out)
    assert len(ds) == 3 and ds.fps == pytest.approx(12.5)
    np.testing.assert_allclose(ds.gt_poses, sub.gt_poses)
    (out / "timestamps.txt").unlink()
    by_rate = open_dataset(out, DataConfig(fps=12.5))
    np.testing.assert_allclose(by_rate.gt_poses, sub.gt_poses)
    (out / "timestamps.txt").write_text("1000\n1000.08\n1000.16\n")       # another clock than the ground truth's
    with pytest.raises(DataError, match="groundtruth.txt: no ground-truth pose within half a frame period"):
        open_dataset(out)
    (out / "timestamps.txt").write_text("0\n0.08\n")
    with pytest.raises(DataError, match="timestamps.txt: 2 timestamps for 3 frames"):
        open_dataset(out)


def test_frame_folder_and_video_file_from_the_command(raw, tmp_path, capsys):
    """`slam run VIDEO --calibration FILE` and `slam inspect` on it: poses recovered, the rectified
    pair written, no vertical disparity left."""
    from slam.app.cli import main

    video = next(raw.glob("*.mp4"))
    ini = raw / "StereoCalibration.ini"
    shutil.copy(raw / "groundtruth.txt", tmp_path / "groundtruth.txt")
    moved = tmp_path / video.name
    shutil.copy(video, moved)
    assert main(["run", str(moved), "--calibration", str(ini), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["frames"] == 6 and m["failed_frames"] == [] and m["ate_rmse_mm"] < 0.5
    capsys.readouterr()
    assert main(["inspect", str(moved), "--calibration", str(ini), "--out", str(tmp_path / "insp")]) == 0
    text = capsys.readouterr().out
    assert "layout" in text and "video" in text and "rectified here (full)" in text
    assert (tmp_path / "insp" / "rectified_pair.png").is_file()
    assert "warning" not in text
    assert main(["run", str(tmp_path / "none.mp4"), "--calibration", str(ini)]) == 2
    assert "none.mp4: no such file" in capsys.readouterr().err


def test_thresholds_follow_the_frame_rate(rigid, tmp_path):
    """Per-frame motion thresholds are given at 25 fps: at 5 fps they allow five times the motion
    per frame, the keyframe gap in frames shrinks (the map's window, in observations, does not); at
    25 fps the config is untouched. A run on every fifth
    frame records its rate."""
    from slam.config import at_frame_rate, load_config
    from slam.app.pipeline import Pipeline

    cfg = load_config(None, [])
    assert at_frame_rate(cfg, 25.0) is cfg
    slow = at_frame_rate(cfg, 5.0)
    assert slow.tracking.keyframe_still_mm == pytest.approx(5 * cfg.tracking.keyframe_still_mm)
    assert slow.depth.temporal_still_mm == pytest.approx(5 * cfg.depth.temporal_still_mm)
    assert slow.solver.max_translation_mm == pytest.approx(5 * cfg.solver.max_translation_mm)
    assert slow.depth.temporal_gate_mm == pytest.approx(5 * cfg.depth.temporal_gate_mm)
    assert slow.tracking.keyframe_gap == 1 and slow.map.unstable_window == cfg.map.unstable_window
    fast = at_frame_rate(cfg, 50.0)
    assert fast.depth.temporal_gate_mm == cfg.depth.temporal_gate_mm      # never below the stereo noise's
    assert fast.tracking.keyframe_gap == 10
    assert cfg.tracking.keyframe_gap == 5       # the original is untouched
    run_cfg = load_config(None, ["weights.mode=constant"])
    ds = open_dataset(rigid, run_cfg.data).select("::2")
    result = Pipeline(run_cfg, ds, tmp_path / "run").run(progress=False)
    assert result.metrics["frame_rate"] == pytest.approx(12.5) and result.metrics["failed_frames"] == []


def test_inspect_warns_about_swapped_and_prerectified_views(rigid, raw, tmp_path, capsys):
    """Views stored rectified but described by a distorted calibration are row-aligned already;
    left and right swapped give negative disparities."""
    from slam.config import load_config
    from slam.app.inspect import inspect

    src = open_dataset(rigid)
    out = _write_folders(src, tmp_path / "swapped", names=("right", "left"))     # the folders' names swapped
    _rectified_json(src, out / "calibration.json")
    report = inspect(out, load_config(None, []), tmp_path / "i1")
    assert any("swapped" in w for w in report["warnings"])
    out = _write_folders(src, tmp_path / "pre", names=("left", "right"))
    shutil.copy(raw / "StereoCalibration.ini", out / "StereoCalibration.ini")    # a raw rig's calibration
    report = inspect(out, load_config(None, []), tmp_path / "i2")
    assert any("row-aligned already" in w for w in report["warnings"])
    assert "rectified here" in report["rectified"]
