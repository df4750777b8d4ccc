"""The tracking view of one dataset frame: stereo depth, or the generator's exact depth when an
analysis asks for it (``analysis.depth_source: groundtruth``), shared by the pipeline, the
training's pair cache and the analysis tools."""
from __future__ import annotations

from pathlib import Path

from slam.io.datasets.base import StereoFrame
from slam.errors import SlamError
from vo.odometry import StereoOdometry, View


def frame_view(odometry: StereoOdometry, frame: StereoFrame, dataset_path: str | Path,
               timings: dict | None = None, depth_source: str = "stereo") -> View:
    """``odometry``'s view of ``frame``, with its depth from ``depth_source`` (``stereo``, or
    ``groundtruth``: the generator's exact depth).

    Raises:
        SlamError: ``groundtruth`` on a frame without ground-truth depth (naming ``dataset_path``).
    """
    gt_depth = None
    if depth_source == "groundtruth":
        gt_depth = frame.gt_depth
        if gt_depth is None:
            raise SlamError(f"{dataset_path}: analysis.depth_source=groundtruth needs ground-truth depth maps "
                            "(synthetic data)")
    return odometry.make_view(frame.left, frame.right, frame.mask, gt_depth, timings, frame.specular)
