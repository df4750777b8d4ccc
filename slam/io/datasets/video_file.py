"""A stereo video file as a recorder writes it: both views in each frame, with a calibration.

::

    slam run recording.mp4 --calibration FILE [--stereo-layout top-bottom|side-by-side]

or a folder holding it::

    <seq>/
      recording.mp4 (.avi .mov .mkv ...)   exactly one video
      <calibration>                        any file slam.io.calibration.read_calibration reads: a known
                                           name, or the only .ini/.json/.yaml/.yml (a warning names it;
                                           one that is not a calibration is an error suggesting
                                           --calibration)
      timestamps.txt                       optional: one timestamp per frame (seconds)
      groundtruth.txt                      optional, TUM, metres, T_wc of the original left camera

Which half holds which view (``data.stereo_layout: auto``) is read off the calibration's image
size against the video frame (a 1280x2048 frame with a 1280x1024 calibration is top-bottom), else
off the frame's aspect ratio. Frames are rectified when the calibration says they are not
(``data.rectified: auto``, as frame folders); timestamps come from ``timestamps.txt``, else
frame index / ``data.fps`` (0: the video's own rate).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from slam.io.calibration import RawStereoCalibration
from slam.io.datasets.config import DataConfig
from slam.io.datasets.dataset import RawFrame, StereoDataset, load_groundtruth
from slam.io.datasets.frames import GT_FILE, TIMESTAMPS_FILE, calibration_processor, load_calibration
from slam.io.datasets.images import read_timestamps
from slam.io.datasets.video import VIDEO_SUFFIXES, StackedStereoVideo, frame_size_of, stereo_layout_of
from slam.errors import DataError


def find_video(path: Path) -> Path | None:
    """The video of a sequence: ``path`` itself if it is a video file, else the one video file in
    the folder (None if there is none; DataError for several)."""
    if path.is_file():
        return path if path.suffix.lower() in VIDEO_SUFFIXES else None
    videos = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
    if len(videos) > 1:
        raise DataError(f"{path}: {len(videos)} videos ({', '.join(v.name for v in videos)}); expected one")
    return videos[0] if videos else None


class VideoFileDataset(StereoDataset):
    layout = "video"

    @staticmethod
    def detect(path: Path) -> bool:
        return find_video(path) is not None

    def __init__(self, path: Path, config: DataConfig):
        path = Path(path)
        video_path = find_video(path)
        if video_path is None:
            raise DataError(f"{path}: no stereo video file ({', '.join(VIDEO_SUFFIXES)})")
        folder = path if path.is_dir() else path.parent
        calib_path, calib = load_calibration(folder, config, "the video")
        calib_size = calib.image_size if isinstance(calib, RawStereoCalibration) else (calib.width, calib.height)
        layout = stereo_layout_of(frame_size_of(video_path), calib_size, config.stereo_layout, str(calib_path),
                                  str(video_path))
        video = StackedStereoVideo(video_path, layout)
        try:
            processor = calibration_processor(calib, video.view_size, config, str(calib_path))
            n = video.num_frames
            stamps = read_timestamps(folder / TIMESTAMPS_FILE, n) if path.is_dir() else None
            fps = config.fps if config.fps > 0 else video.fps
            stamps, poses = load_groundtruth(folder / GT_FILE, n, stamps, fps)
            if stamps is None and fps > 0:
                stamps = np.arange(n, dtype=np.float64) / fps
        except Exception:
            video.close()
            raise
        super().__init__(path, config, processor, n, stamps, poses)
        self.video = video
        self.calibration_path = calib_path

    def close(self) -> None:
        self.video.close()

    def _read(self, index: int) -> RawFrame:
        left, right = self.video.read(index)
        return RawFrame(left=left, right=right, source=f"{self.video.path} frame {index}")
