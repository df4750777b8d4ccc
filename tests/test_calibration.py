"""Calibration readers and rectification (synthetic data made here, no files from elsewhere)."""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from slam.io.calibration import (RawStereoCalibration, read_calibration, read_json_calibration, read_plain_yaml,
                              read_scared_yaml, read_stereomis_ini)
from slam.errors import DataError
from slam.io.rectification import (
    ResizeOnly,
    StereoRectifier,
    make_rectifier,
    original_to_rect_pose,
    rect_to_original_pose,
    resolve_output_size,
)


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------

def rotation(axis, degrees) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis) * np.deg2rad(degrees)
    return cv2.Rodrigues(axis.reshape(3, 1))[0]


def write_ini(path: Path, K1, D1, K2, D2, R, T, size, sep=" = ") -> Path:
    def cam(K, D):
        lines = [f"res_x{sep}{size[0]}", f"res_y{sep}{size[1]}", f"fc_x{sep}{float(K[0][0])!r}", f"fc_y{sep}{float(K[1][1])!r}",
                 f"cc_x{sep}{float(K[0][2])!r}", f"cc_y{sep}{float(K[1][2])!r}"]
        D = list(D) + [0.0] * (8 - len(D))
        lines += [f"kc_{i}{sep}{float(d)!r}" for i, d in enumerate(D)]
        return lines
    text = ["[StereoLeft]", *cam(K1, D1), "", "[StereoRight]", *cam(K2, D2)]
    text += [f"T_{i}{sep}{float(t)!r}" for i, t in enumerate(np.ravel(T))]
    text += [f"R_{i}{sep}{float(r)!r}" for i, r in enumerate(np.ravel(R))]
    path.write_text("\n".join(text) + "\n")
    return path


def write_scared_yaml(path: Path, K1, D1, K2, D2, R, T, size=None) -> Path:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("R", np.asarray(R, dtype=np.float64))
    fs.write("T", np.asarray(T, dtype=np.float64).reshape(3, 1))
    fs.write("M1", np.asarray(K1, dtype=np.float64))
    fs.write("D1", np.asarray(D1, dtype=np.float64).reshape(1, -1))
    fs.write("M2", np.asarray(K2, dtype=np.float64))
    fs.write("D2", np.asarray(D2, dtype=np.float64).reshape(1, -1))
    if size is not None:
        fs.write("width", int(size[0]))
        fs.write("height", int(size[1]))
    fs.release()
    return path


class Rig:
    """A raw stereo rig built from a known rectified one: both raw cameras are rotated (1-2 deg)
    and distorted versions of an ideal rectified pair with baseline ``b`` along +x."""

    W, H = 320, 256
    b = 5.0

    def __init__(self, rotate=True):
        self.Rl = rotation([0.3, 1.0, 0.2], 1.5) if rotate else np.eye(3)
        self.Rr = rotation([-0.5, 0.2, 1.0], 1.2) if rotate else np.eye(3)
        C = np.array([self.b, 0.0, 0.0])  # right optical centre in the ideal rectified frame
        self.R = self.Rr @ self.Rl.T
        self.T = -self.Rr @ C
        self.K1 = np.array([[255.0, 0, 162.0], [0, 257.0, 126.0], [0, 0, 1]])
        self.K2 = np.array([[265.0, 0, 155.0], [0, 266.0, 133.0], [0, 0, 1]])
        self.D1 = np.array([-0.12, 0.05, 0.0005, -0.0003, 0.0])
        self.D2 = np.array([-0.10, 0.03, -0.0004, 0.0002, 0.0])

    def calib(self) -> RawStereoCalibration:
        return RawStereoCalibration(self.K1, self.D1, self.K2, self.D2, self.R, self.T, (self.W, self.H))

    def points_left(self) -> np.ndarray:
        """3D points in the raw left camera frame, spread over the view, 60-100 mm deep."""
        us, vs = np.meshgrid(np.linspace(50, self.W - 50, 6), np.linspace(45, self.H - 45, 5))
        rays = np.stack([(us.ravel() - 160) / 256, (vs.ravel() - 128) / 256, np.ones(us.size)], 1)
        depth = 60 + 40 * ((np.arange(us.size) * 7) % 11) / 10
        return rays * depth[:, None]

    def project_raw(self, X_left: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pl = cv2.projectPoints(X_left, np.zeros(3), np.zeros(3), self.K1, self.D1)[0].reshape(-1, 2)
        X_right = X_left @ self.R.T + self.T
        pr = cv2.projectPoints(X_right, np.zeros(3), np.zeros(3), self.K2, self.D2)[0].reshape(-1, 2)
        return pl, pr


def render_blobs(centres: np.ndarray, size: tuple[int, int], sigma: float = 1.6) -> np.ndarray:
    W, H = size
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    img = np.zeros((H, W))
    for cx, cy in centres:
        img += np.exp(-((xs - cx) ** 2 + (ys - cy) ** 2) / (2 * sigma**2))
    img = np.clip(img * 250, 0, 255).astype(np.uint8)
    return np.repeat(img[:, :, None], 3, axis=2)


def blob_centroids(img: np.ndarray, expected: np.ndarray, radius: int = 6) -> np.ndarray:
    """Intensity-weighted centroid of the blob nearest each expected position."""
    gray = img[..., 0].astype(np.float64)
    out = []
    for ex, ey in expected:
        x0, y0 = int(round(ex)), int(round(ey))
        ys, xs = np.mgrid[y0 - radius:y0 + radius + 1, x0 - radius:x0 + radius + 1]
        win = gray[ys.clip(0, gray.shape[0] - 1), xs.clip(0, gray.shape[1] - 1)]
        win = np.where(win > 20, win - 20, 0)
        out.append([(win * xs).sum() / win.sum(), (win * ys).sum() / win.sum()])
    return np.asarray(out)


# ---------------------------------------------------------------------------------------------
# calibration readers
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("sep", [" = ", "="])
def test_read_stereomis_ini(tmp_path, sep):
    rig = Rig()
    D1 = np.array([-0.12, 0.05, 0.0005, -0.0003, 0.01, 0.001, 0.002, 0.003])
    path = write_ini(tmp_path / "StereoCalibration.ini", rig.K1, D1, rig.K2, rig.D2, rig.R, rig.T, (320, 256), sep)
    cal = read_stereomis_ini(path)
    np.testing.assert_allclose(cal.K1, rig.K1)
    np.testing.assert_allclose(cal.K2, rig.K2)
    np.testing.assert_allclose(cal.D1, D1)
    assert cal.D1.shape == (8,) and cal.D2.shape == (8,)
    np.testing.assert_allclose(cal.R, rig.R)  # row-major
    np.testing.assert_allclose(cal.T, rig.T)
    assert cal.image_size == (320, 256)
    assert cal.baseline_mm == pytest.approx(rig.b)
    assert cal.source == path


def test_read_stereomis_ini_errors(tmp_path):
    with pytest.raises(DataError, match="StereoCalibration.ini: calibration file not found"):
        read_stereomis_ini(tmp_path / "StereoCalibration.ini")
    bad = tmp_path / "bad.ini"
    bad.write_text("[StereoLeft]\nres_x = 10\n")
    with pytest.raises(DataError, match=r"bad.ini: missing section \[StereoRight\]"):
        read_stereomis_ini(bad)
    rig = Rig()
    path = write_ini(tmp_path / "x.ini", rig.K1, rig.D1, rig.K2, rig.D2, rig.R, rig.T, (320, 256))
    path.write_text(path.read_text().replace("fc_y = 257.0", "fc_y = abc"))
    with pytest.raises(DataError, match=r"x.ini: 'fc_y' in \[StereoLeft\] is not a number"):
        read_stereomis_ini(path)
    path.write_text("no section header\n")
    with pytest.raises(DataError, match="x.ini: cannot parse"):
        read_stereomis_ini(path)


def test_read_scared_yaml(tmp_path):
    rig = Rig()
    path = write_scared_yaml(tmp_path / "endoscope_calibration.yaml", rig.K1, rig.D1, rig.K2, rig.D2, rig.R, rig.T)
    assert read_scared_yaml(path).image_size is None      # SCARED files rarely name it: fitted to the frames
    cal = read_scared_yaml(path, image_size=(320, 256))
    np.testing.assert_allclose(cal.K1, rig.K1)
    np.testing.assert_allclose(cal.D2, rig.D2)
    np.testing.assert_allclose(cal.R, rig.R)
    np.testing.assert_allclose(cal.T, rig.T)
    assert cal.image_size == (320, 256)
    sized = write_scared_yaml(tmp_path / "sized.yaml", rig.K1, rig.D1, rig.K2, rig.D2, rig.R, rig.T, size=(640, 512))
    assert read_scared_yaml(sized, image_size=(320, 256)).image_size == (640, 512)


def test_read_scared_yaml_opencv_1_0_header(tmp_path):
    """The files SCARED ships start with ``%YAML:1.0``."""
    def mat(name, rows, cols, data):
        return (f"{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n"
                f"   data: [ {', '.join(repr(float(v)) for v in data)} ]\n")
    text = "%YAML:1.0\n---\n" + mat("M1", 3, 3, [1000, 0, 640, 0, 1000, 512, 0, 0, 1]) + mat("D1", 1, 5, [0] * 5)
    text += mat("M2", 3, 3, [1000, 0, 650, 0, 1000, 510, 0, 0, 1]) + mat("D2", 1, 5, [0] * 5)
    text += mat("R", 3, 3, np.eye(3).ravel()) + mat("T", 3, 1, [-4.2, 0.02, 0.1])
    text += "imageSize: [ 1280, 1024 ]\n"
    path = tmp_path / "endoscope_calibration.yaml"
    path.write_text(text)
    cal = read_scared_yaml(path)
    assert cal.image_size == (1280, 1024)
    np.testing.assert_allclose(cal.T, [-4.2, 0.02, 0.1])


def test_read_scared_yaml_errors(tmp_path):
    with pytest.raises(DataError, match="calibration file not found"):
        read_scared_yaml(tmp_path / "nope.yaml")
    garbage = tmp_path / "garbage.yaml"
    garbage.write_text("%YAML:1.0\nM1: [\n  : : broken")
    with pytest.raises(DataError, match="garbage.yaml: cannot"):
        read_scared_yaml(garbage, image_size=(10, 10))
    rig = Rig()
    path = write_scared_yaml(tmp_path / "c.yaml", rig.K1, rig.D1, rig.K2, rig.D2, rig.R, rig.T)
    path.write_text(path.read_text().replace("M2:", "MX:"))
    with pytest.raises(DataError, match="c.yaml: missing matrix 'M2'") as err:
        read_scared_yaml(path, image_size=(320, 256))
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("names", [("M_l", "D_l", "M_r", "D_r", "R", "T"),
                                   ("cameraMatrix1", "distCoeffs1", "cameraMatrix2", "distCoeffs2", "R", "T"),
                                   ("K_left", "dist_left", "K_right", "dist_right", "rotation", "translation"),
                                   ("LEFT_CAMERA_MATRIX", "left_distortion", "right_camera_matrix", "RIGHT-DISTORTION",
                                    "r", "t")])
@pytest.mark.parametrize("suffix", [".yaml", ".xml"])
def test_opencv_calibrations_under_other_names(tmp_path, names, suffix):
    """The da Vinci's ``M_l M_r D_l D_r``, OpenCV's samples' ``cameraMatrix1``, other tools'
    ``K_left``: read as SCARED's ``M1 D1 M2 D2`` (names compared without case, ``_`` and ``-``),
    from YAML or XML, through the reader of any calibration file."""
    rig = Rig()
    path = tmp_path / f"rig{suffix}"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for name, value in zip(names, (rig.K1, rig.D1[None], rig.K2, rig.D2[None], rig.R, rig.T.reshape(3, 1))):
        fs.write(name, np.asarray(value, dtype=np.float64))
    fs.release()
    cal = read_calibration(path)
    for got, want in ((cal.K1, rig.K1), (cal.D1, rig.D1), (cal.K2, rig.K2), (cal.D2, rig.D2), (cal.R, rig.R),
                      (cal.T, rig.T)):
        np.testing.assert_allclose(got, want)


def test_a_missing_matrix_names_what_was_looked_for(tmp_path):
    rig = Rig()
    path = write_scared_yaml(tmp_path / "c.yaml", rig.K1, rig.D1, rig.K2, rig.D2, rig.R, rig.T)
    path.write_text(path.read_text().replace("M2:", "MX:"))
    with pytest.raises(DataError) as err:
        read_calibration(path)
    assert str(err.value).startswith(f"{path}: missing matrix 'M2' (the right camera matrix; also read as K2, M_r, "
                                     "K_r, M_right, K_right, cameraMatrix2")


@pytest.mark.parametrize("deviation, warned", [(5e-4, False), (1.9e-3, True), (1.5e-2, True)])
def test_a_rotation_written_with_few_digits_is_projected(tmp_path, caplog, deviation, warned):
    rig = Rig()
    R = rig.R * np.sqrt(1 + deviation)
    path = write_scared_yaml(tmp_path / "c.yaml", rig.K1, rig.D1, rig.K2, rig.D2, R, rig.T)
    with caplog.at_level(logging.WARNING, logger="slam"):
        cal = read_calibration(path)
    if warned:
        assert caplog.messages == [f"{path}: stereo rotation R is {deviation:.1e} from orthonormal (max |R R^T - I|): "
                                   "taken as the nearest rotation"]
        np.testing.assert_allclose(cal.R, rig.R, atol=1e-12)
    else:
        assert caplog.messages == [] and np.array_equal(cal.R, R)


@pytest.mark.parametrize("R, figures", [("scaled", "max |R R^T - I| = 0.05, det 1.08"),
                                        ("reflection", "max |R R^T - I| = 0, det -1")])
def test_a_matrix_far_from_a_rotation_is_refused_with_its_figures(tmp_path, R, figures):
    rig = Rig()
    R = rig.R * np.sqrt(1.05) if R == "scaled" else rig.R @ np.diag([1.0, 1.0, -1.0])
    path = write_scared_yaml(tmp_path / "c.yaml", rig.K1, rig.D1, rig.K2, rig.D2, R, rig.T)
    with pytest.raises(DataError) as err:
        read_calibration(path)
    assert str(err.value) == (f"{path}: stereo rotation R is not a rotation matrix ({figures}; up to 0.02 is taken "
                              "for a rotation written with few digits)")


def test_read_plain_yaml(tmp_path):
    path = tmp_path / "calibration.yaml"
    path.write_text("fx: 500\nfy: 501.5\ncx: 319.5\ncy: 255.5\nbaseline_mm: 4.5\nwidth: 640\nheight: 512\n")
    cam = read_plain_yaml(path)
    np.testing.assert_allclose(cam.K, [[500, 0, 319.5], [0, 501.5, 255.5], [0, 0, 1]])
    assert (cam.baseline_mm, cam.width, cam.height) == (4.5, 640, 512)
    path.write_text("fx: 500\nfy: 500\ncx: 319.5\ncy: 255.5\nwidth: 640\nheight: 512\n")
    with pytest.raises(DataError, match="calibration.yaml: missing key 'baseline_mm'"):
        read_plain_yaml(path)
    path.write_text("fx: [1, 2\n")
    with pytest.raises(DataError, match="calibration.yaml: cannot parse YAML"):
        read_plain_yaml(path)
    path.write_text("fx: -1\nfy: 500\ncx: 1\ncy: 1\nbaseline_mm: 4\nwidth: 64\nheight: 48\n")
    with pytest.raises(DataError, match="'fx' must be positive"):
        read_plain_yaml(path)


# ---------------------------------------------------------------------------------------------
# rectification
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("out_size", [(0, 0), (160, 128)])
def test_full_rectification_end_to_end(out_size):
    """Raw, rotated, distorted views of known 3D points -> rectified views in which each point
    lies on the same row in both views, at the disparity fx * b / Z, where R1 and the rectified
    K say it should be."""
    rig = Rig()
    rect = StereoRectifier(rig.calib(), "full", out_size)
    cam = rect.camera
    W, H = (rig.W, rig.H) if out_size == (0, 0) else out_size
    assert (cam.width, cam.height) == (W, H) == rect.output_size
    assert cam.baseline_mm == pytest.approx(rig.b)
    np.testing.assert_allclose(rect.R1 @ rect.R1.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(rect.R1) == pytest.approx(1.0)
    assert rect.valid_mask.shape == (H, W) and rect.valid_mask.mean() > 0.99  # alpha = 0

    X = rig.points_left()
    pl, pr = rig.project_raw(X)
    assert np.abs(pl[:, 1] - pr[:, 1]).max() > 2.0  # the raw views do have vertical parallax
    left_raw, right_raw = render_blobs(pl, (rig.W, rig.H)), render_blobs(pr, (rig.W, rig.H))
    left, right = rect.rectify(left_raw, right_raw)
    assert left.shape == (H, W, 3) and left.dtype == np.uint8

    # where the rectified camera (K, R1) says each point is
    Xr = X @ rect.R1.T
    z = Xr[:, 2]
    ql = np.stack([cam.fx * Xr[:, 0] / z + cam.cx, cam.fy * Xr[:, 1] / z + cam.cy], 1)
    qr = ql - np.stack([cam.fx * cam.baseline_mm / z, np.zeros_like(z)], 1)
    inside = (ql[:, 0] > 8) & (ql[:, 0] < W - 8) & (qr[:, 0] > 8) & (ql[:, 1] > 8) & (ql[:, 1] < H - 8)
    assert inside.sum() >= 15
    found_l = blob_centroids(left, ql[inside], radius=4 if W < 200 else 6)
    found_r = blob_centroids(right, qr[inside], radius=4 if W < 200 else 6)
    tol = 0.15  # measured ~0.03 px
    np.testing.assert_allclose(found_l, ql[inside], atol=tol)  # K and R1 are consistent with the images
    np.testing.assert_allclose(found_r, qr[inside], atol=tol)  # disparity fx * b / Z, right at +x
    vertical_parallax = np.abs(found_l[:, 1] - found_r[:, 1])
    assert vertical_parallax.max() < 0.5
    assert np.median(vertical_parallax) < 0.1


def test_rectification_R1_maps_original_to_rectified_frame():
    """Projecting a point with the original K1, D1 and mapping the pixel through the rectification
    lands where the rectified K projects R1 @ X."""
    rig = Rig()
    rect = StereoRectifier(rig.calib(), "full")
    X = np.array([[5.0, -3.0, 70.0]])
    pl, pr = rig.project_raw(X)
    left, _ = rect.rectify(render_blobs(pl, (rig.W, rig.H), 2.0), render_blobs(pr, (rig.W, rig.H), 2.0))
    Xr = rect.R1 @ X[0]
    q = rect.camera.K @ (Xr / Xr[2])
    found = blob_centroids(left, q[None, :2])[0]
    np.testing.assert_allclose(found, q[:2], atol=0.2)
    # the pose relation documented in slam.io.rectification
    rng = np.random.default_rng(0)
    T_wc_orig = np.eye(4)
    T_wc_orig[:3, :3] = rotation(rng.normal(size=3), 20)
    T_wc_orig[:3, 3] = rng.normal(size=3) * 10
    T_wc_rect = original_to_rect_pose(T_wc_orig, rect.R1)
    Xw = T_wc_orig @ np.append(X[0], 1.0)
    np.testing.assert_allclose((np.linalg.inv(T_wc_rect) @ Xw)[:3], rect.R1 @ X[0], atol=1e-9)
    np.testing.assert_allclose(rect_to_original_pose(T_wc_rect, rect.R1), T_wc_orig, atol=1e-12)


def test_pseudo_rectification_undistorts_to_common_K():
    rig = Rig(rotate=False)  # pseudo rectification is exact when the views are not rotated
    rect = StereoRectifier(rig.calib(), "pseudo")
    np.testing.assert_allclose(rect.R1, np.eye(3))
    f = np.mean([rig.K1[0, 0], rig.K1[1, 1], rig.K2[0, 0], rig.K2[1, 1]])
    cam = rect.camera
    assert cam.fx == pytest.approx(f) and cam.fy == pytest.approx(f)
    assert cam.cx == pytest.approx((rig.K1[0, 2] + rig.K2[0, 2]) / 2)
    assert cam.baseline_mm == pytest.approx(rig.b)
    X = rig.points_left()
    pl, pr = rig.project_raw(X)
    left, right = rect.rectify(render_blobs(pl, (rig.W, rig.H)), render_blobs(pr, (rig.W, rig.H)))
    z = X[:, 2]
    ql = np.stack([f * X[:, 0] / z + cam.cx, f * X[:, 1] / z + cam.cy], 1)
    qr = ql - np.stack([f * rig.b / z, np.zeros_like(z)], 1)
    ok = (ql[:, 0] > 8) & (qr[:, 0] > 8) & (ql[:, 0] < rig.W - 8)
    np.testing.assert_allclose(blob_centroids(left, ql[ok]), ql[ok], atol=0.25)
    np.testing.assert_allclose(blob_centroids(right, qr[ok]), qr[ok], atol=0.25)


def test_swapped_views_are_rejected():
    rig = Rig()
    cal = rig.calib()
    cal.T = -cal.T  # right camera now at -x
    for mode in ("full", "pseudo"):
        with pytest.raises(DataError, match="not at \\+x"):
            StereoRectifier(cal, mode)


def test_trivially_rectified_calibration_keeps_K():
    """Already-rectified calibrations (what the synthetic generator writes) rectify to themselves."""
    K = np.array([[300.0, 0, 150.0], [0, 300.0, 120.0], [0, 0, 1]])
    cal = RawStereoCalibration(K, np.zeros(5), K, np.zeros(5), np.eye(3), [-4.0, 0, 0], (320, 256))
    for mode in ("full", "pseudo"):
        rect = StereoRectifier(cal, mode)
        np.testing.assert_allclose(rect.camera.K, K, atol=1e-9)
        np.testing.assert_allclose(rect.R1, np.eye(3), atol=1e-12)
    pre = make_rectifier(cal, "full", (160, 128), already_rectified=True)
    assert isinstance(pre, ResizeOnly)
    np.testing.assert_allclose(pre.camera.K, [[150, 0, 74.75], [0, 150, 59.75], [0, 0, 1]])


def test_rectify_left_mask_nearest_and_size_check():
    rig = Rig()
    rect = StereoRectifier(rig.calib(), "full", (160, 128))
    mask = np.ones((rig.H, rig.W), dtype=bool)
    mask[:, : rig.W // 2] = False
    out = rect.rectify_left_mask(mask)
    assert out.shape == (128, 160) and out.dtype == bool
    assert not out[:, :60].any() and out[:, 100:].all()
    with pytest.raises(DataError, match="expected 320x256"):
        rect.rectify(np.zeros((10, 10, 3), np.uint8), np.zeros((10, 10, 3), np.uint8), "frame.png")


def test_resize_only():
    from vo.camera import StereoCamera

    cam = StereoCamera(K=np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]]), baseline_mm=4.0, width=64, height=48)
    ro = ResizeOnly(cam, (32, 24))
    np.testing.assert_allclose(ro.camera.K, cam.scaled(32, 24).K)
    np.testing.assert_allclose(ro.R1, np.eye(3))
    img = np.zeros((48, 64, 3), np.uint8)
    img[::2, ::2] = 200  # a fine checkerboard: INTER_AREA averages it
    left, right = ro.rectify(img, img)
    assert left.shape == (24, 32, 3)
    assert np.abs(left.astype(int) - 50).max() <= 1
    assert ResizeOnly(cam).camera is cam
    assert resolve_output_size((64, 48), (32, 0)) == (32, 24)
    assert resolve_output_size((64, 48), (0, 0)) == (64, 48)


@pytest.mark.parametrize("content", ["", "  \n\t\n"], ids=["zero bytes", "whitespace"])
@pytest.mark.parametrize("name, reader", [
    ("StereoCalibration.ini", read_stereomis_ini), ("endoscope_calibration.yaml", read_scared_yaml),
    ("calibration.yaml", read_plain_yaml), ("calibration.json", read_json_calibration),
    ("c.ini", read_calibration), ("c.yaml", read_calibration), ("c.yml", read_calibration),
    ("c.xml", read_calibration), ("c.json", read_calibration),
])
def test_an_empty_calibration_file_says_so(tmp_path, name, reader, content):
    """Not a missing section, key or matrix, nor a parse error: one line, the same in every format."""
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(DataError) as err:
        reader(path)
    assert str(err.value) == f"{path}: empty calibration file"
