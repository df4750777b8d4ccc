"""RAFT architecture (vo.raft) and the raft correspondence backend (vo.correspondence.raft_backend)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from vo.correspondence.raft_backend import (
    MISSING_CHECKPOINT_MESSAGE,
    CheckpointMismatchError,
    InputPadder,
    MissingCheckpointError,
    RaftFlow,
)
from vo.raft import RAFT, CorrBlock, convex_upsample

FIXTURES = Path(__file__).parent / "fixtures"


@pytest.fixture(autouse=True)
def _few_threads():
    previous = torch.get_num_threads()
    torch.set_num_threads(min(2, previous))
    yield
    torch.set_num_threads(previous)


# 1. state-dict layout of the published checkpoints ------------------------------------------------


@pytest.mark.parametrize(
    "small, fixture, count",
    [(False, "raft_things_state_dict.json", 179), (True, "raft_small_state_dict.json", 106)],
)
def test_state_dict_matches_published_checkpoint(small, fixture, count):
    expected = json.loads((FIXTURES / fixture).read_text())
    assert len(expected) == count
    got = {name: list(t.shape) for name, t in RAFT(small=small).state_dict().items()}
    missing = sorted(set(expected) - set(got))
    extra = sorted(set(got) - set(expected))
    assert not missing, f"missing: {missing[:10]}"
    assert not extra, f"extra: {extra[:10]}"
    wrong = {k: (got[k], expected[k]) for k in expected if got[k] != expected[k]}
    assert not wrong, f"shape mismatches: {wrong}"


# 2. correlation pyramid and lookup ----------------------------------------------------------------


def _brute_force_pyramid(f1: torch.Tensor, f2: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """Level k as (B, H, W, Hk, Wk): explicit dot products, then 2^k x 2^k block means over image 2."""
    b, d, h, w = f1.shape
    corr = torch.zeros(b, h, w, h, w, dtype=torch.float64)
    for i in range(h):
        for j in range(w):
            corr[:, i, j] = torch.einsum("bc,bckl->bkl", f1[:, :, i, j].double(), f2.double())
    corr /= math.sqrt(d)
    out = []
    for k in range(levels):
        s = 2**k
        hk, wk = h // s, w // s
        blocks = corr[..., : hk * s, : wk * s].reshape(b, h, w, hk, s, wk, s)
        out.append(blocks.mean(dim=(4, 6)))
    return out


def test_correlation_pyramid_matches_brute_force():
    torch.manual_seed(0)
    b, d, h, w = 2, 16, 8, 12  # coarsest level is 1 x 1
    f1, f2 = torch.randn(b, d, h, w), torch.randn(b, d, h, w)
    block = CorrBlock(f1, f2, num_levels=4, radius=3)
    reference = _brute_force_pyramid(f1, f2, 4)
    for k, (ours, ref) in enumerate(zip(block.corr_pyramid, reference)):
        assert ours.shape == (b * h * w, 1, h // 2**k, w // 2**k)
        torch.testing.assert_close(ours.view(ref.shape).double(), ref, rtol=1e-5, atol=1e-5, msg=f"level {k}")


@pytest.mark.parametrize("radius", [3, 4])
def test_lookup_at_integer_offsets_indexes_the_volume(radius):
    torch.manual_seed(1)
    b, d, h, w, levels = 1, 8, 8, 12, 4
    f1, f2 = torch.randn(b, d, h, w), torch.randn(b, d, h, w)
    block = CorrBlock(f1, f2, num_levels=levels, radius=radius)
    reference = _brute_force_pyramid(f1, f2, levels)
    win = 2 * radius + 1
    for k in range(levels):
        s, hk, wk = 2**k, h // 2**k, w // 2**k
        # integer centres at level k, some of them partly or wholly outside the map
        cx = torch.randint(-2, wk + 2, (b, h, w)).float()
        cy = torch.randint(-2, hk + 2, (b, h, w)).float()
        out = block(torch.stack([cx, cy], dim=1) * s)
        assert out.shape == (b, levels * win * win, h, w)
        ref = reference[k]
        for i in range(h):
            for j in range(w):
                x0, y0 = int(cx[0, i, j]), int(cy[0, i, j])
                for dx in range(-radius, radius + 1):
                    for dy in range(-radius, radius + 1):
                        x, y = x0 + dx, y0 + dy
                        want = float(ref[0, i, j, y, x]) if 0 <= x < wk and 0 <= y < hk else 0.0
                        c = k * win * win + (dx + radius) * win + (dy + radius)  # x-major window
                        assert abs(float(out[0, c, i, j]) - want) < 1e-4, (k, i, j, dx, dy)


def test_lookup_is_bilinear_between_pixels():
    torch.manual_seed(2)
    b, d, h, w, r = 1, 8, 8, 8, 2
    f1, f2 = torch.randn(b, d, h, w), torch.randn(b, d, h, w)
    block = CorrBlock(f1, f2, num_levels=1, radius=r)
    vol = _brute_force_pyramid(f1, f2, 1)[0][0]  # (H, W, H, W)
    coords = torch.rand(b, 2, h, w) * torch.tensor([w - 1.0, h - 1.0]).view(1, 2, 1, 1)
    out = block(coords)

    def at(i, j, y, x):
        return float(vol[i, j, y, x]) if 0 <= x < w and 0 <= y < h else 0.0

    win = 2 * r + 1
    for i in range(h):
        for j in range(w):
            x, y = float(coords[0, 0, i, j]), float(coords[0, 1, i, j])
            for dx in range(-r, r + 1):
                for dy in range(-r, r + 1):
                    px, py = x + dx, y + dy
                    x0, y0 = math.floor(px), math.floor(py)
                    ax, ay = px - x0, py - y0
                    want = ((1 - ax) * (1 - ay) * at(i, j, y0, x0) + ax * (1 - ay) * at(i, j, y0, x0 + 1)
                            + (1 - ax) * ay * at(i, j, y0 + 1, x0) + ax * ay * at(i, j, y0 + 1, x0 + 1))
                    got = float(out[0, (dx + r) * win + (dy + r), i, j])
                    assert abs(got - want) < 1e-4


# 3. forward pass ----------------------------------------------------------------------------------


@pytest.mark.parametrize("small", [False, True])
def test_forward_shapes_and_finite(small):
    torch.manual_seed(3)
    model = RAFT(small=small).eval()
    im1, im2 = torch.rand(1, 3, 64, 96) * 255, torch.rand(1, 3, 64, 96) * 255
    with torch.no_grad():
        preds = model(im1, im2, iters=2)
        assert len(preds) == 2
        for p in preds:
            assert p.shape == (1, 2, 64, 96) and torch.isfinite(p).all()
        low, up = model(im1, im2, iters=2, test_mode=True)
        assert low.shape == (1, 2, 8, 12) and up.shape == (1, 2, 64, 96)
        assert torch.isfinite(low).all() and torch.isfinite(up).all()
        torch.testing.assert_close(up, preds[-1])  # test mode returns the last full-resolution estimate
        low_init, _ = model(im1, im2, iters=1, flow_init=torch.ones(1, 2, 8, 12), test_mode=True)
        assert torch.isfinite(low_init).all()
    with pytest.raises(ValueError, match="multiple of 8"):
        model(im1[..., :60], im2[..., :60], iters=1)


def test_convex_upsample_of_constant_flow():
    flow = torch.tensor([1.5, -0.5]).view(1, 2, 1, 1).expand(1, 2, 4, 5).contiguous()
    up = convex_upsample(flow, torch.randn(1, 9 * 64, 4, 5))
    assert up.shape == (1, 2, 32, 40)
    # away from the border every 3x3 neighbour has the same flow, so any convex weights give 8 * flow
    torch.testing.assert_close(up[..., 8:24, 8:32], 8 * flow[..., :1, :1].expand(1, 2, 16, 24))


# 4. the backend -----------------------------------------------------------------------------------


def _save_random_checkpoint(path: Path, small: bool, wrap: str | None = None) -> dict[str, torch.Tensor]:
    torch.manual_seed(4)
    state = {f"module.{k}": v.clone() for k, v in RAFT(small=small).state_dict().items()}
    torch.save({wrap: state} if wrap else state, path)
    return state


def test_backend_loads_dataparallel_checkpoint_and_runs(tmp_path):
    ckpt = tmp_path / "raft-small.pth"
    state = _save_random_checkpoint(ckpt, small=True)
    est = RaftFlow(ckpt, small=True, iters=2)
    assert est.name == "raft" and not est.model.training
    for k, v in est.model.state_dict().items():
        assert torch.equal(v, state[f"module.{k}"])
    im1, im2 = torch.rand(1, 3, 50, 70), torch.rand(1, 3, 50, 70)  # padded to 56 x 72 inside
    flow = est.flow(im1, im2)
    assert flow.shape == (1, 2, 50, 70) and flow.dtype == torch.float32 and torch.isfinite(flow).all()
    assert RaftFlow(ckpt, iters=2).small            # the variant is read off the checkpoint


@pytest.mark.parametrize("wrap", ["state_dict", "model"])
def test_backend_loads_wrapped_full_checkpoint(tmp_path, wrap):
    ckpt = tmp_path / "raft-things.pth"
    _save_random_checkpoint(ckpt, small=False, wrap=wrap)
    est = RaftFlow(str(ckpt), iters=1)
    assert not est.small
    flow = est.flow(torch.rand(1, 3, 40, 48), torch.rand(1, 3, 40, 48))
    assert flow.shape == (1, 2, 40, 48) and torch.isfinite(flow).all()


def test_backend_missing_checkpoint_errors(tmp_path):
    with pytest.raises(MissingCheckpointError) as info:
        RaftFlow(None)
    assert str(info.value) == MISSING_CHECKPOINT_MESSAGE
    assert isinstance(info.value, ValueError)
    missing = tmp_path / "nope" / "raft-things.pth"
    with pytest.raises(FileNotFoundError, match="raft-things.pth"):
        RaftFlow(missing)


def test_backend_wrong_key_and_wrong_variant_errors(tmp_path):
    ckpt = tmp_path / "bad.pth"
    state = {k: v for k, v in RAFT(small=True).state_dict().items()}
    state["update_block.gru.convz_typo.weight"] = state.pop("update_block.gru.convz.weight")
    torch.save(state, ckpt)
    with pytest.raises(CheckpointMismatchError) as info:
        RaftFlow(ckpt, small=True)
    msg = str(info.value)
    assert "missing: update_block.gru.convz.weight" in msg
    assert "unexpected: update_block.gru.convz_typo.weight" in msg

    small_ckpt = tmp_path / "raft-small.pth"
    _save_random_checkpoint(small_ckpt, small=True)
    with pytest.raises(CheckpointMismatchError, match="use small=True"):
        RaftFlow(small_ckpt, small=False)


def test_input_padder_replicates_and_unpads():
    x = torch.arange(2 * 3 * 5 * 7, dtype=torch.float32).view(2, 3, 5, 7)
    padder = InputPadder(5, 7)
    (p,) = padder.pad_images(x)
    assert p.shape == (2, 3, 8, 8)
    assert torch.equal(padder.unpad(p), x)
    left = padder.pad[0]
    assert torch.equal(p[..., 0, left:left + 7], x[..., 0, :])  # replicated first row


def test_pyramid_of_tiny_maps_keeps_size_one_dims():
    torch.manual_seed(5)
    block = CorrBlock(torch.randn(1, 4, 3, 5), torch.randn(1, 4, 3, 5), num_levels=4, radius=2)
    assert [tuple(c.shape[-2:]) for c in block.corr_pyramid] == [(3, 5), (1, 2), (1, 1), (1, 1)]
    out = block(torch.rand(1, 2, 3, 5) * 4)
    assert out.shape == (1, 4 * 25, 3, 5) and torch.isfinite(out).all()


def test_backend_starts_from_a_given_flow_on_its_eighth_grid(tmp_path):
    """A start ``(B, 2, H, W)`` in pixels reaches RAFT as ``flow_init`` on the padded 1/8 grid in
    that grid's pixels (a constant 16 px start: 2 px there), and changes the estimate."""
    ckpt = tmp_path / "raft-small.pth"
    _save_random_checkpoint(ckpt, small=True)
    est = RaftFlow(ckpt, small=True, iters=1)
    seen = {}
    forward = est.model.forward

    def spy(*args, **kwargs):
        seen["flow_init"] = kwargs.get("flow_init")
        return forward(*args, **kwargs)

    est.model.forward = spy
    im1, im2 = torch.rand(1, 3, 50, 70), torch.rand(1, 3, 50, 70)      # padded to 56 x 72 inside
    start = torch.zeros(1, 2, 50, 70)
    start[:, 0] = 16.0
    started = est.flow(im1, im2, start)
    assert seen["flow_init"].shape == (1, 2, 7, 9)
    assert torch.allclose(seen["flow_init"][:, 0], torch.full((1, 7, 9), 2.0))
    assert torch.allclose(seen["flow_init"][:, 1], torch.zeros(1, 7, 9))
    scratch = est.flow(im1, im2)
    assert seen["flow_init"] is None
    assert (started[:, 0] - scratch[:, 0]).mean() > 8.0
