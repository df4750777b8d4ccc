"""Configuration of the dataset readers (one concern: how frames are read and prepared)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class DataConfig:
    """How a sequence folder is read.

    Attributes:
        layout: ``auto`` (detect from the folder) or one of ``stereomis``, ``stereomis_raw``,
            ``scared``, ``plain``, ``frames``, ``video`` (docs/inputs.md).
        calibration: a calibration file to use instead of the sequence's own (any format
            :func:`slam.io.calibration.read_calibration` reads; ``slam run --calibration``).
        rectified: ``auto`` | ``yes`` | ``no``. ``auto``: pre-processed StereoMIS and plain folders
            are rectified, StereoMIS raw and SCARED videos are not; frame folders and video files
            are rectified when their calibration says so (no distortion, no rotation between the
            cameras).
        stereo_layout: how a stereo video file holds its two views: ``auto`` (from the
            calibration's image size against the video frame, then the aspect ratio),
            ``top-bottom`` (left above right) or ``side-by-side`` (left beside right).
        rectify_mode: ``full`` (OpenCV stereoRectify, zero disparity offset) or ``pseudo`` (undistort
            and align the principal points only; SCARED's calibrations are poor for full rectification).
        width, height: size frames are resized to (intrinsics scaled); 0 keeps the native size
            (the configs for StereoMIS and SCARED use 640x512, the paper's half resolution).
        use_mask_files: combine the dataset's instrument masks (``masks/``) when present.
        specular_threshold: a pixel whose maximum channel intensity (0-1) reaches this is specular.
        specular_dilate_px: radius of the dilation applied to the specular mask.
        dark_threshold: a pixel whose maximum channel intensity (0-1) is below this is too dark to
            match (a few grey levels of signal: black borders, unlit depths, a frame the light
            failed on) and invalid; 0 disables. A frame dark all over then fails to track (pose
            carried over, nothing fused) instead of giving a wrong pose.
        fps: the frames' rate when they carry no timestamps (no ``timestamps.txt``, no ground truth
            with one pose per frame); 0 = from the data (a video's header), else 25. Thresholds
            on the motion per frame are scaled by it (``slam.config.at_frame_rate``).
    """

    layout: str = "auto"
    calibration: str = ""
    rectified: str = "auto"
    stereo_layout: str = "auto"
    rectify_mode: str = "full"
    width: int = 0
    height: int = 0
    use_mask_files: bool = True
    specular_threshold: float = 0.96
    specular_dilate_px: int = 3
    dark_threshold: float = 0.04
    fps: float = 0.0
