"""Stereo rectification and resizing (OpenCV), computed once per sequence and applied per frame.

Two classes share one interface (``camera``, ``R1``, ``input_size``, ``output_size``,
``valid_mask``, ``rectify``, ``rectify_left_mask``, ``rectify_left_nearest``):

* :class:`StereoRectifier` turns a raw (distorted, unrectified) stereo pair described by a
  :class:`~slam.io.calibration.RawStereoCalibration` into a rectified pair at the output size.

  - ``full``: ``cv2.stereoRectify`` with ``CALIB_ZERO_DISPARITY`` (both rectified views share the
    principal point, so disparity = ``fx * baseline / depth`` exactly) and ``alpha = 0``: the
    rectified image is zoomed so that *every* output pixel maps inside the raw image. With
    ``alpha = -1``/``1`` the output keeps the whole raw field of view but gets black, undefined
    borders whose hard edges would produce spurious flow and photometric residuals in every frame;
    endoscope images are already vignetted at the corners, so the few border pixels lost to
    ``alpha = 0`` carry little information. (The reference implementation of Hayoz et al. also
    rectifies StereoMIS with ``alpha = 0``.)
  - ``pseudo``: undistort each view to a common intrinsic matrix (mean focal length, principal
    points aligned at the mean of the two) without rotating either camera (``R1 = I``). For
    calibrations whose stereo rotation is unreliable (SCARED); remaining vertical parallax is
    whatever the real stereo rotation implies.

  The undistort/rectify maps are computed once, directly at the output size (the rectified
  intrinsics are scaled, not the rectified image), and applied with ``cv2.remap``. When the output
  is at most half the input size the raw views are first shrunk by the integer factor with
  ``INTER_AREA`` (and the raw intrinsics scaled accordingly) so that downsampling does not alias.

* :class:`ResizeOnly` is for input that is already rectified: it only resizes (``INTER_AREA``
  when shrinking) and scales the intrinsics with :meth:`vo.camera.StereoCamera.scaled`.

Poses. Full rectification rotates the left camera: a point with coordinates ``X`` in the original
left camera frame has coordinates ``X_rect = R1 @ X`` in the rectified left camera frame (same
optical centre). The VO core estimates poses ``T_wc_rect`` of the *rectified* left camera; the
pose of the *original* left camera (the one ground truth refers to) is::

    T_wc_original = T_wc_rect @ [[R1, 0], [0, 1]]

(:func:`rect_to_original_pose`; the inverse mapping is :func:`original_to_rect_pose`). With
``pseudo`` rectification and :class:`ResizeOnly` ``R1`` is the identity unless given.
"""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

from slam.io.calibration import RawStereoCalibration
from slam.errors import DataError
from vo.camera import StereoCamera

RECTIFY_MODES = ("full", "pseudo")
# alpha of cv2.stereoRectify: 0 = only valid pixels in the rectified image (see module docstring).
RECTIFY_ALPHA = 0.0


def resolve_output_size(native: tuple[int, int], requested: tuple[int, int] | None) -> tuple[int, int]:
    """The output ``(width, height)``: ``(0, 0)``/None keeps ``native``; one zero keeps the aspect ratio."""
    nw, nh = int(native[0]), int(native[1])
    if requested is None:
        return nw, nh
    w, h = int(requested[0]), int(requested[1])
    if w < 0 or h < 0:
        raise ValueError(f"output size must not be negative, got {w}x{h}")
    if w == 0 and h == 0:
        return nw, nh
    if w == 0:
        w = max(1, int(round(nw * h / nh)))
    if h == 0:
        h = max(1, int(round(nh * w / nw)))
    return w, h


def rect_to_original_pose(T_wc_rect: np.ndarray, R1: np.ndarray) -> np.ndarray:
    """Pose(s) of the original left camera from pose(s) ``(..., 4, 4)`` of the rectified one."""
    M = np.eye(4)
    M[:3, :3] = R1
    return np.asarray(T_wc_rect, dtype=np.float64) @ M


def original_to_rect_pose(T_wc_original: np.ndarray, R1: np.ndarray) -> np.ndarray:
    """Pose(s) of the rectified left camera from pose(s) ``(..., 4, 4)`` of the original one."""
    M = np.eye(4)
    M[:3, :3] = np.asarray(R1).T
    return np.asarray(T_wc_original, dtype=np.float64) @ M


def _check_image(img: np.ndarray, size: tuple[int, int], what: str, source: str) -> None:
    w, h = size
    if img is None or img.ndim < 2 or img.shape[0] != h or img.shape[1] != w:
        got = "nothing" if img is None else f"{img.shape[1]}x{img.shape[0]}" if img.ndim >= 2 else str(img.shape)
        raise DataError(f"{what}: image is {got}, expected {w}x{h} ({source})")


def _scale_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics of an image resampled by ``(sx, sy)`` (pixel-centre convention, as StereoCamera.scaled)."""
    K = np.asarray(K, dtype=np.float64).copy()
    K[0, 0] *= sx
    K[0, 1] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


class StereoRectifier:
    """Rectifies and resizes raw stereo pairs (see the module docstring).

    Args:
        calib: the raw calibration; its ``image_size`` is the input size.
        mode: ``full`` or ``pseudo``.
        output_size: ``(width, height)`` of the output; ``(0, 0)`` keeps the input size.

    Attributes:
        camera: the rectified :class:`StereoCamera` at the output size
            (baseline = ``|T|`` mm, right view at +x).
        R1: ``(3, 3)`` rotation from the original to the rectified left camera frame
            (identity in ``pseudo`` mode).
        input_size, output_size: ``(width, height)``.
        valid_mask: ``(H, W)`` bool at the output size, True where the rectified left pixel maps
            inside the raw left image.
    """

    def __init__(self, calib: RawStereoCalibration, mode: str = "full", output_size: tuple[int, int] = (0, 0)):
        if mode not in RECTIFY_MODES:
            raise ValueError(f"unknown rectification mode '{mode}' (expected one of {', '.join(RECTIFY_MODES)})")
        self.calib = calib
        self.mode = mode
        self.input_size = tuple(int(v) for v in calib.image_size)
        self.output_size = resolve_output_size(self.input_size, output_size)
        W, H = self.input_size
        where = calib.name()
        baseline = calib.baseline_mm
        if mode == "full":
            R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(
                calib.K1, calib.D1, calib.K2, calib.D2, (W, H), calib.R, calib.T.reshape(3, 1),
                flags=cv2.CALIB_ZERO_DISPARITY, alpha=RECTIFY_ALPHA,
            )
            P1, P2 = np.asarray(P1, dtype=np.float64), np.asarray(P2, dtype=np.float64)
            if abs(P2[1, 3]) > abs(P2[0, 3]):
                raise DataError(f"{where}: vertical stereo rig (baseline along y) is not supported")
            if not P2[0, 3] < 0:
                raise DataError(
                    f"{where}: after rectification the right camera is not at +x of the left one "
                    f"(P2[0,3] = {P2[0, 3]:.3f} >= 0): left and right views swapped or T has the wrong sign"
                )
            K_native = P1[:3, :3].copy()
            self.R1 = np.asarray(R1, dtype=np.float64)
            self._R2 = np.asarray(R2, dtype=np.float64)
        else:
            centre_right = -calib.R.T @ calib.T  # right optical centre in the left camera frame
            if not centre_right[0] > 0:
                raise DataError(
                    f"{where}: the right camera is not at +x of the left one (its centre is at "
                    f"x = {centre_right[0]:.3f} mm): left and right views swapped or T has the wrong sign"
                )
            f = float(np.mean([calib.K1[0, 0], calib.K1[1, 1], calib.K2[0, 0], calib.K2[1, 1]]))
            cx = float(np.mean([calib.K1[0, 2], calib.K2[0, 2]]))
            cy = float(np.mean([calib.K1[1, 2], calib.K2[1, 2]]))
            K_native = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
            self.R1 = np.eye(3)
            self._R2 = np.eye(3)
        native = StereoCamera(K=K_native, baseline_mm=baseline, width=W, height=H)
        self.camera = native if self.output_size == (W, H) else native.scaled(*self.output_size)
        # integer pre-shrink with INTER_AREA when the output is at most half the input
        ow, oh = self.output_size
        self._shrink = max(1, min(W // ow, H // oh))
        self._maps: Optional[tuple] = None
        self._valid: Optional[np.ndarray] = None

    # -- maps, built lazily on first use ------------------------------------------------------
    def _build_maps(self) -> None:
        W, H = self.input_size
        k = self._shrink
        sw, sh = (W // k, H // k) if k > 1 else (W, H)
        sx, sy = sw / W, sh / H
        K1 = _scale_K(self.calib.K1, sx, sy)
        K2 = _scale_K(self.calib.K2, sx, sy)
        Knew = self.camera.K
        size = self.output_size
        lx, ly = cv2.initUndistortRectifyMap(K1, self.calib.D1, self.R1, Knew, size, cv2.CV_32FC1)
        rx, ry = cv2.initUndistortRectifyMap(K2, self.calib.D2, self._R2, Knew, size, cv2.CV_32FC1)
        self._valid = (lx >= -0.5) & (lx <= sw - 0.5) & (ly >= -0.5) & (ly <= sh - 0.5)
        left_fixed = cv2.convertMaps(lx, ly, cv2.CV_16SC2)
        right_fixed = cv2.convertMaps(rx, ry, cv2.CV_16SC2)
        self._maps = (left_fixed, right_fixed, (lx, ly))
        self._shrunk_size = (sw, sh)

    @property
    def valid_mask(self) -> np.ndarray:
        if self._maps is None:
            self._build_maps()
        return self._valid

    def _shrink_image(self, img: np.ndarray, interpolation: int) -> np.ndarray:
        if self._shrink == 1:
            return img
        return cv2.resize(img, self._shrunk_size, interpolation=interpolation)

    # -- per frame -------------------------------------------------------------------------------
    def rectify(self, left: np.ndarray, right: np.ndarray, source: str = "stereo pair") -> tuple[np.ndarray, np.ndarray]:
        """Rectify and resize a raw pair of ``(H, W, 3)`` uint8 images (RGB or BGR, kept as given).

        Raises:
            DataError: an image does not have the calibration's size (``source`` names it).
        """
        if self._maps is None:
            self._build_maps()
        _check_image(left, self.input_size, source, f"calibration {self.calib.name()}")
        _check_image(right, self.input_size, source, f"calibration {self.calib.name()}")
        (l1, l2), (r1, r2), _ = self._maps
        left = self._shrink_image(left, cv2.INTER_AREA)
        right = self._shrink_image(right, cv2.INTER_AREA)
        out_l = cv2.remap(left, l1, l2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out_r = cv2.remap(right, r1, r2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out_l, out_r

    def rectify_left_nearest(self, image: np.ndarray, source: str = "left image") -> np.ndarray:
        """Map a raw left-view array (mask, depth, labels; any dtype) to the output, nearest
        neighbour, 0 outside the raw image."""
        if self._maps is None:
            self._build_maps()
        _check_image(image, self.input_size, source, f"calibration {self.calib.name()}")
        image = self._shrink_image(image, cv2.INTER_NEAREST)
        _, _, (lx, ly) = self._maps
        return cv2.remap(image, lx, ly, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def rectify_left_mask(self, mask: np.ndarray, source: str = "mask") -> np.ndarray:
        """Map a raw left-view boolean mask (True/non-zero = keep) to the output; False outside."""
        out = self.rectify_left_nearest(np.asarray(mask).astype(np.uint8), source)
        return out > 0


class ResizeOnly:
    """For already-rectified input: resizes the pair and scales the intrinsics.

    Args:
        camera: the rectified camera at the input (native) size.
        output_size: ``(width, height)``; ``(0, 0)`` keeps the native size.
        R1: rotation from the original to the rectified left camera frame when the rectified
            input was produced by rectifying a raw rig (identity when None).
    """

    def __init__(self, camera: StereoCamera, output_size: tuple[int, int] = (0, 0), R1: Optional[np.ndarray] = None):
        self.input_size = (int(camera.width), int(camera.height))
        self.output_size = resolve_output_size(self.input_size, output_size)
        self.camera = camera if self.output_size == self.input_size else camera.scaled(*self.output_size)
        self.R1 = np.eye(3) if R1 is None else np.asarray(R1, dtype=np.float64).reshape(3, 3)
        self.mode = "resize"
        self._valid = np.ones((self.output_size[1], self.output_size[0]), dtype=bool)

    @property
    def valid_mask(self) -> np.ndarray:
        return self._valid

    def _interp(self) -> int:
        ow, oh = self.output_size
        iw, ih = self.input_size
        return cv2.INTER_AREA if (ow <= iw and oh <= ih) else cv2.INTER_LINEAR

    def _resize(self, img: np.ndarray, interpolation: int) -> np.ndarray:
        if self.output_size == self.input_size:
            return img
        return cv2.resize(img, self.output_size, interpolation=interpolation)

    def rectify(self, left: np.ndarray, right: np.ndarray, source: str = "stereo pair") -> tuple[np.ndarray, np.ndarray]:
        _check_image(left, self.input_size, source, "rectified camera size")
        _check_image(right, self.input_size, source, "rectified camera size")
        interp = self._interp()
        return self._resize(left, interp), self._resize(right, interp)

    def rectify_left_nearest(self, image: np.ndarray, source: str = "left image") -> np.ndarray:
        _check_image(image, self.input_size, source, "rectified camera size")
        return self._resize(image, cv2.INTER_NEAREST)

    def rectify_left_mask(self, mask: np.ndarray, source: str = "mask") -> np.ndarray:
        return self.rectify_left_nearest(np.asarray(mask).astype(np.uint8), source) > 0


def make_rectifier(
    calib: RawStereoCalibration, mode: str, output_size: tuple[int, int], already_rectified: bool
) -> StereoRectifier | ResizeOnly:
    """The frame processor for a raw calibration.

    ``already_rectified``: the images were rectified beforehand with this calibration (e.g. the
    pre-processed StereoMIS frames): the rectified camera and ``R1`` are those ``mode`` rectification
    would produce at the native size, and the images are only resized.
    """
    if not already_rectified:
        return StereoRectifier(calib, mode, output_size)
    native = StereoRectifier(calib, mode, (0, 0))  # no maps are built: only camera and R1 are used
    return ResizeOnly(native.camera, output_size, R1=native.R1)
