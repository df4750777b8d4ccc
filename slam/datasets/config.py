"""Configuration of the dataset readers (one concern: how frames are read and prepared)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class DataConfig:
    """How a sequence folder is read.

    Attributes:
        layout: ``auto`` (detect from the folder) or one of ``stereomis``, ``stereomis_raw``,
            ``scared``, ``plain``.
        rectified: ``auto`` | ``yes`` | ``no``. ``auto``: pre-processed StereoMIS and plain folders
            are rectified, video layouts (StereoMIS raw, SCARED) are not.
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
        fps: frame rate used for timestamps when the sequence has no ground truth.
    """

    layout: str = "auto"
    rectified: str = "auto"
    rectify_mode: str = "full"
    width: int = 0
    height: int = 0
    use_mask_files: bool = True
    specular_threshold: float = 0.96
    specular_dilate_px: int = 3
    dark_threshold: float = 0.04
    fps: float = 25.0
