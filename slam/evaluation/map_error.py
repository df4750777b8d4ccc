"""A map's points against the truth: a frame's true depth (how far the fused surface lies from the
tissue), or a reference reconstruction's points.

Depth: the map benchmarks and tests on synthetic sequences, whose frames carry exact depth. Points:
the accuracy gate on the real sequence (``benchmarks/check_accuracy.py``).
"""
from __future__ import annotations

import numpy as np

# a map point further than this behind the true surface is occluded in the frame, not an error of
# it (mm)
OCCLUDED_MM = 5.0


def bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``img`` ``(H, W)`` sampled at ``(M,)`` sub-pixel positions ``u`` (column), ``v`` (row); NaN
    where a corner has no depth (``<= 0``)."""
    u0 = np.clip(np.floor(u).astype(int), 0, img.shape[1] - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, img.shape[0] - 2)
    a, b = u - u0, v - v0
    corners = np.stack([img[v0, u0], img[v0, u0 + 1], img[v0 + 1, u0], img[v0 + 1, u0 + 1]])
    weights = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b])
    out = (corners * weights).sum(0)
    out[(corners <= 0).any(0)] = np.nan
    return out


def depth_errors_mm(points_mm: np.ndarray, T_wc: np.ndarray, K: np.ndarray, R1: np.ndarray,
                    gt_depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed depth errors of map points seen by one frame.

    Args:
        points_mm: ``(M, 3)`` map points in the world frame, mm.
        T_wc: ``(4, 4)`` the frame's true pose (world <- original left camera, mm).
        K: ``(3, 3)`` the rectified left camera's intrinsics.
        R1: ``(3, 3)`` the rectifying rotation (original left camera -> rectified left camera).
        gt_depth: ``(H, W)`` the frame's true depth in the rectified left camera, mm (0 or
            non-finite where there is none).

    Returns:
        ``(seen, err)``: ``(M,)`` bool, the points in front of the camera, inside the image, on a
        pixel with true depth and not more than :data:`OCCLUDED_MM` behind it; ``(S,)`` their
        depth minus the true depth, mm (positive: behind the true surface).
    """
    X = (np.asarray(points_mm, dtype=np.float64) - T_wc[:3, 3]) @ T_wc[:3, :3]
    X = X @ np.asarray(R1, dtype=np.float64).T
    z = X[:, 2]
    seen = z > 1.0
    uv = X[seen] @ np.asarray(K, dtype=np.float64).T
    u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
    h, w = gt_depth.shape
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    gt = np.full(len(u), np.nan)
    gt[inside] = bilinear(gt_depth, u[inside], v[inside])
    err = z[seen] - gt
    ok = np.isfinite(gt) & (gt > 0) & (err < OCCLUDED_MM)
    idx = np.flatnonzero(seen)
    seen[idx[~ok]] = False
    return seen, err[ok]


def read_points_mm(path) -> np.ndarray:
    """``(N, 3)`` the points of a PLY file (metres) in mm; a DataError naming the file where it
    cannot be read or holds no points."""
    from pathlib import Path

    from slam.errors import DataError

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: point cloud not found")
    import open3d as o3d

    points = np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float64)
    if not len(points):
        raise DataError(f"{path}: no points read (a PLY file with x, y, z in metres is expected)")
    return points * 1000.0


def reference_point_errors(reference_mm: np.ndarray, map_mm: np.ndarray, within_mm: float = 1.0) -> dict:
    """A map against a reference reconstruction's points (for example COLMAP's sparse points of a
    real sequence), both in the same world frame: each reference point's distance to the nearest
    map point.

    Args:
        reference_mm: ``(R, 3)`` reference points, mm.
        map_mm: ``(M, 3)`` the map's points, mm, already moved into the reference's frame (the
            trajectory's alignment to the reference's).
        within_mm: the distance the share ``within`` counts up to.

    Returns:
        ``median_mm`` of the distances, ``within`` the share of reference points closer than
        ``within_mm``, ``points`` the reference points (``median_mm`` None where the map is empty).
    """
    from scipy.spatial import cKDTree

    reference_mm = np.asarray(reference_mm, dtype=np.float64).reshape(-1, 3)
    map_mm = np.asarray(map_mm, dtype=np.float64).reshape(-1, 3)
    if not len(map_mm) or not len(reference_mm):
        return {"median_mm": None, "within": 0.0, "points": int(len(reference_mm))}
    distances, _ = cKDTree(map_mm).query(reference_mm, k=1)
    return {"median_mm": float(np.median(distances)), "within": float(np.mean(distances < within_mm)),
            "points": int(len(reference_mm))}
