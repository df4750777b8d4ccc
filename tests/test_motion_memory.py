"""Layout-5 weight-network input: the motion memory (the 3D residual at the solved poses averaged
along the flow over about a second)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from vo.motion_memory import MEMORY_RATE, memory_features, relative_residual, update_memory


def test_residual_is_the_rigid_misfit_over_the_depth():
    """Points moved by a known vector: at the identity the residual is that vector over the depth;
    at the pose that explains the motion it is zero; invalid pixels give 0."""
    H, W = 4, 5
    z = torch.linspace(50, 80, H * W).view(1, 1, H, W)
    cur = torch.cat([torch.randn(1, 2, H, W, generator=torch.Generator().manual_seed(0)) * 5, z], 1)
    shift = torch.tensor([0.3, -0.2, 0.5]).view(1, 3, 1, 1)
    ref = cur - shift
    valid = torch.ones(1, 1, H, W, dtype=torch.bool)
    valid[..., 1, 2] = False
    r = relative_residual(cur, ref, torch.eye(4)[None], valid)
    expected = (shift / z).expand(1, 3, H, W)
    assert torch.allclose(r[..., valid[0, 0]], expected[..., valid[0, 0]], atol=1e-7)
    assert float(r[..., 1, 2].abs().sum()) == 0.0
    T = torch.eye(4)[None]
    T[0, :3, 3] = -shift.view(3)
    assert float(relative_residual(cur, ref, T, valid).abs().max()) < 1e-6


def test_memory_is_an_average_carried_along_the_flow():
    """A constant residual: the mean converges to it while the weight grows as 1 - (1 - rate)^n; with
    a flow of one column to the right, the memory moves one column to the left per frame; a pixel
    without a residual keeps the carried memory, decayed."""
    H, W = 3, 12
    res = torch.zeros(1, 3, H, W)
    res[:, 2, :, 9] = 2e-3                      # one column of tissue moving along the optical axis
    valid = torch.ones(1, 1, H, W, dtype=torch.bool)
    still = torch.zeros(1, 2, H, W)
    mem = None
    for n in range(1, 6):
        mem = update_memory(mem, still, res, valid)
    w = 1 - (1 - MEMORY_RATE) ** 5
    assert torch.allclose(mem[:, 3], torch.full((1, H, W), w), atol=1e-6)
    assert torch.allclose(mem[:, 2, :, 9] / mem[:, 3, :, 9], torch.full((1, H), 2e-3), rtol=1e-5)
    flow = torch.zeros(1, 2, H, W)
    flow[:, 0] = 1.0                            # current pixel x shows the reference's x + 1
    none = torch.zeros(1, 1, H, W, dtype=torch.bool)
    moved = update_memory(mem, flow, torch.zeros_like(res), none)
    assert torch.allclose(moved[:, 2, :, 8], (1 - MEMORY_RATE) * mem[:, 2, :, 9])
    assert float(moved[:, 2, :, 9].abs().max()) == 0.0
    feats = memory_features(moved, torch.zeros(1, 1, H, W))
    assert feats.shape == (1, 2, H, W)
    assert float(feats[0, 0, 0, 8]) == pytest.approx(float(np.arcsinh(2e-3 / 1e-4)), rel=1e-4)
    assert float(memory_features(None, torch.zeros(1, 1, H, W)).abs().sum()) == 0.0
    with pytest.raises(ValueError, match="rate"):
        update_memory(None, flow, res, valid, rate=0.0)


def test_signed_average_lifts_steady_motion_out_of_frame_noise():
    """Per frame, noise twice the motion of a patch; after two seconds the remembered mean
    stands far above the noise there (the noise averages out, the steady motion adds up)."""
    g = torch.Generator().manual_seed(4)
    H, W = 32, 32
    moving = torch.zeros(1, 1, H, W, dtype=torch.bool)
    moving[..., :, :16] = True
    valid = torch.ones(1, 1, H, W, dtype=torch.bool)
    mem = None
    for _ in range(50):
        res = torch.randn(1, 3, H, W, generator=g) * 2e-4 + moving * torch.tensor([0, 0, 1e-4]).view(1, 3, 1, 1)
        single = res.norm(dim=1, keepdim=True)
        mem = update_memory(mem, torch.zeros(1, 2, H, W), res, valid)
    speed = torch.sinh(memory_features(mem, torch.zeros(1, 1, H, W))[:, :1]) * 1e-4
    assert float(single[moving].mean()) / float(single[~moving].mean()) < 1.1     # one frame: no contrast
    assert float(speed[moving].mean()) > 2.0 * float(speed[~moving].mean())


def test_layout_5_inputs_and_networks():
    from vo.weights import IN_CHANNELS, WeightInputs, WeightNetworks, network_inputs, uses_motion_memory

    B, H, W = 2, 32, 40
    g = torch.Generator().manual_seed(1)
    mem = torch.rand(B, 4, H, W, generator=g)
    inp = WeightInputs(image_cur=torch.rand(B, 3, H, W, generator=g), depth_cur=torch.full((B, 1, H, W), 0.5),
                       flow=torch.zeros(B, 2, H, W), parallax_cur=torch.zeros(B, 2, H, W),
                       image_ref=torch.rand(B, 3, H, W, generator=g), depth_ref=torch.full((B, 1, H, W), 0.5),
                       parallax_ref=torch.zeros(B, 2, H, W), valid=torch.ones(B, 1, H, W, dtype=torch.bool),
                       motion_memory_ref=mem)
    x2, x3 = network_inputs(inp, 8, 5)
    assert uses_motion_memory(5) and not uses_motion_memory(2)
    assert (x2.shape[1], x3.shape[1]) == IN_CHANNELS[5] == (15, 22)
    expected = torch.nn.functional.adaptive_avg_pool2d(memory_features(mem, inp.depth_ref), (4, 5))
    assert torch.allclose(x3[:, 13:15], expected, atol=1e-5)
    w2, w3 = WeightNetworks(downscale=8, inputs=5)(inp)
    assert w2.shape == w3.shape == (B, 1, H, W)


def test_training_pairs_remember_where_the_tissue_breathes(tmp_path):
    """The pair cache of layout 5 carries each frame's memory on at the true motion: on breathing
    tissue the remembered residual is larger where the tissue breathes most (the generator's
    non-rigid displacement) than where it hardly moves, and it has no history on the first pair."""
    from slam.synth import generate
    from slam.training import build_pair_samples, load_train_config

    data = generate(tmp_path / "b", "breathing", frames=40, size=(320, 256), seed=5003)
    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump({
        "residuals": "2d3d", "inputs": 5,
        "data": {"scenarios": ["breathing"], "seeds": [5000], "frames": 40, "width": 320, "height": 256,
                 "pairs_per_sequence": 40, "pixels_per_pair": 256, "max_gap": 1, "chain_length": 2,
                 "cache_dir": str(tmp_path / "cache")},
        "optim": {"seed": 3, "threads": 1},
    }))
    cfg = load_train_config(path, ["depth.temporal_gain=0.05"])
    samples = build_pair_samples(data, cfg)
    assert len(samples) == 39 and samples[0]["x3"].shape[0] == 22
    assert float(samples[0]["x3"][14].abs().max()) == 0.0          # frame 0: no history
    import cv2

    peak = None
    for n in range(40):
        nr = cv2.imread(str(data / "nonrigid" / f"{n:06d}l.png"), cv2.IMREAD_UNCHANGED)
        peak = nr if peak is None else np.maximum(peak, nr)
    low = cv2.resize(peak.astype(np.float32), (40, 32), interpolation=cv2.INTER_AREA)
    speed = np.mean([s["x3"][13].float().numpy() for s in samples[25:]], 0)
    breathes, hardly = low > np.quantile(low, 0.7), low < np.quantile(low, 0.3)
    assert speed[breathes].mean() > 1.3 * speed[hardly].mean(), (speed[breathes].mean(), speed[hardly].mean())


def test_tracking_keeps_a_memory_for_layout_5_networks(synth_dir, tmp_path):
    """``slam run`` with a layout-5 checkpoint: every frame tracked, each tracked frame carries a
    memory on, and the run is as accurate as the untrained networks allow (ATE < 0.5 mm)."""
    from slam.cli import main
    from slam.config import load_config
    from slam.datasets import open_dataset
    from slam.pipeline import Pipeline
    from slam.training import load_train_config, save_checkpoint
    from vo.weights import WeightNetworks

    data = synth_dir("breathing", 8, (160, 128))
    cfg_path = tmp_path / "t.yaml"
    cfg_path.write_text(yaml.safe_dump({"residuals": "2d3d", "inputs": 5}))
    tcfg = load_train_config(cfg_path)
    torch.manual_seed(0)
    nets = WeightNetworks(downscale=tcfg.downscale, residuals="2d3d", inputs=5)
    ckpt = tmp_path / "weights_2d3d.pt"
    save_checkpoint(ckpt, tcfg, nets.state_dict(), [], 0, 0, 0, 0.0, 0.0, [], 0.0, True)
    out = tmp_path / "run"
    # the memory was measured on the paper's reference: every frame against the previous one, stereo depth
    paper = ["--config", str(Path(__file__).resolve().parents[1] / "configs" / "paper.yaml")]
    assert main(["run", str(data), "--out", str(out), *paper, "--set", f"weights.checkpoint={ckpt}", "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == 8 and m["failed_frames"] == [] and m["ate_rmse_mm"] < 0.5

    cfg = load_config(paper[1], ["logging.progress=false", f"weights.checkpoint={ckpt}"])
    pipe = Pipeline(cfg, open_dataset(data, cfg.data), tmp_path / "run2")
    odo = pipe.odometry
    assert odo.keeps_motion_memory()
    memories, seen = [], []
    track, weights = odo.track, odo._weights

    def spy_weights(cur, ref, *args, **kwargs):
        seen.append(ref.motion_memory is not None)
        return weights(cur, ref, *args, **kwargs)

    def spy_track(cur, *args, **kwargs):
        result = track(cur, *args, **kwargs)
        memories.append(cur.motion_memory)
        return result

    odo.track, odo._weights = spy_track, spy_weights
    pipe.run(progress=False)
    assert len(memories) == 7 and all(m is not None and m.shape == (1, 4, 128, 160) for m in memories)
    assert seen == [False] + [True] * 6                       # the first frame has no history
