"""SCARED's map accuracy: the exported map against the keyframe's ground-truth depth.

The exported map (``map.ply``, metres, world frame) is moved into the keyframe's left camera with
the run's first pose (which the pipeline sets to the first ground-truth pose), projected with the
left intrinsics and distortion (``M1``, ``D1`` of ``endoscope_calibration.yaml``; scaled if the
depth map's size differs from the calibration's) onto the ground-truth depth map's pixels,
z-buffered (nearest point per pixel), and compared with the ground-truth z: median and mean
absolute depth error (mm) over the pixels with both a ground-truth depth and a map point, and the
coverage (that pixel count over the pixels with ground truth).

Ground-truth depth (the first file found in the keyframe folder, or a name given):

* ``left_depth_map.tiff``: H x W x 3 float32, x y z (mm) of the surface seen by each pixel of the
  keyframe's original (unrectified, distorted) left image, in that left camera's frame, 0 or NaN
  where unknown (as SCARED ships it; channel order x, y, z as ``tifffile`` reads the file). A
  single-channel float TIFF is read as z.
* ``left_depth.npy``: H x W z (mm) or H x W x 3 x y z (mm), same camera and pixels; 0 / NaN = unknown.
* ``left_depth.png``: uint16 z in units of ``png_scale_mm`` (default 0.01 mm, the unit of
  ``slam synth``'s ``depth/`` PNGs); 0 = unknown.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from slam.errors import DataError, one_line

GT_DEPTH_FILES = ("left_depth_map.tiff", "left_depth.npy", "left_depth.png")


def load_gt_depth(folder: Path, name: str | None = None, png_scale_mm: float = 0.01):
    """Ground-truth z (mm, ``(H, W)`` float64, NaN = unknown) of the keyframe's left image and its
    file, or ``(None, None)`` when the folder has none (see the module docstring for the formats)."""
    import cv2

    candidates = [folder / name] if name else [folder / n for n in GT_DEPTH_FILES]
    path = next((p for p in candidates if p.is_file()), None)
    if path is None:
        if name:
            raise DataError(f"{folder / name}: ground-truth depth file not found")
        return None, None
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            arr = np.load(path)
        except (OSError, ValueError) as err:
            raise DataError(f"{path}: cannot read ({one_line(err)})") from None
        arr = np.asarray(arr, dtype=np.float64)
    elif suffix in (".tif", ".tiff"):
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DataError(f"{path}: cannot read TIFF")
        arr = np.asarray(img, dtype=np.float64)
        if arr.ndim == 3:
            arr = arr[..., ::-1]  # OpenCV returns the channels reversed (BGR): back to x, y, z
    elif suffix == ".png":
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None or img.ndim != 2:
            raise DataError(f"{path}: expected a single-channel (uint16) depth PNG")
        arr = img.astype(np.float64) * float(png_scale_mm)
    else:
        raise DataError(f"{path}: unsupported ground-truth depth format (tiff, npy or png)")
    if arr.ndim == 3 and arr.shape[2] == 3:
        z = arr[..., 2].copy()
    elif arr.ndim == 2:
        z = arr.copy()
    else:
        raise DataError(f"{path}: expected H x W (z) or H x W x 3 (x y z), got shape {arr.shape}")
    z[~np.isfinite(z) | (z <= 0)] = np.nan
    if not np.isfinite(z).any():
        raise DataError(f"{path}: no valid ground-truth depth")
    return z, path


def project_depth(points_c: np.ndarray, K: np.ndarray, D: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Z-buffered depth image ``(H, W)`` (mm, NaN = no point) of camera-frame points ``(N, 3)`` (mm),
    projected with intrinsics ``K`` and OpenCV distortion ``D`` (pixel centres at integers)."""
    import cv2

    w, h = size
    z = points_c[:, 2]
    keep = z > 1e-6
    p = points_c[keep]
    # points far outside the view can fold back into it through the distortion polynomial
    uv0 = p[:, :2] / p[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    inside = (uv0[:, 0] > -0.25 * w) & (uv0[:, 0] < 1.25 * w) & (uv0[:, 1] > -0.25 * h) & (uv0[:, 1] < 1.25 * h)
    p = p[inside]
    depth = np.full(h * w, np.inf)
    if len(p):
        uv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.asarray(D, dtype=np.float64))
        uv = np.rint(uv.reshape(-1, 2)).astype(np.int64)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        np.minimum.at(depth, uv[ok, 1] * w + uv[ok, 0], p[ok, 2])
    depth[~np.isfinite(depth)] = np.nan
    return depth.reshape(h, w)


def map_accuracy(ply: Path, T_wc0: np.ndarray, calib_path: Path, gt_z: np.ndarray) -> dict:
    """Depth error of the map ``ply`` (metres, world frame) against the ground-truth z map of the
    keyframe (see the module docstring). ``T_wc0``: the keyframe's left camera pose (mm)."""
    import open3d as o3d

    from slam.io.calibration import read_scared_yaml

    h, w = gt_z.shape
    calib = read_scared_yaml(calib_path, image_size=(w, h))
    K = calib.K1.copy()
    cw, ch = calib.image_size
    if (cw, ch) != (w, h):  # depth map at another resolution than the calibration
        sx, sy = w / cw, h / ch
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    if not ply.is_file():
        raise DataError(f"{ply}: no map exported")
    points = np.asarray(o3d.io.read_point_cloud(str(ply)).points, dtype=np.float64) * 1000.0
    gt_valid = np.isfinite(gt_z)
    out = {"map_points": int(len(points)), "gt_pixels": int(gt_valid.sum())}
    if len(points) == 0:
        return {**out, "map_pixels": 0, "map_coverage": 0.0, "map_median_mm": None, "map_mean_mm": None}
    T_cw = np.linalg.inv(T_wc0)
    pc = points @ T_cw[:3, :3].T + T_cw[:3, 3]
    depth = project_depth(pc, K, calib.D1, (w, h))
    both = gt_valid & np.isfinite(depth)
    err = np.abs(depth[both] - gt_z[both])
    out.update(map_pixels=int(both.sum()), map_coverage=float(both.sum() / max(1, gt_valid.sum())),
               map_median_mm=float(np.median(err)) if len(err) else None,
               map_mean_mm=float(np.mean(err)) if len(err) else None)
    return out


def keyframe_map_accuracy(folder: Path, out_dir: Path, T_wc0: np.ndarray, gt_depth: str = "",
                          png_scale_mm: float = 0.01) -> dict:
    """The map accuracy of the run in ``out_dir`` on the keyframe sequence ``folder`` (fields
    ``map_*``, ``gt_depth``); a problem becomes ``map_note``, not an error: the trajectory's
    figures stand without it."""
    try:
        gt_z, gt_path = load_gt_depth(folder, gt_depth or None, png_scale_mm)
        if gt_z is None:
            return {"map_note": "no ground-truth depth"}
        out = map_accuracy(out_dir / "map.ply", T_wc0, folder / "endoscope_calibration.yaml", gt_z)
        return {**out, "gt_depth": str(gt_path)}
    except Exception as err:  # noqa: BLE001
        return {"map_note": f"map accuracy failed: {one_line(err)}"}
