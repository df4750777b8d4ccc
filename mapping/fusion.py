"""Fusing one depth frame into the surfel store (ElasticFusion, Whelan et al. 2016; Keller et al. 2013).

Per frame:

1. *Measurements*: back-project the depth map; normals by central differences of the
   back-projected points (masked where a neighbour is invalid or across a depth jump); surfel
   radius ``sqrt(2) * depth / f / max(|n . ray|, c_min)``; fusion weight = input weight x radial
   Gaussian confidence (pixels of weight 0 are neither fused nor used to carve free space).
2. *Visible surfels*: chunk boxes against the frustum, then per surfel.
3. *Free space*: a visible surfel in front of the measured surface of its pixel by more than a
   margin lies where the ray passed through: removed if unstable, its confidence decayed if
   stable; either way it takes no part in this frame's association (it must not hide the surface
   behind it in the index map).
4. *Projective data association*: the other visible surfels are z-tested into an index map
   super-sampled ``s x s`` per pixel (every cell keeps its nearest surfel).  The ``s x s`` cells of
   a pixel hold exactly the surfels whose centre falls inside that pixel, so the candidates of all
   pixels are found from the cells' side in one pass over the visible surfels (no gather of
   ``s^2 x pixels`` cells).  A candidate matches when its depth is within ``max(a, b * depth)`` of
   the measurement and the normals agree; the most confident candidate wins, near-ties go to the
   one closest to the pixel's ray.  Matching losers whose centre lies on the winner's disc are
   merged into it (Keller et al. 2013) - this keeps about one surfel per pixel of surface.
5. *Update*: matched surfels take the confidence-weighted running average of position, normal,
   colour and radius (only when the measurement's radius is below ``RADIUS_UPDATE_RATIO`` x the
   surfel's - ElasticFusion's rule favouring fine measurements), ``conf += w``, ``t_last = frame``;
   unmatched fusable pixels become new surfels with ``conf = w``.
6. *Time window*: unstable surfels still unstable ``unstable_window`` frames after their creation
   are removed (slots are in creation order, so only the surfels reaching that age are inspected).

Steps 1-5 are vectorised torch (any device); for a map on the CPU they run by default as the
compiled loops of :mod:`mapping.kernels` (``MapConfig.kernels``), which give the same map.
"""
from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass

import torch

from . import kernels
from .config import MapConfig
from .render import FAR_MM, KEY_EMPTY, NEAR_MM, SPLAT_MAX_HALF, Camera, cell_winners, visible_set
from .surfels import SORT_CELL_MM, SurfelStore, take, to_rows

# ---- per-pixel measurements
# a central-difference normal needs both neighbours along x and y valid and within this fraction of
# the centre depth (depth jumps get no normal and are not fused); 0.03 admits surfaces inclined up
# to ~75-80 deg to the view at 150-600 px focal length
NORMAL_MAX_JUMP_REL = 0.03
# clamp of |n . ray| in the radius r = sqrt(2) * depth / f / max(|n . ray|, c): a grazing surfel's
# radius is at most twice the fronto-parallel one (ElasticFusion's min(2 r, r / |n_z|))
RADIUS_MIN_COS = 0.5
# extra factor on the surfel radius (1 = ElasticFusion's sqrt(2) * depth / f)
RADIUS_SCALE = 1.0
# sigma of the radial confidence weight exp(-d^2 / (2 sigma^2)), d = distance from the principal
# point over that of the farthest image corner (ElasticFusion: 0.6); 0 disables the weighting
RADIAL_SIGMA = 0.6
# pixels whose fusion weight (input weight x radial weight) is at most this are neither fused nor
# used for the free-space test (0: only weight-0 pixels - instruments, specularities, deformation)
MIN_FUSE_WEIGHT = 0.0

# ---- data association and fusion
# super-sampling of the index map of the projective data association (ElasticFusion: 4, i.e. 4x4
# cells per pixel, each holding its nearest surfel)
INDEX_SCALE = 4
# depth tolerance of a match (surfel vs measured depth): max(ASSOC_DEPTH_MM, ASSOC_DEPTH_REL * depth)
ASSOC_DEPTH_MM = 2.0
ASSOC_DEPTH_REL = 0.02
# maximum angle (deg) between the measured and the surfel normal of a match
ASSOC_NORMAL_DEG = 35.0
# candidates within this fraction of the best confidence are tied; the one closest to the pixel's
# ray wins (Keller et al. 2013)
ASSOC_CONF_TIE_REL = 0.05
# a match updates position, normal, colour and radius only when its radius is below this times the
# surfel's (ElasticFusion: coarser measurements never blur finer surfels)
RADIUS_UPDATE_RATIO = 1.5
# a matching candidate that loses to a more confident one is merged into the winner when their
# centres are closer than this times the smaller radius (Keller et al. 2013); 0 disables merging
MERGE_RADIUS_FACTOR = 1.0
# an unmatched pixel within half a radius of a surfel centred in a neighbouring pixel adds no new
# surfel: without this about one mapped pixel in eight adds a duplicate every frame (12 % of a
# scanning frame's pixels; see covered_pixels)
SKIP_COVERED = True

# ---- free space
# free-space margin max(MapConfig.free_space_mm, FREE_SPACE_REL * depth), never below the
# association tolerance
FREE_SPACE_REL = 0.04
# confidence factor applied to a stable surfel violating free space (an unstable one is removed)
FREE_SPACE_DECAY = 0.5


@dataclass
class Measurement:
    """Per-pixel quantities of one input frame (camera frame, flattened to ``H*W``)."""

    points: torch.Tensor    # (HW, 3) mm
    normals: torch.Tensor   # (HW, 3) unit, facing the camera
    radius: torch.Tensor    # (HW,) mm
    weight: torch.Tensor    # (HW,) fusion weight (input weight x radial confidence)
    color: torch.Tensor     # (HW, 3)
    fuse: torch.Tensor      # (HW,) bool: fused (valid geometry, normal and weight > threshold)
    free_depth: torch.Tensor  # (HW,) measured depth usable for the free-space test, 0 elsewhere


@functools.lru_cache(maxsize=8)
def _rays(H: int, W: int, fx: float, fy: float, cx: float, cy: float, device: str):
    """Normalised image coordinates ``rx (1, W)``, ``ry (H, 1)`` of the pixel centres."""
    rx = ((torch.arange(W, dtype=torch.float32, device=device) - cx) / fx).view(1, W)
    ry = ((torch.arange(H, dtype=torch.float32, device=device) - cy) / fy).view(H, 1)
    return rx, ry


@functools.lru_cache(maxsize=8)
def radial_weight(H: int, W: int, cx: float, cy: float, sigma: float, device: str) -> torch.Tensor:
    """ElasticFusion's confidence ``exp(-d^2 / (2 sigma^2))``, ``d`` = distance from (cx, cy)
    normalised by the distance of the farthest image corner."""
    if sigma <= 0:
        return torch.ones(H, W, device=device)
    du = (torch.arange(W, dtype=torch.float32, device=device) - cx).view(1, W)
    dv = (torch.arange(H, dtype=torch.float32, device=device) - cy).view(H, 1)
    dmax2 = max(a * a + b * b for a in (-cx, W - 1 - cx) for b in (-cy, H - 1 - cy))
    d2 = (du * du + dv * dv) / max(dmax2, 1e-12)
    return torch.exp(-d2 / (2.0 * sigma * sigma))


def measure(depth: torch.Tensor, color: torch.Tensor, cam: Camera, cfg: MapConfig,
            weight: torch.Tensor | None = None, valid: torch.Tensor | None = None, *,
            min_fuse_weight: float = MIN_FUSE_WEIGHT) -> Measurement:
    """Back-projected points, normals, radii and fusion weights of one frame (pixels of fusion
    weight at most ``min_fuse_weight`` are not fused).

    Normals are the cross product of the central differences of the back-projected points
    ``P = z (rx, ry, 1)``; with ``z_u = (z[u+1] - z[u-1]) / 2`` and ``m_u = (z[u+1] + z[u-1]) / 2``
    (likewise along v) the differences are ``2 (z_u r + m_u / fx e_x)`` and ``2 (z_v r + m_v / fy e_y)``,
    whose cross product is, up to a positive factor,
    ``n = (fx z_u m_v, fy m_u z_v, -(rx n_x + ry n_y + m_u m_v))`` - facing the camera by construction
    (``n . r = -m_u m_v < 0``).  Computed on depth maps only, no per-pixel 3-vectors.
    """
    dev = cam.R_cw.device
    depth = torch.as_tensor(depth, dtype=torch.float32, device=dev)
    H, W = depth.shape
    if (H, W) != (cam.height, cam.width):
        raise ValueError(f"depth is {H}x{W}, camera is {cam.height}x{cam.width}")
    color = torch.as_tensor(color, dtype=torch.float32, device=dev)
    if color.shape != (3, H, W):
        raise ValueError(f"color must be (3, {H}, {W}), got {tuple(color.shape)}")
    ok = (depth >= cfg.min_depth_mm) & (depth <= cfg.max_depth_mm)      # False for NaN too
    if valid is not None:
        ok &= torch.as_tensor(valid, device=dev).bool()
    w = radial_weight(H, W, cam.cx, cam.cy, float(RADIAL_SIGMA), str(dev))
    if weight is not None:
        win = torch.as_tensor(weight, dtype=torch.float32, device=dev)
        w = w * torch.nan_to_num(win, nan=0.0).clamp(0.0, 1.0)
    ok &= w > min_fuse_weight
    rx, ry = _rays(H, W, cam.fx, cam.fy, cam.cx, cam.cy, str(dev))
    if kernels.use_compiled(cfg, dev):
        HW = H * W
        out = dict(points=torch.empty(HW, 3), normals=torch.empty(HW, 3), radius=torch.empty(HW),
                   weight=torch.empty(HW), fuse=torch.empty(HW, dtype=torch.bool), free_depth=torch.empty(HW))
        kernels.measure(depth.contiguous().numpy(), ok.contiguous().numpy(), w.contiguous().numpy(),
                        rx.reshape(-1).numpy(), ry.reshape(-1).numpy(), cam.fx, cam.fy,
                        float(NORMAL_MAX_JUMP_REL), float(RADIUS_MIN_COS),
                        RADIUS_SCALE * math.sqrt(2.0) / cam.f, *(x.numpy() for x in out.values()))
        return Measurement(color=to_rows(color.reshape(3, HW)), **out)
    z = torch.where(ok, depth, 0.0)

    nx = torch.zeros(H, W, device=dev)
    ny = torch.zeros(H, W, device=dev)
    nz = torch.zeros(H, W, device=dev)
    cos = torch.ones(H, W, device=dev)
    nvalid = torch.zeros(H, W, dtype=torch.bool, device=dev)
    if H >= 3 and W >= 3:
        c = (slice(1, -1), slice(1, -1))
        zl, zr = z[1:-1, :-2], z[1:-1, 2:]
        zt, zb = z[:-2, 1:-1], z[2:, 1:-1]
        zu, mu = (zr - zl) * 0.5, (zr + zl) * 0.5
        zv, mv = (zb - zt) * 0.5, (zb + zt) * 0.5
        zc = z[c]
        tol = NORMAL_MAX_JUMP_REL * zc
        good = (ok[c] & ok[1:-1, 2:] & ok[1:-1, :-2] & ok[2:, 1:-1] & ok[:-2, 1:-1]
                & ((zr - zc).abs() <= tol) & ((zc - zl).abs() <= tol)       # no depth jump on
                & ((zb - zc).abs() <= tol) & ((zc - zt).abs() <= tol))      # either side
        ax = cam.fx * zu * mv
        ay = cam.fy * mu * zv
        muv = mu * mv
        rxc, ryc = rx[:, 1:-1], ry[1:-1]
        az = -(torch.addcmul(torch.addcmul(muv, rxc, ax), ryc, ay))
        inv = torch.rsqrt((ax * ax + ay * ay + az * az).clamp_min(1e-30))
        inv = inv * good
        nx[c], ny[c], nz[c] = ax * inv, ay * inv, az * inv
        # |n . r_hat| = m_u m_v / (|a| |r|)
        cos[c] = muv * inv * torch.rsqrt(1.0 + rxc * rxc + ryc * ryc)
        nvalid[c] = good
    cos = cos.clamp(RADIUS_MIN_COS, 1.0)
    radius = (RADIUS_SCALE * math.sqrt(2.0) / cam.f) * z / cos

    HW = H * W
    P = torch.stack([rx * z, ry * z, z], dim=-1)
    return Measurement(points=P.view(HW, 3), normals=torch.stack([nx, ny, nz], -1).view(HW, 3),
                       radius=radius.view(HW), weight=torch.where(ok, w, 0.0).view(HW),
                       color=to_rows(color.reshape(3, HW)), fuse=(ok & nvalid).view(HW),
                       free_depth=z.view(HW))


def _rowsum(x: torch.Tensor) -> torch.Tensor:
    """``x.sum(1)`` for an ``(N, 3)`` tensor as a matrix-vector product (much faster on CPU)."""
    return x @ torch.ones(x.shape[1], dtype=x.dtype, device=x.device)


class StageTimer:
    """Milliseconds per stage (synchronising the device when enabled, no-op otherwise)."""

    def __init__(self, enabled: bool, device: torch.device):
        self.enabled = enabled
        self.cuda = device.type == "cuda"
        self.times: dict[str, float] = {}
        self._t = time.perf_counter() if enabled else 0.0

    def lap(self, name: str) -> None:
        if not self.enabled:
            return
        if self.cuda:
            torch.cuda.synchronize()
        t = time.perf_counter()
        self.times[name] = self.times.get(name, 0.0) + (t - self._t) * 1e3
        self._t = t


def fuse_frame(store: SurfelStore, cfg: MapConfig, cam: Camera, meas: Measurement, frame: int,
               timer: StageTimer | None = None, *, skip_covered: bool = SKIP_COVERED,
               active_from: int | None = None) -> dict:
    """Fuse one prepared frame into ``store``; returns stats (matched, added, removed, visible, ...).

    ``skip_covered``: unmatched pixels on a neighbour's disc add no surfel (:func:`covered_pixels`).
    ``active_from``: only surfels last fused at this frame or later are matched, updated or
    carved (the active model); the others stay as they are."""
    timer = timer or StageTimer(False, store.device)
    dev = store.device
    H, W = cam.height, cam.width
    HW = H * W
    s = int(INDEX_SCALE)
    cos_thr = math.cos(math.radians(ASSOC_NORMAL_DEG))

    # store maintenance first (it moves slots; the view cached at the end stays valid)
    store.edits += 1                                # matched surfels are updated in place below
    store.scratch.pop("view", None)
    if not store.maybe_compact() and SORT_CELL_MM > 0:
        store.sort_aged(SORT_CELL_MM, min_chunks=max(16, (1 << 16) // store.chunk_size))
    timer.lap("maintain")

    # the visible set includes the ring a render of this view needs (cached for it below); the
    # fusion itself only uses the surfels whose centre lies inside the image
    compiled = kernels.use_compiled(cfg, dev)
    vis = visible_set(store, cam, NEAR_MM, FAR_MM, margin_px=float(SPLAT_MAX_HALF), compiled=compiled,
                      seen_from=active_from)
    timer.lap("cull")

    matched_pix = torch.zeros(HW, dtype=torch.bool, device=dev)
    n_matched = 0
    removed = 0
    decayed = 0
    merged = 0
    n_visible = 0
    touched = None
    covered = torch.zeros(HW, dtype=torch.bool, device=dev)     # unmatched, on a neighbour's disc
    if len(vis) and compiled:
        matched_pix, covered, free_kill, merge_kill, touched, decayed, n_visible = _associate_compiled(
            store, cfg, cam, meas, vis, frame, skip_covered)
        removed += store.kill(free_kill)
        merged = store.kill(merge_kill)
        removed += merged
        n_matched = int(touched.numel())
        timer.lap("associate")
    elif len(vis):
        # pixel of every visible surfel (its centre lies inside the image) and its index-map cell
        fu = vis.u + 0.5
        fv = vis.v + 0.5
        outside = (fu < 0) | (fu >= W) | (fv < 0) | (fv >= H)
        n_visible = len(vis) - int(outside.sum())
        pu = fu.long().clamp_(0, W - 1)             # inside: fu, fv >= 0, truncation is floor
        pv = fv.long().clamp_(0, H - 1)
        pix_all = pv * W + pu
        # ---- free-space violations: surfels in front of the measured surface ---------------------
        # (tested first: a violator is seen through this frame, so it must neither occlude nor be
        # matched in the index map)
        D = take(meas.free_depth, pix_all)
        margin = torch.maximum(torch.clamp_min(FREE_SPACE_REL * D, cfg.free_space_mm),
                               torch.clamp_min(ASSOC_DEPTH_REL * D, ASSOC_DEPTH_MM))
        viol = (D > 0) & (vis.p[:, 2] < D - margin) & ~outside
        vslots = take(vis.slots, viol.nonzero().squeeze(1))
        if vslots.numel():
            vconf = take(store.conf, vslots)
            unstable = vconf < cfg.stable_confidence
            st = vslots[~unstable]
            store.conf.index_copy_(0, st, vconf[~unstable] * FREE_SPACE_DECAY)
            decayed = int(st.numel())
            removed += store.kill(vslots[unstable])
        timer.lap("free_space")

        # ---- index map and candidate pairs (pixel, surfel) -------------------------------------
        # the s x s cells of a pixel hold exactly the surfels whose centre falls in the pixel, so
        # the candidates of all pixels are the cell winners, each paired with its cell's pixel
        cu = (fu * s).long().clamp_(0, W * s - 1) - pu * s           # cell within the pixel, [0, s)
        cv = (fv * s).long().clamp_(0, H * s - 1) - pv * s
        cell = (pv * s + cv) * (W * s) + (pu * s + cu)
        win = cell_winners(cell, vis.p[:, 2], HW * s * s, exclude=viol | outside, scratch=store.scratch)
        cand = win.nonzero().squeeze(1)
        pix = take(pix_all, cand)
        # squared offset of the cell from the pixel centre (in half cells): distance to the ray
        a_off = take(cu, cand) * 2 - (s - 1)
        b_off = take(cv, cand) * 2 - (s - 1)
        dray = a_off * a_off + b_off * b_off
        timer.lap("index_map")

        # ---- association tests and best candidate per pixel ---------------------------------------
        q = take(meas.points, pix)
        nm = take(meas.normals, pix)
        ps = take(vis.p, cand)
        cslots = take(vis.slots, cand)
        ns = cam.rot_to_cam(take(store.normal, cslots))
        zm = q[:, 2]
        tol = torch.clamp_min(ASSOC_DEPTH_REL * zm, ASSOC_DEPTH_MM)
        ok = take(meas.fuse, pix) & ((ps[:, 2] - zm).abs() <= tol) & (_rowsum(ns * nm) >= cos_thr)
        conf = take(store.conf, cslots)
        best_conf = torch.full((HW,), -1.0, device=dev).scatter_reduce_(
            0, pix, torch.where(ok, conf, -1.0), reduce="amax")
        # most confident wins; near-ties go to the candidate closest to the pixel's ray
        tie = ok & (conf >= take(best_conf, pix) * (1.0 - ASSOC_CONF_TIE_REL))
        key = torch.add(torch.arange(pix.numel(), device=dev), dray, alpha=1 << 32)   # dray << 32 | i
        key = torch.where(tie, key, KEY_EMPTY)
        best = torch.full((HW,), KEY_EMPTY, dtype=torch.long, device=dev).scatter_reduce_(
            0, pix, key, reduce="amin")
        chosen_mask = tie & (key == take(best, pix))
        chosen = chosen_mask.nonzero().squeeze(1)
        if skip_covered:
            covered = covered_pixels(cam, meas, pix, take(vis.u, cand), take(vis.v, cand), ps,
                                     ns, take(store.radius, cslots), take(pix, chosen))
        if MERGE_RADIUS_FACTOR > 0:
            merged = merge_redundant(store, cfg, pix, ps, cslots, chosen, ok & ~chosen_mask, HW)
            removed += merged
        pix, q, nm, cslots = (take(x, chosen) for x in (pix, q, nm, cslots))
        timer.lap("associate")
        if pix.numel():
            # ---- running averages (each surfel has at most one pixel: its centre's) -------------
            w = take(meas.weight, pix)
            c = take(store.conf, cslots)
            r_old = take(store.radius, cslots)
            r_new = take(meas.radius, pix)
            upd = r_new <= RADIUS_UPDATE_RATIO * r_old
            a = torch.where(upd, w / (c + w).clamp_min(1e-12), 0.0)[:, None]
            p_old = take(store.pos, cslots)
            store.pos.index_copy_(0, cslots, p_old + a * (cam.to_world(q) - p_old))
            n_old = take(store.normal, cslots)
            n_new = n_old + a * (cam.rot_to_world(nm) - n_old)
            n_new = n_new * torch.rsqrt(_rowsum(n_new * n_new).clamp_min(1e-24))[:, None]
            store.normal.index_copy_(0, cslots, n_new)
            col_old = take(store.color, cslots)
            store.color.index_copy_(0, cslots, col_old + a * (take(meas.color, pix) - col_old))
            store.radius.index_copy_(0, cslots, r_old + a[:, 0] * (r_new - r_old))
            store.conf.index_copy_(0, cslots, torch.clamp_max(c + w, cfg.max_confidence))
            store.t_last.index_fill_(0, cslots, int(frame))
            matched_pix.index_fill_(0, pix, True)
            n_matched = int(pix.numel())
            touched = cslots
        timer.lap("update")

    # ---- new surfels from unmatched fusable pixels ---------------------------------------------------
    new = (meas.fuse & ~matched_pix & ~covered).nonzero().squeeze(1)
    if new.numel() > store.chunk_size:
        # append in image-tile order so every chunk covers a compact patch (tight chunk boxes)
        tile = max(8, int(math.sqrt(store.chunk_size)))
        v = torch.div(new, W, rounding_mode="floor")
        u = new - v * W
        tid = torch.div(v, tile, rounding_mode="floor") * ((W + tile - 1) // tile) + torch.div(
            u, tile, rounding_mode="floor")
        new = take(new, torch.sort(tid, stable=True).indices)
    new_slots = None
    if new.numel():
        new_slots = store.append(cam.to_world(take(meas.points, new)),
                                 cam.rot_to_world(take(meas.normals, new)), take(meas.radius, new),
                                 take(meas.color, new), take(meas.weight, new), int(frame))
    n_added = int(new.numel())
    timer.lap("add")

    # ---- unstable surfels reaching the end of their time window ---------------------------------------
    removed += age_out(store, cfg, frame)
    if touched is not None and touched.numel() and not compiled:     # (the kernel grew them)
        store.grow_boxes(touched)
    # a render of this very view (the usual next call) starts from these slots
    cand = vis.slots if new_slots is None else torch.cat([vis.slots, new_slots])
    store.scratch["view"] = (cam.key, store.version, cand)
    timer.lap("clean")
    return {"matched": n_matched, "added": n_added, "removed": removed, "merged": merged,
            "decayed": decayed, "visible": n_visible, "surfels": store.num_alive}


def _associate_compiled(store: SurfelStore, cfg: MapConfig, cam: Camera, meas: Measurement, vis,
                        frame: int, skip_covered: bool):
    """Free-space test, index map, association, merging and update by the compiled kernel
    (:func:`mapping.kernels.associate_and_update`, CPU); returns torch tensors
    ``(matched_pix, covered, free_kill, merge_kill, touched)`` and the counts ``decayed, n_visible``."""
    H, W = cam.height, cam.width
    np_ = lambda x: x.contiguous().numpy()           # noqa: E731 - views of CPU tensors
    out = kernels.associate_and_update(
        np_(vis.slots), np_(vis.p), np_(vis.u), np_(vis.v),
        np_(meas.points), np_(meas.normals), np_(meas.radius), np_(meas.weight), np_(meas.color),
        np_(meas.fuse), np_(meas.free_depth),
        store.pos.numpy(), store.normal.numpy(), store.radius.numpy(), store.color.numpy(),
        store.conf.numpy(), store.t_last.numpy(), store.box_lo.numpy(), store.box_hi.numpy(), store.chunk_size,
        np_(cam.R_cw), np_(cam.R_wc), np_(cam.t_wc), H, W, int(INDEX_SCALE),
        float(FREE_SPACE_REL), float(cfg.free_space_mm), float(ASSOC_DEPTH_REL),
        float(ASSOC_DEPTH_MM), math.cos(math.radians(ASSOC_NORMAL_DEG)),
        float(ASSOC_CONF_TIE_REL), float(MERGE_RADIUS_FACTOR), float(cfg.stable_confidence),
        float(FREE_SPACE_DECAY), float(RADIUS_UPDATE_RATIO), float(cfg.max_confidence), int(frame),
        bool(skip_covered), cam.f)
    matched_pix, covered, free_kill, merge_kill, touched, decayed, n_visible = out
    return (torch.from_numpy(matched_pix), torch.from_numpy(covered), torch.from_numpy(free_kill),
            torch.from_numpy(merge_kill), torch.from_numpy(touched), int(decayed), int(n_visible))


def covered_pixels(cam: Camera, meas: Measurement, pix: torch.Tensor, u: torch.Tensor, v: torch.Tensor,
                   ps: torch.Tensor, ns: torch.Tensor, radius: torch.Tensor, matched: torch.Tensor) -> torch.Tensor:
    """``(HW,)`` bool: fusable pixels without a match that lie within half the radius (about a
    pixel) of a candidate centred in one of their 8 neighbours and pass the association tests
    against it (depth and normal).

    Association only pairs a pixel with the surfels whose centre falls inside it; about one pixel
    in eight of a mapped surface holds none (the centres are scattered), and each would add a
    duplicate surfel every frame.  Such a pixel is already represented by its neighbour's surfel
    (the renderer shows that surfel there), so it adds nothing (:data:`SKIP_COVERED`).

    Args: the candidates (cell winners) - their pixel ``pix``, projected centre ``u, v``,
    camera-frame position ``ps`` and normal ``ns``, radius - and the matched pixels ``matched``.
    """
    H, W = cam.height, cam.width
    HW = H * W
    dev = pix.device
    free = meas.fuse.clone()
    free[matched] = False
    pu, pv = pix % W, torch.div(pix, W, rounding_mode="floor")
    r_px2 = (0.5 * radius * cam.f / ps[:, 2]).square()      # half the radius: about one pixel
    cos_thr = math.cos(math.radians(ASSOC_NORMAL_DEG))
    covered = torch.zeros(HW, dtype=torch.bool, device=dev)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dx == 0 and dy == 0:
                continue
            nu, nv = pu + dx, pv + dy
            inside = (nu >= 0) & (nu < W) & (nv >= 0) & (nv < H)
            p = nv.clamp(0, H - 1) * W + nu.clamp(0, W - 1)
            zm = take(meas.points, p)[:, 2]
            tol = torch.clamp_min(ASSOC_DEPTH_REL * zm, ASSOC_DEPTH_MM)
            hit = (inside & take(free, p) & ((nu - u).square() + (nv - v).square() <= r_px2)
                   & ((ps[:, 2] - zm).abs() <= tol) & (_rowsum(ns * take(meas.normals, p)) >= cos_thr))
            covered[take(p, hit.nonzero().squeeze(1))] = True
    return covered


def merge_redundant(store: SurfelStore, cfg: MapConfig, pix: torch.Tensor, ps: torch.Tensor,
                    cslots: torch.Tensor, chosen: torch.Tensor, losers: torch.Tensor, HW: int) -> int:
    """Merge matching candidates that were not chosen into their pixel's chosen surfel.

    A candidate passing the association tests but losing to a more confident surfel of the same
    pixel is redundant when its centre lies within ``MERGE_RADIUS_FACTOR x min(radii)`` of the
    winner (Keller et al. 2013, merging of similar points): the winner takes the confidence-weighted
    average of both and the sum of their confidences, the loser is removed.  Keeps the surfel
    count proportional to the observed area when the camera moves.
    """
    others = losers.nonzero().squeeze(1)
    if others.numel() == 0:
        return 0
    dev = pix.device
    owner = torch.full((HW,), -1, dtype=torch.long, device=dev)
    owner.index_copy_(0, take(pix, chosen), chosen)
    b = take(owner, take(pix, others))                      # every pixel with candidates has a winner
    o_slots, b_slots = take(cslots, others), take(cslots, b)
    dd = take(ps, others) - take(ps, b)
    dist = torch.sqrt(_rowsum(dd * dd))
    reach = MERGE_RADIUS_FACTOR * torch.minimum(take(store.radius, o_slots), take(store.radius, b_slots))
    sel = (dist <= reach).nonzero().squeeze(1)
    if sel.numel() == 0:
        return 0
    o_slots, b_slots = take(o_slots, sel), take(b_slots, sel)
    tgt, inv = torch.unique(b_slots, return_inverse=True)
    m = tgt.numel()
    c_o = take(store.conf, o_slots)
    c_t = take(store.conf, tgt)
    csum = torch.zeros(m, device=dev).index_add_(0, inv, c_o) + c_t

    def blend(arr: torch.Tensor) -> torch.Tensor:
        src = take(arr, o_slots)
        w = c_o.view(-1, *([1] * (src.dim() - 1)))
        acc = torch.zeros((m,) + tuple(src.shape[1:]), device=dev).index_add_(0, inv, src * w)
        ct = c_t.view(-1, *([1] * (src.dim() - 1)))
        cs = csum.view(-1, *([1] * (src.dim() - 1))).clamp_min(1e-12)
        return (acc + take(arr, tgt) * ct) / cs

    store.pos.index_copy_(0, tgt, blend(store.pos))
    nrm = blend(store.normal)
    store.normal.index_copy_(0, tgt, nrm / nrm.norm(dim=1, keepdim=True).clamp_min(1e-12))
    store.color.index_copy_(0, tgt, blend(store.color))
    store.radius.index_copy_(0, tgt, blend(store.radius))
    t_last = torch.zeros(m, dtype=store.t_last.dtype, device=dev).scatter_reduce_(
        0, inv, take(store.t_last, o_slots), reduce="amax", include_self=False)
    store.t_last.index_copy_(0, tgt, torch.maximum(take(store.t_last, tgt), t_last))
    store.conf.index_copy_(0, tgt, csum.clamp_max(cfg.max_confidence))
    return store.kill(o_slots)


def age_out(store: SurfelStore, cfg: MapConfig, frame: int) -> int:
    """Remove unstable surfels created at least ``unstable_window`` frames before ``frame``."""
    start, n = store.aged_upto, store.n
    if start >= n:
        return 0
    cutoff = int(frame) - int(cfg.unstable_window)
    t = store.t_init[start:n]
    end = start + int(torch.searchsorted(t, torch.tensor([cutoff], dtype=t.dtype, device=t.device),
                                         right=True)[0])
    if end <= start:
        return 0
    seg = torch.arange(start, end, device=store.device)
    bad = seg[store.alive[start:end] & (store.conf[start:end] < cfg.stable_confidence)]
    store.aged_upto = end
    return store.kill(bad)
