"""tools/check_accuracy.py: the verdict on made-up figures, silent frames along the chain, the
identical-runs failure, the moved copies, the panel's command line and its missing-data message."""
from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks import accuracy_panel as panel_module
from benchmarks.accuracy_panel import moved_copy, panel, real_folder, world_move
from benchmarks.check_accuracy import (GATED, CaseResult, figures, identical, judge, judge_case, main, options_for,
                                       select, verdict)
from slam.evaluation.chain import chain_errors, silent_summary, step_errors
from slam.evaluation.metrics import align, ate_rmse
from slam.io.tum import read_tum, write_tum

MM = GATED[0][2]            # the ATE's floor


def _result(name: str, base: list[float], new: list[float], silent=(0, 0)) -> CaseResult:
    case = next(c for c in panel() if c.name == name)
    r = CaseResult(case, figures={
        "base": [{"ate_mm": a, "silent_over": silent[0]} for a in base],
        "new": [{"ate_mm": a, "silent_over": silent[1]} for a in new]})
    judge_case(r, "base", "new")
    return r


def test_a_shift_inside_the_spread_passes_one_beyond_it_fails_an_improvement_passes():
    # frame2model's runs spread by 0.02 mm: a shift of 0.015 is noise
    inside = _result("real-f2m", [0.170, 0.180, 0.190], [0.185, 0.195, 0.200])
    assert inside.judged["ate_mm"][0] == "same"
    # the same spread, shifted by 0.03: beyond it
    beyond = _result("real-f2m", [0.170, 0.180, 0.190], [0.200, 0.210, 0.220])
    assert beyond.judged["ate_mm"][0] == "regressed"
    assert beyond.judged["ate_mm"][1] == pytest.approx(0.03) and beyond.judged["ate_mm"][2] == pytest.approx(0.02)
    better = _result("real-f2f", [1.40, 1.40, 1.40], [1.20, 1.20, 1.20])
    assert better.judged["ate_mm"][0] == "improved"
    line = verdict([inside, better])
    assert line.startswith("PASS: 2 cases") and "real-f2f ATE" in line
    line = verdict([inside, beyond, better])
    assert line.startswith("FAIL: real-f2m ATE +0.03 beyond 0.02") and "improved: real-f2f ATE" in line


def test_without_spread_the_floor_decides():
    # frame2frame's runs agree to the last digit: the floor (1 %, at least 0.005 mm) is the bound
    assert MM(1.4) == pytest.approx(0.014) and MM(0.1) == pytest.approx(0.005)
    assert judge([1.40] * 3, [1.41] * 3, MM)[0] == "same"
    assert judge([1.40] * 3, [1.42] * 3, MM)[0] == "regressed"
    # one more silent frame in every run is a regression, whatever the ATE
    r = _result("real-2.5fps-f2m", [3.0] * 3, [3.0] * 3, silent=(0, 1))
    assert r.judged["silent_over"][0] == "regressed" and verdict([r]).startswith("FAIL: real-2.5fps-f2m silent frames")


def test_silent_frames_along_the_chain_see_an_inherited_pose_a_snap_back_and_a_wrong_relocalisation():
    """The issue's frames 54-60: a wrong relocalisation (flagged), frames tracked right against it
    (unflagged, carried 12 mm off), a snap back to the map (unflagged): each motion from the frame
    before is right, so RPE at delta 1 sees nothing but the two jumps; the chain sees the carried
    frames and the snap back."""
    truth = np.stack([np.eye(4) for _ in range(8)])
    truth[:, 0, 3] = np.arange(8) * 4.0
    poses = truth.copy()
    poses[2:7, 1, 3] += 12.0                   # from frame 2 (the wrong relocalisation) on, 12 mm aside
    flagged = np.array([0, 0, 1, 1, 0, 0, 0, 0], bool)
    failed = np.zeros(8, bool)
    poses[7, 1, 3] = 0.0                       # frame 7 snaps back
    chain = chain_errors(poses, truth, ~flagged & ~failed)
    assert np.isnan(chain[[0, 2, 3]]).all()
    assert chain[4] == pytest.approx(12.0)     # carries the flagged frames' error: silent
    assert chain[5] == pytest.approx(0.0) and chain[6] == pytest.approx(0.0)
    assert chain[7] == pytest.approx(12.0)     # the jump back
    steps = step_errors(poses, truth)
    assert steps[4] == pytest.approx(0.0)      # the motion from the frame before is right: RPE misses it
    summary = silent_summary(poses, truth, flagged, failed)
    assert summary["silent_over"] == 2 and summary["silent_frames"] == [4, 7]
    assert summary["silent_max_mm"] == pytest.approx(12.0) and summary["unflagged_step_max_mm"] == pytest.approx(12.0)
    # in a world frame of its own the estimate's chain is the same
    moved = silent_summary(world_move(2) @ poses, truth, flagged, failed)
    assert moved["silent_frames"] == [4, 7] and moved["silent_max_mm"] == pytest.approx(12.0)


def _run(folder, poses_mm, flagged, stamps):
    folder.mkdir(parents=True)
    write_tum(folder / "trajectory.txt", stamps, poses_mm)
    rows = ["frame,timestamp,failed,flagged,reason"] + [f"{k},{t:.6f},0,{int(f)}," for k, (t, f) in
                                                         enumerate(zip(stamps, flagged))]
    (folder / "tracking.csv").write_text("\n".join(rows) + "\n")
    (folder / "metrics.json").write_text(json.dumps({"fps": 3.0}))
    return folder


def test_a_runs_figures_are_read_against_its_moved_ground_truth(tmp_path):
    """A run tracked in world frame k (its first pose the moved ground truth's) is measured like
    the unmoved one; identical trajectories are told apart from moved ones."""
    stamps = np.arange(10) * 0.2
    truth = np.stack([np.eye(4) for _ in stamps])
    truth[:, 0, 3] = np.arange(10) * 2.0
    truth[:, 2, 3] = np.sin(np.arange(10))
    (tmp_path / "seq").mkdir()
    write_tum(tmp_path / "seq" / "groundtruth.txt", stamps, truth)
    estimate = truth.copy()
    estimate[5:, 1, 3] += 0.3                   # 0.3 mm off from frame 5 on
    aligned, _ = align(truth, estimate, "se3")
    expected = ate_rmse(truth, aligned)
    assert 0.05 < expected < 0.15
    runs = []
    for k in (0, 1):
        copy = moved_copy(tmp_path / "seq", tmp_path / "seq" / "groundtruth.txt", k, tmp_path / f"k{k}")
        _, moved = read_tum(copy / "groundtruth.txt")
        assert np.allclose(moved, world_move(k) @ truth, atol=1e-5)
        runs.append(_run(tmp_path / f"run{k}", world_move(k) @ estimate, np.zeros(10, bool), stamps))
        f = figures(runs[-1], copy / "groundtruth.txt", k, None)
        assert f["ate_mm"] == pytest.approx(expected, abs=1e-5)     # (TUM rows hold 1e-6 mm)
        assert f["silent_over"] == 0 and f["unflagged_step_max_mm"] == pytest.approx(0.3, abs=1e-4)
        assert f["frames"] == 10 and f["flagged"] == 0 and f["fps"] == 3.0
    assert not identical(runs)
    same = _run(tmp_path / "same", world_move(0) @ estimate, np.zeros(10, bool), stamps)
    assert identical([runs[0], same])


def test_identical_runs_fail_the_verdict():
    r = _result("real-f2m", [0.18] * 3, [0.18] * 3)
    r.problems.append("new: its 3 runs wrote the same trajectory (the moved world frame did not reach them)")
    assert verdict([r]).startswith("FAIL: real-f2m: new: its 3 runs wrote the same trajectory")


def test_options_an_older_commit_lacks_are_not_passed_to_it(tmp_path):
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "default.yaml").write_text("threads: 0\ndata:\n  fps: 0.0\n")
    kept, dropped = options_for(tmp_path, ["--mode", "frame2model", "--set", "threads=1", "--set", "data.fps=5",
                                           "--set", "tracking.model_every=3", "--frames", "::2"])
    assert kept == ["--mode", "frame2model", "--set", "threads=1", "--set", "data.fps=5", "--frames", "::2"]
    assert dropped == ["tracking.model_every=3"]


def test_the_panel_and_its_command_line(capsys):
    cases = panel()
    names = [c.name for c in cases]
    assert len(names) == len(set(names)) == 56
    quick = select(cases, True, None)
    assert {"real-f2m", "real-f2f", "real-2.5fps-f2m"} <= {c.name for c in quick} and len(quick) < 10
    assert all(c.sequence.real for c in select(cases, False, ["real-*"]))
    # the real sequence at 2.5 fps: every second frame, the reference's timestamps
    assert next(c for c in cases if c.name == "real-2.5fps-f2m").options == ("--frames", "::2", "--set", "data.fps=5")
    assert [c.name for c in cases if c.map_error] == ["real-f2m", "real-2.5fps-f2m"]
    # every scenario x look x seed x mode of the generator at 640x512, apart from the tuning seeds
    generated = [c for c in cases if not c.sequence.real and c.sequence.size == (640, 512) and not c.sequence.raw]
    assert len(generated) == 48 and {c.sequence.seed for c in generated} == {9701, 9702}
    assert main(["--base", "HEAD", "--quick", "--list"]) == 0
    assert "real-f2m  (quick)" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="at least 2"):
        main(["--base", "HEAD", "--runs", "1"])


def test_a_missing_real_sequence_says_how_to_get_it(tmp_path, monkeypatch):
    monkeypatch.delenv(panel_module.REAL_ENV, raising=False)
    with pytest.raises(SystemExit) as err:
        real_folder(str(tmp_path / "nowhere"))
    message = str(err.value)
    assert str(tmp_path / "nowhere") in message and "FelTris/camp2_3drecon" in message and "--real" in message
    assert "\n" not in message
    monkeypatch.setenv(panel_module.REAL_ENV, str(tmp_path))
    (tmp_path / "left_image").mkdir()
    (tmp_path / "right_image").mkdir()
    assert real_folder(None) == tmp_path
    with pytest.raises(SystemExit, match="the real sequence is not at"):
        main(["--base", "HEAD", "--cases", "real-f2m", "--real", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")])


def test_the_gate_end_to_end_on_a_small_sequence(tmp_path, monkeypatch, capsys):
    """Both sides through ``slam run`` on a tiny frame2model case, each twice in a moved world frame:
    the same code on both sides passes, its runs differ from each other (the move reaches them),
    the report is written and re-read, and a second gate reuses every run from the cache."""
    from benchmarks import check_accuracy
    from benchmarks.accuracy_panel import Case, Sequence

    tiny = Case("tiny-f2m", Sequence("tiny", "scanning", 12, (160, 128), 5), "frame2model", quick=True)
    monkeypatch.setattr(check_accuracy, "panel", lambda: [tiny])
    # the base: this checkout under a tree key of its own, so that both sides run
    monkeypatch.setattr(check_accuracy, "checkout", lambda commit, out: (panel_module.ROOT, "b" * 40))
    out = tmp_path / "gate"
    assert main(["--base", "HEAD", "--quick", "--runs", "2", "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert "PASS: 1 cases" in printed.out and "tiny-f2m" in printed.out
    report = json.loads(next((out / "reports").glob("*_quick.json")).read_text())
    case = report["cases"][0]
    assert case["problems"] == [] and report["verdict"].startswith("PASS")
    base, new = case["figures"]["base HEAD"], case["figures"]["new"]
    assert len(base) == len(new) == 2
    for f in base + new:
        assert 0 < f["ate_mm"] < 2.0 and f["frames"] == 12 and f["failed"] == 0
    assert [f["ate_mm"] for f in base] == [f["ate_mm"] for f in new]          # the same code, the same runs
    runs = sorted((out / "cache").glob("*/tiny-f2m/k*/run"))
    assert len(runs) == 4 and not identical(runs[:2])
    stamps = {p: p.stat().st_mtime_ns for p in (out / "cache").glob("*/tiny-f2m/k*/done.json")}
    assert main(["--base", "HEAD", "--quick", "--runs", "2", "--out", str(out)]) == 0
    assert {p: p.stat().st_mtime_ns for p in (out / "cache").glob("*/tiny-f2m/k*/done.json")} == stamps


def test_a_run_that_did_not_finish_fails_the_new_side_and_is_a_note_on_the_base(tmp_path):
    """The base's failures are its own (an older commit's metrics that stopped with an error after
    every row was written is still measured); the new side's fail the gate."""
    from benchmarks.accuracy_panel import Case, Sequence
    from benchmarks.check_accuracy import Job, Side, collect

    stamps = np.arange(6) * 0.2
    truth = np.stack([np.eye(4) for _ in stamps])
    truth[:, 0, 3] = np.arange(6) * 1.0
    (tmp_path / "seq").mkdir()
    write_tum(tmp_path / "seq" / "groundtruth.txt", stamps, truth)
    case = Case("c", Sequence("s", "rigid", 6), "frame2frame")
    jobs, records = [], {}
    for k in (0, 1):
        folder = tmp_path / f"k{k}"
        _run(folder / "run", world_move(k) @ truth, np.zeros(6, bool), stamps)
        jobs.append(Job(Side("x", tmp_path, "t"), case, k, tmp_path / "seq", folder))
        records[folder] = {"exit": 0 if k == 0 else 2, "error": "slam run: error: relative pose error"}
    for fails in (False, True):
        r = CaseResult(case)
        collect(r, "side", jobs, records, None, fails=fails)
        assert len(r.figures["side"]) == 2 and r.figures["side"][1]["ate_mm"] < 1e-3
        said = r.problems if fails else r.notes
        assert said == ["side run k1 exit 2: slam run: error: relative pose error"]
        assert (r.notes if fails else r.problems) == []
        assert verdict([r]).startswith("FAIL" if fails else "PASS")
