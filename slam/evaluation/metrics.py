"""Trajectory metrics as in the paper (after Ozyoruk et al. 2021), computed by evo's Python API
(``evo_ape`` / ``evo_rpe`` with the settings below). evo is imported inside the functions that
use it: importing this module, and so a run, does not load it until metrics are computed.

* Poses are ``(N, 4, 4)`` float64 camera-to-world matrices ``T_wc`` in **millimetres**
  (:func:`slam.io.tum.read_tum` converts TUM metres). evo calls lengths metres but never
  converts them here: the figures stay in mm.
* **ATE-RMSE** (mm): RMS of the position errors ``||t_gt,i - t_est,i||`` after alignment
  (evo's ``APE``, ``PoseRelation.translation_part``, RMSE).
* **RPE** between frames ``i`` and ``i + delta``: ``E_i = inv(inv(G_i) G_{i+delta}) inv(P_i)
  P_{i+delta}``; ``rpe_trans = ||translation(E_i)||`` (mm), ``rpe_rot`` its rotation angle
  (degrees, ``PoseRelation.rotation_angle_deg``); mean and population std over the pairs
  ``(0, d), (d, 2d), ...`` (evo's ``RPE`` in frames, ``all_pairs=False``; the paper's
  ``delta = 1``: every consecutive pair). A rigid alignment of the estimate cancels in it.
* **Alignment** (left-multiplying the estimate): ``"se3"`` the rigid Umeyama fit of the
  positions, no scale (evo's ``align(ref, correct_scale=False)``; where evo refuses a
  covariance of rank < 2, as it can for two poses or a frozen or straight-line estimate,
  scipy's Kabsch fit picks one of the equally good rotations: the ATE is the same for all);
  ``"first"`` makes the first poses equal (evo's ``align_origin``); ``"none"``; ``"auto"``:
  ``"first"`` on static sequences (:func:`is_static`: no ground-truth position farther than
  1 mm from their centroid, where a fitted rotation would only fit noise), else ``"se3"``.
* **Association** (:func:`associate`): each pose of the shorter trajectory with the
  nearest-in-time pose of the other within ``max_diff`` (evo's ``matching_time_indices`` as
  ``associate_trajectories`` calls it).
"""
from __future__ import annotations

import numpy as np

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


def _path(poses: np.ndarray):
    """Checked poses as an evo ``PosePath3D`` (evo never changes the matrices it is given)."""
    from evo.core.trajectory import PosePath3D

    return PosePath3D(poses_se3=list(poses))


# --------------------------------------------------------------------------------------------
# alignment
# --------------------------------------------------------------------------------------------
def align_first_pose(gt, est) -> np.ndarray:
    """Transform ``est`` rigidly (left-multiplication) so that its first pose equals ``gt[0]``."""
    gt = _check_poses(gt, "ground truth", 1)
    path = _path(_check_poses(est, "estimate", 1))
    path.align_origin(_path(gt[:1]))
    return np.array(path.poses_se3)


def is_static(gt_poses, spread_mm: float = 1.0) -> bool:
    """True when the camera (practically) never moves.

    Definition: ``max_i ||p_i - mean(p)|| < spread_mm`` over the ground-truth positions ``p_i``
    (the largest distance of any position from the centroid).
    """
    gt = _check_poses(gt_poses, "ground truth", 1)
    p = gt[:, :3, 3]
    spread = float(np.max(np.linalg.norm(p - p.mean(axis=0), axis=1)))
    return spread < spread_mm


def _align_se3(gt: np.ndarray, est: np.ndarray) -> np.ndarray:
    from evo.core.geometry import GeometryException
    from evo.core.lie_algebra import se3

    path = _path(est)
    try:
        path.align(_path(gt), correct_scale=False)
    except GeometryException:  # rank < 2: any rotation fitting the determined axes will do
        import warnings

        from scipy.spatial.transform import Rotation

        src, dst = est[:, :3, 3], gt[:, :3, 3]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "not uniquely defined": known
            R = Rotation.align_vectors(dst - dst.mean(axis=0), src - src.mean(axis=0))[0].as_matrix()
        path.transform(se3(R, dst.mean(axis=0) - R @ src.mean(axis=0)))
    return np.array(path.poses_se3)


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
    return _align_se3(gt, est), "se3"


def alignment_transform(est, aligned) -> np.ndarray:
    """``(4, 4)`` the rigid transform ``A`` with ``aligned = A @ est`` (the estimate's world frame
    into the ground truth's, mm): what moves the estimate's map with its trajectory."""
    est, aligned = np.asarray(est, dtype=np.float64), np.asarray(aligned, dtype=np.float64)
    return aligned[0] @ np.linalg.inv(est[0])


# --------------------------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------------------------
def _ape(gt: np.ndarray, est: np.ndarray):
    from evo.core.metrics import APE, PoseRelation

    ape = APE(PoseRelation.translation_part)
    ape.process_data((_path(gt), _path(est)))
    return ape


def per_frame_translation_error(gt, est_aligned) -> np.ndarray:
    """``(N,)`` position errors ``||t_gt,i - t_est,i||`` (mm) of an already aligned estimate."""
    gt, est = _check_pair(gt, est_aligned, min_len=1)
    return _ape(gt, est).error


def ate_rmse(gt, est) -> float:
    """ATE-RMSE (mm) of an already aligned estimate: ``sqrt(mean_i ||t_gt,i - t_est,i||^2)``."""
    from evo.core.metrics import StatisticsType

    gt, est = _check_pair(gt, est)
    return float(_ape(gt, est).get_statistic(StatisticsType.rmse))


def rpe(gt, est, delta: int = 1) -> dict:
    """Relative pose error over the index pairs ``(0, d), (d, 2d), ...`` (``d = delta``).

    Returns:
        ``dict(trans_mean, trans_std, rot_mean, rot_std)`` in mm and degrees (std: ``ddof=0``).
    """
    from evo import EvoException
    from evo.core.metrics import RPE, PoseRelation, StatisticsType, Unit

    gt, est = _check_pair(gt, est)
    if int(delta) != delta or delta < 1:
        raise EvaluationError(f"delta must be a positive integer number of frames, got {delta}")
    delta = int(delta)
    if delta >= len(gt):
        raise EvaluationError(f"delta = {delta} frames leaves no pose pair in {len(gt)} poses")
    ref, path = _path(gt), _path(est)
    out = {}
    for relation, key in ((PoseRelation.translation_part, "trans"), (PoseRelation.rotation_angle_deg, "rot")):
        metric = RPE(relation, delta=delta, delta_unit=Unit.frames, all_pairs=False)
        try:
            metric.process_data((ref, path))
        except EvoException as exc:  # e.g. a rotation part that is no rotation
            raise EvaluationError(f"relative pose error: {exc}") from None
        out[f"{key}_mean"] = float(metric.get_statistic(StatisticsType.mean))
        out[f"{key}_std"] = float(metric.get_statistic(StatisticsType.std))
    return out


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
    """Read two TUM files (mm) and associate them by timestamp (a timestamp repeated in either is a
    DataError naming its line: one pose per time).

    Returns:
        dict(stamps, gt, est, n_gt, n_est, max_diff): the matched ground-truth stamps ``(M,)``,
        poses ``(M, 4, 4)`` each, and the sizes of the files.
    """
    gt_stamps, gt = read_tum(gt_path, unique_stamps=True)
    est_stamps, est = read_tum(est_path, unique_stamps=True)
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
