"""The surfel map's loop-closure operations: the active/inactive split, moving surfels with
their frames' corrections, and reviving the inactive surfels a corrected view sees."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mapping import SurfelMap
from tests.test_mapping import H, W, intrinsics, pose, ray_cast


@pytest.fixture(autouse=True)
def _one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def _t(T):
    return torch.as_tensor(T, dtype=torch.float32)


def _fused(poses, kernels="torch", start=0):
    from mapping import MapConfig

    K = intrinsics()
    fmap = SurfelMap(MapConfig(kernels=kernels))
    for i, T in enumerate(poses):
        depth, colour, _ = ray_cast(T, K)
        fmap.fuse(depth, colour, K, _t(T), start + i)
    return fmap, K


@pytest.mark.parametrize("kernels", ["torch", "compiled"])
def test_active_and_inactive_renders_split_the_map(kernels):
    """Frames 0-4 at one place, 5-9 at another (no overlap): a render of the surfels last fused before frame 5
    sees only the first place's, one from frame 5 on only the second's; fusion with
    ``active_from`` leaves the inactive surfels untouched."""
    first = [pose([0.0, 0.0, 0.0])] * 5
    second = [pose([120.0, 0.0, 0.0])] * 5
    fmap, K = _fused(first + second, kernels)
    at_first = _t(first[0])
    inactive = fmap.render(K, at_first, H, W, colour=False, seen_before=5)
    active = fmap.render(K, at_first, H, W, colour=False, seen_from=5)
    everything = fmap.render(K, at_first, H, W, colour=False)
    assert inactive.valid.float().mean() > 0.95
    assert active.valid.float().mean() < 0.01
    assert torch.equal(inactive.valid, everything.valid)
    assert fmap.render(K, _t(second[0]), H, W, colour=False, seen_from=5).valid.float().mean() > 0.95
    st = fmap.store
    before = st.t_last[: st.n].clone(), st.conf[: st.n].clone()
    depth, colour, _ = ray_cast(first[0], K)
    fmap.fuse(depth, colour, K, at_first, 10, active_from=5)
    old = (before[0] < 5) & st.alive[: before[0].numel()]
    assert torch.equal(st.t_last[: before[0].numel()][old], before[0][old])   # not matched nor updated
    assert torch.equal(st.conf[: before[0].numel()][old], before[1][old])


def test_moved_surfels_render_as_the_corrected_view():
    """Surfels moved by a correction C render from C T exactly as they rendered from T; the
    chunk boxes follow (nothing is culled), frames past the corrections stay."""
    poses = [pose([2.0 * i, 0.0, 0.0]) for i in range(4)]
    fmap, K = _fused(poses)
    T = _t(poses[1])
    before = fmap.render(K, T, H, W, colour=False)
    C = pose([150.0, -60.0, 4.0], (0.05, -0.03, 0.2))
    corrections = torch.as_tensor(np.stack([C] * 4), dtype=torch.float32)
    assert fmap.move_surfels(corrections) == len(fmap)
    after = fmap.render(K, _t(C) @ T, H, W, colour=False)
    assert torch.equal(before.valid, after.valid)
    both = before.valid
    assert (before.depth[both] - after.depth[both]).abs().max() < 1e-3
    n_before = fmap.render(K, T, H, W, colour=False).valid.float().mean()
    assert n_before < 0.2                                      # nothing left at the old place
    # surfels last fused at a frame the corrections do not reach keep their place
    fmap2, _ = _fused(poses)
    fmap2.move_surfels(torch.as_tensor(np.stack([C] * 2), dtype=torch.float32))   # frames 0, 1
    st = fmap2.store
    late = st.alive[: st.n] & (st.t_last[: st.n] >= 2)
    ref, _ = _fused(poses)
    assert torch.equal(st.pos[: st.n][late], ref.store.pos[: st.n][late])


def test_revived_view_merges_the_duplicated_surface():
    """A surface fused twice, once in the inactive and once in the active model: reviving the
    view keeps one layer (the old surfels, now active, with the duplicates' confidence) and
    removes the duplicates; surfels off the view stay."""
    T = pose([0.0, 0.0, 0.0])
    fmap, K = _fused([T] * 4)                   # frames 0-3: the old surface
    n_old = len(fmap)
    depth, colour, _ = ray_cast(T, K)
    for f in range(4, 8):                       # frames 4-7 fuse it again in the active model alone
        fmap.fuse(depth, colour, K, _t(T), f, active_from=4)
    assert len(fmap) > 1.8 * n_old              # two layers
    conf_old = fmap.store.conf[: fmap.store.n][fmap.store.t_last[: fmap.store.n] < 4].sum()
    revived, merged = fmap.reactivate_view(K, _t(T), H, W, 8, active_from=4)
    assert revived > 0.95 * n_old and merged > 0.9 * (len(fmap) + merged - n_old)
    st = fmap.store
    assert len(fmap) < 1.1 * n_old
    assert int((st.alive[: st.n] & (st.t_last[: st.n] == 8)).sum()) == revived
    assert st.conf[: st.n][st.alive[: st.n]].sum() > conf_old
    single = fmap.render(K, _t(T), H, W, colour=False)
    assert (single.depth[single.valid] - depth[single.valid]).abs().median() < 0.05
