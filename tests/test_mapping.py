"""Tests of the surfel map (mapping/): fusion, removal, splatting renderer, export.

All data is synthetic and exact: a smooth tissue-like height field
``z = 80 + 5 sin(x / 15) cos(y / 20)`` mm in world coordinates, ray-cast to an exact depth map at
any pose by fixed-point iteration, with an analytic colour texture.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mapping import MapConfig, ModelView, SurfelMap, fusion, kernels
from mapping import render as render_module
from mapping.fusion import measure
from mapping.render import FAR_MM, NEAR_MM, Camera, cull_chunks, render, visible_set
from mapping.config import MapConfigError

H, W = 128, 160
F = 150.0


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Small tensors: one thread is faster and immune to oversubscribed CPUs."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


# ------------------------------------------------------------------ synthetic scene
def surface_height(x, y):
    return 80.0 + 5.0 * np.sin(x / 15.0) * np.cos(y / 20.0)


def texture(x, y):
    return np.stack([0.5 + 0.3 * np.sin(x / 2.0), 0.5 + 0.3 * np.cos(y / 3.0),
                     0.5 + 0.2 * np.sin((x + y) / 4.0)])


def intrinsics(w=W, h=H, f=F):
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def rotation(rx, ry, rz):
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def pose(t, r=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    T[:3, :3] = rotation(*r)
    T[:3, 3] = t
    return T


def ray_cast(T_wc, K, h=H, w=W, iters=60):
    """Exact depth (h, w), colour (3, h, w) and world points (h, w, 3) of the height field."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    dw = d @ T_wc[:3, :3].T
    o = T_wc[:3, 3]
    t = (80.0 - o[2]) / dw[..., 2]
    for _ in range(iters):    # contraction: |grad h| * |d_xy / d_z| < 0.3 here
        t = (surface_height(o[0] + t * dw[..., 0], o[1] + t * dw[..., 1]) - o[2]) / dw[..., 2]
    x, y = o[0] + t * dw[..., 0], o[1] + t * dw[..., 1]
    X = np.stack([x, y, surface_height(x, y)], -1)
    return (torch.from_numpy(t.astype(np.float32)), torch.from_numpy(texture(x, y).astype(np.float32)), X)


def project(X, T_wc, K):
    Tcw = np.linalg.inv(T_wc)
    Xc = X @ Tcw[:3, :3].T + Tcw[:3, 3]
    return Xc[..., 0] / Xc[..., 2] * K[0, 0] + K[0, 2], Xc[..., 1] / Xc[..., 2] * K[1, 1] + K[1, 2], Xc[..., 2]


def ring_poses(n=20, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n
        out.append(pose([8 * math.cos(a), 8 * math.sin(a), rng.uniform(-3, 3)], rng.uniform(-0.06, 0.06, 3)))
    return out


def flat(depth_mm, h=H, w=W):
    return torch.full((h, w), float(depth_mm)), torch.full((3, h, w), 0.5)


# ------------------------------------------------------------------ accuracy
def test_novel_view_depth_accuracy():
    """Exact depth fused from 20 poses, rendered at an unseen nearby pose: sub-0.2 mm depth."""
    torch.manual_seed(0)
    K = intrinsics()
    poses = ring_poses()
    m = SurfelMap(MapConfig())
    for i, T in enumerate(poses):
        depth, color, _ = ray_cast(T, K)
        stats = m.fuse(depth, color, K, T, i)
        assert set(stats) >= {"matched", "added", "removed"}
    T_new = pose([3.0, -4.0, 2.0], [0.03, -0.02, 0.05])
    true_depth, true_color, X = ray_cast(T_new, K)
    seen = np.zeros((H, W), dtype=bool)
    for T in poses:        # pixels whose surface point lies inside some fused view (2 px border)
        u, v, z = project(X, T, K)
        seen |= (u >= 2) & (u <= W - 3) & (v >= 2) & (v <= H - 3) & (z > 0)
    assert seen.mean() > 0.5
    view = m.render(K, T_new, H, W)
    assert isinstance(view, ModelView)
    assert view.depth.shape == (H, W) and view.color.shape == (3, H, W) and view.normals.shape == (3, H, W)
    valid = view.valid.numpy()
    assert valid[seen].mean() >= 0.95
    both = seen & valid
    err = np.abs(view.depth.numpy() - true_depth.numpy())[both]
    assert np.median(err) < 0.2
    assert np.percentile(err, 95) < 0.5
    # colours and normals of the rendered surface
    assert np.abs(view.color.numpy() - true_color.numpy())[:, both].mean() < 0.05
    nz = view.normals.numpy()[2][both]
    assert (nz < -0.8).mean() > 0.99       # camera-frame normals face the camera
    # the stable-only view is a subset of the full one
    sv = m.render(K, T_new, H, W, stable_only=True)
    assert not (sv.valid & ~view.valid).any()
    assert 0 < m.num_stable() <= len(m)


# ------------------------------------------------------------------ surfel count
def test_static_camera_count_bounded():
    K = intrinsics()
    T = pose([0.0, 0.0, 0.0])
    depth, color, _ = ray_cast(T, K)
    m = SurfelMap(MapConfig())
    m.fuse(depth, color, K, T, 0)
    n1 = len(m)
    assert n1 > 0.9 * H * W
    for i in range(1, 20):
        stats = m.fuse(depth, color, K, T, i)
    assert len(m) <= 1.2 * n1
    assert stats["matched"] >= 0.95 * n1
    assert m.num_stable() >= 0.95 * n1


def test_panning_grows_with_new_area():
    K = intrinsics()
    m = SurfelMap(MapConfig())
    cell = 1.0                                   # mm, world grid for the seen-area estimate (> pixel)
    seen_cells = set()
    counts = []
    for i in range(30):
        T = pose([1.0 * i, 0.5 * i, 0.0])
        depth, color, X = ray_cast(T, K)
        m.fuse(depth, color, K, T, i)
        counts.append(len(m))
        keys = np.unique(np.floor(X[..., :2].reshape(-1, 2) / cell).astype(np.int64), axis=0)
        if i == 0:
            first_cells = len(keys)
        seen_cells.update(map(tuple, keys))
    # about one surfel per pixel of surface: expected growth = new area in first-frame pixels
    # (less: rim surfels seen only at low radial weight never get confirmed and expire, and a
    # pixel within half a radius of a neighbour's surfel adds none - skip_covered)
    expected_new = (len(seen_cells) - first_cells) / first_cells * counts[0]
    growth = counts[-1] - counts[0]
    assert expected_new > 0.5 * counts[0]
    assert 0.45 * expected_new < growth < 1.3 * expected_new
    density = len(visible_set(m.store, Camera.make(K, T, H, W, m.device), 5.0, 400.0)) / (H * W)
    assert 0.8 < density < 1.1
    assert counts[0] < counts[10] < counts[20] < counts[-1]         # grows along the way


# ------------------------------------------------------------------ weights, masks, removal
def test_zero_weight_and_invalid_pixels_add_nothing():
    K = intrinsics()
    T = np.eye(4)
    depth, color = flat(80.0)
    weight = torch.ones(H, W)
    weight[:, : W // 2] = 0.0
    m = SurfelMap(MapConfig())
    stats = m.fuse(depth, color, K, T, 0, weight=weight)
    p = m.points(stable_only=False)["positions"]
    u = p[:, 0] / p[:, 2] * K[0, 0] + K[0, 2]
    assert stats["added"] == len(m) > 0
    assert (u > W // 2 - 0.5).all()                         # nothing from the weight-0 half
    valid = torch.ones(H, W, dtype=torch.bool)
    valid[: H // 2] = False
    m2 = SurfelMap(MapConfig())
    m2.fuse(depth, color, K, T, 0, weight=weight, valid=valid)
    p2 = m2.points(stable_only=False)["positions"]
    v = p2[:, 1] / p2[:, 2] * K[1, 1] + K[1, 2]
    assert len(m2) > 0 and (v > H // 2 - 0.5).all()
    m3 = SurfelMap(MapConfig())
    assert m3.fuse(depth, color, K, T, 0, weight=torch.zeros(H, W))["added"] == 0
    assert len(m3) == 0


def _bump(depth, height_mm=8.0, radius_px=20):
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    inside = ((u - W / 2) ** 2 + (v - H / 2) ** 2) < radius_px ** 2
    return torch.where(inside, depth - height_mm, depth), inside


def test_deforming_region_with_zero_weight_never_fused():
    K = intrinsics()
    T = np.eye(4)
    depth, color = flat(80.0)
    bumped, inside = _bump(depth)
    weight = (~inside).float()
    m = SurfelMap(MapConfig())
    frame = 0
    for _ in range(5):
        m.fuse(depth, color, K, T, frame)
        frame += 1
    n_flat = len(m)
    for _ in range(4):                     # tissue deforms; the weight map masks it out
        m.fuse(bumped, color, K, T, frame, weight=weight)
        frame += 1
    for _ in range(3):
        m.fuse(depth, color, K, T, frame)
        frame += 1
    z = m.points(stable_only=False)["positions"][:, 2]
    assert (np.abs(z - 72.0) < 2.0).sum() == 0
    assert abs(len(m) - n_flat) <= 0.02 * n_flat


def test_transient_bump_is_removed():
    """A bump fused with full weight for 3 frames disappears once the flat surface is seen again."""
    K = intrinsics()
    T = np.eye(4)
    depth, color = flat(80.0)
    bumped, inside = _bump(depth)
    m = SurfelMap(MapConfig())
    frame = 0
    for d in [depth] * 5 + [bumped] * 3 + [depth] * 4:
        m.fuse(d, color, K, T, frame)
        frame += 1
    z = m.points(stable_only=False)["positions"][:, 2]
    assert (np.abs(z - 72.0) < 2.0).sum() == 0
    view = m.render(K, T, H, W)
    assert torch.allclose(view.depth[inside], torch.tensor(80.0), atol=0.05)


def test_free_space_violation_removes_surfels():
    K = intrinsics()
    T = np.eye(4)
    near, color = flat(80.0)
    far, _ = flat(100.0)
    m = SurfelMap(MapConfig())
    for i in range(10):
        m.fuse(near, color, K, T, i)
    assert m.num_stable() > 0.9 * H * W
    removed = 0
    for i in range(10, 16):
        removed += m.fuse(far, color, K, T, i)["removed"]
    z = m.points(stable_only=False)["positions"][:, 2]
    assert (np.abs(z - 80.0) < 1.0).sum() == 0
    assert removed > 0.9 * H * W
    assert len(m) <= 1.05 * H * W                            # no duplicates of the new surface
    view = m.render(K, T, H, W)
    assert view.coverage() > 0.95
    assert torch.allclose(view.depth[view.valid], torch.tensor(100.0), atol=0.05)


def test_unstable_surfels_expire():
    cfg = MapConfig(unstable_window=5)
    K = intrinsics()
    depth, color = flat(80.0)
    m = SurfelMap(cfg)
    m.fuse(depth, color, K, np.eye(4), 0, weight=torch.full((H, W), 0.1))   # conf 0.1: unstable
    n0 = len(m)
    assert n0 > 0 and m.num_stable() == 0
    far_away = pose([500.0, 0.0, 0.0])
    for i in range(1, 7):
        m.fuse(depth, color, K, far_away, i)
    # the first batch expired; of the far-away batch (created at frame 1, age 5 now) only the
    # surfels that became stable (well inside the image: radial weight) survive
    pos = m.points(stable_only=False)["positions"]
    assert (pos[:, 0] < 250).sum() == 0
    assert 0.5 * n0 < len(m) == m.num_stable()


# ------------------------------------------------------------------ store mechanics
def test_capacity_growth_compaction_and_culling():
    compact_fraction = 0.1
    K = intrinsics()
    m = SurfelMap(MapConfig(), capacity=1000, chunk_size=256, compact_fraction=compact_fraction)
    for i, T in enumerate(ring_poses(8)):
        depth, color, _ = ray_cast(T, K)
        m.fuse(depth, color, K, T, i)
    assert m.store.capacity >= len(m) > H * W
    far, color = flat(120.0)
    for i in range(8, 12):                               # carve most of the map away -> compaction
        m.fuse(far, color, K, np.eye(4), i)
    st = m.store
    st.maybe_compact()                                   # (fusion runs it before each frame)
    assert st.num_dead < compact_fraction * max(st.n, 1) + 1
    assert int(st.alive[: st.n].sum()) == len(m)
    assert not st.alive[st.n:].any()
    # chunk culling finds exactly the surfels a brute-force projection finds
    for T in [np.eye(4), pose([20.0, 10.0, 0.0], [0.1, -0.2, 0.3]), pose([0.0, 0.0, 0.0], [0.0, math.pi, 0.0])]:
        cam = Camera.make(K, T, H, W, st.device)
        vis = visible_set(st, cam, NEAR_MM, FAR_MM, margin_px=2.0)
        idx = st.alive[: st.n].nonzero().squeeze(1)
        p = cam.to_cam(st.pos[idx])
        z = p[:, 2]
        u = p[:, 0] / z.clamp_min(1e-6) * K[0, 0] + K[0, 2]
        v = p[:, 1] / z.clamp_min(1e-6) * K[1, 1] + K[1, 2]
        ok = ((z >= NEAR_MM) & (z <= FAR_MM) & (u >= -2.5) & (u < W + 1.5) & (v >= -2.5) & (v < H + 1.5))
        assert set(vis.slots.tolist()) == set(idx[ok].tolist())


def test_render_after_fuse_reuses_view_exactly():
    """The render right after fusing at the same view starts from the fused view's surfels; it
    must equal a render that culls the whole map."""
    K = intrinsics()
    m = SurfelMap(MapConfig())
    for i, T in enumerate(ring_poses(6)):
        depth, color, _ = ray_cast(T, K)
        m.fuse(depth, color, K, T, i)
    assert "view" in m.store.scratch
    cached = m.render(K, T, H, W)
    m.store.scratch.pop("view")
    full = m.render(K, T, H, W)
    for a, b in [(cached.depth, full.depth), (cached.color, full.color), (cached.index, full.index)]:
        assert torch.equal(a, b)
    depth, color, _ = ray_cast(T, K)
    m.fuse(depth, color, K, T, 6)
    other = pose([5.0, 0.0, 0.0])
    with_cache = m.render(K, other, H, W)           # cache present, but for another view
    m.store.scratch.pop("view")
    assert torch.equal(with_cache.depth, m.render(K, other, H, W).depth)


def test_render_empty_map_and_empty_view():
    K = intrinsics()
    m = SurfelMap(MapConfig())
    view = m.render(K, np.eye(4), H, W)
    assert view.valid.shape == (H, W) and not view.valid.any()
    assert view.coverage() == 0.0 and (view.depth == 0).all()
    assert len(m) == 0 and m.num_stable() == 0
    depth, color = flat(80.0)
    m.fuse(depth, color, K, np.eye(4), 0)
    behind = m.render(K, pose([0.0, 0.0, 0.0], [0.0, math.pi, 0.0]), H, W)   # looking away
    assert not behind.valid.any()
    pts = m.points(stable_only=False)
    for k in ("positions", "normals", "colors"):
        assert pts[k].shape == (len(m), 3)
    assert pts["radii"].shape == (len(m),) and pts["confidence"].shape == (len(m),)


# ------------------------------------------------------------------ export
def _stable_map():
    K = intrinsics(80, 64, 75.0)
    m = SurfelMap(MapConfig())
    for i in range(6):
        T = pose([0.5 * (i % 3), 0.5 * (i // 3), 0.0])
        depth, color, _ = ray_cast(T, K, 64, 80)
        m.fuse(depth, color, K, T, i)
    return m


def test_save_ply_roundtrip(tmp_path):
    o3d = pytest.importorskip("open3d")
    m = _stable_map()
    n = m.save_ply(tmp_path / "map.ply")
    assert n == m.num_stable() > 1000
    pcd = o3d.io.read_point_cloud(str(tmp_path / "map.ply"))
    assert len(pcd.points) == n
    assert pcd.has_colors() and pcd.has_normals()
    pts = np.asarray(pcd.points)
    assert 0.07 < np.median(pts[:, 2]) < 0.09                 # metres
    cols = np.asarray(pcd.colors)
    assert cols.min() >= 0 and cols.max() <= 1 and cols.std() > 0.01
    assert np.allclose(np.linalg.norm(np.asarray(pcd.normals), axis=1), 1.0, atol=1e-3)
    n_all = m.save_ply(tmp_path / "all.ply", stable_only=False, scale=1.0)
    assert n_all == len(m)
    assert 70 < np.median(np.asarray(o3d.io.read_point_cloud(str(tmp_path / "all.ply")).points)[:, 2]) < 90
    assert SurfelMap(MapConfig()).save_ply(tmp_path / "empty.ply") == 0
    assert len(o3d.io.read_point_cloud(str(tmp_path / "empty.ply")).points) == 0


def test_save_mesh(tmp_path):
    o3d = pytest.importorskip("open3d")
    m = _stable_map()
    ntri = m.save_mesh(tmp_path / "mesh.ply", depth=7)
    assert ntri > 100
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "mesh.ply"))
    assert len(mesh.triangles) == ntri
    v = np.asarray(mesh.vertices)
    assert 0.07 < np.median(v[:, 2]) < 0.09
    assert SurfelMap(MapConfig()).save_mesh(tmp_path / "empty.ply") == 0


# ------------------------------------------------------------------ config
def test_config_validation():
    with pytest.raises(MapConfigError):
        MapConfig(min_depth_mm=300.0)
    with pytest.raises(MapConfigError, match="unstable_window"):
        MapConfig(unstable_window=0)
    with pytest.raises(MapConfigError, match="kernels"):
        MapConfig(kernels="fast")


def test_render_without_colour_gives_the_same_geometry():
    K = intrinsics()
    m = SurfelMap(MapConfig())
    for i, T in enumerate(ring_poses(6)):
        depth, color, _ = ray_cast(T, K)
        m.fuse(depth, color, K, T, i)
    T = pose([1.0, 0.5, 0.0])
    full = m.render(K, T, H, W)
    bare = m.render(K, T, H, W, colour=False)
    assert full.valid.float().mean() > 0.5 and full.color.abs().sum() > 0
    for a, b in [(full.depth, bare.depth), (full.valid, bare.valid), (full.index, bare.index),
                 (full.confidence, bare.confidence)]:
        assert torch.equal(a, b)
    assert bare.color.shape == full.color.shape and not bare.color.any()
    # the blending pass on demand gives the colour of the full render; not once the map changed
    assert torch.equal(bare.with_colour().color, full.color) and bare.pending_colour is None
    late = m.render(K, T, H, W, colour=False)
    depth, color, _ = ray_cast(T, K)
    m.fuse(depth, color, K, T, 6)
    with pytest.raises(RuntimeError, match="changed"):
        late.with_colour()


# ------------------------------------------------------------------ compiled kernels vs torch


def test_kernel_selection():
    assert not kernels.use_compiled(MapConfig(kernels="torch"), "cpu")
    assert kernels.AVAILABLE                       # numba is a dependency: the default CPU path is compiled
    assert kernels.use_compiled(MapConfig(kernels="auto"), "cpu")
    assert not kernels.use_compiled(MapConfig(kernels="auto"), "cuda:0")
    with pytest.raises(ValueError, match="CPU"):
        kernels.use_compiled(MapConfig(kernels="compiled"), "cuda:0")


def test_compiled_measurements_equal_torch():
    """Points, normals, radii, weights and the fusable mask of a noisy frame with holes and NaNs."""
    K = intrinsics()
    T = pose([2.0, -1.0, 1.0], [0.05, -0.03, 0.1])
    depth, color, _ = ray_cast(T, K)
    g = torch.Generator().manual_seed(3)
    depth = depth + 0.3 * torch.randn(depth.shape, generator=g)
    depth[40:50, 60:90] = 0.0
    depth[70:75, 10:20] = float("nan")
    weight = torch.rand(depth.shape, generator=g)
    cam = Camera.make(K, T, H, W, torch.device("cpu"))
    a = measure(depth, color, cam, MapConfig(kernels="torch"), weight, min_fuse_weight=0.1)
    b = measure(depth, color, cam, MapConfig(kernels="compiled"), weight, min_fuse_weight=0.1)
    assert 0.2 < a.fuse.float().mean() < 0.9        # holes, low weights and depth jumps excluded
    assert torch.equal(a.fuse, b.fuse)
    for f in ("points", "normals", "radius", "weight", "color", "free_depth"):
        torch.testing.assert_close(getattr(b, f), getattr(a, f), rtol=1e-5, atol=1e-5, msg=f)


def test_compiled_fusion_builds_the_same_map_as_torch():
    """Noisy depth, random fusion weights, a moving camera (association, merging, free space and
    the time window all act): both implementations give the same per-frame statistics, the same
    surfels and the same rendered view (floating-point rounding aside)."""
    K = intrinsics()
    g = torch.Generator().manual_seed(1)
    maps = {k: SurfelMap(MapConfig(kernels=k)) for k in ("torch", "compiled")}
    acted = set()
    for i in range(24):
        a = 2 * math.pi * i / 24
        T = pose([6 * math.cos(a), 6 * math.sin(a), 1.5 * math.sin(3 * a)], [0.04 * math.sin(a), 0.03, 0.1 * a])
        depth, color, _ = ray_cast(T, K)
        depth = depth + 0.15 * torch.randn(depth.shape, generator=g)
        if i in (12, 13):     # the tissue pushed 10 mm away: the stable surfels lie in free space
            depth[50:70, 60:90] += 10.0
        weight = torch.rand(depth.shape, generator=g) * 0.9 + 0.1
        stats = {k: m.fuse(depth, color, K, T, i, weight=weight) for k, m in maps.items()}
        acted.update(k for k in ("merged", "decayed", "removed") if stats["torch"][k] > 0)
        for key in ("matched", "added", "removed", "merged", "decayed", "visible", "surfels"):
            ta, tb = stats["torch"][key], stats["compiled"][key]
            assert abs(ta - tb) <= max(3, 0.002 * ta), (i, key, ta, tb)
    assert acted == {"merged", "decayed", "removed"}
    sizes = {k: len(m) for k, m in maps.items()}
    assert sizes["torch"] > 5000 and abs(sizes["torch"] - sizes["compiled"]) <= 0.002 * sizes["torch"]
    T = pose([1.0, 2.0, 0.5], [0.02, -0.02, 0.3])
    va, vb = (maps[k].render(K, T, H, W) for k in ("torch", "compiled"))
    both = va.valid & vb.valid
    assert both.float().mean() > 0.9 and (va.valid ^ vb.valid).float().mean() < 0.002
    dz = (va.depth - vb.depth).abs()[both]
    assert dz.median() < 1e-3 and (dz > 0.05).float().mean() < 0.005
    dc = (va.color - vb.color).abs()[:, both]
    assert dc.mean() < 2e-3


@pytest.mark.parametrize("constants, render_kw", [
    ({}, {}),
    ({(fusion, "RADIUS_SCALE"): 2.0}, {}),
    ({(render_module, "RENDER_BLEND_SIGMA"): 0.5}, {"cull_hidden_unstable": False})],
    ids=["defaults", "radius_scale_2", "no_culling_sigma_0.5"])
def test_compiled_splatting_equals_torch(constants, render_kw, monkeypatch):
    """The compiled splatting passes render what the torch passes render: noisy depth (stable and
    unstable surfels, oblique discs), footprints of 1x1 to 7x7 pixels, colour now or on demand."""
    from dataclasses import replace

    for (module, name), value in constants.items():
        monkeypatch.setattr(module, name, value)
    K = intrinsics()
    g = torch.Generator().manual_seed(3)
    m = SurfelMap(MapConfig(kernels="torch"))
    for i, T in enumerate(ring_poses(10)):
        depth, color, _ = ray_cast(T, K)
        m.fuse(depth + 0.1 * torch.randn(depth.shape, generator=g), color, K, T, i)
    stable = m.store.conf[:m.store.n][m.store.alive[:m.store.n]] >= m.config.stable_confidence
    assert 0.2 < stable.float().mean() < 0.95                  # both kinds are there
    for T in (pose([1.0, 2.0, 0.5], [0.02, -0.02, 0.3]), pose([0.0, 0.0, 35.0], [0.2, 0.1, 0.0])):   # near: 3-7 px footprints
        views = {}
        for mode in ("torch", "compiled"):
            view, _ = render(m.store, replace(m.config, kernels=mode), K, T, H, W, colour=False,
                             **render_kw)
            views[mode] = view.with_colour()
        a, b = views["torch"], views["compiled"]
        assert a.valid.float().mean() > 0.4
        assert torch.equal(a.valid, b.valid)
        assert (a.index == b.index).float().mean() > 0.99       # (ties of equal depth may differ)
        torch.testing.assert_close(b.depth, a.depth, rtol=0, atol=0.01)
        torch.testing.assert_close(b.color, a.color, rtol=0, atol=1e-3)
        torch.testing.assert_close(b.normals[:, b.index == a.index], a.normals[:, b.index == a.index])
    cam = Camera.make(K, T, H, W, torch.device("cpu"))
    r_px = m.store.radius[:m.store.n] * cam.f / cam.to_cam(m.store.pos[:m.store.n])[:, 2]
    assert r_px.max() > 2.5                                     # large footprints were splatted too


def test_compiled_culling_and_visible_set_equal_torch():
    K = intrinsics()
    m = SurfelMap(MapConfig(kernels="torch"), chunk_size=64)
    for i, T in enumerate(ring_poses(8)):
        depth, color, _ = ray_cast(T, K)
        m.fuse(depth, color, K, T, i)
    st = m.store
    for T in (pose([1.0, 0.5, 0.0]), pose([30.0, 0.0, 0.0], [0.0, 0.3, 0.0]), pose([0.0, 0.0, 200.0])):
        cam = Camera.make(K, T, H, W, torch.device("cpu"))
        a = cull_chunks(st, cam, 5.0, 400.0, 3.0)
        b = cull_chunks(st, cam, 5.0, 400.0, 3.0, compiled=True)
        assert torch.equal(a, b)
        for kw in ({}, {"stable_threshold": 3.0}, {"candidates": torch.arange(0, st.n, 3)}):
            va = visible_set(st, cam, 5.0, 400.0, 3.0, **kw)
            vb = visible_set(st, cam, 5.0, 400.0, 3.0, compiled=True, **kw)
            assert torch.equal(va.slots, vb.slots), kw
            torch.testing.assert_close(vb.p, va.p, rtol=0, atol=1e-4)
            torch.testing.assert_close(vb.u, va.u, rtol=0, atol=1e-3)
            torch.testing.assert_close(vb.v, va.v, rtol=0, atol=1e-3)
    assert len(visible_set(st, Camera.make(K, pose([1.0, 0.5, 0.0]), H, W, torch.device("cpu")), 5.0, 400.0,
                           compiled=True)) > 0.5 * H * W


def test_hidden_unstable_surfels_are_not_splatted_and_the_view_keeps_its_surface():
    """Unstable duplicates under a stable surface (the noisy frames after many exact ones) change
    nothing where the stable surface is seen; unstable surfels on their own still render."""
    K = intrinsics()
    m = SurfelMap(MapConfig(kernels="torch"))
    poses = ring_poses(8)
    for i, T in enumerate(poses):
        depth, color, _ = ray_cast(T, K)
        m.fuse(depth, color, K, T, i)
    g = torch.Generator().manual_seed(5)
    T = pose([1.0, 0.5, 0.0])
    depth, color, _ = ray_cast(T, K)
    # a frame whose normals disagree with the map: nothing associates, all of it is new and unstable
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fusion, "ASSOC_NORMAL_DEG", 1e-3)
        m.fuse(depth + 0.2 * torch.randn(depth.shape, generator=g), color, K, T, 8)
    conf = m.store.conf[: m.store.n]
    assert (conf[m.store.alive[: m.store.n]] < 3.0).sum() > 0.5 * H * W
    views = {}
    for cull in (True, False):
        views[cull] = render(m.store, m.config, K, T, H, W, cull_hidden_unstable=cull)[0]
    a, b = views[True], views[False]
    stable = b.confidence >= 3.0
    assert stable.float().mean() > 0.8
    for x, y in [(a.depth, b.depth), (a.index, b.index), (a.confidence, b.confidence)]:
        assert torch.equal(x[stable], y[stable])
    torch.testing.assert_close(a.color[:, stable], b.color[:, stable])
    assert (a.valid ^ b.valid).float().mean() < 0.002
    # a map of unstable surfels only renders as before
    fresh = SurfelMap(MapConfig(kernels="torch"))
    fresh.fuse(depth, color, K, T, 0)
    views = {}
    for cull in (True, False):
        views[cull] = render(fresh.store, fresh.config, K, T, H, W, cull_hidden_unstable=cull)[0]
    assert views[True].valid.float().mean() > 0.95
    assert torch.equal(views[True].depth, views[False].depth)


@pytest.mark.parametrize("kernels_mode", ["torch", "compiled"])
def test_pixels_on_a_neighbours_disc_add_no_duplicate(kernels_mode):
    """A camera moving by fractions of a pixel over a mapped surface seen with noisy depth (as
    stereo): pixels into which no surfel centre falls are not turned into duplicate surfels when
    a neighbour's surfel covers them."""
    K = intrinsics()
    added = {}
    for skip in (True, False):
        m = SurfelMap(MapConfig(kernels=kernels_mode), skip_covered=skip)
        g = torch.Generator().manual_seed(7)
        stats = []
        for i in range(8):
            T = pose([0.13 * i, -0.07 * i, 0.0], [0.0, 0.0, 0.002 * i])
            depth, color, _ = ray_cast(T, K)
            depth = depth + 0.2 * torch.randn(depth.shape, generator=g)
            stats.append(m.fuse(depth, color, K, T, i))
        added[skip] = sum(st["added"] for st in stats[1:]) / 7
        view = m.render(K, pose([0.5, -0.2, 0.0]), H, W)
        assert view.coverage() > 0.99
    assert added[False] > 0.1 * H * W             # without: a duplicate for every pixel left empty
    assert added[True] < 0.5 * added[False]


def _fuse_two_frames(out=None) -> int:
    """Fuse two frames with the compiled kernels; returns the map size (also put on ``out``, a
    queue, when run in a worker process)."""
    K = intrinsics()
    m = SurfelMap(MapConfig(kernels="compiled"))
    for i, T in enumerate((pose([0.0, 0.0, 0.0]), pose([1.0, 0.0, 0.0]))):
        depth, color, _ = ray_cast(T, K)
        m.fuse(depth, color, K, T, i)
    if out is not None:
        out.put(len(m))
    return len(m)


def test_a_process_that_fused_can_fork_workers_that_fuse():
    """Benchmarks and users' scripts fork worker processes after the parent ran a frame2model
    pipeline: the kernels must leave the process forkable (an OpenMP-parallel kernel did not: the
    child was killed or hung)."""
    import multiprocessing

    size = _fuse_two_frames()
    torch.ones(512, 512).matmul(torch.ones(512, 512))     # torch's own thread pool is up too
    ctx = multiprocessing.get_context("fork")
    out = ctx.Queue()
    child = ctx.Process(target=_fuse_two_frames, args=(out,))
    child.start()
    child.join(timeout=120)
    if child.is_alive():
        child.kill()
        child.join()
        pytest.fail("the forked worker hung")
    assert child.exitcode == 0, f"the forked worker died (exit code {child.exitcode})"
    assert out.get(timeout=5) == size > 1000


@pytest.mark.parametrize("kernels_mode", ["torch", "compiled"])
def test_warm_up_leaves_the_map_empty_and_fusion_works_after_it(kernels_mode):
    m = SurfelMap(MapConfig(kernels=kernels_mode))
    m.warm_up()
    assert len(m) == 0 and m.store.n == 0 and m.frames_fused == 0
    K = intrinsics()
    depth, color, _ = ray_cast(pose([0.0, 0.0, 0.0]), K)
    m.fuse(depth, color, K, pose([0.0, 0.0, 0.0]), 0)
    assert len(m) > 0.9 * H * W
    view = m.render(K, pose([0.0, 0.0, 0.0]), H, W)
    assert view.coverage() > 0.95
    torch.testing.assert_close(view.depth[view.valid].median(), depth[view.valid].median(), rtol=0, atol=0.05)
