"""Tests of the synthetic sequence generator (tiny sizes, few frames)."""
from __future__ import annotations

import configparser
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from slam.errors import DataError
from slam.synth import SCENARIOS, generate
from slam.synth.camera_paths import make_path
from slam.io.tum import read_tum

SIZE = (96, 80)
FRAMES = {"rigid": 8, "breathing": 6, "scanning": 6, "deforming": 8, "loop": 300}


@pytest.fixture(scope="module")
def sequences(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("synth")
    out = {}
    for sc in SCENARIOS:
        size = (64, 48) if sc == "loop" else SIZE
        out[sc] = generate(root / sc, sc, frames=FRAMES[sc], size=size, seed=3)
    return out


def _rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _depth(path: Path) -> np.ndarray:
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert d is not None and d.dtype == np.uint16, path
    return d.astype(np.float64) * 0.01


def _calib(seq: Path) -> configparser.ConfigParser:
    cfg = configparser.ConfigParser()
    assert cfg.read(seq / "StereoCalibration.ini")
    return cfg


def _K(cfg, section="StereoLeft") -> np.ndarray:
    s = cfg[section]
    return np.array([[float(s["fc_x"]), 0, float(s["cc_x"])], [0, float(s["fc_y"]), float(s["cc_y"])], [0, 0, 1]])


def _colour_diff(ref: np.ndarray, other: np.ndarray, mapx: np.ndarray, mapy: np.ndarray, valid: np.ndarray):
    """Median absolute colour difference (0-255, mean over channels) between ``ref`` and ``other``
    sampled at (mapx, mapy), and the fraction of pixels that differ by less than 6 levels."""
    h, w = ref.shape[:2]
    valid = valid & (mapx >= 1) & (mapx <= w - 2) & (mapy >= 1) & (mapy <= h - 2)
    assert valid.mean() > 0.5
    warped = cv2.remap(other.astype(np.float32), mapx.astype(np.float32), mapy.astype(np.float32), cv2.INTER_LINEAR)
    diff = np.abs(warped - ref.astype(np.float32)).mean(-1)[valid]
    return float(np.median(diff)), float((diff < 6).mean())


# -- arguments -------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs", [dict(scenario="nope"), dict(scenario="rigid", size=(5, 80)),
                                    dict(scenario="rigid", size=(96,)), dict(scenario="rigid", frames=0),
                                    dict(scenario="scanning", camera_speed=0), dict(scenario="scanning", camera_speed="x")])
def test_bad_arguments(tmp_path, kwargs):
    with pytest.raises(DataError) as err:
        generate(tmp_path / "x", **kwargs)
    assert "\n" not in str(err.value)


def test_refuses_a_foreign_non_empty_folder(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(DataError):
        generate(tmp_path, "rigid", frames=1, size=(32, 24))


def test_an_interrupted_run_can_be_rerun_into_its_folder_and_is_not_taken_as_finished(tmp_path, monkeypatch):
    from benchmarks.runs import synthetic
    from slam.synth.writer import SequenceWriter, is_finished

    write = SequenceWriter.write

    def write_then_stop(self, i, *args, **kwargs):
        if i == 1:
            raise KeyboardInterrupt
        return write(self, i, *args, **kwargs)

    monkeypatch.setattr(SequenceWriter, "write", write_then_stop)
    with pytest.raises(KeyboardInterrupt):
        generate(tmp_path / "seq", "rigid", frames=3, size=(32, 24), seed=1)
    assert (tmp_path / "seq" / "video_frames" / "000000l.png").is_file()
    assert (tmp_path / "seq" / "synth.json").is_file() and not is_finished(tmp_path / "seq")
    monkeypatch.setattr(SequenceWriter, "write", write)
    # the benchmarks' sequences: an interrupted one is rendered again, not taken as it is
    out = synthetic(tmp_path / "seq", "rigid", frames=3, size=(32, 24), seed=1)
    assert is_finished(out)
    assert json.loads((out / "synth.json").read_text())["frames"] == 3
    assert len(list((out / "video_frames").glob("*l.png"))) == 3
    assert (out / "StereoCalibration.ini").is_file()


# -- layout ----------------------------------------------------------------------------------
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_layout(sequences, scenario):
    seq = sequences[scenario]
    n = FRAMES[scenario]
    w, h = (64, 48) if scenario == "loop" else SIZE
    for side in "lr":
        files = sorted((seq / "video_frames").glob(f"*{side}.png"))
        assert [f.name for f in files] == [f"{i:06d}{side}.png" for i in range(n)]
    assert _rgb(seq / "video_frames" / "000000r.png").shape == (h, w, 3)
    assert len(list((seq / "depth").glob("*l.png"))) == n
    assert len(list((seq / "nonrigid").glob("*l.png"))) == n
    depth = _depth(seq / "depth" / "000000l.png")
    assert depth.shape == (h, w) and 30 < depth.min() and depth.max() < 110  # working distance, mm

    cfg = _calib(seq)
    assert int(cfg["StereoLeft"]["res_x"]) == w and int(cfg["StereoRight"]["res_y"]) == h
    assert [float(cfg["StereoRight"][f"T_{i}"]) for i in range(3)] == pytest.approx([-4.5, 0, 0])
    assert np.allclose([float(cfg["StereoRight"][f"R_{i}"]) for i in range(9)], np.eye(3).ravel())
    assert all(float(cfg["StereoLeft"][f"kc_{i}"]) == 0 for i in range(8))
    fx = float(cfg["StereoLeft"]["fc_x"])
    assert 50 <= np.rad2deg(2 * np.arctan(w / 2 / fx)) <= 70

    stamps, poses = read_tum(seq / "groundtruth.txt")
    assert len(stamps) == n and stamps == pytest.approx(np.arange(n) / 25.0)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    if scenario in ("breathing", "deforming"):
        assert np.allclose(steps, 0) and np.allclose(poses, poses[0])
    else:
        assert steps.min() >= 0.1 and steps.max() <= 1.5, (steps.min(), steps.max())
    if scenario == "loop":
        assert np.linalg.norm(poses[-1, :3, 3] - poses[0, :3, 3]) < 0.5
        assert np.abs(poses[:, :3, 3] - poses[0, :3, 3]).max() > 5  # it does go somewhere

    nonrigid = np.stack([_depth(seq / "nonrigid" / f"{i:06d}l.png") for i in range(n)])
    if scenario in ("rigid", "loop"):
        assert nonrigid.max() == 0
    else:
        assert 0.3 < nonrigid.max() < 12
        assert nonrigid.std(axis=(1, 2)).max() > 0.05  # spatially varying

    meta = json.loads((seq / "synth.json").read_text())
    assert meta["scenario"] == scenario and meta["frames"] == n and meta["size"] == [w, h]
    assert meta["baseline_mm"] == pytest.approx(4.5) and meta["depth_scale_mm"] == 0.01
    assert np.allclose(meta["K"], _K(cfg))

    masks = sorted((seq / "masks").glob("*l.png")) if (seq / "masks").exists() else []
    if scenario == "deforming":
        assert len(masks) == n
        m = np.stack([cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in masks])
        assert set(np.unique(m)) <= {0, 255}
        frac_inst = (m == 0).mean(axis=(1, 2))
        assert (frac_inst > 0.005).all() and (frac_inst < 0.4).all()
    else:
        assert not masks


def test_breathing_is_periodic_motion(sequences):
    seq = sequences["breathing"]
    d = np.stack([_depth(seq / "depth" / f"{i:06d}l.png") for i in range(FRAMES["breathing"])])
    change = np.abs(d[-1] - d[0])
    assert 0.02 < np.median(change) < 3.0  # it moves, by millimetres at most in 0.2 s


def _redness(rgb: np.ndarray) -> np.ndarray:
    """Minus the green/red ratio of an sRGB image, blurred (red parenchyma high, pale and fat low)."""
    rgb = rgb.astype(np.float32)
    return cv2.GaussianBlur(-(rgb[..., 1] + 1) / (rgb[..., 0] + 1), (0, 0), 3.0)


def test_breathing_amplitude_can_follow_the_tissue_look():
    from slam.synth.deformation import make_breathing, tissue_look
    from slam.synth.scene import make_scene

    scene = make_scene(3)
    look = tissue_look(scene)
    c = slice(scene.geo.size // 2 - 280, scene.geo.size // 2 + 280)  # the +-70 mm the cameras see
    corr = lambda a: np.corrcoef(a[c, c].ravel(), look[c, c].ravel())[0, 1]  # noqa: E731
    independent, coupled = make_breathing(scene, 3), make_breathing(scene, 3, 0.8)
    assert abs(corr(independent.amp)) < 0.3 and corr(coupled.amp) > 0.6
    # same random draws: 0 is the earlier generator, the period and the phase are kept
    assert np.array_equal(make_breathing(scene, 3, 0.0).amp, independent.amp)
    assert (coupled.period_s, coupled.phase0) == (independent.period_s, independent.phase0)
    assert coupled.amp.max() == pytest.approx(independent.amp.max(), rel=0.05)  # same peak amplitude
    with pytest.raises(ValueError):
        make_breathing(scene, 3, 1.5)


def test_breathing_that_follows_the_tissue_is_visible_in_the_images(sequences, tmp_path):
    """What a weight network can learn from: with the coupling, the tissue that looks red moves most."""
    coupled = generate(tmp_path / "ft", "breathing", frames=FRAMES["breathing"], size=SIZE, seed=3,
                       breathing_follows_tissue=0.8)
    assert json.loads((coupled / "synth.json").read_text())["breathing_follows_tissue"] == 0.8
    k = FRAMES["breathing"] - 1
    corr = {}
    for name, seq in (("independent", sequences["breathing"]), ("coupled", coupled)):
        moved = cv2.imread(str(seq / "nonrigid" / f"{k:06d}l.png"), cv2.IMREAD_UNCHANGED).astype(np.float32)
        red = _redness(_rgb(seq / "video_frames" / f"{k:06d}l.png"))
        corr[name] = np.corrcoef(moved.ravel(), red.ravel())[0, 1]
    assert abs(corr["independent"]) < 0.3 and corr["coupled"] > 0.5, corr
    with pytest.raises(DataError):
        generate(tmp_path / "bad", "breathing", frames=1, size=SIZE, breathing_follows_tissue=-0.1)


def test_deforming_instrument_is_in_front(sequences):
    seq = sequences["deforming"]
    m = cv2.imread(str(seq / "masks" / "000003l.png"), cv2.IMREAD_UNCHANGED) == 0
    d = _depth(seq / "depth" / "000003l.png")
    nr = _depth(seq / "nonrigid" / "000003l.png")
    assert (nr[m] == 0).all() and (d[m] > 0).all()
    assert np.median(d[m]) < np.median(d[~m])


# -- geometry --------------------------------------------------------------------------------
@pytest.mark.parametrize("scenario,frame", [("rigid", 0), ("rigid", 5), ("deforming", 4)])
def test_stereo_consistency(sequences, scenario, frame):
    """Left depth -> disparity fx B / Z: the right image sampled there matches the left one."""
    seq = sequences[scenario]
    cfg = _calib(seq)
    K = _K(cfg)
    baseline = -float(cfg["StereoRight"]["T_0"])
    left = _rgb(seq / "video_frames" / f"{frame:06d}l.png")
    right = _rgb(seq / "video_frames" / f"{frame:06d}r.png")
    depth = _depth(seq / "depth" / f"{frame:06d}l.png")
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    disparity = K[0, 0] * baseline / depth
    good, frac = _colour_diff(left, right, u - disparity, v, depth > 0)
    wrong = min(_colour_diff(left, right, u - s * disparity, v, depth > 0)[0] for s in (0.6, 1.4))
    assert good < 4.5 and frac > 0.75, (good, frac)  # what is left is sensor noise and speculars
    assert good < 0.8 * wrong, (good, wrong)


def test_temporal_consistency(sequences):
    """Depth at frame 0 moved by the ground-truth relative pose projects where frame 7 matches."""
    seq = sequences["rigid"]
    K = _K(_calib(seq))
    _, poses = read_tum(seq / "groundtruth.txt")
    t0, t1 = 0, 7
    img0 = _rgb(seq / "video_frames" / f"{t0:06d}l.png")
    img1 = _rgb(seq / "video_frames" / f"{t1:06d}l.png")
    depth = _depth(seq / "depth" / f"{t0:06d}l.png")
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    T_10 = np.linalg.inv(poses[t1]) @ poses[t0]

    def warp_diff(scale, T):
        X = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) * (scale * depth)[..., None]
        Y = X @ T[:3, :3].T + T[:3, 3]
        return _colour_diff(img0, img1, K[0, 0] * Y[..., 0] / Y[..., 2] + K[0, 2],
                            K[1, 1] * Y[..., 1] / Y[..., 2] + K[1, 2], depth > 0)

    good, frac = warp_diff(1.0, T_10)
    assert good < 4.5 and frac > 0.7, (good, frac)  # sensor noise, light moving with the camera
    wrong = min(warp_diff(0.7, T_10)[0], warp_diff(1.0, np.eye(4))[0])
    assert good < 0.8 * wrong, (good, wrong)


def test_scene_does_not_depend_on_size(tmp_path):
    a = generate(tmp_path / "a", "rigid", frames=1, size=(64, 48), seed=5)
    b = generate(tmp_path / "b", "rigid", frames=1, size=(128, 96), seed=5)
    da = _depth(a / "depth" / "000000l.png")
    db = _depth(b / "depth" / "000000l.png")
    db2 = db.reshape(48, 2, 64, 2).mean(axis=(1, 3))
    assert np.median(np.abs(da - db2)) < 0.05
    ia = _rgb(a / "video_frames" / "000000l.png").astype(np.float32)
    ib = cv2.resize(_rgb(b / "video_frames" / "000000l.png"), (64, 48), interpolation=cv2.INTER_AREA).astype(np.float32)
    assert np.median(np.abs(ia - ib)) < 12


# -- paths -----------------------------------------------------------------------------------
@pytest.mark.parametrize("frames", [2, 40, 300, 1200])
def test_paths(frames):
    for scenario in ("rigid", "scanning", "loop"):
        poses = make_path(scenario, frames, seed=11)
        steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        assert poses.shape == (frames, 4, 4)
        if not (scenario == "loop" and frames == 2):  # a 2-frame loop is back at its start
            assert steps.min() >= 0.1 and steps.max() <= 1.5
        angles = np.degrees(np.arccos(np.clip((np.trace(poses[:, :3, :3] @ poses[0, :3, :3].T, axis1=1, axis2=2) - 1) / 2, -1, 1)))
        assert angles.max() < 15
        if scenario == "loop":
            assert np.allclose(poses[-1], poses[0], atol=1e-6)


def test_camera_speed_scales_the_motion_per_frame_along_the_same_path(tmp_path):
    """``camera_speed`` (``slam synth --camera-speed``): a creeping camera moves a tenth as far per
    frame along the same curve, from the same start; 1 is the default path exactly."""
    for scenario in ("rigid", "scanning"):
        normal, slow = make_path(scenario, 60, seed=4), make_path(scenario, 60, seed=4, speed=0.1)
        assert np.array_equal(make_path(scenario, 60, seed=4, speed=1.0), normal)
        np.testing.assert_allclose(slow[0], normal[0], atol=1e-9)
        step = lambda p: np.linalg.norm(np.diff(p[:, :3, 3], axis=0), axis=1)
        assert np.mean(step(slow)) == pytest.approx(0.1 * np.mean(step(normal)), rel=0.05)
        assert step(slow).max() < 0.1          # below tracking's still threshold (0.1 mm per frame)
    out = generate(tmp_path / "slow", "scanning", frames=3, size=(96, 80), seed=4, camera_speed=0.1)
    assert json.loads((out / "synth.json").read_text())["camera_speed"] == 0.1


# -- raw mode --------------------------------------------------------------------------------
def test_raw_mode(tmp_path):
    seq = generate(tmp_path / "rawseq", "deforming", frames=5, size=SIZE, seed=3, raw=True)
    videos = list(seq.glob("*.mp4"))
    assert len(videos) == 1
    cap = cv2.VideoCapture(str(videos[0]))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    cap.release()
    assert len(frames) == 5 and frames[0].shape == (2 * SIZE[1], SIZE[0], 3)
    assert not (seq / "video_frames").exists()
    assert len(list((seq / "masks").glob("*l.png"))) == 5
    cfg = _calib(seq)
    R = np.array([float(cfg["StereoRight"][f"R_{i}"]) for i in range(9)]).reshape(3, 3)
    angle = np.degrees(np.arccos((np.trace(R) - 1) / 2))
    assert 0.4 < angle < 2.5 and np.allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert float(cfg["StereoLeft"]["kc_0"]) != 0 and float(cfg["StereoRight"]["kc_0"]) != 0
    assert float(cfg["StereoLeft"]["fc_x"]) != float(cfg["StereoRight"]["fc_x"])
    assert len(read_tum(seq / "groundtruth.txt")[0]) == 5
    meta = json.loads((seq / "synth.json").read_text())
    assert meta["raw"] is True and meta["has_depth"] is False


def test_raw_calibration_matches_rendering():
    """A left raw pixel's 3D point projected with the ini's R, T, K, D lands where the right raw
    view shows the same colour."""
    from slam.synth.cameras import raw_rig
    from slam.synth.deformation import FrameDeformation
    from slam.synth.render import Renderer
    from slam.synth.scene import make_scene

    scene = make_scene(3)
    rig = raw_rig(*SIZE, seed=3)
    T = make_path("rigid", 1, 3)[0]
    ren = Renderer(scene, None, mm_per_px=scene.rest_depth_mm / rig.left.K[0, 0])
    deform = FrameDeformation(t=0.0)
    L = ren.render(rig.left, T, T[:3, 3], deform, None, np.random.default_rng(0))
    R = ren.render(rig.right, T, T[:3, 3], deform, None, np.random.default_rng(1))
    X = rig.left.rays * L.depth[..., None]  # left camera frame
    uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3).astype(np.float64), cv2.Rodrigues(rig.R)[0], rig.T,
                              rig.right.K, rig.right.dist)
    uv = uv.reshape(*L.depth.shape, 2)
    good, frac = _colour_diff(L.rgb, R.rgb, uv[..., 0], uv[..., 1], L.depth > 0)
    assert good < 4.5 and frac > 0.75, (good, frac)
    # and the ray grid inverts the distortion: re-projecting the left rays gives the pixels back
    back = rig.left.project(rig.left.rays.reshape(-1, 3)).reshape(*L.depth.shape, 2)
    u, v = np.meshgrid(np.arange(SIZE[0]), np.arange(SIZE[1]))
    assert np.abs(back - np.stack([u, v], -1)).max() < 1e-3


# -- determinism -----------------------------------------------------------------------------
def test_deterministic(tmp_path):
    a = generate(tmp_path / "a", "deforming", frames=2, size=(48, 40), seed=9)
    b = generate(tmp_path / "b", "deforming", frames=2, size=(48, 40), seed=9)
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert files_a == files_b and len(files_a) >= 13
    for f in files_a:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    c = generate(tmp_path / "c", "deforming", frames=2, size=(48, 40), seed=10)
    assert (a / "video_frames/000000l.png").read_bytes() != (c / "video_frames/000000l.png").read_bytes()
