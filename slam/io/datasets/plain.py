"""Plain folders of rectified stereo images.

::

    <seq>/
      left/*.png  right/*.png    rectified RGB views in natural order (``2.png`` before ``10.png``),
                                 paired by name or frame number (``0007.png`` / ``7.png``), else by order
      calibration.yaml           rectified fx fy cx cy baseline_mm width height (slam.io.calibration.read_plain_yaml)
      groundtruth.txt            optional, TUM, metres, T_wc of the left camera, one row per frame
      masks/<left file name>     optional, non-zero = tissue, 0 = instrument

Images are only resized (``rectified: no`` is not supported for this layout). The calibration's
``width`` x ``height`` must be the size of the first readable left image or an integer multiple or
fraction of it (then scaled, :func:`slam.io.calibration.fit_camera`); any other is a DataError naming
``calibration.yaml``.
"""
from __future__ import annotations

from pathlib import Path

from slam.io.calibration import fit_camera, read_plain_yaml
from slam.io.datasets.config import DataConfig
from slam.io.datasets.dataset import RawFrame, StereoDataset, first_readable_size, load_groundtruth, read_mask, read_rgb
from slam.io.datasets.images import natural_key, pair_files
from slam.errors import ConfigError, DataError
from slam.io.rectification import ResizeOnly

CALIB_FILE = "calibration.yaml"
GT_FILE = "groundtruth.txt"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def list_images(folder: Path) -> list[Path]:
    """The images of ``folder`` in natural order (``2.png`` before ``10.png``, as every layout)."""
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                  key=lambda p: natural_key(p.name))


class PlainDataset(StereoDataset):
    layout = "plain"

    @staticmethod
    def detect(path: Path) -> bool:
        # left/ and right/ with the plain calibration, or with no other calibration to use
        from slam.io.datasets.frames import calibration_candidates

        others = [p for p in calibration_candidates(path) if p.name != CALIB_FILE]
        return (path / "left").is_dir() and (path / "right").is_dir() and ((path / CALIB_FILE).is_file() or not others)

    def __init__(self, path: Path, config: DataConfig):
        path = Path(path)
        left_dir, right_dir = path / "left", path / "right"
        for d in (left_dir, right_dir):
            if not d.is_dir():
                raise DataError(f"{d}: folder not found (plain layout needs left/ and right/)")
        if config.rectified == "no":
            raise ConfigError(f"rectified: no is not supported for plain folders ({path}): their images must be rectified")
        left = list_images(left_dir)
        if not left:
            raise DataError(f"{left_dir}: no images (*.png, *.jpg, *.jpeg)")
        self._left, self._right = (list(side) for side in zip(*pair_files(left, list_images(right_dir), left_dir,
                                                                             right_dir)))
        calib_path = path / CALIB_FILE
        camera = read_plain_yaml(calib_path)
        size = first_readable_size(self._left)
        if size is not None:        # none of the first frames reads: they fail one by one later
            camera = fit_camera(camera, size, str(calib_path))
        processor = ResizeOnly(camera, (config.width, config.height))
        n = len(self._left)
        stamps, poses = load_groundtruth(path / GT_FILE, n, None, config.fps)
        super().__init__(path, config, processor, n, stamps, poses)
        self._masks_dir = path / "masks"
        self.calibration_path = calib_path

    def _read(self, index: int) -> RawFrame:
        left_path, right_path = self._left[index], self._right[index]
        left = read_rgb(left_path)
        right = read_rgb(right_path)
        if right.shape != left.shape:
            raise DataError(f"{right_path}: image is {right.shape[1]}x{right.shape[0]}, "
                            f"the left image {left_path.name} is {left.shape[1]}x{left.shape[0]}")
        instrument = None
        if self.config.use_mask_files and self._masks_dir.is_dir():
            for candidate in (self._masks_dir / left_path.name, self._masks_dir / (left_path.stem + ".png")):
                if candidate.exists():
                    instrument = read_mask(candidate, left.shape)
                    break
        return RawFrame(left=left, right=right, instrument=instrument, source=str(left_path))
