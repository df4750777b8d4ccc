"""The stereo rig: rectified (pre-processed) or raw (distorted, slightly rotated right camera).

Conventions: OpenCV axes (x right, y down, z forward), pixel centres at integer coordinates,
``X_r = R X_l + T`` between the left and right camera frames, millimetres.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

BASELINE_MM = 4.5
HFOV_DEG = 60.0


@dataclass
class ViewCamera:
    """One camera of the rig.

    Attributes:
        K: ``(3, 3)`` intrinsics; dist: ``(8,)`` OpenCV coefficients k1 k2 p1 p2 k3 k4 k5 k6.
        width, height: image size.
        R_lc, C_l: rotation (camera -> left camera frame) and centre in the left camera frame.
        rays: ``(H, W, 3)`` float32 ray of every pixel in the camera's own frame, with z = 1.
    """

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    R_lc: np.ndarray
    C_l: np.ndarray
    rays: np.ndarray

    def world_rays(self, T_wl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Origin ``(3,)`` and directions ``(H, W, 3)`` (camera-z component 1) in the world."""
        R = (T_wl[:3, :3] @ self.R_lc).astype(np.float32)
        o = T_wl[:3, :3] @ self.C_l + T_wl[:3, 3]
        return o, self.rays @ R.T

    def project(self, X_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates of points ``(N, 3)`` in this camera's frame (with distortion)."""
        uv, _ = cv2.projectPoints(X_cam.reshape(-1, 1, 3).astype(np.float64), np.zeros(3), np.zeros(3), self.K, self.dist)
        return uv.reshape(-1, 2)


@dataclass
class StereoRig:
    left: ViewCamera
    right: ViewCamera
    rectified: bool

    @property
    def R(self) -> np.ndarray:
        """OpenCV stereo rotation: ``X_r = R X_l + T``."""
        return self.right.R_lc.T

    @property
    def T(self) -> np.ndarray:
        return -self.right.R_lc.T @ self.right.C_l

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.right.C_l))


def pinhole_K(width: int, height: int, hfov_deg: float = HFOV_DEG) -> np.ndarray:
    f = width / 2.0 / np.tan(np.deg2rad(hfov_deg) / 2.0)
    return np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1.0]])


def _pixel_grid(width: int, height: int) -> np.ndarray:
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([u, v], -1)


def _rays(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> np.ndarray:
    uv = _pixel_grid(width, height).reshape(-1, 1, 2)
    if np.any(dist != 0):
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        xy = cv2.undistortPoints(uv, K, dist, None, None, None, crit).reshape(-1, 2)
    else:
        xy = np.stack([(uv[:, 0, 0] - K[0, 2]) / K[0, 0], (uv[:, 0, 1] - K[1, 2]) / K[1, 1]], -1)
    rays = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    return rays.reshape(height, width, 3).astype(np.float32)


def rectified_rig(width: int, height: int) -> StereoRig:
    """The rectified pair: shared ``K`` (60 deg horizontal FOV), right camera at +4.5 mm x."""
    K = pinhole_K(width, height)
    dist = np.zeros(8)
    rays = _rays(K, dist, width, height)
    left = ViewCamera(K, dist, width, height, np.eye(3), np.zeros(3), rays)
    right = ViewCamera(K.copy(), dist.copy(), width, height, np.eye(3), np.array([BASELINE_MM, 0.0, 0.0]), rays)
    return StereoRig(left, right, rectified=True)


def raw_rig(width: int, height: int, seed: int) -> StereoRig:
    """An unrectified pair with realistic small distortion, a right camera rotated by 0.5-2 deg
    and slightly different focal lengths / principal points (seeded)."""
    rng = np.random.default_rng([seed, 6])
    s = width / 640.0

    def intrinsics():
        K = pinhole_K(width, height, HFOV_DEG + rng.uniform(-2, 2))
        K[0, 0] *= 1 + rng.normal(0, 0.004)
        K[1, 1] = K[0, 0] * (1 + rng.normal(0, 0.002))
        K[0, 2] += rng.normal(0, 4) * s
        K[1, 2] += rng.normal(0, 4) * s
        dist = np.zeros(8)
        dist[0] = -rng.uniform(0.10, 0.18)
        dist[1] = rng.uniform(0.02, 0.07)
        dist[2:4] = rng.normal(0, 4e-4, 2)
        return K, dist

    Kl, Dl = intrinsics()
    Kr, Dr = intrinsics()
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R_lr = Rotation.from_rotvec(axis * np.deg2rad(rng.uniform(0.5, 2.0))).as_matrix()  # right -> left
    C = np.array([BASELINE_MM + rng.normal(0, 0.05), rng.normal(0, 0.05), rng.normal(0, 0.1)])
    left = ViewCamera(Kl, Dl, width, height, np.eye(3), np.zeros(3), _rays(Kl, Dl, width, height))
    right = ViewCamera(Kr, Dr, width, height, R_lr, C, _rays(Kr, Dr, width, height))
    return StereoRig(left, right, rectified=False)
