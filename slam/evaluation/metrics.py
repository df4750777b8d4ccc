"""Trajectory metrics: ATE-RMSE and RPE, computed like the paper (after Ozyoruk et al. 2021)
and numerically identical to ``evo`` (``evo_ape`` / ``evo_rpe`` with the settings below).

Conventions
-----------
* Poses are ``(N, 4, 4)`` float64 camera-to-world matrices ``T_wc`` in **millimetres**
  (OpenCV camera axes). TUM files are in metres; :func:`slam.io.tum.read_tum` converts.
* **ATE-RMSE** (mm): root mean square of the position errors ``||t_gt,i - t_est,i||`` after
  aligning the estimate to the ground truth (see *Alignment*). Equals ``evo_ape tum GT EST -a``
  (``PoseRelation.translation_part``, RMSE statistic).
* **RPE** between frames ``i`` and ``i + delta`` (``delta = 1`` in the paper)::

      E_i = inv(inv(G_i) G_{i+delta}) @ (inv(P_i) P_{i+delta})

  ``rpe_trans`` = ``||translation(E_i)||`` (mm), ``rpe_rot`` = rotation angle of ``E_i``
  (degrees, the norm of its rotation vector); mean and population std (``ddof=0``) over the
  pairs. The pairs are ``(0, d), (d, 2d), ...`` as in evo with ``all_pairs=False`` (for
  ``delta = 1``: every consecutive pair). RPE does not depend on a rigid alignment of the
  estimate (it cancels in ``inv(P_i) P_j``).

Alignment
---------
* ``"se3"``: rigid Horn/Umeyama least-squares fit (rotation + translation, *no scale*) of the
  estimated positions onto the ground-truth positions; the estimate is left-multiplied by the
  fitted transform (exactly evo's ``traj_est.align(traj_ref, correct_scale=False)``).
* ``"first"``: the estimate is left-multiplied by ``G_0 inv(P_0)`` so its first pose equals the
  ground truth's first pose (evo's ``align_origin``).
* ``"none"``: used as given.
* ``"auto"``: ``"first"`` for static-camera sequences, else ``"se3"``. A sequence is *static*
  when ``max_i ||g_i - mean(g)|| < spread_mm`` (1 mm by default), ``g_i`` the ground-truth
  positions: the largest distance of any ground-truth position from their centroid. A free
  rotation fitted to such a point cloud would only fit noise.

Association (:func:`associate`) pairs each pose of the shorter trajectory with the
nearest-in-time pose of the other one when the time difference is ``<= max_diff``: evo's
``matching_time_indices`` as ``evo.core.sync.associate_trajectories`` calls it.
"""
from __future__ import annotations


import numpy as np
from scipy.spatial.transform import Rotation

from slam.errors import DataError
from slam.io.tum import read_tum

ALIGN_METHODS = ("auto", "se3", "first", "none")
METRIC_KEYS = (
    "ate_rmse_mm",
    "rpe_trans_mm",
    "rpe_trans_std_mm",
    "rpe_rot_deg",
    "rpe_rot_std_deg",
    "alignment",
    "frames",
)
DEFAULT_MAX_DIFF = 0.01  # evo / TUM benchmark default, in the timestamps' unit (seconds)


class EvaluationError(DataError, ValueError):
    """Inputs the metrics cannot be computed on (non-finite, too few poses, no matches...).

    A ``ValueError`` for library callers and a :class:`slam.errors.SlamError` so the command
    line prints it as one clear line.
    """


# --------------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------------
def _check_poses(poses, name: str = "poses", min_len: int = 2) -> np.ndarray:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise EvaluationError(f"{name}: expected an (N, 4, 4) array of poses, got shape {arr.shape}")
    if len(arr) < min_len:
        raise EvaluationError(f"{name}: need at least {min_len} poses, got {len(arr)}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(arr.reshape(len(arr), -1)), axis=1))[0])
        raise EvaluationError(f"{name}: non-finite values (NaN/inf) in pose {bad}")
    return arr


def _check_pair(gt, est, min_len: int = 2) -> tuple[np.ndarray, np.ndarray]:
    gt = _check_poses(gt, "ground truth", min_len)
    est = _check_poses(est, "estimate", min_len)
    if len(gt) != len(est):
        raise EvaluationError(
            f"ground truth has {len(gt)} poses but the estimate has {len(est)}; "
            "associate them first (see associate())"
        )
    return gt, est


def _check_points(xyz, name: str) -> np.ndarray:
    arr = np.asarray(xyz, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise EvaluationError(f"{name}: expected an (N, 3) array of points, got shape {arr.shape}")
    if len(arr) < 2:
        raise EvaluationError(f"{name}: need at least 2 points, got {len(arr)}")
    if not np.all(np.isfinite(arr)):
        raise EvaluationError(f"{name}: non-finite values (NaN/inf) in points")
    return arr


def _inv_se3(T: np.ndarray) -> np.ndarray:
    """Inverse of one ``(4,4)`` or a stack ``(N,4,4)`` of rigid transforms."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


# --------------------------------------------------------------------------------------------
# alignment
# --------------------------------------------------------------------------------------------
def umeyama_alignment(src_xyz, dst_xyz, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (or rigid) transform mapping ``src`` points onto ``dst``.

    Minimises ``sum_i ||dst_i - (s R src_i + t)||^2`` (Umeyama 1991, Horn 1987).

    Args:
        src_xyz, dst_xyz: ``(N, 3)`` corresponding points (N >= 2).
        with_scale: also estimate the scale ``s`` (else ``s = 1``).

    Returns:
        ``R (3, 3)`` proper rotation, ``t (3,)``, ``s`` float.
        For degenerate inputs (collinear or coincident points) the rotation about the
        undetermined axes is arbitrary but still a least-squares minimiser.
    """
    src = _check_points(src_xyz, "source points")
    dst = _check_points(dst_xyz, "destination points")
    if src.shape != dst.shape:
        raise EvaluationError(f"point sets differ in shape: {src.shape} vs {dst.shape}")
    n = len(src)
    mu_s = src.mean(axis=0)
    mu_d = dst.mean(axis=0)
    xs = src - mu_s
    xd = dst - mu_d
    cov = xd.T @ xs / n  # (3, 3) cross-covariance, Umeyama eq. 38
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2, 2] = -1.0  # keep a right-handed rotation (no reflection)
    R = U @ S @ Vt
    s = 1.0
    if with_scale:
        var_s = float(np.sum(xs**2)) / n
        if var_s > 0.0:
            s = float(np.trace(np.diag(D) @ S) / var_s)
    t = mu_d - s * (R @ mu_s)
    return R, t, s


def align_first_pose(gt, est) -> np.ndarray:
    """Transform ``est`` rigidly (left-multiplication) so that its first pose equals ``gt[0]``."""
    gt = _check_poses(gt, "ground truth", 1)
    est = _check_poses(est, "estimate", 1)
    T = gt[0] @ _inv_se3(est[0])
    return T @ est


def is_static(gt_poses, spread_mm: float = 1.0) -> bool:
    """True when the camera (practically) never moves.

    Definition: ``max_i ||p_i - mean(p)|| < spread_mm`` over the ground-truth positions ``p_i``
    (the largest distance of any position from the centroid).
    """
    gt = _check_poses(gt_poses, "ground truth", 1)
    p = gt[:, :3, 3]
    spread = float(np.max(np.linalg.norm(p - p.mean(axis=0), axis=1)))
    return spread < spread_mm


def align(gt, est, method: str = "auto") -> tuple[np.ndarray, str]:
    """Align ``est`` to ``gt`` (same length).

    Args:
        method: ``"auto"`` (``"first"`` if :func:`is_static` else ``"se3"``), ``"se3"``,
            ``"first"`` or ``"none"``.

    Returns:
        the aligned estimate ``(N, 4, 4)`` and the method actually used.
    """
    if method not in ALIGN_METHODS:
        raise EvaluationError(f"unknown alignment method {method!r}; use one of {', '.join(ALIGN_METHODS)}")
    gt, est = _check_pair(gt, est)
    if method == "auto":
        method = "first" if is_static(gt) else "se3"
    if method == "none":
        return est.copy(), "none"
    if method == "first":
        return align_first_pose(gt, est), "first"
    R, t, _ = umeyama_alignment(est[:, :3, 3], gt[:, :3, 3], with_scale=False)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T @ est, "se3"


# --------------------------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------------------------
def per_frame_translation_error(gt, est_aligned) -> np.ndarray:
    """``(N,)`` position errors ``||t_gt,i - t_est,i||`` (mm) of an already aligned estimate."""
    gt, est = _check_pair(gt, est_aligned, min_len=1)
    return np.linalg.norm(gt[:, :3, 3] - est[:, :3, 3], axis=1)


def ate_rmse(gt, est) -> float:
    """ATE-RMSE (mm) of an already aligned estimate: ``sqrt(mean_i ||t_gt,i - t_est,i||^2)``."""
    gt, est = _check_pair(gt, est)
    err = per_frame_translation_error(gt, est)
    return float(np.sqrt(np.mean(err**2)))


def rpe(gt, est, delta: int = 1) -> dict:
    """Relative pose error over the index pairs ``(0, d), (d, 2d), ...`` (``d = delta``).

    Returns:
        ``dict(trans_mean, trans_std, rot_mean, rot_std)`` in mm and degrees (std: ``ddof=0``).
    """
    gt, est = _check_pair(gt, est)
    if int(delta) != delta or delta < 1:
        raise EvaluationError(f"delta must be a positive integer number of frames, got {delta}")
    delta = int(delta)
    ids = np.arange(0, len(gt), delta)
    if len(ids) < 2:
        raise EvaluationError(f"delta = {delta} frames leaves no pose pair in {len(gt)} poses")
    i, j = ids[:-1], ids[1:]
    gt_rel = _inv_se3(gt[i]) @ gt[j]
    est_rel = _inv_se3(est[i]) @ est[j]
    E = _inv_se3(gt_rel) @ est_rel
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = np.degrees(Rotation.from_matrix(E[:, :3, :3]).magnitude())
    return {
        "trans_mean": float(np.mean(trans)),
        "trans_std": float(np.std(trans)),
        "rot_mean": float(np.mean(rot)),
        "rot_std": float(np.std(rot)),
    }


def evaluate(gt, est, align_method: str = "auto") -> dict:
    """All paper metrics for two associated trajectories (same length, mm).

    Returns a dict with exactly the keys ``ate_rmse_mm, rpe_trans_mm, rpe_trans_std_mm,
    rpe_rot_deg, rpe_rot_std_deg, alignment, frames``.
    """
    gt, est = _check_pair(gt, est)
    aligned, used = align(gt, est, align_method)
    r = rpe(gt, aligned, delta=1)
    return {
        "ate_rmse_mm": ate_rmse(gt, aligned),
        "rpe_trans_mm": r["trans_mean"],
        "rpe_trans_std_mm": r["trans_std"],
        "rpe_rot_deg": r["rot_mean"],
        "rpe_rot_std_deg": r["rot_std"],
        "alignment": used,
        "frames": int(len(gt)),
    }


# --------------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------------
def associate(gt_stamps, est_stamps, max_diff: float = DEFAULT_MAX_DIFF) -> tuple[np.ndarray, np.ndarray]:
    """Pair poses by nearest timestamps (TUM / evo style).

    Every stamp of the shorter sequence is matched to the nearest stamp of the longer one if
    they differ by at most ``max_diff`` (same unit as the stamps; ties: the earlier stamp);
    unmatched poses are dropped. evo's ``matching_time_indices`` in the order
    ``evo.core.sync.associate_trajectories`` calls it.

    Returns:
        ``(gt_idx, est_idx)`` int arrays of equal length.
    """
    from evo.core.sync import matching_time_indices

    g = np.asarray(gt_stamps, dtype=np.float64).ravel()
    e = np.asarray(est_stamps, dtype=np.float64).ravel()
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(e))):
        raise EvaluationError("non-finite timestamps")
    if len(g) == 0 or len(e) == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    if len(e) > len(g):  # evo starts from the shorter trajectory (ties: the first one)
        gi, ei = matching_time_indices(g, e, max_diff)
    else:
        ei, gi = matching_time_indices(e, g, max_diff)
    return np.asarray(gi, dtype=int), np.asarray(ei, dtype=int)


def default_max_diff(gt_stamps) -> float:
    """Association tolerance used when none is given: half the median ground-truth frame
    interval (unit-agnostic: 16.7 ms for 30 fps stamps in seconds, 0.5 for frame indices),
    falling back to evo's 0.01 when that cannot be computed."""
    g = np.sort(np.asarray(gt_stamps, dtype=np.float64).ravel())
    dt = np.diff(g)
    dt = dt[dt > 0]
    if len(dt) == 0:
        return DEFAULT_MAX_DIFF
    return 0.5 * float(np.median(dt))


def load_associated(gt_path, est_path, max_diff: float | None = None) -> dict:
    """Read two TUM files (mm) and associate them by timestamp.

    Returns:
        dict(stamps, gt, est, n_gt, n_est, max_diff): the matched ground-truth stamps ``(M,)``,
        poses ``(M, 4, 4)`` each, and the sizes of the files.
    """
    gt_stamps, gt = read_tum(gt_path)
    est_stamps, est = read_tum(est_path)
    if max_diff is None:
        max_diff = default_max_diff(gt_stamps)
    gi, ei = associate(gt_stamps, est_stamps, max_diff)
    if len(gi) < 2:
        raise EvaluationError(
            f"{est_path}: only {len(gi)} of {len(est_stamps)} poses match a timestamp of {gt_path} "
            f"within {max_diff:g}; need at least 2 (are both files in the same time base?)"
        )
    return {
        "stamps": gt_stamps[gi],
        "gt": gt[gi],
        "est": est[ei],
        "n_gt": len(gt_stamps),
        "n_est": len(est_stamps),
        "max_diff": float(max_diff),
    }


def evaluate_files(gt_path, est_path, align_method: str = "auto", max_diff: float | None = None) -> dict:
    """Read two TUM files (metres -> mm), associate them by timestamp (see :func:`associate`,
    tolerance :func:`default_max_diff` unless given) and :func:`evaluate` them."""
    data = load_associated(gt_path, est_path, max_diff)
    return evaluate(data["gt"], data["est"], align_method)
