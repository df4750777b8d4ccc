"""Trajectory metrics: agreement with evo and the properties the paper's metrics rely on."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.evaluation import metrics as ev
from slam.errors import SlamError
from slam.io.tum import write_tum


# ------------------------------------------------------------------------------------------
# synthetic trajectories (mm)
# ------------------------------------------------------------------------------------------
def smooth_gt(rng: np.random.Generator, n: int = 120, extent_mm: float = 40.0) -> np.ndarray:
    """A smooth random camera path: sums of low-frequency sines for position and rotation."""
    s = np.linspace(0.0, 1.0, n)
    pos = np.zeros((n, 3))
    rotvec = np.zeros((n, 3))
    for k in range(1, 4):
        pos += rng.normal(size=3) * extent_mm / k * np.sin(np.outer(s, 2 * np.pi * k * rng.uniform(0.3, 1.0, 3))
                                                            + rng.uniform(0, 2 * np.pi, 3))
        rotvec += rng.normal(size=3) * 0.3 / k * np.sin(np.outer(s, 2 * np.pi * k * rng.uniform(0.3, 1.0, 3))
                                                        + rng.uniform(0, 2 * np.pi, 3))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    poses[:, :3, 3] = pos
    return poses


def rigid(rng: np.random.Generator, trans_mm: float = 50.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.normal(size=3) * trans_mm
    return T


def noisy(rng: np.random.Generator, poses: np.ndarray, trans_mm: float = 1.0, rot_deg: float = 0.5) -> np.ndarray:
    out = poses.copy()
    n = len(poses)
    dR = Rotation.from_rotvec(np.radians(rot_deg) * rng.normal(size=(n, 3))).as_matrix()
    out[:, :3, :3] = poses[:, :3, :3] @ dR
    # drift-like error (random walk) plus white noise, so the alignment really matters
    out[:, :3, 3] += np.cumsum(rng.normal(size=(n, 3)) * 0.3 * trans_mm, axis=0) + rng.normal(size=(n, 3)) * trans_mm
    return out


# ------------------------------------------------------------------------------------------
# agreement with evo
# ------------------------------------------------------------------------------------------
def evo_metrics(gt_file, est_file, max_diff: float = 0.01) -> dict:
    from evo.core import metrics, sync
    from evo.tools import file_interface

    traj_ref = file_interface.read_tum_trajectory_file(str(gt_file))
    traj_est = file_interface.read_tum_trajectory_file(str(est_file))
    traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est, max_diff=max_diff)
    traj_est.align(traj_ref, correct_scale=False)

    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    out = {"frames": traj_ref.num_poses, "ate_rmse_mm": 1000.0 * ape.get_statistic(metrics.StatisticsType.rmse)}
    for relation, key, scale in ((metrics.PoseRelation.translation_part, "rpe_trans", 1000.0),
                                 (metrics.PoseRelation.rotation_angle_deg, "rpe_rot", 1.0)):
        r = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
        r.process_data((traj_ref, traj_est))
        out[key] = scale * r.get_statistic(metrics.StatisticsType.mean)
        out[key + "_std"] = scale * r.get_statistic(metrics.StatisticsType.std)
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_metrics_match_evo(tmp_path, seed):
    rng = np.random.default_rng(seed)
    n = 150
    gt = smooth_gt(rng, n)
    est = rigid(rng) @ noisy(rng, gt)  # rigid offset + rotation: alignment matters
    stamps = 1000.0 + np.arange(n) / 30.0
    # the estimate has a few frames missing and small timestamp jitter: association matters
    keep = np.sort(rng.choice(n, size=n - 12, replace=False))
    est_stamps = stamps[keep] + rng.uniform(-0.002, 0.002, size=len(keep))
    write_tum(tmp_path / "gt.txt", stamps, gt)
    write_tum(tmp_path / "est.txt", est_stamps, est[keep])

    ours = ev.evaluate_files(tmp_path / "gt.txt", tmp_path / "est.txt", max_diff=0.01)
    ref = evo_metrics(tmp_path / "gt.txt", tmp_path / "est.txt", max_diff=0.01)

    assert set(ours) == set(ev.METRIC_KEYS)
    assert ours["alignment"] == "se3"
    assert ours["frames"] == ref["frames"] == n - 12
    assert ours["ate_rmse_mm"] > 1.0  # non-trivial numbers
    np.testing.assert_allclose(ours["ate_rmse_mm"], ref["ate_rmse_mm"], rtol=1e-6)
    np.testing.assert_allclose(ours["rpe_trans_mm"], ref["rpe_trans"], rtol=1e-6)
    np.testing.assert_allclose(ours["rpe_trans_std_mm"], ref["rpe_trans_std"], rtol=1e-6)
    np.testing.assert_allclose(ours["rpe_rot_deg"], ref["rpe_rot"], rtol=1e-6)
    np.testing.assert_allclose(ours["rpe_rot_std_deg"], ref["rpe_rot_std"], rtol=1e-6)
    # the default, unit-agnostic tolerance gives the same association here
    assert ev.evaluate_files(tmp_path / "gt.txt", tmp_path / "est.txt") == ours


def test_associate_matches_evo():
    from evo.core.sync import matching_time_indices

    rng = np.random.default_rng(3)
    gt_stamps = np.cumsum(rng.uniform(0.02, 0.05, size=200))
    est_stamps = np.sort(rng.choice(gt_stamps, 150, replace=False) + rng.uniform(-0.015, 0.015, 150))
    gi, ei = ev.associate(gt_stamps, est_stamps, max_diff=0.01)
    ref_e, ref_g = matching_time_indices(est_stamps, gt_stamps, 0.01)  # evo: shorter first
    np.testing.assert_array_equal(gi, ref_g)
    np.testing.assert_array_equal(ei, ref_e)
    assert np.all(np.abs(gt_stamps[gi] - est_stamps[ei]) <= 0.01)
    # longer estimate: evo iterates over the (shorter) ground truth
    gi, ei = ev.associate(est_stamps, gt_stamps, max_diff=0.01)
    ref_g2, ref_e2 = matching_time_indices(est_stamps, gt_stamps, 0.01)
    np.testing.assert_array_equal(gi, ref_g2)
    np.testing.assert_array_equal(ei, ref_e2)
    # unsorted stamps fall back to a full search with the same result
    perm = rng.permutation(len(gt_stamps))
    gi_u, ei_u = ev.associate(gt_stamps[perm], est_stamps, max_diff=0.01)
    np.testing.assert_array_equal(perm[gi_u], ref_g)
    np.testing.assert_array_equal(ei_u, ref_e)


# ------------------------------------------------------------------------------------------
# properties
# ------------------------------------------------------------------------------------------
def test_umeyama_recovers_rigid_transform():
    rng = np.random.default_rng(10)
    src = rng.normal(size=(50, 3)) * 20.0
    T = rigid(rng)
    dst = src @ T[:3, :3].T + T[:3, 3]
    R, t, s = ev.umeyama_alignment(src, dst)
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-10)
    np.testing.assert_allclose(t, T[:3, 3], atol=1e-9)
    assert s == 1.0
    assert np.isclose(np.linalg.det(R), 1.0)
    # with scale
    R, t, s = ev.umeyama_alignment(src, 2.5 * dst, with_scale=True)
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-10)
    np.testing.assert_allclose(t, 2.5 * T[:3, 3], atol=1e-9)
    assert np.isclose(s, 2.5)


def test_umeyama_matches_evo_geometry():
    from evo.core.geometry import umeyama_alignment as evo_umeyama

    rng = np.random.default_rng(11)
    src = rng.normal(size=(40, 3)) * 10.0
    dst = src @ rigid(rng)[:3, :3].T + rng.normal(size=(40, 3))  # noisy: a genuine fit
    for with_scale in (False, True):
        R, t, s = ev.umeyama_alignment(src, dst, with_scale)
        R_e, t_e, s_e = evo_umeyama(src.T, dst.T, with_scale)
        np.testing.assert_allclose(R, R_e, atol=1e-10)
        np.testing.assert_allclose(t, t_e, atol=1e-9)
        assert np.isclose(s, s_e)


def test_rigidly_transformed_gt_has_zero_error():
    rng = np.random.default_rng(20)
    gt = smooth_gt(rng)
    est = rigid(rng) @ gt
    m = ev.evaluate(gt, est)
    assert m["alignment"] == "se3"
    assert m["ate_rmse_mm"] < 1e-9
    assert m["rpe_trans_mm"] < 1e-9 and m["rpe_rot_deg"] < 1e-5
    aligned, used = ev.align(gt, est)
    np.testing.assert_allclose(aligned, gt, atol=1e-9)
    # without alignment the offset shows
    assert ev.evaluate(gt, est, align_method="none")["ate_rmse_mm"] > 1.0


def test_static_sequence_uses_first_pose_alignment():
    rng = np.random.default_rng(30)
    n = 60
    gt = np.tile(rigid(rng), (n, 1, 1))
    gt[:, :3, 3] += rng.normal(size=(n, 3)) * 0.05  # jitter well below 1 mm
    assert ev.is_static(gt)
    assert not ev.is_static(smooth_gt(rng))
    # is_static's definition: max distance of a position from the centroid vs spread_mm
    line = np.tile(np.eye(4), (3, 1, 1))
    line[:, 0, 3] = [-0.9, 0.0, 0.9]
    assert ev.is_static(line) and not ev.is_static(line, spread_mm=0.9)

    T = rigid(rng)
    est = T @ noisy(rng, gt, trans_mm=0.2, rot_deg=0.1)
    aligned, used = ev.align(gt, est)
    assert used == "first"
    np.testing.assert_allclose(aligned[0], gt[0], atol=1e-9)
    np.testing.assert_allclose(aligned, ev.align_first_pose(gt, est))
    m = ev.evaluate(gt, est)
    assert m["alignment"] == "first"
    np.testing.assert_allclose(m["ate_rmse_mm"], ev.ate_rmse(gt, aligned))
    # forcing se3 is still possible
    assert ev.align(gt, est, "se3")[1] == "se3"


def test_frozen_camera_on_moving_gt_gives_large_ate():
    rng = np.random.default_rng(40)
    gt = smooth_gt(rng, extent_mm=40.0)
    est = np.tile(np.eye(4), (len(gt), 1, 1))
    m = ev.evaluate(gt, est)
    spread = np.sqrt(np.mean(np.sum((gt[:, :3, 3] - gt[:, :3, 3].mean(0)) ** 2, axis=1)))
    # the best rigid fit of a single point is the centroid: ATE = RMS distance from it
    np.testing.assert_allclose(m["ate_rmse_mm"], spread, rtol=1e-9)
    assert m["ate_rmse_mm"] > 10.0


def test_rpe_against_explicit_loop_and_delta():
    rng = np.random.default_rng(50)
    gt = smooth_gt(rng, n=40)
    est = noisy(rng, gt)
    for delta in (1, 3):
        ids = np.arange(0, len(gt), delta)
        t_err, r_err = [], []
        for i, j in zip(ids[:-1], ids[1:]):
            E = np.linalg.inv(np.linalg.inv(gt[i]) @ gt[j]) @ (np.linalg.inv(est[i]) @ est[j])
            t_err.append(np.linalg.norm(E[:3, 3]))
            r_err.append(np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1))))
        r = ev.rpe(gt, est, delta=delta)
        np.testing.assert_allclose(r["trans_mean"], np.mean(t_err), rtol=1e-9)
        np.testing.assert_allclose(r["trans_std"], np.std(t_err), rtol=1e-9)
        np.testing.assert_allclose(r["rot_mean"], np.mean(r_err), rtol=1e-6)
        np.testing.assert_allclose(r["rot_std"], np.std(r_err), rtol=1e-5)
    # RPE does not depend on a rigid transform of the estimate
    r1 = ev.rpe(gt, est)
    r2 = ev.rpe(gt, rigid(rng) @ est)
    for k in r1:
        np.testing.assert_allclose(r1[k], r2[k], rtol=1e-9)


def test_per_frame_error_and_ate():
    gt = np.tile(np.eye(4), (4, 1, 1))
    gt[:, 0, 3] = [0, 10, 20, 30]
    est = gt.copy()
    est[:, 1, 3] = [3, -3, 4, 0]
    np.testing.assert_allclose(ev.per_frame_translation_error(gt, est), [3, 3, 4, 0])
    assert np.isclose(ev.ate_rmse(gt, est), np.sqrt((9 + 9 + 16) / 4))


# ------------------------------------------------------------------------------------------
# bad inputs
# ------------------------------------------------------------------------------------------
def test_bad_inputs_raise_value_error():
    rng = np.random.default_rng(60)
    gt = smooth_gt(rng, n=10)
    bad = gt.copy()
    bad[4, 0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        ev.evaluate(gt, bad)
    with pytest.raises(ValueError, match="non-finite"):
        ev.evaluate(bad, gt)
    with pytest.raises(ValueError, match="at least 2"):
        ev.evaluate(gt[:1], gt[:1])
    with pytest.raises(ValueError, match="associate"):
        ev.evaluate(gt, gt[:5])
    with pytest.raises(ValueError, match="shape"):
        ev.evaluate(gt[:, :3, :], gt[:, :3, :])
    with pytest.raises(ValueError, match="alignment method"):
        ev.align(gt, gt, "sim3")
    with pytest.raises(ValueError, match="delta"):
        ev.rpe(gt, gt, delta=10)
    with pytest.raises(ValueError, match="non-finite"):
        ev.umeyama_alignment(np.full((3, 3), np.inf), np.zeros((3, 3)))
    # the error is also a SlamError, so the CLI prints one line
    with pytest.raises(SlamError):
        ev.ate_rmse(gt, bad)


def test_files_without_matching_stamps(tmp_path):
    rng = np.random.default_rng(70)
    gt = smooth_gt(rng, n=10)
    write_tum(tmp_path / "gt.txt", np.arange(10.0), gt)
    write_tum(tmp_path / "est.txt", np.arange(10.0) + 100.0, gt)
    with pytest.raises(ValueError, match="match a timestamp"):
        ev.evaluate_files(tmp_path / "gt.txt", tmp_path / "est.txt")


# ------------------------------------------------------------------------------------------
# output
# ------------------------------------------------------------------------------------------
def test_format_and_main_eval(tmp_path, capsys):
    rng = np.random.default_rng(80)
    gt = smooth_gt(rng, n=30)
    est = noisy(rng, gt)
    stamps = np.arange(30) / 30.0
    write_tum(tmp_path / "gt.txt", stamps, gt)
    write_tum(tmp_path / "est.txt", stamps, est)
    m = ev.evaluate_files(tmp_path / "gt.txt", tmp_path / "est.txt")
    from slam.app.eval_command import format_metrics, main_eval

    text = format_metrics(m)
    assert "ATE-RMSE" in text and "RPE trans" in text and "RPE rot" in text and f"{m['ate_rmse_mm']:.4f}" in text

    rc = main_eval(tmp_path / "gt.txt", tmp_path / "est.txt", json_path=tmp_path / "m.json")
    out = capsys.readouterr().out
    assert rc == 0 and "ATE-RMSE" in out and "30 matched" in out
    assert json.loads((tmp_path / "m.json").read_text()) == pytest.approx(m)

    from slam.app.cli import main

    rc = main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "missing.txt")])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("slam eval: error: ") and "missing.txt" in err
    assert len(err.strip().splitlines()) == 1
