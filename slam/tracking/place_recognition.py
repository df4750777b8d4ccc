"""Appearance loop candidates: ORB features of the graph keyframes, matched against a frame and
solved for its pose by PnP (OpenCV), for a drift too large for the inactive model rendered at the
tracked pose to overlap the frame.

Per graph keyframe (:meth:`PlaceRecognition.add`) the left image's ORB keypoints where the depth
is valid are kept with their 3D points in the keyframe's camera (mm) and their descriptors: a few
tens of kilobytes a keyframe. A query (:meth:`PlaceRecognition.query`) matches the frame's ORB
descriptors against each candidate keyframe's (Lowe's ratio test), solves the frame's pose in the
keyframe's camera from the matched 3D points by RANSAC PnP, and returns the keyframe with the
most inliers, if it has :data:`MIN_INLIERS`. The pose is only a starting point: the tracker
renders the inactive model there and registers the frame against it with the dense tracker,
which the loop's verification and the pose graph's gate then judge.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional

import cv2
import numpy as np

# ORB features per image (OpenCV's default count), with a lower FAST threshold than OpenCV's 20
# and a smaller patch (31 px): tissue is low in contrast and small endoscopic images lose a
# patch's width at every border
ORB_FEATURES = 500
ORB_FAST_THRESHOLD = 10
ORB_PATCH_PX = 19
# Lowe's ratio test between the best and second-best descriptor distance
MATCH_RATIO = 0.8
# matches a keyframe needs before PnP is tried, and PnP inliers a match needs
MIN_MATCHES = 30
MIN_INLIERS = 25
# RANSAC's reprojection threshold, pixels at 320 px image width (scaled with the width)
REPROJECTION_PX_AT_320 = 2.0
# RANSAC's iterations
_RANSAC_ITERATIONS = 200


@dataclass
class KeyframeFeatures:
    """A keyframe's ORB features: ``descriptors`` ``(N, 32)`` uint8 and ``points`` ``(N, 3)``
    float32 in the keyframe's camera (mm)."""

    descriptors: np.ndarray
    points: np.ndarray


@dataclass
class AppearanceMatch:
    """A keyframe the frame looks like.

    Attributes:
        position: the keyframe's frame (sequence position).
        relative: ``(4, 4)`` the frame's pose in the keyframe's camera, ``T_kf_cur`` (mm).
        matches: descriptor matches that passed the ratio test.
        inliers: PnP's RANSAC inliers among them.
    """

    position: int
    relative: np.ndarray
    matches: int
    inliers: int


class PlaceRecognition:
    """The ORB features of a sequence's graph keyframes.

    Args:
        K: ``(3, 3)`` rectified left intrinsics (pixels).
        width: image width (pixels; scales the RANSAC threshold).
    """

    def __init__(self, K: np.ndarray, width: int):
        self.K = np.asarray(K, dtype=np.float64)
        self.orb = cv2.ORB_create(nfeatures=ORB_FEATURES, fastThreshold=ORB_FAST_THRESHOLD,
                                  edgeThreshold=ORB_PATCH_PX, patchSize=ORB_PATCH_PX)
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.reprojection_px = REPROJECTION_PX_AT_320 * width / 320.0
        self.keyframes: dict[int, KeyframeFeatures] = {}

    def _detect(self, gray: np.ndarray, mask: Optional[np.ndarray]) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """``(N, 2)`` keypoint pixels and ``(N, 32)`` descriptors of ``gray`` (``(H, W)`` uint8)
        inside ``mask`` (``(H, W)`` bool or None: everywhere)."""
        m = None if mask is None else mask.astype(np.uint8) * 255
        keypoints, descriptors = self.orb.detectAndCompute(gray, m)
        if descriptors is None or not keypoints:
            return np.zeros((0, 2), np.float32), None
        return np.array([kp.pt for kp in keypoints], dtype=np.float32), descriptors

    def add(self, position: int, gray: np.ndarray, depth: np.ndarray, valid: np.ndarray) -> int:
        """Keep the features of the keyframe at ``position``: ``gray`` ``(H, W)`` uint8, ``depth``
        ``(H, W)`` mm, ``valid`` ``(H, W)`` bool. Returns how many were kept."""
        xy, descriptors = self._detect(gray, valid)
        if descriptors is None:
            return 0
        u = np.clip(np.round(xy[:, 0]).astype(int), 0, depth.shape[1] - 1)
        v = np.clip(np.round(xy[:, 1]).astype(int), 0, depth.shape[0] - 1)
        z = depth[v, u]
        keep = valid[v, u] & (z > 0)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        points = np.stack([(xy[:, 0] - cx) / fx * z, (xy[:, 1] - cy) / fy * z, z], 1)[keep]
        self.keyframes[int(position)] = KeyframeFeatures(descriptors[keep], points.astype(np.float32))
        return int(keep.sum())

    def remove(self, position: int) -> None:
        """Forget the keyframe at ``position`` (culled from the graph)."""
        self.keyframes.pop(int(position), None)

    def query(self, gray: np.ndarray, mask: Optional[np.ndarray], candidates: Iterable[int]) -> Optional[AppearanceMatch]:
        """The keyframe among ``candidates`` (positions) that the frame ``gray`` (``(H, W)`` uint8;
        ``mask``: the pixels to take features from, or None) matches best, with the frame's pose
        in its camera; None when none reaches :data:`MIN_INLIERS`."""
        xy, descriptors = self._detect(gray, mask)
        if descriptors is None or len(descriptors) < MIN_MATCHES:
            return None
        best: Optional[AppearanceMatch] = None
        for position in candidates:
            kf = self.keyframes.get(int(position))
            if kf is None or len(kf.descriptors) < MIN_MATCHES:
                continue
            pairs = self.matcher.knnMatch(descriptors, kf.descriptors, k=2)
            good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < MATCH_RATIO * p[1].distance]
            if len(good) < MIN_MATCHES:
                continue
            image = xy[[m.queryIdx for m in good]].astype(np.float64)
            world = kf.points[[m.trainIdx for m in good]].astype(np.float64)
            cv2.setRNGSeed(0)
            ok, rvec, tvec, inliers = cv2.solvePnPRansac(world, image, self.K, None, iterationsCount=_RANSAC_ITERATIONS,
                                                         reprojectionError=self.reprojection_px, confidence=0.999,
                                                         flags=cv2.SOLVEPNP_EPNP)
            n = 0 if inliers is None else len(inliers)
            if not ok or n < MIN_INLIERS or (best is not None and n <= best.inliers):
                continue
            idx = inliers.ravel()
            ok, rvec, tvec = cv2.solvePnP(world[idx], image[idx], self.K, None, rvec, tvec, useExtrinsicGuess=True,
                                          flags=cv2.SOLVEPNP_ITERATIVE)
            if not ok:
                continue
            T_cur_kf = np.eye(4)
            T_cur_kf[:3, :3] = cv2.Rodrigues(rvec)[0]
            T_cur_kf[:3, 3] = tvec.ravel()
            best = AppearanceMatch(int(position), np.linalg.inv(T_cur_kf), len(good), n)
        return best
