"""Appearance loop candidates (slam.tracking.place_recognition): ORB against a keyframe, PnP for the pose."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from slam.config import load_config
from slam.io.datasets import open_dataset
from slam.tracking.place_recognition import PlaceRecognition


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    from slam.synth import generate

    data = tmp_path_factory.mktemp("places") / "rigid"
    generate(data, "rigid", frames=40, size=(320, 256), seed=11)
    return open_dataset(data, load_config(None, []).data)


def _rect_pose(dataset, k: int) -> np.ndarray:
    R1 = np.eye(4)
    R1[:3, :3] = dataset.R1
    return dataset.frame(k).gt_pose @ R1.T


def _gray(frame) -> np.ndarray:
    return cv2.cvtColor(frame.left, cv2.COLOR_RGB2GRAY)


def test_pose_from_a_keyframe_seen_again(scan):
    places = PlaceRecognition(scan.camera.K, scan.camera.width)
    first = scan.frame(0)
    assert places.add(0, _gray(first), first.gt_depth, first.mask & (first.gt_depth > 0)) >= 100
    other = scan.frame(8)
    match = places.query(_gray(other), other.mask, [0])
    assert match is not None and match.position == 0 and match.inliers >= 50
    truth = np.linalg.inv(_rect_pose(scan, 0)) @ _rect_pose(scan, 8)
    assert np.linalg.norm(truth[:3, 3]) > 2.0            # the camera moved
    # a start for the dense registration (which converges from several mm): PnP on pixel-
    # quantised ORB keypoints at 320x256 and 70 mm depth is good to about a millimetre
    error = np.linalg.inv(truth) @ match.relative
    assert np.linalg.norm(error[:3, 3]) < 1.5             # mm
    assert np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1))) < 1.5


def test_no_match_on_other_tissue(scan, tmp_path):
    from slam.synth import generate

    other = tmp_path / "other"
    generate(other, "rigid", frames=1, size=(320, 256), seed=12)
    elsewhere = open_dataset(other, load_config(None, []).data).frame(0)
    places = PlaceRecognition(scan.camera.K, scan.camera.width)
    first = scan.frame(0)
    places.add(0, _gray(first), first.gt_depth, first.mask & (first.gt_depth > 0))
    assert places.query(_gray(elsewhere), elsewhere.mask, [0]) is None
    places.remove(0)
    assert places.query(_gray(scan.frame(1)), None, [0]) is None
