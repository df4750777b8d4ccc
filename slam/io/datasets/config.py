"""Configuration of the dataset readers (one concern: how frames are read and prepared)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

LAYOUTS = ("stereomis", "stereomis_raw", "scared", "plain", "frames", "video")
#: the smallest frame side the tracking takes (pixels): OpenCV's DIS optical flow refuses smaller images
MIN_FRAME_PX = 12


def fixed(why: str, default):
    """A field a person does not set (``slam.schema``): a constant of the readers."""
    return field(default=default, metadata={"fixed": why})


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
            (the configs for StereoMIS and SCARED use 640x512, the paper's half resolution); at
            least :data:`MIN_FRAME_PX` each.
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

    layout: Literal["auto", "stereomis", "stereomis_raw", "scared", "plain", "frames", "video"] = "auto"
    calibration: str = ""
    rectified: Literal["auto", "yes", "no"] = "auto"
    stereo_layout: Literal["auto", "top-bottom", "side-by-side"] = "auto"
    rectify_mode: Literal["full", "pseudo"] = "full"
    width: int = 0
    height: int = 0
    use_mask_files: bool = True
    fps: float = 0.0
    specular_threshold: float = fixed("near-saturated pixels are the light's mirror image", 0.96)
    specular_dilate_px: int = fixed("the highlight's halo", 3)
    dark_threshold: float = fixed("a few grey levels of signal", 0.04)

    def __post_init__(self):
        def need(ok: bool, message: str) -> None:
            if not ok:
                raise ValueError(message)

        need(self.width >= 0 and self.height >= 0, "data.width/height must be >= 0 (0 = native size)")
        need((self.width == 0) == (self.height == 0), "data.width and data.height: set both or neither")
        need(self.width == 0 or min(self.width, self.height) >= MIN_FRAME_PX,
             f"data.width and data.height must be at least {MIN_FRAME_PX} px (the optical flow's smallest image), "
             f"got {self.width}x{self.height}")
        need(self.fps >= 0, "data.fps must be >= 0 (0 = from the data)")
        need(0 < self.specular_threshold, "data.specular_threshold must be > 0 (> 1 disables)")
        need(0 <= self.dark_threshold < 1, "data.dark_threshold must be in [0, 1) (0 disables)")
        need(self.specular_dilate_px >= 0, "data.specular_dilate_px must be >= 0")
