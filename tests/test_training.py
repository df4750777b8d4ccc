"""`slam train` (single process): a tiny end-to-end training writes a usable, reproducible checkpoint."""
import numpy as np
import pytest
import torch
import yaml

from slam.app.cli import main
from vo.weights import (DEPTH_CHANGE_REL, IN_CHANNELS, INPUT_VERSION, WeightInputs, WeightNetworks,
                        load_weight_networks, network_inputs)

TINY = {
    "residuals": "2d3d",
    "data": {"scenarios": ["rigid", "breathing"], "seeds": [5000], "frames": 12, "width": 96, "height": 80,
             "pairs_per_sequence": 8, "pixels_per_pair": 512, "workers": 1},
    "optim": {"epochs": 2, "batch_size": 4, "patience": 2, "seed": 3, "threads": 1},
}


def train_once(tmp_path, name):
    cfg = dict(TINY)
    cfg["data"] = {**TINY["data"], "cache_dir": str(tmp_path / "cache")}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / name
    assert main(["train", "--config", str(path), "--out", str(out)]) == 0
    return out / "weights_2d3d.pt"


def test_training_writes_a_reproducible_usable_checkpoint(tmp_path):
    ckpt = train_once(tmp_path, "a")
    data = torch.load(ckpt, weights_only=False)
    meta = data["meta"]
    assert meta["residuals"] == "2d3d" and meta["image_size"] == [96, 80] and meta["max_depth_mm"] > 0
    assert meta["correspondence"]["backend"] == "dis" and meta["finished"] is True
    assert meta["data"]["pairs_train"] + meta["data"]["pairs_val"] == 16
    assert len(meta["data"]["sequences"]) == 2 and meta["val_loss"] > 0
    assert meta["history"][0]["epoch"] == 0 and len(meta["history"]) >= 2
    nets, loaded_meta = load_weight_networks(ckpt, "2d3d")
    assert loaded_meta["val_loss"] == meta["val_loss"]
    assert meta["inputs"] == INPUT_VERSION and nets.inputs == INPUT_VERSION
    # same seed, same data (the pair cache is reused): the same weights
    again = torch.load(train_once(tmp_path, "b"), weights_only=False)
    for k, v in data["state_dict"].items():
        assert torch.equal(v, again["state_dict"][k]), k


def test_training_with_the_first_input_layout(tmp_path):
    """`inputs: 1` trains (and records) the version-1 layout the shipped 3D checkpoint has."""
    cfg = {**TINY, "inputs": 1, "optim": {**TINY["optim"], "epochs": 1},
           "data": {**TINY["data"], "scenarios": ["rigid"], "cache_dir": str(tmp_path / "cache")}}
    path = tmp_path / "v1.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["train", "--config", str(path), "--out", str(tmp_path / "v1")]) == 0
    nets, meta = load_weight_networks(tmp_path / "v1" / "weights_2d3d.pt", "2d3d")
    assert meta["inputs"] == 1 and nets.inputs == 1
    assert nets.net3d.enc1[0].in_channels == IN_CHANNELS[1][1]


def test_validation_holds_out_whole_sequences(tmp_path):
    """`optim.split: sequence` (the default) validates on sequences no training pair comes from,
    one per scenario here; with one sequence per scenario it falls back to a split of the pairs."""
    from slam.training.trainer import load_train_config, sequence_name, training_data

    cfg_dict = {**TINY, "optim": {**TINY["optim"], "val_fraction": 0.5},
                "data": {**TINY["data"], "seeds": [5000, 5001], "pairs_per_sequence": 4,
                         "cache_dir": str(tmp_path / "cache")}}
    path = tmp_path / "split.yaml"
    path.write_text(yaml.safe_dump(cfg_dict))
    cfg = load_train_config(path)
    assert cfg.optim.split == "sequence"
    sequences, train_set, val = training_data(cfg, progress=False)
    seq_of = lambda samples: {sequence_name(s) for s in samples}
    assert len(sequences) == 4 and seq_of(train_set).isdisjoint(seq_of(val))
    assert len(seq_of(val)) == 2 and {n.split("_s")[0] for n in seq_of(val)} == {"rigid", "breathing"}
    assert len(train_set) + len(val) == 16
    # by pair: the same pairs, validation drawn across all four sequences
    _, train_p, val_p = training_data(load_train_config(path, ["optim.split=pair"]), progress=False)
    assert len(train_p) + len(val_p) == 16 and len(val_p) == 8
    assert not seq_of(train_p).isdisjoint(seq_of(val_p))
    # one sequence per scenario: nothing to hold out whole, the pairs are split
    _, train_1, val_1 = training_data(load_train_config(path, ["data.seeds=[5000]"]), progress=False)
    assert len(val_1) == 4 and seq_of(train_1) & seq_of(val_1)


def test_bad_training_config(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text("optim:\n  epoch: 3\n")
    assert main(["train", "--config", str(path)]) == 2
    assert "unknown key 'optim.epoch'" in capsys.readouterr().err
    path.write_text("inputs: 7\n")
    assert main(["train", "--config", str(path)]) == 2
    assert "'inputs' must be one of 1, 2 (weight-network input versions)" in capsys.readouterr().err
    path.write_text("optim:\n  split: random\n")
    assert main(["train", "--config", str(path)]) == 2
    assert "'optim.split' must be one of sequence, pair" in capsys.readouterr().err
    path.write_text("data:\n  reference: rendered\n")
    assert main(["train", "--config", str(path)]) == 2
    assert f"{path}: 'data.reference' must be one of frame, model" in capsys.readouterr().err
    path.write_text("map:\n  unstable_window: 0\n")
    assert main(["train", "--config", str(path)]) == 2
    assert "map: map.unstable_window must be >= 1" in capsys.readouterr().err
    path.write_text("data:\n  appearance: texture=2\n")
    assert main(["train", "--config", str(path)]) == 2
    assert f"{path}: data.appearance: synthetic appearance: texture 2.0 is outside 0.0..1.0" in capsys.readouterr().err
    path.write_text("optim:\n  init: nowhere.pt\n")
    assert main(["train", "--config", str(path)]) == 2
    assert f"{path}: optim.init checkpoint nowhere.pt not found" in capsys.readouterr().err


def _inputs(depth_ratio: float = 1.0) -> WeightInputs:
    g = torch.Generator().manual_seed(0)
    H, W = 64, 80
    depth = 0.2 + 0.1 * torch.rand(1, 1, H, W, generator=g)
    return WeightInputs(torch.rand(1, 3, H, W, generator=g), depth, torch.zeros(1, 2, H, W), torch.zeros(1, 2, H, W),
                        torch.rand(1, 3, H, W, generator=g), depth / depth_ratio, torch.zeros(1, 2, H, W),
                        torch.ones(1, 1, H, W, dtype=torch.bool))


def test_network_inputs_layouts_and_depth_change():
    for version, (c2, c3) in IN_CHANNELS.items():
        inp = _inputs()
        x2, x3 = network_inputs(inp, 8, version)
        assert x2.shape == (1, c2, 8, 10) and x3.shape == (1, c3, 8, 10)
        assert torch.equal(x2, x3[:, :c2])
    # the same depth in both views: no change; the current view 1 % farther: asinh(0.01 / scale)
    assert network_inputs(_inputs(), 8)[1][0, -1].abs().max() < 1e-3  # float32 round-off of the warp
    change = network_inputs(_inputs(1.0 / 0.99), 8)[1][0, -1]
    expected = torch.asinh(torch.tensor(0.01 / DEPTH_CHANGE_REL))
    assert torch.allclose(change[1:-1, 1:-1], expected.expand_as(change[1:-1, 1:-1]), rtol=1e-3)


def test_checkpoint_of_the_previous_input_layout_still_loads(tmp_path):
    old = WeightNetworks(inputs=1)
    path = tmp_path / "old.pt"
    torch.save({"state_dict": old.state_dict(), "meta": {"residuals": "2d3d", "downscale": 8, "base": 16}}, path)
    nets, _ = load_weight_networks(path, "2d3d")
    assert nets.inputs == 1
    w2, w3 = nets(_inputs())
    assert w2.shape == w3.shape == (1, 1, 64, 80)


def _rigid_pairs_config(tmp_path, frames: int, pairs: int):
    """A rigid synthetic sequence of ``frames`` frames and a tiny training config drawing ``pairs`` pairs."""
    from slam.synth import generate

    data = generate(tmp_path / "rigid", "rigid", frames=frames, size=(96, 80), seed=5001)
    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump({**TINY, "data": {**TINY["data"], "cache_dir": str(tmp_path / "cache"),
                                                     "pairs_per_sequence": pairs}}))
    return data, path


def _residuals_at_true_pose_mm(samples: list[dict], max_depth_mm: float) -> torch.Tensor:
    """Per sample, the median 3D residual (mm) of its valid pixels at the ground-truth pose."""
    from vo.lie import se3_exp

    res = []
    for s in samples:
        T = se3_exp(s["p_gt"][None].double())[0].float()
        moved = T[:3, :3] @ s["points_cur"] + T[:3, 3:]
        res.append((moved - s["points_ref"])[:, s["valid3"]].norm(dim=0).median() * max_depth_mm)
    return torch.stack(res)


def test_pair_samples_with_the_generators_depth(tmp_path):
    """``analysis.depth_source=groundtruth``: the pair samples' points are the exact depth back-projected, so
    at the true pose the 3D residual of a rigid scene is what the flow leaves (the stereo adds most of it)."""
    from slam.training.trainer import build_pair_samples, load_train_config

    data, path = _rigid_pairs_config(tmp_path, frames=6, pairs=4)
    errors = {}
    for source in ("stereo", "groundtruth"):
        cfg = load_train_config(path, [f"analysis.depth_source={source}"])
        samples = build_pair_samples(data, cfg)
        assert samples
        errors[source] = float(_residuals_at_true_pose_mm(samples, cfg.depth.max_depth_mm).median())
        # the cache file is renamed into place (no half-written file for a second training to read)
        again = build_pair_samples(data, cfg)
        assert len(again) == len(samples) and torch.equal(again[0]["points_ref"], samples[0]["points_ref"])
    assert len(list((tmp_path / "cache" / "pairs").glob("*.pt"))) == 2
    assert not list((tmp_path / "cache").rglob("*.tmp"))
    assert errors["groundtruth"] < 0.1                           # mm: exact depth; what is left is the flow
    assert errors["stereo"] > 3 * errors["groundtruth"]            # 0.40 against 0.04 mm when written


def test_pair_samples_against_model_views(tmp_path):
    """``data.reference: model``: the reference is the surfel map fused at the ground-truth poses and
    rendered at the reference frame's pose (what frame2model tracks against): with exact depth the true
    pose still aligns the current points with the rendered ones, which are not the frame's own."""
    from slam.training.trainer import build_pair_samples, load_train_config

    data, path = _rigid_pairs_config(tmp_path, frames=10, pairs=6)
    per_reference = {}
    for reference in ("frame", "model"):
        cfg = load_train_config(path, ["analysis.depth_source=groundtruth", f"data.reference={reference}"])
        samples = build_pair_samples(data, cfg)
        assert len(samples) == 6
        assert float(_residuals_at_true_pose_mm(samples, cfg.depth.max_depth_mm).max()) < 0.2   # (0.13 when written)
        per_reference[reference] = samples
        again = build_pair_samples(data, cfg)             # cached under its own key
        assert torch.equal(again[0]["points_ref"], samples[0]["points_ref"])
    assert len(list((tmp_path / "cache" / "pairs").glob("*.pt"))) == 2
    frame, model = per_reference["frame"], per_reference["model"]
    assert [s["source"] for s in frame] == [s["source"] for s in model]   # the same pairs
    differs = [float((f["points_ref"] - m["points_ref"]).abs().max()) for f, m in zip(frame, model)]
    assert min(differs) > 0          # the rendered depth is the map's, not the frame's
    assert not torch.equal(frame[0]["x3"], model[0]["x3"])


def test_validation_loss_tool_reproduces_the_checkpoints_validation_loss(tmp_path, capsys):
    """benchmarks/validation_loss.py scores a checkpoint on the pairs `slam train` held out with the same
    config: the checkpoint's own best validation loss and its w = 1 reference come out again."""
    import json

    from benchmarks import validation_loss

    ckpt = train_once(tmp_path, "a")
    meta = torch.load(ckpt, weights_only=False)["meta"]
    config = tmp_path / "a.yaml"
    assert validation_loss.main(["--config", str(config), "--checkpoints", str(ckpt), "--out", str(tmp_path / "v")]) == 0
    data = json.loads((tmp_path / "v" / "validation_loss.json").read_text())
    assert data["pairs"] == meta["data"]["pairs_val"]
    assert abs(data["loss"][str(ckpt)]["all"] - meta["val_loss"]) < 1e-9
    assert abs(data["loss"]["w = 1"]["all"] - meta["val_loss_constant_w1"]) < 1e-9
    assert set(data["loss"]["w = 1"]) == {"all", "rigid", "breathing"}     # one held-out sequence each
    assert "| w = 1 |" in capsys.readouterr().out
    assert validation_loss.main(["--config", str(config), "--checkpoints", str(tmp_path / "none.pt")]) == 2
    assert "none.pt: checkpoint not found" in capsys.readouterr().err


def test_fine_tuning_starts_from_the_named_checkpoint(tmp_path, capsys):
    """`optim.init`: training starts from a checkpoint's weights (its validation loss is the new
    run's epoch-0 loss on the same pairs); a checkpoint of another layout is a one-line error."""
    first = train_once(tmp_path, "a")
    meta = torch.load(first, weights_only=False)["meta"]
    cfg = {**TINY, "optim": {**TINY["optim"], "epochs": 1, "init": str(first)},
           "data": {**TINY["data"], "cache_dir": str(tmp_path / "cache")}}
    path = tmp_path / "ft.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["train", "--config", str(path), "--out", str(tmp_path / "ft")]) == 0
    tuned = torch.load(tmp_path / "ft" / "weights_2d3d.pt", weights_only=False)["meta"]
    assert abs(tuned["history"][0]["val"] - meta["val_loss"]) < 1e-9
    assert tuned["train_config"]["optim"]["init"] == str(first)
    capsys.readouterr()
    assert main(["train", "--config", str(path), "--out", str(tmp_path / "ft2"), "--set", "residuals=2d"]) == 2
    err = capsys.readouterr().err.strip().splitlines()     # (before any pair is computed)
    assert len(err) == 1 and f"{first}: optim.init checkpoint has another layout: residuals 2d3d (config: 2d)" in err[0]


def test_chain_loss_on_consecutive_pairs(tmp_path):
    """``data.chain_length``: chains of consecutive pairs (fixed for validation, drawn afresh each
    epoch for training, never across a missing pair); the loss of eq. 7 on their composed pose
    (zero at the truth, the per-pair loss for one link, gradients to every link); a tiny training
    runs on chains and its validation loss is the chain loss."""
    import random

    from slam.training.trainer import chain_pose_loss, chain_runs, chains_of, draw_chains, evaluate_loss, load_train_config
    from vo.lie import se3_exp, se3_log

    # consecutive pairs of two sequences; pair 5 -> 6 of "a" is missing (too few valid pixels)
    samples = [{"seq": "a", "link": i} for i in range(20) if i != 5] + [{"seq": "b", "link": i} for i in range(9)]
    runs = chain_runs(samples)
    assert [[samples[k]["link"] for k in r] for r in runs] == [list(range(5)), list(range(6, 20)), list(range(9))]
    fixed = chains_of(samples, 4)
    assert [[samples[k]["link"] for k in c] for c in fixed] == [
        [0, 1, 2, 3], [6, 7, 8, 9], [10, 11, 12, 13], [14, 15, 16, 17], [0, 1, 2, 3], [4, 5, 6, 7]]
    draws = [draw_chains(samples, 4, 3, random.Random(f"0:chains:{e}")) for e in (1, 2)]
    for chains in draws:
        assert len(chains) == 6 and all(len(c) == 4 for c in chains)
        for c in chains:    # consecutive links of one sequence, never across the gap
            links = [samples[k]["link"] for k in c]
            assert links == list(range(links[0], links[0] + 4)) and len({samples[k]["seq"] for k in c}) == 1
            assert not (links[0] <= 5 <= links[-1] and samples[c[0]]["seq"] == "a")
    assert draws[0] != draws[1] and draws[0] == draw_chains(samples, 4, 3, random.Random("0:chains:1"))

    g = torch.Generator().manual_seed(1)
    p_gt = 0.01 * torch.randn(6, 6, generator=g, dtype=torch.float64)
    ok = torch.ones(6, dtype=torch.bool)
    loss, ok_chain = chain_pose_loss(p_gt.clone(), p_gt, ok, 3)
    assert loss.shape == (2,) and float(loss.abs().max()) < 1e-12 and bool(ok_chain.all())
    p = (p_gt + 0.001 * torch.randn(6, 6, generator=g, dtype=torch.float64)).requires_grad_(True)
    single, _ = chain_pose_loss(p, p_gt, ok, 1)
    assert torch.allclose(single, (p - p_gt).abs().sum(1))
    loss, _ = chain_pose_loss(p, p_gt, ok, 3)
    T = se3_exp(p.detach()).view(2, 3, 4, 4)
    T_gt = se3_exp(p_gt).view(2, 3, 4, 4)
    expected = (se3_log(T[:, 0] @ T[:, 1] @ T[:, 2]) - se3_log(T_gt[:, 0] @ T_gt[:, 1] @ T_gt[:, 2])).abs().sum(1)
    assert torch.allclose(loss.detach(), expected, atol=1e-10)
    loss.sum().backward()
    assert bool((p.grad.abs().sum(1) > 0).all())
    ok[4] = False                                                  # a failed link fails its chain only
    _, ok_chain = chain_pose_loss(p.detach(), p_gt, ok, 3)
    assert ok_chain.tolist() == [True, False]

    tiny = {**TINY, "data": {**TINY["data"], "chain_length": 3, "pairs_per_sequence": 9, "cache_dir": str(tmp_path / "cache")},
            "optim": {**TINY["optim"], "epochs": 1, "batch_size": 6}}
    path = tmp_path / "chain.yaml"
    path.write_text(yaml.safe_dump(tiny))
    assert main(["train", "--config", str(path), "--out", str(tmp_path / "chain")]) == 0
    ckpt = torch.load(tmp_path / "chain" / "weights_2d3d.pt", weights_only=False)["meta"]
    assert ckpt["train_config"]["data"]["chain_length"] == 3 and ckpt["val_loss"] > 0
    from slam.training.trainer import training_data
    tcfg = load_train_config(path)
    _, train_set, val = training_data(tcfg, progress=False)
    assert all("seq" in s for s in train_set) and len(train_set) + len(val) <= 2 * 11   # every consecutive pair
    assert len(chains_of(val, 3)) * 3 == len(val) > 0               # validation holds whole chains
    nets, _ = load_weight_networks(tmp_path / "chain" / "weights_2d3d.pt", "2d3d")
    assert abs(evaluate_loss(nets, val, tcfg)[0] - ckpt["val_loss"]) < 1e-6


def test_training_sequences_with_random_looks(tmp_path):
    """data.appearance=random: one look per scenario and seed, drawn as slam synth --appearance
    random draws it from appearance_seed, in folders of their own beside the default look's;
    rendered by two worker processes (the batch engine) as by this one."""
    import json

    from slam.synth.appearance import random_appearance
    from slam.training.trainer import appearance_seed, load_train_config, training_sequences

    cfg = dict(TINY)
    cfg["data"] = {**TINY["data"], "frames": 3, "cache_dir": str(tmp_path / "cache"), "workers": 2}
    path = tmp_path / "looks.yaml"
    path.write_text(yaml.safe_dump(cfg))
    paths = training_sequences(load_train_config(path, ["data.appearance=random"]), progress=False)
    assert [p.name for p in paths] == ["rigid_s5000_96x80_n3_random", "breathing_s5000_96x80_n3_random"]
    looks = [json.loads((p / "synth.json").read_text())["appearance"] for p in paths]
    assert looks[0] != looks[1]
    for scenario, look in zip(["rigid", "breathing"], looks):
        assert look == random_appearance(appearance_seed(scenario, 5000)).as_dict()
    plain = training_sequences(load_train_config(path), progress=False)
    assert [p.name for p in plain] == ["rigid_s5000_96x80_n3", "breathing_s5000_96x80_n3"]
    assert json.loads((plain[0] / "synth.json").read_text())["appearance"]["texture"] == 1.0
    alone = training_sequences(load_train_config(path, ["data.workers=1", f"data.cache_dir={tmp_path / 'alone'}"]),
                               progress=False)
    for a, b in zip(alone, plain):
        assert (a / "groundtruth.txt").read_text() == (b / "groundtruth.txt").read_text()
        assert (a / "video_frames" / "000002r.png").read_bytes() == (b / "video_frames" / "000002r.png").read_bytes()
