"""`slam train` (single process): a tiny end-to-end training writes a usable, reproducible checkpoint."""
import torch
import yaml

from slam.cli import main
from vo.weights import load_weight_networks

TINY = {
    "residuals": "2d3d",
    "data": {"scenarios": ["rigid", "breathing"], "seeds": [5000], "frames": 12, "width": 96, "height": 80,
             "pairs_per_sequence": 8, "pixels_per_pair": 512},
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
    # same seed, same data (the pair cache is reused): the same weights
    again = torch.load(train_once(tmp_path, "b"), weights_only=False)
    for k, v in data["state_dict"].items():
        assert torch.equal(v, again["state_dict"][k]), k


def test_bad_training_config(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text("optim:\n  epoch: 3\n")
    assert main(["train", "--config", str(path)]) == 2
    assert "unknown key 'optim.epoch'" in capsys.readouterr().err
