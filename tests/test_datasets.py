"""Dataset readers: layouts, selection, masks and bad input (all data written by the tests)."""
from __future__ import annotations

import io
import json
import logging
import tarfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.io.datasets import DataConfig, StereoFrame, detect_layout, open_dataset, parse_frames, specular_mask
from slam.io.datasets.masks import combine_masks
from slam.errors import ConfigError, DataError
from slam.io.tum import write_tum

W, H = 64, 48
K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])
BASELINE = 4.0


def native(**kw) -> DataConfig:
    """Config keeping the native size (DataConfig's default resizes to 640x512)."""
    kw.setdefault("width", 0)
    kw.setdefault("height", 0)
    kw.setdefault("specular_threshold", 1.01)  # off unless a test wants it
    return DataConfig(**kw)


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.2).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(n, 3)) * 20.0
    return poses


def write_ini(path: Path, K1=K, K2=K, D1=None, D2=None, R=None, T=(-BASELINE, 0.0, 0.0), size=(W, H)) -> None:
    D1 = np.zeros(8) if D1 is None else np.r_[D1, np.zeros(8 - len(D1))]
    D2 = np.zeros(8) if D2 is None else np.r_[D2, np.zeros(8 - len(D2))]
    R = np.eye(3) if R is None else R
    lines = []
    for name, Kc, Dc in (("StereoLeft", K1, D1), ("StereoRight", K2, D2)):
        lines += [f"[{name}]", f"res_x={size[0]}", f"res_y={size[1]}", f"fc_x={Kc[0, 0]}", f"fc_y={Kc[1, 1]}",
                  f"cc_x={Kc[0, 2]}", f"cc_y={Kc[1, 2]}"] + [f"kc_{i}={float(d)}" for i, d in enumerate(Dc)]
    lines += [f"T_{i}={float(t)}" for i, t in enumerate(T)] + [f"R_{i}={float(r)}" for i, r in enumerate(np.ravel(R))]
    path.write_text("\n".join(lines) + "\n")


def frame_images(i: int) -> tuple[np.ndarray, np.ndarray]:
    """Distinct RGB views of frame i (flat grey levels, robust to video compression)."""
    left = np.full((H, W, 3), 20 + 20 * i, np.uint8)
    left[:, :, 2] = 100
    right = np.full((H, W, 3), 230 - 20 * i, np.uint8)
    right[:, :, 1] = 60
    return left, right


def write_png_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def write_video(path: Path, n: int, size=(W, H)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (w, 2 * h))
    assert writer.isOpened()
    for i in range(n):
        left, right = frame_images(i)
        writer.write(cv2.cvtColor(np.vstack([left, right]), cv2.COLOR_RGB2BGR))
    writer.release()


def make_stereomis(root: Path, n: int = 10, gt: bool = True, masks: bool = True) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        left, right = frame_images(i)
        write_png_rgb(root / "video_frames" / f"{i:06d}l.png", left)
        write_png_rgb(root / "video_frames" / f"{i:06d}r.png", right)
        if masks:
            m = np.full((H, W), 255, np.uint8)
            m[:, :10] = 0  # instrument on the left border
            (root / "masks").mkdir(exist_ok=True)
            cv2.imwrite(str(root / "masks" / f"{i:06d}l.png"), m)
    write_ini(root / "StereoCalibration.ini")
    if gt:
        write_tum(root / "groundtruth.txt", 100.0 + 0.04 * np.arange(n), random_poses(n))
    return root


def assert_frame(frame: StereoFrame, size=(W, H)) -> None:
    w, h = size
    assert frame.left.shape == (h, w, 3) and frame.left.dtype == np.uint8
    assert frame.right.shape == (h, w, 3) and frame.right.dtype == np.uint8
    assert frame.mask.shape == (h, w) and frame.mask.dtype == bool


# ---------------------------------------------------------------------------------------------
# StereoMIS pre-processed
# ---------------------------------------------------------------------------------------------

def test_stereomis_layout(tmp_path):
    root = make_stereomis(tmp_path / "seq")
    assert detect_layout(root) == "stereomis"
    ds = open_dataset(root, native())
    assert ds.layout == "stereomis" and len(ds) == 10
    np.testing.assert_allclose(ds.camera.K, K, atol=1e-9)
    assert ds.camera.baseline_mm == pytest.approx(BASELINE)
    assert (ds.camera.width, ds.camera.height) == (W, H)
    np.testing.assert_allclose(ds.R1, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(ds.timestamps, 100.0 + 0.04 * np.arange(10), atol=1e-9)
    np.testing.assert_allclose(ds.gt_poses, random_poses(10), atol=1e-6)  # mm, as written
    frame = ds.frame(3)
    assert_frame(frame)
    assert frame.index == 3 and frame.timestamp == pytest.approx(100.12)
    np.testing.assert_array_equal(frame.left, frame_images(3)[0])  # RGB, untouched at native size
    np.testing.assert_array_equal(frame.right, frame_images(3)[1])
    assert not frame.mask[:, :10].any() and frame.mask[:, 10:].all()
    np.testing.assert_allclose(frame.gt_pose, random_poses(10)[3], atol=1e-6)
    assert frame.gt_depth is None
    assert [f.index for f in ds] == list(range(10))


def test_stereomis_resized_with_depth(tmp_path):
    root = make_stereomis(tmp_path / "seq", n=3, gt=False)
    depth = (np.arange(W * H, dtype=np.uint16).reshape(H, W) * 7) % 5000 + 1
    for i in range(3):
        (root / "depth").mkdir(exist_ok=True)
        (root / "nonrigid").mkdir(exist_ok=True)
        cv2.imwrite(str(root / "depth" / f"{i:06d}l.png"), depth)
        cv2.imwrite(str(root / "nonrigid" / f"{i:06d}l.png"), np.full((H, W), 40, np.uint16))
    (root / "synth.json").write_text(json.dumps({"depth_scale_mm": 0.05}))
    ds = open_dataset(root, native(width=32, height=24, fps=10.0))
    np.testing.assert_allclose(ds.camera.K, [[25, 0, 15.5], [0, 25, 11.5], [0, 0, 1]])
    assert ds.gt_poses is None
    np.testing.assert_allclose(ds.timestamps, [0.0, 0.1, 0.2])  # index / fps
    frame = ds.frame(1)
    assert_frame(frame, (32, 24))
    assert frame.gt_depth.shape == (24, 32) and frame.gt_depth.dtype == np.float32
    assert set(np.round(frame.gt_depth.ravel() / 0.05).astype(int)) <= set(depth.ravel().tolist())  # nearest
    np.testing.assert_allclose(frame.extras["nonrigid_mm"], 2.0)
    assert not frame.mask[:, :4].any() and frame.mask[:, 6:].all()


def test_masks_combine_instrument_and_specular(tmp_path):
    root = make_stereomis(tmp_path / "seq", n=2, gt=False)
    left, right = frame_images(0)
    left[20:22, 40:42] = 255  # a specular highlight
    write_png_rgb(root / "video_frames" / "000000l.png", left)
    frame = open_dataset(root, native(specular_threshold=0.96, specular_dilate_px=2)).frame(0)
    assert not frame.mask[:, :10].any()  # instrument
    # the 2x2 highlight at rows 20-21, cols 40-41, dilated by an elliptical 2 px radius
    assert not frame.mask[19:23, 39:43].any() and not frame.mask[20:22, 38:44].any() and not frame.mask[18:24, 40:42].any()
    assert frame.mask[18, 38] and frame.mask[23, 43] and frame.mask[20:22, 44].all()
    assert frame.mask[30:, 20:].all() and frame.mask[:15, 15:].all()
    no_files = open_dataset(root, native(specular_threshold=0.96, specular_dilate_px=2, use_mask_files=False)).frame(0)
    assert no_files.mask[:, :10].all() and not no_files.mask[20, 40]


def test_selection(tmp_path):
    ds = open_dataset(make_stereomis(tmp_path / "seq"), native())
    view = ds.select("2:8:2")
    assert len(view) == 3 and list(view.indices) == [2, 4, 6]
    np.testing.assert_allclose(view.timestamps, ds.timestamps[[2, 4, 6]])
    np.testing.assert_allclose(view.gt_poses, ds.gt_poses[[2, 4, 6]])
    frames = list(view)
    assert [f.index for f in frames] == [2, 4, 6]
    np.testing.assert_array_equal(frames[1].left, frame_images(4)[0])
    assert view.frame(-1).index == 6
    assert len(ds.select("4")) == 4 and list(ds.select(4).indices) == [0, 1, 2, 3]
    assert list(view.select("1:").indices) == [4, 6]  # a view of a view
    assert len(ds) == 10  # the original is untouched
    with pytest.raises(IndexError):
        view.frame(3)


def test_parse_frames():
    assert parse_frames(None, 5) == [0, 1, 2, 3, 4]
    assert parse_frames("", 3) == [0, 1, 2]
    assert parse_frames("3", 10) == [0, 1, 2]
    assert parse_frames(20, 4) == [0, 1, 2, 3]
    assert parse_frames("2:8:2", 10) == [2, 4, 6]
    assert parse_frames("::3", 7) == [0, 3, 6]
    assert parse_frames("5:", 7) == [5, 6]
    assert parse_frames(":2", 7) == [0, 1]
    assert parse_frames("-2:", 7) == [5, 6]
    assert parse_frames("0:10:5,10:30:10,30::5", 40) == [0, 5, 10, 20, 30, 35]
    for bad in ("a:b", "1:2:0", "::-1", "0", "1:2:3:4", "x", "20:", "0:5,3:8", "0:5,,6:8", "5:8,0:2"):
        with pytest.raises(ConfigError):
            parse_frames(bad, 10)


# ---------------------------------------------------------------------------------------------
# StereoMIS raw video
# ---------------------------------------------------------------------------------------------

def test_stereomis_raw_layout(tmp_path):
    root = tmp_path / "raw"
    write_video(root / "recording.mp4", 12)
    R = Rotation.from_rotvec([0.0, 0.02, 0.005]).as_matrix()
    write_ini(root / "StereoCalibration.ini", D1=[-0.05, 0.01], D2=[-0.04, 0.0], R=R)
    write_tum(root / "groundtruth.txt", np.arange(12) * 0.04, random_poses(12, seed=3))
    assert detect_layout(root) == "stereomis_raw"
    ds = open_dataset(root, native())
    assert ds.layout == "stereomis_raw" and len(ds) == 12
    assert (ds.camera.width, ds.camera.height) == (W, H)
    assert ds.camera.baseline_mm == pytest.approx(np.linalg.norm([BASELINE, 0, 0]))
    assert not np.allclose(ds.R1, np.eye(3))  # fully rectified: the left camera was rotated
    np.testing.assert_allclose(ds.gt_poses, random_poses(12, seed=3), atol=1e-6)
    # sequential, backward (seek) and skip-ahead reads return the right frames
    for i in (0, 1, 2, 9, 3, 11, 0):
        frame = ds.frame(i)
        assert_frame(frame)
        expect_l, expect_r = frame_images(i)
        centre = (slice(16, 32), slice(20, 44))
        assert np.abs(frame.left[centre].astype(float).mean(axis=(0, 1)) - expect_l[0, 0]).max() < 6
        assert np.abs(frame.right[centre].astype(float).mean(axis=(0, 1)) - expect_r[0, 0]).max() < 6
    ds.close()
    pre = open_dataset(root, native(rectified="yes", width=32, height=24))
    assert pre.frame(0).left.shape == (24, 32, 3)
    pre.close()


# ---------------------------------------------------------------------------------------------
# SCARED
# ---------------------------------------------------------------------------------------------

def make_scared(root: Path, n: int = 6, tar: bool = False, stamps: bool = False) -> np.ndarray:
    write_video(root / "data" / "rgb.mp4", n)
    fs = cv2.FileStorage(str(root / "endoscope_calibration.yaml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (("M1", K), ("D1", np.zeros((1, 5))), ("M2", K), ("D2", np.zeros((1, 5))),
                       ("R", np.eye(3)), ("T", np.array([[-BASELINE], [0.0], [0.0]]))):
        fs.write(key, value)
    fs.release()
    T_cw = random_poses(n, seed=5)
    jsons = {}
    for i in range(n):
        data = {"camera-calibration": {"KL": K.tolist()}, "camera-pose": T_cw[i].tolist()}
        if stamps:
            data["timestamp"] = 1000 + 10 * i
        jsons[f"frame_data{i:06d}.json"] = json.dumps(data).encode()
    if tar:
        with tarfile.open(root / "data" / "frame_data.tar.gz", "w:gz") as archive:
            for name in sorted(jsons, reverse=True):  # stored out of order: the reader sorts
                info = tarfile.TarInfo(f"frame_data/{name}")
                info.size = len(jsons[name])
                archive.addfile(info, io.BytesIO(jsons[name]))
    else:
        (root / "data" / "frame_data").mkdir(parents=True)
        for name, text in jsons.items():
            (root / "data" / "frame_data" / name).write_bytes(text)
    return T_cw


@pytest.mark.parametrize("tar", [False, True])
def test_scared_layout(tmp_path, tar):
    root = tmp_path / "keyframe_1"
    T_cw = make_scared(root, tar=tar, stamps=tar)
    assert detect_layout(root) == "scared"
    ds = open_dataset(root, native(rectify_mode="pseudo"))
    assert ds.layout == "scared" and len(ds) == 6
    np.testing.assert_allclose(ds.camera.K, K, atol=1e-9)  # size from the video: no size in the yaml
    assert ds.camera.baseline_mm == pytest.approx(BASELINE)
    # camera-pose is world-to-camera (see slam/io/datasets/scared.py): T_wc = inv(camera-pose)
    np.testing.assert_allclose(ds.gt_poses, np.linalg.inv(T_cw), atol=1e-9)
    expected_t = 1000.0 + 10 * np.arange(6) if tar else np.arange(6) / 25.0
    np.testing.assert_allclose(ds.timestamps, expected_t)
    frame = ds.select("1:4:2").frame(1)
    assert frame.index == 3
    assert_frame(frame)
    assert abs(int(frame.left[24, 32, 0]) - int(frame_images(3)[0][0, 0, 0])) < 6
    ds.close()


# ---------------------------------------------------------------------------------------------
# plain folders
# ---------------------------------------------------------------------------------------------

def make_plain(root: Path, n: int = 5) -> Path:
    for i in range(n):
        left, right = frame_images(i)
        write_png_rgb(root / "left" / f"img_{i:04d}.png", left)
        write_png_rgb(root / "right" / f"img_{i:04d}.png", right)
    (root / "calibration.yaml").write_text(
        f"fx: 50\nfy: 50\ncx: 31.5\ncy: 23.5\nbaseline_mm: {BASELINE}\nwidth: {W}\nheight: {H}\n")
    return root


def test_plain_layout(tmp_path):
    root = make_plain(tmp_path / "plain")
    (root / "masks").mkdir()
    m = np.full((H, W), 255, np.uint8)
    m[40:] = 0
    cv2.imwrite(str(root / "masks" / "img_0002.png"), m)
    write_tum(root / "groundtruth.txt", np.arange(5) * 0.5, random_poses(5, seed=9))
    assert detect_layout(root) == "plain"
    ds = open_dataset(root, native(width=32, height=24))
    assert ds.layout == "plain" and len(ds) == 5
    assert (ds.camera.width, ds.camera.height) == (32, 24)
    np.testing.assert_allclose(ds.camera.K, [[25, 0, 15.5], [0, 25, 11.5], [0, 0, 1]])
    np.testing.assert_allclose(ds.timestamps, np.arange(5) * 0.5)
    np.testing.assert_allclose(ds.gt_poses, random_poses(5, seed=9), atol=1e-6)
    frame = ds.frame(2)
    assert_frame(frame, (32, 24))
    assert not frame.mask[20:].any() and frame.mask[:20].all()
    assert ds.frame(1).mask.all()  # no mask file for that frame
    assert len(ds.select("2:8:2")) == 2


# ---------------------------------------------------------------------------------------------
# bad input: one-line DataError naming the file and the problem
# ---------------------------------------------------------------------------------------------

def one_line(excinfo) -> str:
    message = str(excinfo.value)
    assert "\n" not in message
    return message


def test_missing_calibration(tmp_path):
    root = make_stereomis(tmp_path / "seq", n=2)
    (root / "StereoCalibration.ini").unlink()
    with pytest.raises(DataError) as err:
        open_dataset(root, native())
    assert "StereoCalibration.ini" in one_line(err) and "not found" in str(err.value)
    plain = make_plain(tmp_path / "plain", n=2)
    (plain / "calibration.yaml").unlink()
    with pytest.raises(DataError, match="calibration.yaml: calibration file not found"):
        open_dataset(plain, native())


def test_left_right_counts_differ(tmp_path):
    root = make_plain(tmp_path / "plain", n=4)
    (root / "right" / "img_0003.png").unlink()
    with pytest.raises(DataError) as err:
        open_dataset(root, native())
    message = one_line(err)
    assert message == f"{root / 'left'} and {root / 'right'}: the frames do not pair: 1 left frames without a right " \
                      "one (first img_0003.png)"
    seq = make_stereomis(tmp_path / "seq", n=3)
    (seq / "video_frames" / "000001r.png").unlink()
    with pytest.raises(DataError, match="3 left frames .* 2 right frames"):
        open_dataset(seq, native())


def test_unreadable_png(tmp_path):
    root = make_stereomis(tmp_path / "seq", n=5)
    bad = root / "video_frames" / "000003l.png"
    bad.write_bytes(b"not a png at all")
    ds = open_dataset(root, native())  # opening does not read frames
    ds.frame(2)
    with pytest.raises(DataError) as err:
        ds.frame(3)
    assert str(bad) in one_line(err) and "cannot read image" in str(err.value)


def test_empty_and_unknown_folders(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError) as err:
        open_dataset(empty, native())
    message = one_line(err)
    assert str(empty) in message and "empty folder" in message
    assert "video_frames/" in message and "endoscope_calibration.yaml" in message and "left/" in message
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("hello")
    with pytest.raises(DataError, match="unknown dataset layout"):
        open_dataset(other, native())
    with pytest.raises(DataError, match="no such folder"):
        open_dataset(tmp_path / "missing", native())
    with pytest.raises(DataError, match="no frames"):
        (tmp_path / "vf" / "video_frames").mkdir(parents=True)
        open_dataset(tmp_path / "vf", native())


def test_video_cannot_be_opened(tmp_path):
    root = tmp_path / "raw"
    root.mkdir()
    (root / "recording.mp4").write_bytes(b"\x00\x01 definitely not a video" * 10)
    write_ini(root / "StereoCalibration.ini")
    with pytest.raises(DataError) as err:
        open_dataset(root, native())
    assert str(root / "recording.mp4") in one_line(err) and "cannot open video" in str(err.value)


def gt_warnings(caplog) -> list[str]:
    """The one-line warnings the readers logged (``slam`` logger) since the last call."""
    lines = [r.getMessage() for r in caplog.records if r.name == "slam" and r.levelno == logging.WARNING]
    caplog.clear()
    assert all("\n" not in line for line in lines)
    return lines


@pytest.mark.filterwarnings("error")       # a warning is a log line, not a Python UserWarning
def test_groundtruth_shorter_than_frames(tmp_path, caplog):
    """Another pose count than frames: the poses are associated by timestamp (the frames at
    data.fps from the first pose), never by index; frames without a pose within half a frame
    period get none, and one log line says how many; timestamps that meet no frame are a
    one-line error."""
    caplog.set_level(logging.WARNING, logger="slam")
    root = make_stereomis(tmp_path / "seq", n=6, gt=False)
    gt = root / "groundtruth.txt"
    poses = random_poses(8)
    write_tum(gt, 5.0 + np.arange(4) * 0.04, poses[:4])
    ds = open_dataset(root, native())
    assert gt_warnings(caplog) == [f"{gt}: 2 of 6 frames have no ground-truth pose within half a frame period "
                                   "(left out of the evaluation)"]
    np.testing.assert_allclose(ds.gt_poses[:4], poses[:4], atol=1e-6)
    assert np.isnan(ds.gt_poses[4:]).all()
    write_tum(gt, 5.0 + np.arange(8) * 0.04, poses)
    ds = open_dataset(root, native())  # longer: the frames' times pick theirs
    assert gt_warnings(caplog) == []
    np.testing.assert_allclose(ds.gt_poses, poses[:6], atol=1e-6)
    write_tum(gt, 5.0 + np.arange(8) * 0.02, poses)      # at 50 fps: every second one
    ds = open_dataset(root, native())
    assert [line.split(": ", 1)[1][:13] for line in gt_warnings(caplog)] == ["1 of 6 frames"]
    np.testing.assert_allclose(ds.gt_poses[:4], poses[0:8:2], atol=1e-6)
    write_tum(gt, np.arange(4) * 4e7, poses[:4])        # nanoseconds: only the first frame meets one
    open_dataset(root, native())
    assert [line.split(": ", 1)[1][:13] for line in gt_warnings(caplog)] == ["5 of 6 frames"]


@pytest.mark.filterwarnings("error")
def test_scared_poses_past_the_last_frame_are_dropped_with_one_log_line(tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="slam")
    root = tmp_path / "keyframe_1"
    T_cw = make_scared(root, n=6)
    frame_data = root / "data" / "frame_data"
    for i in (6, 7):
        (frame_data / f"frame_data{i:06d}.json").write_text((frame_data / "frame_data000005.json").read_text())
    ds = open_dataset(root, native(rectify_mode="pseudo"))
    assert gt_warnings(caplog) == [f"{frame_data}: 8 poses for 6 frames; ignoring the last 2",
                                   f"{root}: no timestamps (timestamps.txt, ground truth, a video's rate) and no "
                                   "--fps: the frames are taken at 25 fps"]
    np.testing.assert_allclose(ds.gt_poses, np.linalg.inv(T_cw), atol=1e-9)
    ds.close()


def test_bad_config(tmp_path):
    from slam.config import load_config

    with pytest.raises(ConfigError, match="'data.layout' must be one of auto, stereomis"):
        load_config(None, ["data.layout=kitti"])
    with pytest.raises(ConfigError, match="rectify_mode"):
        load_config(None, ["data.rectify_mode=magic"])
    with pytest.raises(DataError, match="no video_frames"):
        open_dataset(make_plain(tmp_path / "plain", n=2), native(layout="stereomis"))


# ---------------------------------------------------------------------------------------------
# specular mask
# ---------------------------------------------------------------------------------------------

def test_specular_mask():
    img = np.full((40, 40, 3), 100, np.uint8)
    img[20, 20] = (255, 240, 250)  # max channel 255 -> specular
    img[5, 5] = (244, 10, 10)  # 244/255 = 0.957 < 0.96
    img[5, 30] = (10, 10, 245)  # 245/255 = 0.961 >= 0.96 (any channel)
    spec = specular_mask(img, 0.96, 0)
    assert spec.dtype == bool and spec.shape == (40, 40)
    assert set(zip(*np.nonzero(spec))) == {(20, 20), (5, 30)}
    dilated = specular_mask(img, 0.96, 3)
    assert dilated[20, 17] and dilated[20, 23] and dilated[17, 20] and dilated[23, 20]
    assert not dilated[17, 17]  # elliptical, not square
    assert dilated.sum() < 2 * 49
    assert not specular_mask(img, 1.01, 3).any()
    instrument = np.ones((40, 40), bool)
    instrument[:, :3] = False
    mask = combine_masks(img, instrument, 0.96, 0)
    assert not mask[:, :3].any() and not mask[20, 20] and mask[10, 10]
