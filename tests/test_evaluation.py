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
# figures recorded from the implementation before it went through evo (commit f633b9a)
# ------------------------------------------------------------------------------------------
def reference_cases() -> dict:
    """Name -> (gt, est) of the cases whose figures are recorded in RECORDED below."""
    cases = {}
    for seed in (100, 101, 102, 103):
        rng = np.random.default_rng(seed)
        gt = smooth_gt(rng, n=90)
        cases[f"random{seed}"] = (gt, rigid(rng) @ noisy(rng, gt))
    rng = np.random.default_rng(110)  # static: jitter well below 1 mm, 'auto' picks 'first'
    gt = np.tile(rigid(rng), (70, 1, 1))
    gt[:, :3, 3] += rng.normal(size=(70, 3)) * 0.05
    cases["static"] = (gt, rigid(rng) @ noisy(rng, gt, trans_mm=0.2, rot_deg=0.1))
    rng = np.random.default_rng(111)
    gt = smooth_gt(rng, n=50)
    cases["two_poses"] = (gt[[0, 49]], noisy(rng, gt)[[0, 49]])
    cases["identical"] = (gt, gt.copy())
    cases["frozen"] = (gt, np.tile(rigid(rng), (50, 1, 1)))  # coincident estimated positions
    line = noisy(rng, gt)
    line[:, :3, 3] = np.outer(np.linspace(0.0, 30.0, 50), [0.6, 0.0, 0.8])  # collinear
    cases["straight"] = (gt, line)
    axis = noisy(rng, gt)
    axis[:, :3, 3] = 0.0
    axis[:, 0, 3] = np.linspace(0.0, 30.0, 50)  # exactly on an axis: covariance of rank 1 exactly
    cases["on_axis"] = (gt, axis)
    return cases


def reference_stamps() -> dict:
    """Name -> (gt_stamps, est_stamps, max_diff) of the association cases in RECORDED_ASSOCIATION."""
    rng = np.random.default_rng(120)
    gt = np.cumsum(rng.uniform(0.02, 0.05, size=200))
    est = np.sort(rng.choice(gt, 150, replace=False) + rng.uniform(-0.015, 0.015, 150))
    ties = np.arange(10.0)  # frame indices: every estimate stamp halfway between two
    return {
        "shorter_estimate": (gt, est, 0.01),
        "longer_estimate": (est, gt, 0.01),
        "unsorted": (gt[rng.permutation(len(gt))], est, 0.01),
        "ties": (ties, ties[:-1] + 0.5, 0.5),
        "default_tolerance": (gt, est, None),
    }


def reference_files(tmp_path) -> tuple:
    """Two TUM files: frames missing and jittered stamps in the estimate."""
    rng = np.random.default_rng(130)
    n = 120
    gt = smooth_gt(rng, n)
    est = rigid(rng) @ noisy(rng, gt)
    stamps = 500.0 + np.arange(n) / 30.0
    keep = np.sort(rng.choice(n, size=n - 15, replace=False))
    write_tum(tmp_path / "gt.txt", stamps, gt)
    write_tum(tmp_path / "est.txt", stamps[keep] + rng.uniform(-0.004, 0.004, len(keep)), est[keep])
    return tmp_path / "gt.txt", tmp_path / "est.txt"


RECORDED = {
    'random100': {
        'auto': 'se3', 'static': False,
        'se3': (2.125493785904007, 2.3515392073106516, 0.9055480833696409, 1.056309479219626, 0.4908573395202999),
        'first': (3.854129368801871, 2.351539207310653, 0.9055480833696412, 1.0563094792196264, 0.49085733952029975),
        'none': (96.18261576296162, 2.3515392073106516, 0.9055480833696402, 1.0563094792196264, 0.4908573395202998),
        'rpe3': (2.4695298424560113, 0.9016378703690933, 1.0014053042282665, 0.4343874370727217),
    },
    'random101': {
        'auto': 'se3', 'static': False,
        'se3': (2.6994603783514424, 2.4511924274050694, 1.0292591291796496, 1.1533865992275296, 0.4773030084746755),
        'first': (3.924335926148317, 2.45119242740507, 1.0292591291796496, 1.1533865992275296, 0.4773030084746753),
        'none': (122.62809587916725, 2.451192427405069, 1.0292591291796507, 1.1533865992275294, 0.4773030084746753),
        'rpe3': (2.579058165345415, 1.1804961834566339, 1.116837566930036, 0.5116817501538685),
    },
    'random102': {
        'auto': 'se3', 'static': False,
        'se3': (2.8327892201455924, 2.3411325923881914, 0.9019512530151068, 1.068667181511892, 0.46411830758580236),
        'first': (5.424542309661852, 2.34113259238819, 0.9019512530151061, 1.068667181511892, 0.4641183075858027),
        'none': (162.7161397917059, 2.341132592388189, 0.9019512530151068, 1.068667181511892, 0.46411830758580264),
        'rpe3': (2.4587955729020363, 1.0517809174612698, 1.0442802194278324, 0.5156441740059039),
    },
    'random103': {
        'auto': 'se3', 'static': False,
        'se3': (2.6598751960330724, 2.4596249693665677, 0.8569349752467607, 1.0869522846011332, 0.4319338055659742),
        'first': (4.908118805486537, 2.459624969366566, 0.8569349752467591, 1.0869522846011324, 0.4319338055659744),
        'none': (138.61280754120318, 2.459624969366567, 0.8569349752467592, 1.0869522846011328, 0.4319338055659744),
        'rpe3': (2.4288214367073153, 0.9889752592818889, 1.128379437698588, 0.46316585885645944),
    },
    'static': {
        'auto': 'first', 'static': True,
        'se3': (0.45902400944090466, 0.4559155548379036, 0.20849396588495306, 0.2513349430568082, 0.10295049263363931),
        'first': (0.6909249593452759, 0.455915554837905, 0.20849396588495414, 0.2513349430568081, 0.10295049263363891),
        'none': (29.18425992897927, 0.45591555483790386, 0.20849396588495203, 0.25133494305680826, 0.10295049263363887),
        'rpe3': (0.48623674353424323, 0.23823326082782414, 0.2472929757972337, 0.11602113980650854),
    },
    'two_poses': {
        'auto': 'se3', 'static': False,
        'se3': (2.404289402213031, 6.260405418087568, 0.0, 1.3681300300377432, 0.0),
        'first': (4.426775124106711, 6.260405418087545, 0.0, 1.368130030037747, 0.0),
        'none': (4.495545743238836, 6.260405418087549, 0.0, 1.3681300300377428, 0.0),
    },
    'identical': {
        'auto': 'se3', 'static': False,
        'se3': (1.9639722923389327e-14, 9.186005573286602e-15, 4.6633887088521684e-15, 1.6541772445107677e-15, 7.942642604141234e-16),
        'first': (9.061297269471504e-15, 6.093318742040637e-15, 3.391071143871002e-15, 1.4275738770443034e-15, 7.035576672288135e-16),
        'none': (0.0, 3.2111952687542575e-16, 5.008990543474807e-16, 0.0, 0.0),
        'rpe3': (7.884318198314588e-16, 9.78349822124399e-16, 0.0, 0.0),
    },
    'frozen': {
        'auto': 'se3', 'static': False,
        'se3': (45.54884248605229, 8.95904831672702, 2.689656888051234, 3.2195385607816527, 1.08520555511335),
        'first': (55.79157024773744, 8.95904831672702, 2.689656888051234, 3.219538560781653, 1.0852055551133502),
        'none': (96.43215981274999, 8.95904831672702, 2.689656888051234, 3.2195385607816527, 1.08520555511335),
        'rpe3': (26.453305099463016, 7.86084856178441, 9.429262715412607, 2.967912610156167),
    },
    'straight': {
        'auto': 'se3', 'static': False,
        'se3': (42.11289104785088, 9.049861099015613, 2.6129316416956914, 1.092789454719828, 0.5264442303415057),
        'first': (60.304821789770635, 9.049861099015613, 2.612931641695692, 1.0927894547198282, 0.5264442303415059),
        'none': (51.370456641047156, 9.049861099015613, 2.6129316416956914, 1.0927894547198285, 0.5264442303415061),
        'rpe3': (26.711187989452025, 7.637522168709951, 1.1723441034704218, 0.45059471860724787),
    },
    'on_axis': {
        'auto': 'se3', 'static': False,
        'se3': (42.11289104785088, 9.102316781709918, 2.4879665550221075, 1.1224486576912451, 0.4200451113506907),
        'first': (63.66191701300672, 9.102316781709918, 2.4879665550221066, 1.1224486576912454, 0.42004511135069067),
        'none': (50.65784692525229, 9.102316781709918, 2.4879665550221075, 1.1224486576912454, 0.42004511135069067),
        'rpe3': (26.86133142235267, 7.258894497898767, 1.0607654892834844, 0.36545862964736553),
    },
}
RECORDED_ALIGNED_LAST = {
    ('random100', 'se3'): [[0.643336596734, 0.144723385447, -0.751779997744, -32.472894677021], [-0.376260480656, 0.914962507272, -0.145848075009, 7.840445060512], [0.666742884476, 0.376694507515, 0.643082556138, 30.153564468307]],
    ('random100', 'first'): [[0.672819516761, 0.156129737064, -0.723144109476, -29.005924760504], [-0.377622500284, 0.913027033093, -0.154217003344, 8.183954671508], [0.636172260591, 0.376835696352, 0.673260508874, 30.735628255303]],
    ('static', 'se3'): [[0.008229535224, 0.914840541506, -0.403731418604, 6.701462224083], [-0.790366547878, -0.241383281916, -0.563076221489, 61.563644435853], [-0.612578970211, 0.32372966319, 0.721072888428, -1.209981411304]],
    ('static', 'first'): [[-0.800291665201, 0.470914169786, -0.371177983323, 6.647777931999], [-0.568610247372, -0.792494365633, 0.220533596132, 62.026604598636], [-0.190304065098, 0.387546803798, 0.901993258108, -0.582277301863]],
}
RECORDED_ASSOCIATION = {  # name: (max_diff used, matches, sum gt idx, sum est idx, sum gt idx * est idx)
    'shorter_estimate': (0.01, 101, 10511, 7783, 1071851),
    'longer_estimate': (0.01, 101, 7783, 10511, 1071851),
    'unsorted': (0.01, 101, 9741, 7783, 743640),
    'ties': (0.5, 9, 36, 36, 204),
    'default_tolerance': (0.015968546232729808, 150, 15080, 11175, 1506663),
}
RECORDED_FILES = (3.0096987467966945, 2.4104774694850266, 1.0173487274294817, 1.081222757295247, 0.36636926223892785, 'se3', 105)


def assert_as_recorded(new, old, what: str) -> None:
    """Equal to 1e-9, relative below 1 and absolute above (the stricter of the two), and within
    1e-12 where the recorded figure is rounding noise around zero."""
    new, old = np.asarray(new, dtype=np.float64), np.asarray(old, dtype=np.float64)
    tol = 1e-9 * np.minimum(1.0, np.abs(old)) + 1e-12
    assert np.all(np.abs(new - old) <= tol), f"{what}: {new.tolist()} != recorded {old.tolist()}"


@pytest.mark.parametrize("name", sorted(RECORDED))
def test_figures_as_recorded_before_evo(name):
    gt, est = reference_cases()[name]
    rec = RECORDED[name]
    assert ev.is_static(gt) is rec["static"]
    auto = ev.evaluate(gt, est)
    assert auto["alignment"] == rec["auto"] and auto["frames"] == len(gt)
    assert_as_recorded([auto[k] for k in ev.METRIC_KEYS[:5]], rec[rec["auto"]], f"{name} auto")
    for method in ("se3", "first", "none"):
        m = ev.evaluate(gt, est, method)
        assert m["alignment"] == method
        assert_as_recorded([m[k] for k in ev.METRIC_KEYS[:5]], rec[method], f"{name} {method}")
    if "rpe3" in rec:
        r = ev.rpe(gt, est, delta=3)
        assert_as_recorded([r["trans_mean"], r["trans_std"], r["rot_mean"], r["rot_std"]], rec["rpe3"],
                           f"{name} rpe delta 3")


@pytest.mark.parametrize("name", ["frozen", "on_axis"])
def test_cases_evo_refuses_to_align(name):
    """These recorded figures cover the fallback for a covariance of rank < 2."""
    from evo.core.geometry import GeometryException, umeyama_alignment

    gt, est = reference_cases()[name]
    with pytest.raises(GeometryException):
        umeyama_alignment(est[:, :3, 3].T, gt[:, :3, 3].T)


@pytest.mark.parametrize("key", sorted(RECORDED_ALIGNED_LAST))
def test_aligned_poses_as_recorded_before_evo(key):
    name, method = key
    gt, est = reference_cases()[name]
    aligned, used = ev.align(gt, est, method)
    assert used == method and aligned.shape == est.shape
    np.testing.assert_allclose(aligned[-1][:3], RECORDED_ALIGNED_LAST[key], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(aligned[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (len(est), 1)))


@pytest.mark.parametrize("name", sorted(RECORDED_ASSOCIATION))
def test_association_as_recorded_before_evo(name):
    gt_stamps, est_stamps, max_diff = reference_stamps()[name]
    if max_diff is None:
        max_diff = ev.default_max_diff(gt_stamps)
    gi, ei = ev.associate(gt_stamps, est_stamps, max_diff)
    assert gi.dtype.kind == ei.dtype.kind == "i"
    assert (max_diff, len(gi), int(gi.sum()), int(ei.sum()), int((gi * ei).sum())) == RECORDED_ASSOCIATION[name]


def test_files_as_recorded_before_evo(tmp_path):
    m = ev.evaluate_files(*reference_files(tmp_path))
    assert_as_recorded([m[k] for k in ev.METRIC_KEYS[:5]], RECORDED_FILES[:5], "files")
    assert (m["alignment"], m["frames"]) == RECORDED_FILES[5:]


def test_importing_the_metrics_does_not_import_evo():
    """evo (and pandas behind it) load only when metrics are computed, not with a run."""
    import subprocess
    import sys
    from pathlib import Path

    code = "import sys, slam.evaluation.metrics; print('evo' in sys.modules, 'pandas' in sys.modules)"
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root).stdout
    assert out.split() == ["False", "False"]


# ------------------------------------------------------------------------------------------
# properties
# ------------------------------------------------------------------------------------------
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


def _write_ply(path, points_mm):
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points_mm) / 1000.0))
    assert o3d.io.write_point_cloud(str(path), cloud)


def test_eval_measures_a_map_against_reference_points_after_the_trajectorys_alignment(tmp_path, capsys):
    """``slam eval GT EST --map MAP --points REF``: the map lives in the estimate's world frame (here
    the truth's moved by 20 degrees and 30 mm), the reference's points in the truth's; after the
    trajectory's alignment a map 0.2 mm off the surface errs by 0.2 mm, one 2 mm off by 2 mm."""
    from slam.app.cli import main

    rng = np.random.default_rng(4)
    stamps = np.arange(30) * 0.2
    truth = np.stack([np.eye(4) for _ in stamps])
    truth[:, :3, 3] = np.c_[np.arange(30) * 1.5, np.sin(np.arange(30) / 4) * 3, np.zeros(30)]
    move = np.eye(4)
    move[:3, :3] = Rotation.from_rotvec([0.1, 0.3, 0.2]).as_matrix()
    move[:3, 3] = [30.0, -10.0, 5.0]
    write_tum(tmp_path / "gt.txt", stamps, truth)
    write_tum(tmp_path / "est.txt", stamps, move @ truth)
    grid = np.stack(np.meshgrid(np.arange(0, 40, 0.25), np.arange(0, 40, 0.25)), -1).reshape(-1, 2)
    surface = np.c_[grid, np.full(len(grid), 60.0)]                # a plane 60 mm away, dense map points
    reference = surface[rng.choice(len(surface), 500, replace=False)]
    _write_ply(tmp_path / "ref.ply", reference)
    for offset, median, within in ((0.2, 0.2, 1.0), (2.0, 2.0, 0.0)):
        cloud = (surface + [0.0, 0.0, offset]) @ move[:3, :3].T + move[:3, 3]
        _write_ply(tmp_path / "map.ply", cloud)
        assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--map", str(tmp_path / "map.ply"),
                     "--points", str(tmp_path / "ref.ply"), "--json", str(tmp_path / "m.json")]) == 0
        metrics = json.loads((tmp_path / "m.json").read_text())
        assert metrics["ate_rmse_mm"] < 1e-3
        assert metrics["map_median_mm"] == pytest.approx(median, abs=0.01)
        assert metrics["map_within_1mm"] == within and metrics["map_points"] == 500
        assert "within 1 mm" in capsys.readouterr().out
    # the two go together; a missing cloud is one line naming it, before anything is printed
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--map", str(tmp_path / "map.ply")]) == 2
    assert "--map and --points go together" in capsys.readouterr().err
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--map", str(tmp_path / "none.ply"),
                 "--points", str(tmp_path / "ref.ply")]) == 2
    out = capsys.readouterr()
    assert "none.ply: point cloud not found" in out.err and out.out == ""
