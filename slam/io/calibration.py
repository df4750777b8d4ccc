"""Reading stereo calibration files.

Four formats are read here, each into a plain data structure (:func:`read_calibration` tells
them apart):

* ``StereoCalibration.ini`` (StereoMIS): :func:`read_stereomis_ini` -> :class:`RawStereoCalibration`
* ``endoscope_calibration.yaml`` (SCARED, OpenCV FileStorage): :func:`read_scared_yaml`
  -> :class:`RawStereoCalibration`
* ``calibration.yaml`` (plain folders of rectified images): :func:`read_plain_yaml`
  -> :class:`vo.camera.StereoCamera`
* ``calibration.json`` (this project's own, see :func:`read_json_calibration`)
  -> :class:`RawStereoCalibration`

A calibration and the frames it is used with must agree: :func:`fit_to_frames` scales a
calibration made at an integer multiple (or fraction) of the frames' size and refuses one that
fits no such factor (:func:`fit_calibration` logs the scaling, :func:`fit_camera` does the same for
a rectified camera); :func:`is_rectified` tells rectified calibrations (no distortion, no rotation
between the cameras) from raw ones.

A raw calibration describes two distorted, unrectified pinhole cameras; turning it into the
rectified :class:`~vo.camera.StereoCamera` the VO core works with is the job of
:mod:`slam.io.rectification`. Lengths are millimetres throughout.

Every missing, unreadable, empty or malformed file raises :class:`slam.errors.DataError` with a
one-line message naming the file and the problem (``<file>: empty calibration file`` for zero
bytes or whitespace only, in every format: :func:`calibration_file`).
"""
from __future__ import annotations

import configparser
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from slam.errors import DataError
from vo.camera import StereoCamera

log = logging.getLogger("slam")


@dataclass
class RawStereoCalibration:
    """An unrectified, distorted stereo pair in OpenCV conventions.

    Attributes:
        K1, K2: ``(3, 3)`` float64 intrinsics of the left / right camera, pixels.
        D1, D2: float64 distortion coefficients in OpenCV order
            ``k1 k2 p1 p2 [k3 [k4 k5 k6]]`` (length 4, 5 or 8).
        R: ``(3, 3)`` rotation and ``T``: ``(3,)`` translation (mm) of the OpenCV stereo convention
            ``X_right = R @ X_left + T`` (points expressed in the left camera frame mapped to the
            right camera frame). For a right camera to the right of the left one ``T[0] < 0``.
        image_size: ``(width, height)`` of each view, pixels, or None where the file names none
            (:func:`fit_to_frames` then decides it from the principal point).
        source: the file the calibration was read from (for error messages), or None.
    """

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    image_size: Optional[tuple[int, int]]
    source: Optional[Path] = None

    def __post_init__(self) -> None:
        self.K1 = np.asarray(self.K1, dtype=np.float64).reshape(3, 3)
        self.K2 = np.asarray(self.K2, dtype=np.float64).reshape(3, 3)
        self.D1 = np.asarray(self.D1, dtype=np.float64).reshape(-1)
        self.D2 = np.asarray(self.D2, dtype=np.float64).reshape(-1)
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.T = np.asarray(self.T, dtype=np.float64).reshape(3)
        if self.image_size is not None:
            self.image_size = (int(self.image_size[0]), int(self.image_size[1]))

    @property
    def baseline_mm(self) -> float:
        """Distance between the optical centres, ``|T|`` in mm."""
        return float(np.linalg.norm(self.T))

    def name(self) -> str:
        """How error messages refer to this calibration."""
        return str(self.source) if self.source is not None else "calibration"

    def validate(self) -> "RawStereoCalibration":
        """Check the values are usable; raise DataError naming the file otherwise."""
        where = self.name()
        if self.image_size is not None and min(self.image_size) <= 0:
            w, h = self.image_size
            raise DataError(f"{where}: invalid image size {w}x{h}")
        for label, K in (("left", self.K1), ("right", self.K2)):
            if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
                raise DataError(f"{where}: invalid {label} intrinsics (focal lengths must be positive and finite)")
        for label, D in (("left", self.D1), ("right", self.D2)):
            if D.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(D)):
                raise DataError(f"{where}: invalid {label} distortion coefficients ({D.size} values)")
        if not np.all(np.isfinite(self.R)) or not np.all(np.isfinite(self.T)):
            raise DataError(f"{where}: non-finite stereo extrinsics")
        self.R = rotation_matrix(self.R, where)
        if self.baseline_mm <= 0:
            raise DataError(f"{where}: zero stereo baseline (T = 0)")
        return self


#: a stereo rotation within this of orthonormal (max |R R^T - I|) is taken as it is
R_EXACT = 1e-3
#: up to this it is a rotation written with few digits: projected onto the nearest rotation, with a
#: warning; beyond it (or with a negative determinant) it is no rotation and refused
R_PROJECTED = 2e-2


def rotation_matrix(R: np.ndarray, where: str) -> np.ndarray:
    """The stereo rotation ``R`` ``(3, 3)`` of a calibration as a rotation matrix: as it is within
    :data:`R_EXACT` of orthonormal, projected onto the nearest rotation (SVD, a warning giving the
    figure) up to :data:`R_PROJECTED`, else DataError naming ``where`` with the figures."""
    deviation = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if deviation <= R_EXACT and abs(det - 1.0) <= R_EXACT:
        return R
    if det <= 0 or deviation > R_PROJECTED:
        raise DataError(f"{where}: stereo rotation R is not a rotation matrix (max |R R^T - I| = {round(deviation, 4):g}, "
                        f"det {det:.3g}; up to {R_PROJECTED:g} is taken for a rotation written with few digits)")
    U, _, Vt = np.linalg.svd(R)
    log.warning("%s: stereo rotation R is %.1e from orthonormal (max |R R^T - I|): taken as "
                                      "the nearest rotation", where, deviation)
    return U @ Vt


# --------------------------------------------------------------------------------------------
# StereoMIS: StereoCalibration.ini
# --------------------------------------------------------------------------------------------

def read_stereomis_ini(path: str | Path) -> RawStereoCalibration:
    """Read a StereoMIS ``StereoCalibration.ini``.

    Format: two sections ``[StereoLeft]`` and ``[StereoRight]`` with ``key = value`` (or
    ``key=value``) lines: ``res_x res_y`` (image size), ``fc_x fc_y`` (focal lengths),
    ``cc_x cc_y`` (principal point), ``kc_0 .. kc_7`` (distortion in OpenCV order
    ``k1 k2 p1 p2 k3 k4 k5 k6``; missing ``kc_5..kc_7`` default to 0). The right section also holds
    ``T_0..T_2`` (mm) and ``R_0..R_8`` (row-major) with ``X_right = R X_left + T``.
    """
    path = calibration_file(path)
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            parser.read_file(fh)
    except (configparser.Error, OSError, UnicodeError) as exc:
        raise DataError(f"{path}: cannot parse calibration file ({_one_line(exc)})") from None

    def section(name: str) -> configparser.SectionProxy:
        for sec in parser.sections():
            if sec.strip().lower() == name.lower():
                return parser[sec]
        raise DataError(f"{path}: missing section [{name}]")

    def number(sec: configparser.SectionProxy, key: str, default: Optional[float] = None) -> float:
        raw = sec.get(key)
        if raw is None:
            if default is not None:
                return default
            raise DataError(f"{path}: missing key '{key}' in [{sec.name}]")
        try:
            value = float(raw.strip().strip('"').strip("'"))
        except ValueError:
            raise DataError(f"{path}: '{key}' in [{sec.name}] is not a number: '{raw}'") from None
        if not math.isfinite(value):
            raise DataError(f"{path}: '{key}' in [{sec.name}] is not finite")
        return value

    def camera(sec: configparser.SectionProxy) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        K = np.array(
            [[number(sec, "fc_x"), 0.0, number(sec, "cc_x")],
             [0.0, number(sec, "fc_y"), number(sec, "cc_y")],
             [0.0, 0.0, 1.0]]
        )
        D = np.array([number(sec, f"kc_{i}", 0.0 if i >= 5 else None) for i in range(8)])
        size = (int(round(number(sec, "res_x"))), int(round(number(sec, "res_y"))))
        return K, D, size

    left, right = section("StereoLeft"), section("StereoRight")
    K1, D1, size1 = camera(left)
    K2, D2, size2 = camera(right)
    if size1 != size2:
        raise DataError(f"{path}: left and right image sizes differ ({size1[0]}x{size1[1]} vs {size2[0]}x{size2[1]})")
    T = np.array([number(right, f"t_{i}") for i in range(3)])
    R = np.array([number(right, f"r_{i}") for i in range(9)]).reshape(3, 3)
    return RawStereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T, image_size=size1, source=path).validate()


# --------------------------------------------------------------------------------------------
# SCARED: endoscope_calibration.yaml (OpenCV FileStorage)
# --------------------------------------------------------------------------------------------

_SIZE_PAIRS = (("width", "height"), ("image_width", "image_height"), ("Camera.width", "Camera.height"),
               ("imageWidth", "imageHeight"), ("res_x", "res_y"))
_SIZE_VECTORS = ("image_size", "imageSize", "ImageSize", "size")

#: the names OpenCV stereo calibrations give each matrix, SCARED's first: OpenCV's samples
#: (``M1``, ``cameraMatrix1``, ``distCoeffs1``), the da Vinci's (``M_l``, ``D_r``) and other tools'
#: (``K_left``, ``left_camera_matrix``); matched ignoring case, ``_``, ``-`` and ``.``
OPENCV_NAMES = {
    "M1": ("M1", "K1", "M_l", "K_l", "M_left", "K_left", "cameraMatrix1", "cameraMatrixL", "cameraMatrixLeft",
           "camera_matrix_left", "left_camera_matrix", "left_K", "left_M", "intrinsics_left", "left_intrinsics"),
    "D1": ("D1", "D_l", "D_left", "distCoeffs1", "distCoeffsL", "distCoeffsLeft", "dist_coeffs_left",
           "left_dist_coeffs", "distortion_left", "left_distortion", "dist_left", "left_D"),
    "M2": ("M2", "K2", "M_r", "K_r", "M_right", "K_right", "cameraMatrix2", "cameraMatrixR", "cameraMatrixRight",
           "camera_matrix_right", "right_camera_matrix", "right_K", "right_M", "intrinsics_right", "right_intrinsics"),
    "D2": ("D2", "D_r", "D_right", "distCoeffs2", "distCoeffsR", "distCoeffsRight", "dist_coeffs_right",
           "right_dist_coeffs", "distortion_right", "right_distortion", "dist_right", "right_D"),
    "R": ("R", "rotation", "R_lr", "R_l2r"),
    "T": ("T", "translation", "T_lr", "T_l2r"),
}
_WHAT = {"M1": "the left camera matrix", "D1": "the left distortion", "M2": "the right camera matrix",
         "D2": "the right distortion", "R": "the stereo rotation", "T": "the stereo translation"}


def _plain_name(name: str) -> str:
    """A matrix name as :data:`OPENCV_NAMES` compares them: lower case, no ``_``, ``-`` or ``.``."""
    return name.lower().replace("_", "").replace("-", "").replace(".", "")


def read_scared_yaml(path: str | Path, image_size: Optional[Sequence[int]] = None) -> RawStereoCalibration:
    """Read an OpenCV FileStorage stereo calibration (YAML or XML, ``!!opencv-matrix`` nodes), such
    as SCARED's ``endoscope_calibration.yaml``.

    Matrices ``M1 D1 M2 D2 R T`` (``T`` in mm, ``X_right = R X_left + T``), or the same under the
    other names of :data:`OPENCV_NAMES` (``M_l D_l M_r D_r R T``, ``cameraMatrix1``, ...). The
    image size is taken from the file when present (``width``/``height``,
    ``image_width``/``image_height``, ``Camera.width``/``Camera.height`` or a 2-vector
    ``image_size``/``imageSize``), else from ``image_size`` = ``(width, height)`` given by the
    caller, else None (SCARED files usually have none: :func:`fit_to_frames` decides it from the
    principal point).
    """
    import cv2

    path = calibration_file(path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except Exception as exc:  # cv2.error, or SystemError wrapping it (OpenCV 5 bindings)
        raise DataError(f"{path}: cannot parse OpenCV calibration file ({_one_line(exc)})") from None
    if not fs.isOpened():
        raise DataError(f"{path}: cannot open OpenCV calibration file")
    try:
        names = {_plain_name(key): key for key in fs.root().keys()}

        def matrix(key: str, shape: tuple[int, ...] | None) -> np.ndarray:
            found = [names[_plain_name(alias)] for alias in OPENCV_NAMES[key] if _plain_name(alias) in names]
            if not found:
                raise DataError(f"{path}: missing matrix '{key}' ({_WHAT[key]}; also read as "
                                f"{', '.join(OPENCV_NAMES[key][1:])})")
            name = found[0]
            node = fs.getNode(name)
            if node.empty() or node.isNone():
                raise DataError(f"{path}: missing matrix '{name}' ({_WHAT[key]})")
            if node.isSeq():
                values = [node.at(i).real() for i in range(node.size())]
                mat = np.asarray(values, dtype=np.float64)
            else:
                mat = node.mat()
                if mat is None:
                    raise DataError(f"{path}: '{name}' is not a matrix")
                mat = np.asarray(mat, dtype=np.float64)
            if shape is not None:
                if mat.size != int(np.prod(shape)):
                    raise DataError(f"{path}: '{name}' has {mat.size} values, expected {int(np.prod(shape))}")
                mat = mat.reshape(shape)
            return mat

        K1 = matrix("M1", (3, 3))
        D1 = matrix("D1", None).reshape(-1)
        K2 = matrix("M2", (3, 3))
        D2 = matrix("D2", None).reshape(-1)
        R = matrix("R", None)
        if R.size == 3:  # a Rodrigues vector
            R = cv2.Rodrigues(R.reshape(3, 1))[0]
        elif R.size == 9:
            R = R.reshape(3, 3)
        else:
            raise DataError(f"{path}: 'R' has {R.size} values, expected 9 (or a 3-vector)")
        T = matrix("T", (3,))
        size = _filestorage_size(fs)
    finally:
        fs.release()
    if size is None and image_size is not None:
        size = (int(image_size[0]), int(image_size[1]))
    return RawStereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T, image_size=size, source=path).validate()


def _filestorage_size(fs) -> Optional[tuple[int, int]]:
    def scalar(key: str) -> Optional[float]:
        node = fs.getNode(key)
        if node.empty() or node.isNone():
            return None
        if node.isInt() or node.isReal():
            return float(node.real())
        if node.isString():
            try:
                return float(node.string())
            except ValueError:
                return None
        return None

    for wkey, hkey in _SIZE_PAIRS:
        w, h = scalar(wkey), scalar(hkey)
        if w is not None and h is not None and w > 0 and h > 0:
            return int(round(w)), int(round(h))
    for key in _SIZE_VECTORS:
        node = fs.getNode(key)
        if node.empty() or node.isNone():
            continue
        if node.isSeq() and node.size() == 2:
            w, h = node.at(0).real(), node.at(1).real()
        else:
            mat = node.mat()
            if mat is None or mat.size != 2:
                continue
            w, h = mat.reshape(-1)[:2]
        if w > 0 and h > 0:
            return int(round(w)), int(round(h))
    return None


# --------------------------------------------------------------------------------------------
# Plain folders: calibration.yaml (already rectified)
# --------------------------------------------------------------------------------------------

_PLAIN_KEYS = ("fx", "fy", "cx", "cy", "baseline_mm", "width", "height")


def read_plain_yaml(path: str | Path) -> StereoCamera:
    """Read the ``calibration.yaml`` of a plain folder of *rectified* stereo images.

    Format (YAML mapping, all keys required, lengths in mm, pixel coordinates with the origin at
    the centre of the top-left pixel)::

        fx: 520.0          # focal length, pixels (shared by both rectified views)
        fy: 520.0
        cx: 319.5          # principal point, pixels
        cy: 255.5
        baseline_mm: 4.3   # distance between the optical centres; the right view is at +x
        width: 640         # image size the intrinsics refer to (the PNGs' size)
        height: 512

    Unknown keys are ignored (e.g. a ``comment``).
    """
    import yaml

    path = calibration_file(path)
    try:
        with open(path, encoding="utf-8") as fh:
            data = yaml.safe_load(fh)
    except (yaml.YAMLError, OSError, UnicodeError) as exc:
        raise DataError(f"{path}: cannot parse YAML ({_one_line(exc)})") from None
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a mapping with keys {', '.join(_PLAIN_KEYS)}")
    values = {}
    for key in _PLAIN_KEYS:
        if key not in data:
            raise DataError(f"{path}: missing key '{key}'")
        raw = data[key]
        if isinstance(raw, bool):
            raise DataError(f"{path}: '{key}' is not a number: {raw!r}")
        try:
            value = float(raw)
        except (TypeError, ValueError):
            raise DataError(f"{path}: '{key}' is not a number: {raw!r}") from None
        if not math.isfinite(value):
            raise DataError(f"{path}: '{key}' is not finite")
        values[key] = value
    for key in ("fx", "fy", "baseline_mm", "width", "height"):
        if values[key] <= 0:
            raise DataError(f"{path}: '{key}' must be positive, got {values[key]:g}")
    for key in ("width", "height"):
        if values[key] != int(values[key]):
            raise DataError(f"{path}: '{key}' must be an integer, got {values[key]:g}")
    K = np.array([[values["fx"], 0.0, values["cx"]], [0.0, values["fy"], values["cy"]], [0.0, 0.0, 1.0]])
    return StereoCamera(K=K, baseline_mm=values["baseline_mm"], width=int(values["width"]), height=int(values["height"]))


# --------------------------------------------------------------------------------------------
# This project's JSON calibration
# --------------------------------------------------------------------------------------------

def read_json_calibration(path: str | Path) -> RawStereoCalibration:
    """Read a stereo calibration in this project's JSON format::

        {
          "left":  {"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "D": [k1, k2, p1, p2, k3]},
          "right": {"K": [[...], [...], [...]],                  "D": [...]},
          "R": [[...], [...], [...]],        # X_right = R X_left + T (OpenCV's stereo convention)
          "T": [tx, ty, tz],                 # mm; a right camera to the right of the left: tx < 0
          "image_size": [width, height]      # optional: the size the intrinsics refer to
        }

    ``D`` may be omitted or empty (no distortion: rectified views with ``R`` the identity).
    """
    import json

    path = calibration_file(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, OSError, UnicodeError) as exc:
        raise DataError(f"{path}: cannot parse JSON ({_one_line(exc)})") from None
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected an object with 'left', 'right', 'R' and 'T'")

    def array(value, key: str, size: int | None) -> np.ndarray:
        try:
            arr = np.asarray(value, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise DataError(f"{path}: '{key}' is not a list of numbers") from None
        if size is not None and arr.size != size:
            raise DataError(f"{path}: '{key}' has {arr.size} values, expected {size}")
        if not np.all(np.isfinite(arr)):
            raise DataError(f"{path}: '{key}' is not finite")
        return arr

    def camera(side: str) -> tuple[np.ndarray, np.ndarray]:
        cam = data.get(side)
        if not isinstance(cam, dict) or "K" not in cam:
            raise DataError(f"{path}: missing '{side}' with its 'K'")
        D = cam.get("D") or [0.0, 0.0, 0.0, 0.0, 0.0]
        return array(cam["K"], f"{side}.K", 9).reshape(3, 3), array(D, f"{side}.D", None)

    for key in ("R", "T"):
        if key not in data:
            raise DataError(f"{path}: missing '{key}'")
    K1, D1 = camera("left")
    K2, D2 = camera("right")
    R = array(data["R"], "R", None)
    if R.size == 3:
        import cv2

        R = cv2.Rodrigues(R.reshape(3, 1))[0]
    elif R.size != 9:
        raise DataError(f"{path}: 'R' has {R.size} values, expected 9 (or a rotation vector of 3)")
    size = None
    if data.get("image_size") is not None:
        wh = array(data["image_size"], "image_size", 2)
        size = (int(round(wh[0])), int(round(wh[1])))
    return RawStereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, R=R.reshape(3, 3), T=array(data["T"], "T", 3),
                                image_size=size, source=path).validate()


# --------------------------------------------------------------------------------------------
# Any calibration file, and whether it fits the frames
# --------------------------------------------------------------------------------------------

#: the calibration files a sequence folder may hold, in the order they are looked for
CALIBRATION_NAMES = ("StereoCalibration.ini", "endoscope_calibration.yaml", "calibration.yaml", "calibration.json")


def read_calibration(path: str | Path) -> RawStereoCalibration | StereoCamera:
    """Any calibration file the project reads, told apart by its extension and content: a StereoMIS
    ``.ini``, this project's ``.json``, an OpenCV FileStorage ``.xml``, or a ``.yaml``/``.yml``
    holding either OpenCV's ``M1 D1 M2 D2 R T`` (SCARED, or another naming of
    :data:`OPENCV_NAMES`; a raw calibration: the file starts with OpenCV's ``%YAML:1.0`` or holds
    ``!!opencv-matrix`` nodes) or ``fx fy cx cy baseline_mm`` (a plain, rectified camera)."""
    path = calibration_file(path)
    suffix = path.suffix.lower()
    if suffix == ".ini":
        return read_stereomis_ini(path)
    if suffix == ".json":
        return read_json_calibration(path)
    if suffix in (".yaml", ".yml", ".xml"):
        text = path.read_text(encoding="utf-8", errors="replace")
        if suffix == ".xml" or text.lstrip().startswith("%YAML:") or "opencv-matrix" in text or "M1" in text:
            return read_scared_yaml(path)       # OpenCV's FileStorage (its header, its matrices)
        return read_plain_yaml(path)
    raise DataError(f"{path}: unknown calibration format (expected .ini, .json, .yaml, .yml or .xml)")


def is_rectified(calib: RawStereoCalibration, tol_px: float = 0.5, tol_rad: float = 1e-4) -> bool:
    """Whether a raw calibration describes views that are rectified already: no distortion, no
    rotation between the cameras, the same focal lengths and principal row, the right camera
    displaced along x only (within ``tol_px`` pixels and ``tol_rad`` radians)."""
    no_distortion = np.abs(calib.D1).max() < 1e-9 and np.abs(calib.D2).max() < 1e-9
    angle = math.acos(max(-1.0, min(1.0, (float(np.trace(calib.R)) - 1.0) / 2.0)))
    K1, K2 = calib.K1, calib.K2
    same_camera = (abs(K1[0, 0] - K2[0, 0]) < tol_px and abs(K1[1, 1] - K2[1, 1]) < tol_px
                   and abs(K1[1, 2] - K2[1, 2]) < tol_px and abs(K1[0, 1]) < 1e-9 and abs(K2[0, 1]) < 1e-9)
    along_x = math.hypot(calib.T[1], calib.T[2]) < 1e-3 * max(abs(calib.T[0]), 1e-9)
    return bool(no_distortion and angle < tol_rad and same_camera and along_x)


def rectified_camera(calib: RawStereoCalibration) -> StereoCamera:
    """The :class:`StereoCamera` of a calibration :func:`is_rectified` accepts (its image size known)."""
    w, h = calib.image_size
    return StereoCamera(K=calib.K1.copy(), baseline_mm=abs(float(calib.T[0])), width=w, height=h)


def _scaled(calib: RawStereoCalibration, factor: float, size: tuple[int, int]) -> RawStereoCalibration:
    S = np.diag([factor, factor, 1.0])
    # pixel centres: x' + 0.5 = factor (x + 0.5)
    shift = np.array([[0.0, 0.0, 0.5 * (factor - 1.0)], [0.0, 0.0, 0.5 * (factor - 1.0)], [0.0, 0.0, 0.0]])
    K1, K2 = S @ calib.K1 + shift, S @ calib.K2 + shift
    return RawStereoCalibration(K1=K1, D1=calib.D1, K2=K2, D2=calib.D2, R=calib.R, T=calib.T, image_size=size,
                                source=calib.source)


def fit_calibration(calib: RawStereoCalibration, frame_size: tuple[int, int]) -> RawStereoCalibration:
    """:func:`fit_to_frames`, logging a scaled calibration."""
    fitted, factor = fit_to_frames(calib, frame_size)
    if factor != 1.0:
        log.info("%s: calibration made at %gx the frames' size: intrinsics scaled by %g", calib.name(),
                 1.0 / factor, factor)
    return fitted


#: what a calibration of larger images than the frames needs when the frames are a crop of them
CROP_HINT = ("frames cropped from the calibrated images need the calibration of the crop: the crop's size, "
             "and each principal point less the crop's offset")


def _size_mismatch(where: str, calib_size: tuple[int, int], frame_size: tuple[int, int]) -> DataError:
    """The error of a calibration made for ``calib_size`` used with frames of ``frame_size``
    (``(width, height)`` each), with :data:`CROP_HINT` where the frames fit inside those images."""
    (cw, ch), (W, H) = calib_size, frame_size
    hint = f"; {CROP_HINT}" if W <= cw and H <= ch else ""
    return DataError(f"{where}: calibration for {cw}x{ch} images does not fit frames of {W}x{H} "
                     f"(neither equal nor an integer multiple or fraction of them{hint})")


def check_principal_points(where: str, cameras: dict[str, np.ndarray], frame_size: tuple[int, int]) -> None:
    """DataError naming ``where`` when the principal point of one of ``cameras`` (label ->
    ``(3, 3)`` intrinsics, already at the frames' size) lies outside frames of ``frame_size``:
    intrinsics of other images (another size, a crop)."""
    W, H = frame_size
    for label, K in cameras.items():
        cx, cy = float(K[0, 2]), float(K[1, 2])
        if not (-0.5 <= cx <= W - 0.5 and -0.5 <= cy <= H - 0.5):
            raise DataError(f"{where}: the {label} principal point ({cx:.1f}, {cy:.1f}) lies outside the "
                            f"{W}x{H} frames: intrinsics of other images ({CROP_HINT})")


def fit_camera(camera: StereoCamera, frame_size: tuple[int, int], where: str,
               max_factor: int = 4) -> StereoCamera:
    """A rectified camera (a plain ``calibration.yaml``) at the frames' ``(width, height)``: as it
    is when its size is theirs, scaled (and logged) when it is an integer multiple or fraction of
    it up to ``max_factor``, the rule of :func:`fit_to_frames`; else DataError naming ``where``
    (also when its principal point lies outside the frames, :func:`check_principal_points`)."""
    W, H = int(frame_size[0]), int(frame_size[1])
    cw, ch = int(camera.width), int(camera.height)
    fitted = camera if (cw, ch) == (W, H) else None
    for k in range(2, max_factor + 1):
        if fitted is None and ((cw, ch) == (k * W, k * H) or (k * cw, k * ch) == (W, H)):
            factor = W / cw
            log.info("%s: calibration made at %gx the frames' size: intrinsics scaled by %g", where, 1.0 / factor,
                     factor)
            fitted = camera.scaled(W, H)
    if fitted is None:
        raise _size_mismatch(where, (cw, ch), (W, H))
    check_principal_points(where, {"rectified": fitted.K}, (W, H))
    return fitted


def fit_to_frames(calib: RawStereoCalibration, frame_size: tuple[int, int],
                  max_factor: int = 4) -> tuple[RawStereoCalibration, float]:
    """The calibration at the frames' ``(width, height)``, and the factor its intrinsics were
    scaled by (1: it fits as it is).

    With an image size in the file, it must be the frames' or an integer multiple or fraction of
    it (the aspect ratio kept). Without one, the principal point decides: near ``(W/2, H/2)`` the
    calibration is the frames'; near ``(k W/2, k H/2)`` it was made at ``k`` times their size
    (a SCARED calibration of 1280x1024 views used with frames halved to 640x512), and likewise at
    a ``1/k`` fraction. Raises DataError naming the file when no factor up to ``max_factor`` fits,
    and when a principal point of the fitted calibration lies outside the frames
    (:func:`check_principal_points`).
    """
    fitted, factor = _fitted(calib, (int(frame_size[0]), int(frame_size[1])), max_factor)
    check_principal_points(calib.name(), {"left": fitted.K1, "right": fitted.K2}, fitted.image_size)
    return fitted, factor


def _fitted(calib: RawStereoCalibration, frame_size: tuple[int, int], max_factor: int
            ) -> tuple[RawStereoCalibration, float]:
    """:func:`fit_to_frames` but for the principal points' check."""
    W, H = frame_size
    where = calib.name()
    if calib.image_size is not None:
        cw, ch = calib.image_size
        if (cw, ch) == (W, H):
            return calib, 1.0
        for k in range(2, max_factor + 1):
            if (cw, ch) == (k * W, k * H):
                return _scaled(calib, 1.0 / k, (W, H)), 1.0 / k
            if (k * cw, k * ch) == (W, H):
                return _scaled(calib, float(k), (W, H)), float(k)
        raise _size_mismatch(where, (cw, ch), (W, H))
    cx, cy = 0.5 * (calib.K1[0, 2] + calib.K2[0, 2]), 0.5 * (calib.K1[1, 2] + calib.K2[1, 2])
    candidates = [float(k) for k in range(1, max_factor + 1)] + [1.0 / k for k in range(2, max_factor + 1)]
    for scale in candidates:        # scale = calibration size / frame size
        # the principal point within a fifth of the half-size of the image centre, on both axes
        if abs(cx - scale * W / 2) < 0.2 * scale * W / 2 and abs(cy - scale * H / 2) < 0.2 * scale * H / 2:
            size = (int(round(scale * W)), int(round(scale * H)))
            fitted = RawStereoCalibration(K1=calib.K1, D1=calib.D1, K2=calib.K2, D2=calib.D2, R=calib.R,
                                          T=calib.T, image_size=size, source=calib.source)
            if scale == 1.0:
                return fitted, 1.0
            return _scaled(fitted, 1.0 / scale, (W, H)), 1.0 / scale
    raise DataError(f"{where}: its principal point ({cx:.0f}, {cy:.0f}) fits no calibration size for frames "
                    f"of {W}x{H} (expected near ({W / 2:.0f}, {H / 2:.0f}) or an integer multiple of it; "
                    f"{CROP_HINT})")


def calibration_file(path: str | Path) -> Path:
    """``path`` as a Path once it is known to hold something: DataError naming it when it is
    missing, unreadable or empty (zero bytes or whitespace only; every reader says so the same way
    rather than as a missing section or key)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: calibration file not found")
    try:
        content = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read calibration file ({exc.strerror or exc})") from None
    if not content.strip():
        raise DataError(f"{path}: empty calibration file")
    return path


def _one_line(exc: BaseException) -> str:
    """A short one-line description of an exception (OpenCV's multi-line errors condensed)."""
    if exc.__cause__ is not None and isinstance(exc, SystemError):
        exc = exc.__cause__
    text = " ".join(str(exc).split())
    marker = text.find("error: (")
    if marker >= 0:  # "OpenCV(5.0.0) /path/file.cpp:365: error: (-212:Parsing error) ..." -> the part after "error:"
        text = text[marker + len("error: "):]
    return text[:200] if text else type(exc).__name__
