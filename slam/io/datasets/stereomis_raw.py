"""StereoMIS, raw layout: the recorded stereo video.

::

    <seq>/
      <name>.mp4                 exactly one; each frame holds the left view on top of the right view
      StereoCalibration.ini      raw calibration (see slam.io.calibration)
      groundtruth.txt            optional, TUM, metres, T_wc of the original left camera
      masks/000000l.png ...      optional, by frame index, non-zero = tissue, 0 = instrument

The video is not rectified (``rectified: auto`` = no): frames are rectified with the calibration
in ``rectify_mode``.
"""
from __future__ import annotations

from pathlib import Path

from slam.io.calibration import fit_calibration, read_stereomis_ini
from slam.io.datasets.config import DataConfig
from slam.io.datasets.dataset import RawFrame, StereoDataset, load_groundtruth, read_mask
from slam.io.datasets.stereomis import CALIB_FILE, GT_FILE, wants_prerectified
from slam.io.datasets.video import StackedStereoVideo
from slam.errors import DataError
from slam.io.rectification import make_rectifier


def find_videos(path: Path) -> list[Path]:
    return sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() == ".mp4")


class StereoMISRawDataset(StereoDataset):
    layout = "stereomis_raw"

    @staticmethod
    def detect(path: Path) -> bool:
        # an mp4 with StereoMIS's calibration, or with no other calibration to use
        from slam.io.datasets.frames import calibration_candidates

        others = [p for p in calibration_candidates(path) if p.name != CALIB_FILE]
        return bool(find_videos(path)) and ((path / CALIB_FILE).is_file() or not others)

    def __init__(self, path: Path, config: DataConfig):
        path = Path(path)
        videos = find_videos(path)
        if not videos:
            raise DataError(f"{path}: no *.mp4 video (StereoMIS raw layout)")
        if len(videos) > 1:
            raise DataError(f"{path}: {len(videos)} videos ({', '.join(v.name for v in videos)}); expected exactly one *.mp4")
        calib = read_stereomis_ini(path / CALIB_FILE)
        video = StackedStereoVideo(videos[0])
        try:
            calib = fit_calibration(calib, video.view_size)
            processor = make_rectifier(calib, config.rectify_mode, (config.width, config.height),
                                       already_rectified=wants_prerectified(config, False))
            n = video.num_frames
            stamps, poses = load_groundtruth(path / GT_FILE, n, None, config.fps or video.fps)
        except Exception:
            video.close()
            raise
        super().__init__(path, config, processor, n, stamps, poses)
        self.video = video
        self._masks_dir = path / "masks"

    def close(self) -> None:
        self.video.close()

    def _read(self, index: int) -> RawFrame:
        left, right = self.video.read(index)
        instrument = None
        if self.config.use_mask_files:
            mask_path = self._masks_dir / f"{index:06d}l.png"
            if mask_path.exists():
                instrument = read_mask(mask_path, left.shape)
        return RawFrame(left=left, right=right, instrument=instrument, source=f"{self.video.path} frame {index}")
