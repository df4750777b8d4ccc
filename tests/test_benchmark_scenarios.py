"""benchmarks/benchmark_scenarios.py end to end on tiny sequences: Table 1's layout, the averages it
prints, and the weight-map check on moving tissue."""
from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from benchmarks import benchmark_scenarios as B


def test_table_has_per_scenario_mean_and_both_averages(tmp_path, monkeypatch, capsys):
    out = tmp_path / "bench"
    monkeypatch.setattr(sys, "argv", ["benchmark_scenarios.py", "--scenarios", "breathing", "scanning",
                                      "--seeds", "5", "6", "--frames", "12", "--size", "160x128",
                                      "--workers", "1", "--methods", "w = 1", "learned 2D&3D", "--out", str(out)])
    B.main()
    results = json.loads((out / "scenarios.json").read_text())
    assert {(r["scenario"], r["seed"], r["method"]) for r in results} == {
        (s, seed, m) for s in ("breathing", "scanning") for seed in (5, 6) for m in ("w = 1", "learned 2D&3D")}
    for r in results:
        assert r["failed"] == 0 and 0 < r["ate_rmse_mm"] < 3.0, r
    assert len(list((out / "runs").glob("*/trajectory.txt"))) == len(results)
    table = (out / "scenarios.md").read_text()
    assert table.splitlines()[0] == "| method | breathing | scanning | micro avg. | macro avg. |"
    assert table.splitlines()[0] in capsys.readouterr().out
    learned = {(r["scenario"], r["seed"]): r["ate_rmse_mm"] for r in results if r["method"] == "learned 2D&3D"}
    # scanning here: (a, b); micro over all four sequences; macro over the two scenario means
    scan = [learned["scanning", 5], learned["scanning", 6]]
    allv = list(learned.values())
    means = [np.mean([learned["breathing", 5], learned["breathing", 6]]), np.mean(scan)]
    row = next(line for line in table.splitlines() if line.startswith("| learned 2D&3D |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2] == f"{np.mean(scan):.2f} ± {np.std(scan):.2f}"
    assert cells[3] == f"{np.mean(allv):.2f} ± {np.std(allv):.2f}"
    assert cells[4] == f"{np.mean(means):.2f} ± {np.std(means):.2f}"
    # the weight check: breathing sequences only (scanning is not in it), learned methods only
    check = [line for line in table.splitlines() if line.startswith("| learned 2D&3D | breathing s")]
    assert [line.split("|")[2].strip() for line in check] == ["breathing s5", "breathing s6"]
    for r in results:
        if r["method"] == "learned 2D&3D" and r["scenario"] == "breathing":
            w = r["w3d"]
            assert 0 < w["fraction_moving"] < 1
            assert 0 < w["moving"] < 1 and 0 < w["still"] < 1 and 0 < w["w2d_moving"] < 1 and 0 < w["w2d_still"] < 1
            # against a keyframe (the default gap 5) there is no split by the motion between two frames
            assert "pair_threshold_mm" not in w and "pair_moving" not in w
            line = next(line for line in check if line.startswith(f"| learned 2D&3D | breathing s{r['seed']} "))
            assert line.endswith(f"| {w['moving'] / w['still']:.2f} | {w['w2d_moving'] / w['w2d_still']:.2f} |")
        else:
            assert r["method"] != "w = 1" or r["w3d"] is None
    assert "between frames" not in table


def test_previous_frame_reference_also_splits_by_the_motion_between_the_frames(tmp_path, monkeypatch):
    """With the paper's reference (``tracking.keyframe_gap=1``, every frame against the previous one)
    the weight check also splits the pixels by how far their tissue moved between the two frames."""
    out = tmp_path / "bench"
    monkeypatch.setattr(sys, "argv", ["benchmark_scenarios.py", "--scenarios", "breathing", "--seeds", "5",
                                      "--frames", "12", "--size", "160x128", "--workers", "1", "--methods",
                                      "learned 2D&3D", "--set", "tracking.keyframe_gap=1", "--out", str(out)])
    B.main()
    (r,) = json.loads((out / "scenarios.json").read_text())
    w = r["w3d"]
    assert r["failed"] == 0 and 0 < r["ate_rmse_mm"] < 3.0
    # breathing moves some tissue every frame
    assert w["pair_threshold_mm"] == 0.02 and 0 < w["fraction_pair_moving"] < 1
    assert 0 < w["pair_moving"] < 1 and 0 < w["pair_still"] < 1 and 0 < w["w2d_pair_moving"] < 1
    table = (out / "scenarios.md").read_text()
    line = next(line for line in table.splitlines() if line.startswith("| learned 2D&3D | breathing s5 "))
    assert line.endswith(f"| {w['moving'] / w['still']:.2f} | {w['w2d_moving'] / w['w2d_still']:.2f} "
                         f"| {w['pair_moving'] / w['pair_still']:.2f} | {w['w2d_pair_moving'] / w['w2d_pair_still']:.2f} |")
    assert "| w3D ratio, moved > 0.02 mm between frames | w2D ratio, moved > 0.02 mm between frames |" in table


def test_weight_check_lists_every_learned_method():
    def stats(moving, still, w2m=None, w2s=None):
        return {"moving": moving, "still": still, "w2d_moving": w2m, "w2d_still": w2s, "fraction_moving": 0.5}

    results = [
        {"scenario": "breathing", "seed": 1, "method": "learned 3D", "w3d": stats(0.02, 0.04)},
        {"scenario": "breathing", "seed": 1, "method": "learned 2D&3D", "w3d": stats(0.01, 0.02, 0.3, 0.6)},
        {"scenario": "breathing", "seed": 1, "method": "learned 2D", "w3d": stats(None, None, 0.45, 0.5)},
        {"scenario": "scanning", "seed": 1, "method": "learned 2D&3D", "w3d": stats(0.01, 0.01, 0.5, 0.5)},
        {"scenario": "breathing", "seed": 1, "method": "w = 1", "w3d": None},
    ]
    rows = B.weight_check(results).splitlines()[2:]
    assert rows == ["| learned 2D&3D | breathing s1 | 0.50 | 0.0100 | 0.0200 | 0.50 | 0.50 |",
                    "| learned 3D | breathing s1 | 0.50 | 0.0200 | 0.0400 | 0.50 | - |",
                    "| learned 2D | breathing s1 | 0.50 | - | - | - | 0.90 |"]


def test_paired_ratio_of_learned_against_the_best_constant(tmp_path, monkeypatch, capsys):
    """The gap per scenario with its bootstrap interval over the sequences, resampled in pairs;
    `--report DIR` rebuilds the tables of a finished run without running it."""
    b = np.array([0.5, 1.0, 2.0, 0.8])
    assert B.paired_ratio(2 * b, b) == (2.0, 2.0, 2.0)       # a constant ratio has no spread
    rng = np.random.default_rng(1)
    a = b * rng.uniform(0.8, 1.4, size=4)
    ratio, lo, hi = B.paired_ratio(a, b)
    assert abs(ratio - a.mean() / b.mean()) < 1e-12 and lo < ratio < hi
    assert B.paired_ratio(a, b) == (ratio, lo, hi)              # seeded
    results = [{"scenario": s, "seed": k, "method": m, "ate_rmse_mm": float(v), "rpe_trans_mm": 0.01, "w3d": None}
               for s, f in (("breathing", 0.5), ("scanning", 1.0)) for k in range(4)
               for m, v in (("best constant", b[k]), ("learned 2D&3D", f * b[k] * (1.2 if k == 0 else 1.0)))]
    rows = B.paired_ratio_table(results, ["breathing", "scanning"], "learned 2D&3D", "best constant").splitlines()
    assert rows[4].startswith("| breathing | 4 | 0.51 | ") and rows[4].endswith(" | 4 |")
    assert rows[5].startswith("| scanning | 4 | 1.02 | 1.00 - ") and rows[5].endswith(" | 0 |")
    (tmp_path / "scenarios.json").write_text(json.dumps(results))
    monkeypatch.setattr(sys, "argv", ["benchmark_scenarios.py", "--report", str(tmp_path)])
    B.main()
    md = (tmp_path / "scenarios.md").read_text()
    assert "| scanning | 4 | 1.02 |" in md and md.splitlines()[0] in capsys.readouterr().out
    assert not (tmp_path / "runs").exists()                     # nothing was run


def test_weight_ratio_summary_covers_scanning_too():
    def stats(moving, still, w2m=None, w2s=None):
        return {"moving": moving, "still": still, "w2d_moving": w2m, "w2d_still": w2s, "fraction_moving": 0.5}

    results = [{"scenario": "breathing", "seed": k, "method": "learned 2D&3D", "w3d": stats(0.01 * k, 0.02, 0.3, 0.6)}
               for k in (1, 2, 3)]
    results += [{"scenario": "scanning", "seed": 1, "method": "learned 2D&3D", "w3d": stats(0.01, 0.01, 0.5, 0.5)},
                {"scenario": "scanning", "seed": 1, "method": "learned 2D", "w3d": stats(None, None, 0.4, 0.5)},
                {"scenario": "scanning", "seed": 1, "method": "w = 1", "w3d": None}]
    rows = B.weight_ratio_summary(results, ["breathing", "scanning"]).splitlines()[2:]
    assert rows == ["| learned 2D&3D | breathing | 3 | 1.00 (0.50-1.50) | 0.50 (0.50-0.50) |",
                    "| learned 2D&3D | scanning | 1 | 1.00 (1.00-1.00) | 1.00 (1.00-1.00) |",
                    "| learned 2D | scanning | 1 | - | 0.80 (0.80-0.80) |"]


def test_pooled_ratio_counts_every_pixel_once():
    """With pixel counts the summary also gives the ratio over all the scenario's pixels pooled:
    a sequence with many displaced pixels weighs more than one with few."""
    def stats(moving, n_moving, still, n_still):
        return {"moving": moving, "still": still, "n_moving": n_moving, "n_still": n_still,
                "w2d_moving": None, "w2d_still": None, "fraction_moving": n_moving / (n_moving + n_still)}

    a, b = stats(0.02, 300, 0.1, 100), stats(0.06, 100, 0.1, 300)     # ratios 0.2 and 0.6
    pooled = (0.02 * 300 + 0.06 * 100) / 400 / 0.1
    assert B.pooled_ratio([a, b], "moving", "still") == pytest.approx(pooled)     # 0.3, not the mean 0.4
    assert B.pooled_ratio([a, {"moving": 0.1, "still": 0.2}], "moving", "still") is None   # a run without counts
    results = [{"scenario": "breathing", "seed": k, "method": "learned 2D&3D", "w3d": w} for k, w in ((1, a), (2, b))]
    rows = B.weight_ratio_summary(results, ["breathing"]).splitlines()
    assert rows[0] == "| method | scenario | sequences | w3D ratio, median (range); pooled |"
    assert rows[2] == f"| learned 2D&3D | breathing | 2 | 0.40 (0.20-0.60); pooled {pooled:.2f} |"


def test_weight_stats_split_by_rest_shape_and_by_motion_between_frames():
    """The logger's two splits on hand-made frames: displacement from the rest shape (the w3D check's
    check) and motion between the two frames along the flow; a failed frame breaks the chain."""
    import torch
    from types import SimpleNamespace as NS

    H, W = 4, 6
    w3 = torch.full((1, 1, H, W), 0.02)
    w3[..., :3] = 0.01                                   # half the weight on the left half
    w2 = torch.ones(1, 1, H, W)
    zero_flow = torch.zeros(1, 2, H, W)

    def frame(nonrigid):
        return NS(extras={"nonrigid_mm": nonrigid.astype(np.float32)})

    def track(flow=zero_flow, failed=False):
        return NS(failed=failed, flow=flow, w3d=w3, w2d=w2)

    displaced = np.zeros((H, W))
    displaced[:, :3] = 0.6                               # the left half is displaced from rest
    st = B.WeightStats(pair_threshold_mm=0.02)
    st.log_frame(0, frame(np.zeros((H, W))), None, None, None, None, None, None)
    st.log_frame(1, frame(displaced), None, track(), None, None, None, None)     # left half moved 0.6 mm
    st.log_frame(2, frame(displaced), None, track(), None, None, None, None)     # nothing moved
    m = st.means()
    assert abs(m["moving"] / m["still"] - 0.5) < 1e-6                           # 0.01 against 0.02
    assert abs(m["pair_moving"] - 0.01) < 1e-6 and abs(m["pair_still"] - (0.02 * 12 + 0.015 * 24) / 36) < 1e-6
    assert abs(m["fraction_pair_moving"] - 12 / 48) < 1e-9 and m["w2d_pair_moving"] == m["w2d_pair_still"] == 1.0
    # the flow: the tissue at x sits at x + 1 px in the reference; shifted the same way, nothing moved
    shifted = np.zeros((H, W))
    shifted[:, :2] = 0.6
    st = B.WeightStats(pair_threshold_mm=0.02)
    st.log_frame(0, frame(displaced), None, None, None, None, None, None)
    flow = torch.zeros(1, 2, H, W)
    flow[:, 0] = 1.0
    st.log_frame(1, frame(shifted), None, track(flow), None, None, None, None)
    assert st.sums["pair_moving"][1] == 0 and st.sums["pair_still"][1] == H * W
    st = B.WeightStats(pair_threshold_mm=0.02)                                  # without the flow: column 2 "moved"
    st.log_frame(0, frame(displaced), None, None, None, None, None, None)
    st.log_frame(1, frame(shifted), None, track(), None, None, None, None)
    assert st.sums["pair_moving"][1] == H
    # a failed frame: the next is not split by motion (its reference is not known to be the frame before)
    st = B.WeightStats(pair_threshold_mm=0.02)
    st.log_frame(0, frame(np.zeros((H, W))), None, None, None, None, None, None)
    st.log_frame(1, frame(displaced), None, track(failed=True), None, None, None, None)
    st.log_frame(2, frame(displaced), None, track(), None, None, None, None)
    assert st.sums["pair_moving"][1] == st.sums["pair_still"][1] == 0 and st.sums["moving"][1] == 12
    assert "pair_moving" not in B.WeightStats().means()                         # frame2model: no such split


def test_several_looks_give_one_table_each(tmp_path, monkeypatch, capsys):
    """``--appearance default texture=0,highlights=1``: every sequence rendered in both looks (the
    weak one from the same seed, its own folder), each run recorded with its look, and the tables
    once per look under a heading; ``--report`` rebuilds the same."""
    out = tmp_path / "bench"
    monkeypatch.setattr(sys, "argv", ["benchmark_scenarios.py", "--scenarios", "scanning", "--seeds", "5",
                                      "--frames", "8", "--size", "160x128", "--workers", "1", "--methods",
                                      "best constant", "--appearance", "default", "texture=0,highlights=1",
                                      "--out", str(out)])
    B.main()
    results = json.loads((out / "scenarios.json").read_text())
    assert sorted(r["look"] for r in results) == ["default", "texture=0,highlights=1"]
    assert sorted(p.name for p in (out / "data").iterdir()) == [
        "scanning_s5_160x128_8", "scanning_s5_160x128_8_texture0_highlights1"]
    assert sorted(p.name for p in (out / "runs").iterdir()) == [
        "scanning_s5_best_constant", "scanning_s5_texture0_highlights1_best_constant"]
    md = (out / "scenarios.md").read_text()
    assert md.startswith("### Look: default\n") and "\n### Look: texture=0,highlights=1\n" in md
    for look, section in zip(("default", "texture=0,highlights=1"), md.split("### Look: ")[1:]):
        ate = next(r["ate_rmse_mm"] for r in results if r["look"] == look)
        row = next(line for line in section.splitlines() if line.startswith("| best constant |"))
        assert row.split("|")[2].strip() == f"{ate:.2f} ± 0.00", (look, row)
    assert "### Look: texture=0,highlights=1" in capsys.readouterr().out
    monkeypatch.setattr(sys, "argv", ["benchmark_scenarios.py", "--report", str(out)])
    B.main()
    assert (out / "scenarios.md").read_text() == md
