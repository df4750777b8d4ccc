"""benchmarks/check_gpu.py: the device path (torch kernels) against the CPU's numba kernels."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from benchmarks import check_gpu


def test_pose_differences_measure_a_known_perturbation():
    rng = np.random.default_rng(0)
    ref = np.tile(np.eye(4), (5, 1, 1))
    ref[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.05, (5, 3))).as_matrix()
    ref[:, :3, 3] = rng.normal(0, 2.0, (5, 3))
    bump = np.eye(4)
    bump[:3, :3] = Rotation.from_rotvec([0.0, np.radians(0.01), 0.0]).as_matrix()
    bump[:3, 3] = [0.0, 0.002, 0.0]
    dev = ref.copy()
    dev[3] = ref[3] @ bump
    dt, dr = check_gpu.pose_differences(ref, dev)
    np.testing.assert_allclose(dt, [0, 0, 0, 0.002, 0], atol=1e-9)
    np.testing.assert_allclose(dr, [0, 0, 0, 0.01, 0], atol=1e-7)


def test_torch_kernels_on_the_cpu_match_the_numba_kernels(tmp_path, capsys):
    """The CI run of the GPU check: ``--device cpu`` runs the code a GPU runs (torch kernels);
    frame2frame's per-frame poses must equal the numba reference to 1e-3 mm / 1e-3 deg."""
    code = check_gpu.main(["--device", "cpu", "--frames", "12", "--size", "320x256", "--modes", "frame2frame",
                           "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "| frame2frame |" in out and "PASS" in out


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (torch.cuda.is_available() is False)")
def test_cuda_matches_the_cpu(tmp_path, capsys):
    code = check_gpu.main(["--device", "cuda", "--frames", "20", "--size", "320x256", "--out", str(tmp_path)])
    assert code == 0, capsys.readouterr().out
