"""tools/benchmark_frame_rate.py: frame errors, gap sequences on disk, and the report re-read."""
from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.benchmark_frame_rate import frame_errors, frame_files, summary, with_gap
from slam.evaluation.chain import chain_errors


def _pose(t) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


def test_frame_errors_measure_each_motion_from_the_last_tracked_frame():
    truth = np.stack([_pose([k, 0.0, 0.0]) for k in range(5)])
    poses = truth.copy()
    poses[2] = _pose([2.0, 0.3, 0.0])       # frame 2 off by 0.3 mm sideways
    poses[3] = poses[2]                     # frame 3 failed: it keeps the last pose
    poses[4] = _pose([4.0, 0.3, 0.4])       # frame 4's motion from frame 2: (2, 0, 0.4) against (2, 0, 0)
    errors = frame_errors(poses, truth, np.array([False, False, False, True, False]))
    assert np.isnan(errors[0]) and np.isnan(errors[3])
    assert errors[1] == pytest.approx(0.0, abs=1e-9)
    assert errors[2] == pytest.approx(0.3, abs=1e-9)
    assert errors[4] == pytest.approx(0.4, abs=1e-9)
    chain = chain_errors(poses, truth, np.array([True, True, False, False, True]))
    case = {"errors_mm": [None if np.isnan(e) else e for e in errors], "flagged": [2], "failed": [3],
            "chain_mm": [None if np.isnan(e) else e for e in chain],
            "relocalised": [], "ate_rmse_mm": 0.1, "frames": 5, "gap": 1, "gap_from": 3, "after": 4}
    row = summary(case)
    # the flagged frame's 0.3 mm is not silent itself, but frame 4 carries it: along the chain of
    # trusted frames (0, 1, 4) its position errs by (0, 0.3, 0.4) against frame 1's
    assert row["silent_max"] == pytest.approx(0.5) and row["silent_over"] == 0
    assert row["first_after"] == (pytest.approx(0.4), "tracked") and row["back_after"] == 1


def test_gaps_are_written_to_disk_and_tracked_as_failed(synth_dir, tmp_path):
    """A gap of black or unreadable frames in a copy of the sequence: the copy links the other
    files; the benchmark's run fails the gap frames (nothing to track), writes its table and json,
    and the json re-reads with a row per condition."""
    import cv2

    from benchmarks.benchmark_frame_rate import main

    data = synth_dir("scanning", 24, (160, 128))
    black = with_gap(data, tmp_path / "black", range(10, 12), "black")
    left = frame_files(black, 10)[0]
    assert left.is_file() and not left.is_symlink() and cv2.imread(str(left)).max() == 0
    assert frame_files(black, 12)[0].is_symlink()
    unreadable = with_gap(data, tmp_path / "unreadable", range(10, 12), "unreadable")
    assert frame_files(unreadable, 11)[1].stat().st_size == 0

    out = tmp_path / "bench"
    main(["--scenarios", "scanning", "--seeds", "3", "--frames", "24", "--size", "160x128", "--steps", "1", "2",
          "--gaps", "3", "--gap-step", "2", "--bursts", "4", "--burst-frames", "2", "--modes", "frame2frame",
          "--workers", "1", "--out", str(out)])
    report = json.loads((out / "frame_rate.json").read_text())
    cases = {(c["step"], c["gap"], c["kind"], c["burst"]): c for c in report["cases"]}
    assert set(cases) == {(1, 0, "", 0), (2, 0, "", 0), (2, 3, "black", 0), (2, 3, "unreadable", 0), (2, 0, "", 4)}
    # the burst: frames 0-8 every 2nd, 8-16 every 4th, then every 2nd again (10 frames, 12.5 fps)
    burst = cases[(2, 0, "", 4)]
    assert burst["frames"] == 10 and burst["gap_from"] == 4 and burst["after"] == 7
    assert "2 frames at 6.25 fps in 12.5 fps" in (out / "frame_rate.md").read_text()
    cases = {k[:3]: c for k, c in cases.items() if not k[3]}
    assert cases[(1, 0, "")]["frames"] == 24 and cases[(2, 0, "")]["frames"] == 12
    for kind in ("black", "unreadable"):
        case = cases[(2, 3, kind)]
        assert case["gap_from"] == 4 and set(range(4, 7)) <= set(case["failed"])
    assert "gap 3 unreadable at 12.5 fps" in (out / "frame_rate.md").read_text()
