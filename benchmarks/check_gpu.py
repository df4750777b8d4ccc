"""Check the GPU path: the same sequence on the CPU and on ``--device``, pose by pose, and the fps.

    .venv/bin/python tools/check_gpu.py [--device cuda] [--frames 60] [--size 640x512]
                                        [--modes frame2frame frame2model] [--set key=value ...]

It renders a synthetic ``scanning`` sequence (seed 4242), runs it in the default configuration
on the CPU (the reference: numba kernels for the solver and the map) and on ``--device`` (DIS
stays on the CPU in its thread; RAFT when configured, the weight networks, the solve, the render
and the fusion on the device; the numba kernels give way to the torch code there), then prints
for each mode the largest difference of the per-frame relative poses (mm, deg) and both runs' fps.

Without a GPU, ``--device cpu`` runs the device side on the CPU with the torch kernels forced
(``analysis.solver_kernel=torch``, ``analysis.map_kernels=torch``): the code a GPU runs, on this machine. The exit
code is 1 when a frame2frame pose differs by more than ``--tol-mm`` / ``--tol-deg`` (1e-3 each).
frame2model's figures are printed beside it: there a pose also depends on the map built from
every earlier pose, so the two runs' inputs are identical only as far as the maps agree, and a
rounding difference in the fusion grows with the sequence.

A GPU machine runs it in under 5 minutes at the defaults. The first run also loads the numba
kernels, so the fps columns are for reading, not for a speed comparison
(``tools/benchmark_speed.py`` is that).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from slam.app.cli import parse_size
from slam.app.runner import run_from_config
from slam.config import load_config
from slam.synth import generate


def relative_poses(records: list) -> np.ndarray:
    """``(N-1, 4, 4)`` motion from each frame to the next, mm."""
    poses = np.stack([r.pose for r in records])
    return np.linalg.inv(poses[:-1]) @ poses[1:]


def pose_differences(ref: np.ndarray, dev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, the translation (mm) and rotation (deg) between two runs' relative poses."""
    delta = np.linalg.inv(ref) @ dev
    return np.linalg.norm(delta[:, :3, 3], axis=1), np.degrees(Rotation.from_matrix(delta[:, :3, :3]).magnitude())


def run(data: Path, out: Path, mode: str, device: str, torch_kernels: bool, sets: list[str]) -> tuple[np.ndarray, float]:
    overrides = [f"tracking.mode={mode}", f"device={device}", *sets]
    if torch_kernels:
        overrides += ["analysis.solver_kernel=torch", "analysis.map_kernels=torch"]
    result = run_from_config(data, load_config(None, overrides), out=out, print_summary=False, overwrite=True)
    return relative_poses(result.records), float(result.metrics["fps"])


def main(argv: list[str] | None = None) -> int:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", default="640x512")
    ap.add_argument("--modes", nargs="+", default=["frame2frame", "frame2model"])
    ap.add_argument("--set", action="append", default=[], help="config override for both runs (key=value)")
    ap.add_argument("--tol-mm", type=float, default=1e-3)
    ap.add_argument("--tol-deg", type=float, default=1e-3)
    ap.add_argument("--out", default="", help="folder for the sequence and the runs (default: a temporary one)")
    args = ap.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        print(f"--device {args.device}: torch sees no CUDA device (torch {torch.__version__})")
        return 2
    sets = ["threads=1", *args.set]
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.out or tmp)
        data = generate(root / "data", "scanning", frames=args.frames, size=parse_size(args.size), seed=4242)
        print(f"{args.frames} frames at {args.size}: cpu (numba kernels) against {args.device} (torch kernels)")
        print(f"| mode | max dt mm | max dR deg | cpu (numba) fps | {args.device} (torch) fps | within tolerance |")
        print("|---|---|---|---|---|---|")
        ok = True
        for mode in args.modes:
            ref, fps_ref = run(data, root / f"{mode}_cpu", mode, "cpu", False, sets)
            dev, fps_dev = run(data, root / f"{mode}_{args.device.replace(':', '')}", mode, args.device, True, sets)
            dt, dr = pose_differences(ref, dev)
            within = bool(dt.max() <= args.tol_mm and dr.max() <= args.tol_deg)
            if mode == "frame2frame":
                ok &= within
            print(f"| {mode} | {dt.max():.2e} | {dr.max():.2e} | {fps_ref:.1f} | {fps_dev:.1f} | "
                  f"{'yes' if within else 'no'}{'' if mode == 'frame2frame' else ' (informative)'} |")
    print(f"{'PASS' if ok else 'FAIL'}: frame2frame poses within {args.tol_mm:g} mm and {args.tol_deg:g} deg "
          f"({time.perf_counter() - started:.0f} s)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
