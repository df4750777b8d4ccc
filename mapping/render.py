"""View culling, the splatting renderer and the super-sampled index map.

Everything is vectorised over surfels: the visible set is found by testing the chunk bounding
boxes of :class:`mapping.surfels.SurfelStore` against the frustum, then the surfels of the
surviving chunks individually.  The renderer expands every visible surfel into the pixels of its
projected footprint (at most ``(2 h + 1)^2``, grouped by footprint size) and takes the depth of
each pixel from the ray's intersection with the surfel's plane (exact, sub-pixel).  Pass 1
z-buffers with one ``scatter_reduce`` on an int64 key ``(stable, quantised inverse depth) << 32 |
surfel`` (the front surface; a pixel's depth is its front surfel's plane depth); pass 2 blends the
colour of the surfels of that surface with weights falling off with the distance from the pixel
centre to each surfel's projected centre (``scatter_add``), so the view is sharp and sub-pixel
exact (surface splatting).
The index map used by the fusion is a super-sampled depth buffer z-tested with ``scatter_reduce``.
On a CPU map the per-surfel coefficients and the two splatting passes run compiled
(:mod:`mapping.kernels`, same formulas).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Callable

import torch

from . import kernels
from .config import MapConfig
from .surfels import SurfelStore, take, to_columns

KEY_EMPTY = torch.iinfo(torch.int64).max
_ID_MASK = (1 << 32) - 1
_Q_MAX = (1 << 30) - 1       # quantised inverse depth range of the z-buffer keys
_CHUNK = 1 << 17             # splat entries evaluated at a time

# near and far clipping distances (mm) of the renderer and of the view culling: the endoscope sees
# tissue 20-200 mm away (MapConfig's depth range), with room on both sides
NEAR_MM = 5.0
FAR_MM = 400.0
# the renderer splats a surfel into at most a (2 * SPLAT_MAX_HALF + 1)^2 pixel footprint (3 -> 7x7);
# also the margin (px) of the view culling, so that surfels centred just outside still render
SPLAT_MAX_HALF = 3
# footprint half-size is floor(R + SPLAT_ROUND) pixels for a footprint radius R (0.5 = every pixel
# the footprint can touch; 0.25 is faster and the neighbouring discs of a surface still close every gap)
SPLAT_ROUND = 0.25
# surfels seen at |n . ray| below this are splatted only into their centre pixel, at their centre
# depth (ray/plane intersection is ill-conditioned at grazing angles)
RENDER_MIN_COS = 0.05
# the blending pass takes, per pixel, the surfels of the front's class whose plane depth lies within
# max(RENDER_DEPTH_TOL_MM, RENDER_DEPTH_TOL_REL * depth) behind the front (the visible surface;
# occluded surfaces lie farther behind)
RENDER_DEPTH_TOL_MM = 1.0
RENDER_DEPTH_TOL_REL = 0.02
# width of the blending kernel relative to the footprint radius R: weight (1 - d^2 / R^2)^k,
# k = round(1 / (2 sigma^2)) = 4, about a Gaussian of sigma * R px (smaller: jagged, larger: blurred)
RENDER_BLEND_SIGMA = 0.35
# unstable surfels whose footprint stable ones cover are not splatted at all (they would not show):
# on a scanning run about 15 % less render time (paired runs)
RENDER_CULL_HIDDEN_UNSTABLE = True


@dataclass
class ModelView:
    """The map rendered from one camera.

    Attributes:
        color: ``(3, H, W)`` float32 RGB in [0, 1] (0 where empty; all 0 if rendered without colour).
        depth: ``(H, W)`` float32 depth along the optical axis, mm (0 where empty).
        normals: ``(3, H, W)`` float32 unit normals in the camera frame (0 where empty).
        confidence: ``(H, W)`` float32 confidence of the visible surfel (0 where empty).
        valid: ``(H, W)`` bool, True where a surfel covers the pixel.
        index: ``(H, W)`` int64 slot of the visible surfel, -1 where empty (valid until the
            map is next modified).
        pending_colour: set when rendered without colour: computes it (see :meth:`with_colour`).
    """

    color: torch.Tensor
    depth: torch.Tensor
    normals: torch.Tensor
    confidence: torch.Tensor
    valid: torch.Tensor
    index: torch.Tensor
    pending_colour: Callable[[], torch.Tensor] | None = field(default=None, repr=False)

    def with_colour(self) -> "ModelView":
        """Fill ``color`` of a view rendered with ``colour=False`` (the blending pass, run only now:
        a caller that may not use the colour skips it).  The map must not have changed since."""
        if self.pending_colour is not None:
            self.color = self.pending_colour()
            self.pending_colour = None
        return self

    def coverage(self) -> float:
        """Fraction of the pixels covered by the map."""
        return float(self.valid.float().mean()) if self.valid.numel() else 0.0

    def points(self, K: torch.Tensor) -> torch.Tensor:
        """``(3, H, W)`` camera-frame points back-projected from ``depth`` with intrinsics ``K``."""
        H, W = self.depth.shape
        K = torch.as_tensor(K, dtype=torch.float32, device=self.depth.device)
        v, u = torch.meshgrid(torch.arange(H, device=self.depth.device, dtype=torch.float32),
                              torch.arange(W, device=self.depth.device, dtype=torch.float32), indexing="ij")
        x = (u - K[0, 2]) / K[0, 0] * self.depth
        y = (v - K[1, 2]) / K[1, 1] * self.depth
        return torch.stack([x, y, self.depth])

    @staticmethod
    def empty(height: int, width: int, device: torch.device) -> "ModelView":
        z = torch.zeros(height, width, device=device)
        return ModelView(color=torch.zeros(3, height, width, device=device), depth=z.clone(),
                         normals=torch.zeros(3, height, width, device=device), confidence=z.clone(),
                         valid=torch.zeros(height, width, dtype=torch.bool, device=device),
                         index=torch.full((height, width), -1, dtype=torch.long, device=device))


@dataclass
class Camera:
    """A pinhole camera at a pose: intrinsics, image size and the world-to-camera transform."""

    fx: float
    fy: float
    cx: float
    cy: float
    height: int
    width: int
    R_cw: torch.Tensor   # (3, 3) float32
    t_cw: torch.Tensor   # (3,) float32
    R_wc: torch.Tensor   # (3, 3) float32
    t_wc: torch.Tensor   # (3,) float32

    @staticmethod
    def make(K, T_wc, height: int, width: int, device: torch.device) -> "Camera":
        K = torch.as_tensor(K, dtype=torch.float64).cpu()
        T = torch.as_tensor(T_wc, dtype=torch.float64).cpu()
        if K.shape != (3, 3) or T.shape != (4, 4):
            raise ValueError(f"K must be (3, 3) and T_wc (4, 4), got {tuple(K.shape)} and {tuple(T.shape)}")
        R_wc, t_wc = T[:3, :3], T[:3, 3]
        R_cw = R_wc.T
        t_cw = -R_cw @ t_wc
        f32 = dict(dtype=torch.float32, device=device)
        return Camera(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                      height=int(height), width=int(width),
                      R_cw=R_cw.to(**f32), t_cw=t_cw.to(**f32), R_wc=R_wc.to(**f32), t_wc=t_wc.to(**f32),
                      key=(int(height), int(width), *K.reshape(-1).tolist(), *T.reshape(-1).tolist()))

    key: tuple = ()      # identifies intrinsics, image size and pose (view caching)

    @property
    def f(self) -> float:
        return 0.5 * (self.fx + self.fy)

    def to_cam(self, p: torch.Tensor) -> torch.Tensor:
        """World ``(..., 3)`` -> camera frame."""
        return p @ self.R_cw.T + self.t_cw

    def rot_to_cam(self, n: torch.Tensor) -> torch.Tensor:
        return n @ self.R_cw.T

    def to_world(self, p: torch.Tensor) -> torch.Tensor:
        return p @ self.R_wc.T + self.t_wc

    def rot_to_world(self, n: torch.Tensor) -> torch.Tensor:
        return n @ self.R_wc.T


@dataclass
class VisibleSet:
    """Surfels inside a camera's frustum.

    Attributes:
        slots: ``(V,)`` int64 store slots.
        p: ``(V, 3)`` camera-frame positions.
        u, v: ``(V,)`` projected centre in pixels.
    """

    slots: torch.Tensor
    p: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor

    def __len__(self) -> int:
        return int(self.slots.numel())


def _frustum_slopes(cam: Camera, margin_px: float) -> tuple[float, float, float, float]:
    """``x / z`` and ``y / z`` bounds of the image rectangle grown by ``margin_px``."""
    return ((-0.5 - margin_px - cam.cx) / cam.fx, (cam.width - 0.5 + margin_px - cam.cx) / cam.fx,
            (-0.5 - margin_px - cam.cy) / cam.fy, (cam.height - 0.5 + margin_px - cam.cy) / cam.fy)


def _culled_chunk_ids(store: SurfelStore, cam: Camera, near: float, far: float, margin_px: float) -> torch.Tensor:
    """Int64 ids of the chunks :func:`cull_chunks` keeps, by the compiled kernel (CPU store)."""
    nch = store.num_chunks
    ids = kernels.cull_chunks(store.box_lo[:nch].numpy(), store.box_hi[:nch].numpy(),
                              cam.R_cw.contiguous().numpy(), cam.t_cw.numpy(), near, far,
                              *_frustum_slopes(cam, margin_px))
    return torch.from_numpy(ids)


def cull_chunks(store: SurfelStore, cam: Camera, near: float, far: float, margin_px: float,
                compiled: bool = False) -> torch.Tensor:
    """Bool mask over the used chunks whose bounding box may intersect the view frustum.

    The frustum is the image rectangle grown by ``margin_px`` on each side between ``near`` and
    ``far``; a box is culled when all 8 corners lie outside one of its 6 planes.  ``compiled``:
    by :func:`mapping.kernels.cull_chunks` (CPU store).
    """
    nch = store.num_chunks
    if compiled:
        ids = _culled_chunk_ids(store, cam, near, far, margin_px)
        return torch.zeros(nch, dtype=torch.bool).index_fill_(0, ids, True)
    lo, hi = store.box_lo[:nch], store.box_hi[:nch]
    xmin, xmax, ymin, ymax = _frustum_slopes(cam, margin_px)
    finite = torch.isfinite(lo).all(dim=1) & torch.isfinite(hi).all(dim=1)
    lo = torch.where(finite[:, None], lo, 0.0)
    hi = torch.where(finite[:, None], hi, 0.0)
    sel = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=torch.bool,
                       device=lo.device)
    corners = torch.where(sel[None], hi[:, None, :], lo[:, None, :])          # (B, 8, 3)
    c = cam.to_cam(corners)
    x, y, z = c.unbind(-1)
    outside = ((z < near).all(1) | (z > far).all(1)
               | (x < xmin * z).all(1) | (x > xmax * z).all(1)
               | (y < ymin * z).all(1) | (y > ymax * z).all(1))
    return finite & ~outside


def seen_mask(store: SurfelStore, seen_from: int | None, seen_before: int | None) -> torch.Tensor:
    """``(capacity,)`` bool: live surfels last fused at a frame in ``[seen_from, seen_before)``
    (an open end where None)."""
    n = store.n
    mask = store.alive.clone()
    if seen_from is not None:
        mask[:n] &= store.t_last[:n] >= int(seen_from)
    if seen_before is not None:
        mask[:n] &= store.t_last[:n] < int(seen_before)
    return mask


def visible_set(store: SurfelStore, cam: Camera, near: float, far: float, margin_px: float = 0.0,
                stable_threshold: float | None = None, candidates: torch.Tensor | None = None,
                compiled: bool = False, seen_from: int | None = None,
                seen_before: int | None = None) -> VisibleSet:
    """Live surfels whose centre projects inside the image grown by ``margin_px``, depth in [near, far].

    ``stable_threshold``: keep only surfels with at least this confidence.
    ``candidates``: slots known to contain every such surfel (skips the chunk culling).
    ``compiled``: test the surfels with :func:`mapping.kernels.visible_surfels` (CPU store).
    ``seen_from``, ``seen_before``: keep only surfels last fused at a frame in
    ``[seen_from, seen_before)`` (the active or the inactive model; an open end where None).
    """
    filtered = seen_from is not None or seen_before is not None
    dev = store.device
    if store.n == 0:
        e = torch.zeros(0, device=dev)
        return VisibleSet(torch.zeros(0, dtype=torch.long, device=dev), torch.zeros(0, 3, device=dev), e, e)
    if compiled:
        none = torch.zeros(0, dtype=torch.long)
        chunks = _culled_chunk_ids(store, cam, near, far, margin_px) if candidates is None else none
        out = kernels.visible_surfels(
            chunks.numpy(), (none if candidates is None else candidates).numpy(), store.chunk_size, store.n,
            (seen_mask(store, seen_from, seen_before) if filtered else store.alive).numpy(), store.conf.numpy(), store.pos.numpy(), cam.R_cw.contiguous().numpy(), cam.t_cw.numpy(),
            cam.fx, cam.fy, cam.cx, cam.cy, near, far, -0.5 - margin_px, cam.width - 0.5 + margin_px,
            -0.5 - margin_px, cam.height - 0.5 + margin_px,
            -float("inf") if stable_threshold is None else float(stable_threshold))
        return VisibleSet(*(torch.from_numpy(x) for x in out))
    if candidates is None:
        slots = store.chunk_candidates(cull_chunks(store, cam, near, far, margin_px))
    else:
        slots = take(candidates, take(store.alive, candidates).nonzero().squeeze(1))
    if stable_threshold is not None and slots.numel():
        slots = take(slots, (take(store.conf, slots) >= stable_threshold).nonzero().squeeze(1))
    if filtered and slots.numel():
        slots = take(slots, take(seen_mask(store, seen_from, seen_before), slots).nonzero().squeeze(1))
    p = cam.to_cam(take(store.pos, slots))
    z = p[:, 2]
    zs = z.clamp_min(1e-6)
    u = p[:, 0] / zs * cam.fx + cam.cx
    v = p[:, 1] / zs * cam.fy + cam.cy
    keep = ((z >= near) & (z <= far)
            & (u >= -0.5 - margin_px) & (u < cam.width - 0.5 + margin_px)
            & (v >= -0.5 - margin_px) & (v < cam.height - 0.5 + margin_px))
    idx = keep.nonzero().squeeze(1)
    return VisibleSet(take(slots, idx), take(p, idx), take(u, idx), take(v, idx))


def index_map(vis: VisibleSet, cam: Camera, scale: int, exclude: torch.Tensor | None = None,
              scratch: dict | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Super-sampled index map: each of the ``(scale*H) x (scale*W)`` cells keeps its nearest surfel.

    Returns ``(cell, win)``: ``cell`` ``(V,)`` int64 linear cell of each surfel (-1 outside the
    image or excluded) and ``win`` ``(V,)`` bool, True for the nearest surfel of its cell.
    See :func:`cell_winners` for ``exclude`` and ``scratch``.
    """
    Hs, Ws = cam.height * scale, cam.width * scale
    cu = torch.floor((vis.u + 0.5) * scale).long()
    cv = torch.floor((vis.v + 0.5) * scale).long()
    inside = (cu >= 0) & (cu < Ws) & (cv >= 0) & (cv < Hs)
    if exclude is not None:
        inside &= ~exclude
    cell = torch.where(inside, cv * Ws + cu, -1)
    return cell, cell_winners(cell, vis.p[:, 2], Hs * Ws, scratch=scratch)


def cell_winners(cell: torch.Tensor, z: torch.Tensor, num_cells: int, exclude: torch.Tensor | None = None,
                 scratch: dict | None = None) -> torch.Tensor:
    """Z-test of points in an index map: True for the nearest point of each cell.

    The index map is a float depth buffer z-tested with one ``scatter_reduce(amin)``; instead of
    reading ids back per cell, every point checks whether it is the one its cell kept.

    Args:
        cell: ``(V,)`` int64 linear cell per point, -1 = not in the map.
        z: ``(V,)`` depth per point.
        num_cells: size of the map.
        exclude: optional ``(V,)`` bool of points left out of the map.
        scratch: optional dict holding a persistent ``+inf`` buffer between calls (only the touched
            cells are reset, so the cost follows the points, not the map resolution).
    """
    dev = z.device
    inside = cell >= 0
    if exclude is not None:
        inside = inside & ~exclude
    idx = inside.nonzero().squeeze(1)
    c_in = take(cell, idx)
    z_in = take(z.contiguous(), idx)
    key = ("index_map", num_cells)
    buf = scratch.get(key) if scratch is not None else None
    if buf is None:
        buf = torch.full((num_cells,), float("inf"), device=dev)
        if scratch is not None:
            for k in [k for k in scratch if isinstance(k, tuple) and k[0] == "index_map"]:
                del scratch[k]                        # one index-map size at a time
            scratch[key] = buf
    buf.scatter_reduce_(0, c_in, z_in, reduce="amin")
    win = torch.zeros(cell.shape[0], dtype=torch.bool, device=dev)
    win.index_copy_(0, idx, take(buf, c_in) == z_in)
    buf.index_fill_(0, c_in, float("inf"))          # leave the scratch buffer clean
    return win


def _kernel_power(sigma: float) -> int:
    """Exponent ``k`` of the blending kernel ``(1 - d^2 / R^2)^k`` ~ ``exp(-k d^2 / R^2)``: a bell of
    width ``sigma * R`` for ``k = 1 / (2 sigma^2)`` (rounded; 4 for the default 0.35)."""
    return max(1, int(round(0.5 / (sigma * sigma))))


def _int_pow_(x: torch.Tensor, k: int) -> torch.Tensor:
    """``x ** k`` in place for an integer ``k >= 1`` by repeated squaring (``pow`` is ~8x slower)."""
    if k == 1:
        return x
    rest = x.clone() if k & 1 else None
    x = _int_pow_(x.square_(), k >> 1)
    return x.mul_(rest) if rest is not None else x


def _coefficients_compiled(store: SurfelStore, vis: VisibleSet, cam: Camera, cfg: MapConfig, q_scale: float,
                           k_pow: int, pad: int, Wp: int) -> tuple:
    """:func:`splat`'s per-surfel quantities by :func:`mapping.kernels.splat_coefficients` (CPU):
    ``n (V, 3), conf (V,), coef (7, V), half (V,), base (1, V), stab (1, V), c4 (1, V)``."""
    V = len(vis)
    n, conf, half, stab, c4 = torch.empty(V, 3), torch.empty(V), torch.empty(V, dtype=torch.long), \
        torch.empty(V), torch.empty(V)
    coef, base = torch.empty(7, V), torch.empty(V, dtype=torch.long)
    kernels.splat_coefficients(
        vis.slots.numpy(), vis.p.contiguous().numpy(), vis.u.contiguous().numpy(), vis.v.contiguous().numpy(),
        store.normal.numpy(), store.radius.numpy(), store.conf.numpy(), cam.R_cw.contiguous().numpy(),
        cam.fx, cam.fy, cam.cx, cam.cy, cam.f, q_scale, float(RENDER_MIN_COS), float(SPLAT_ROUND),
        int(SPLAT_MAX_HALF), float(cfg.stable_confidence), 1.0 / k_pow, pad, Wp,
        n.numpy(), conf.numpy(), coef.numpy(), half.numpy(), base.numpy(), stab.numpy(), c4.numpy())
    return n, conf, coef, half, base[None, :], stab[None, :], c4[None, :]


def _coefficients_torch(store: SurfelStore, vis: VisibleSet, cam: Camera, cfg: MapConfig, q_scale: float,
                        k_pow: int, pad: int, Wp: int) -> tuple:
    """:func:`splat`'s per-surfel quantities (any device): ``n (V, 3), conf (V,), coef (ncoef, V),
    monos, half (V,), base (1, V), stab (1, V), c4 (1, V)``; ``monos``: per block of ``coef``'s rows,
    the monomials of the pixel offset they multiply."""
    slots = vis.slots
    hmax = int(SPLAT_MAX_HALF)
    n = cam.rot_to_cam(take(store.normal, slots))
    r = take(store.radius, slots)
    conf = take(store.conf, slots)
    # per-surfel quantities as contiguous rows (structure of arrays)
    px, py, pz = to_columns(vis.p)
    nx, ny, nz = to_columns(n)
    uc = torch.round(vis.u)
    vc = torch.round(vis.v)
    rx0 = (uc - cam.cx) / cam.fx                              # centre pixel ray (rx0, ry0, 1)
    ry0 = (vc - cam.cy) / cam.fy
    # inverse depth at pixel offset (ox, oy) = (n . ray) / (n . p), affine in (ox, oy); scaled to
    # the z-buffer's 30-bit integer range right away (depth >= near / 4 fits)
    den0 = torch.addcmul(torch.addcmul(nz, nx, rx0), ny, ry0)
    ndp = torch.addcmul(torch.addcmul(nz * pz, nx, px), ny, py)
    # |n . ray| / |ray| at the centre pixel; grazing surfels (small): centre pixel only, at the
    # centre depth (ray-disc intersection is ill-conditioned there)
    cos_v = den0.abs() * torch.rsqrt(torch.addcmul(torch.addcmul(torch.ones_like(rx0), rx0, rx0), ry0, ry0))
    good = cos_v >= RENDER_MIN_COS
    scale = torch.where(good, q_scale / ndp, 0.0)
    L0 = torch.where(good, den0 * scale, q_scale / pz)
    L1 = nx * scale * (1.0 / cam.fx)
    L2 = ny * scale * (1.0 / cam.fy)
    r_px = r * cam.f / pz
    # the disc's image is an ellipse of half-axes ~ r_px and r_px |cos|; the circle of equal
    # area (the fusion enlarges oblique radii by 1 / |cos|: splatting that isotropically would
    # smear oblique surfels over their neighbours)
    R_fp = r_px * torch.sqrt(cos_v.clamp(RENDER_MIN_COS, 1.0))
    # t = 1 - d^2 / R^2 with d^2 = ox^2 + oy^2 - 2 du ox - 2 dv oy + du^2 + dv^2
    du = vis.u - uc
    dv = vis.v - vc
    g = -1.0 / (R_fp * R_fp)
    t0 = torch.addcmul(torch.ones_like(g), g, torch.addcmul(du * du, dv, dv))
    rows = [t0, -2.0 * g * du, -2.0 * g * dv, g]
    monos = [("1", "x", "y", "rr")]                           # block 0: t
    rows += [L0, L1, L2]
    monos.append(("1", "x", "y"))                             # block 1: inverse depth
    coef = torch.stack(rows)                                  # (ncoef, V)
    # blending weight (c^(1/k) t)^k: kernel exponent k ~ 1 / (2 sigma^2) (a bell of ~ sigma R) and
    # the confidence factor c as its k-th root
    c4 = (conf.clamp(1e-4, cfg.stable_confidence) * (1.0 / cfg.stable_confidence)).pow_(1.0 / k_pow)[None, :]
    # stable surfels' z-buffer values are raised by 2^30 (above any quantised inverse depth)
    stab = torch.where(conf >= cfg.stable_confidence, float(_Q_MAX + 1), 0.0)[None, :]

    half = torch.where(good, torch.floor(R_fp + SPLAT_ROUND), 0.0).clamp(0, hmax).long()
    base = ((vc.long() + pad) * Wp + (uc.long() + pad))[None, :]   # padded pixel of the centre
    return n, conf, coef, monos, half, base, stab, c4


def splat(store: SurfelStore, vis: VisibleSet, cam: Camera, cfg: MapConfig, colour: bool = True, *,
          cull_hidden_unstable: bool = RENDER_CULL_HIDDEN_UNSTABLE) -> ModelView:
    """Two-pass surface splatting of the visible surfels into a ``(H, W)`` view.

    ``colour=False`` skips the colour (``ModelView.color`` is all zero until
    ``ModelView.with_colour()`` runs the blending pass): tracking that takes its image from the
    last real frame needs only the model's depth, and a caller that may not use the view (a
    coverage check first) pays for the blending only when it does.

    Every surfel is expanded into the ``(2h + 1)^2`` pixel offsets ``(ox, oy)`` around its centre
    pixel (``h`` from its footprint radius, surfels grouped by ``h``).  For an offset, the inverse
    depth of the pixel ray's intersection with the surfel's plane is affine in ``(ox, oy)`` (exact
    sub-pixel depth on the disc's plane) and ``t = 1 - d^2 / R^2`` is a quadratic, ``d`` the
    distance from the pixel centre to the projected surfel centre and ``R`` the footprint radius:
    the footprint is the circle ``t >= 0`` of the same area as the disc's image ellipse
    (``R = r_px sqrt(|cos|)``, ``r_px`` the projected radius; cheap, and the depth is still exact on
    the disc's plane).  The coefficients are computed once per surfel, and one small
    matrix product against the monomials of the offsets evaluates every entry.  The centre pixel of
    every surfel is always covered, so no surfel vanishes between pixel centres.  The buffers are
    padded so no bounds tests are needed per entry.

    Pass 1 (visibility) z-buffers the footprints with one ``scatter_reduce(amax)`` over int64 keys
    ``(stable * 2^30 + quantised inverse depth) << 32 | surfel``: the front surface of every pixel
    and its front-most surfel (``index``, ``normals``, ``confidence``); a pixel's depth is the
    front surfel's plane depth along its ray (exact sub-pixel depth of the disc the pixel sees; it
    tracks at least as well as a blended depth: mean ATE 0.43 vs 0.47 mm over four sequences, and
    a depth-only render needs no blending pass).  Stable surfels (confidence
    >= ``stable_confidence``) take precedence: unstable ones (fresh, or noise not yet removed) only
    show where no stable surfel covers the pixel, as in ElasticFusion's model prediction (with
    ``cull_hidden_unstable`` the stable surfels are z-buffered first and unstable ones whose
    footprint they cover are not splatted at all).  Pass 2
    (blending) keeps, per pixel, the entries of the front's class (stable or not) within
    ``max(RENDER_DEPTH_TOL_MM, RENDER_DEPTH_TOL_REL * depth)`` behind the front depth - the surfels
    of the visible surface - and averages their colour with the weights
    ``min(conf / stable_confidence, 1) * t^k`` (a compact bell, ~ a Gaussian of sigma
    ``RENDER_BLEND_SIGMA * R``, ``k = 1 / (2 RENDER_BLEND_SIGMA^2)``: 4 by default), normalised per
    pixel (``scatter_add``).  A pixel thus takes its colour from the surfels centred
    near it, interpolated, instead of from whichever overlapping disc happens to lie in front
    (which shifts and jitters the image by up to a splat radius).

    All per-entry arithmetic is float (no boolean masks: they are several times slower on CPU),
    evaluated in chunks of about ``_CHUNK`` entries whose temporaries the allocator recycles; pass 2
    recomputes the entries rather than storing them.  On a CPU map (``MapConfig.kernels``) both
    passes run as the compiled loops :func:`mapping.kernels.splat_front` and
    :func:`mapping.kernels.splat_blend` over the same per-surfel coefficients.
    """
    H, W = cam.height, cam.width
    dev = store.device
    if len(vis) == 0:
        return ModelView.empty(H, W, dev)
    hmax = int(SPLAT_MAX_HALF)
    V = len(vis)
    slots = vis.slots
    # the z-buffer's 30-bit integer range holds inverse depth scaled so that depth >= near / 4 fits
    q_scale = float(_Q_MAX) * NEAR_MM * 0.25
    k_pow = _kernel_power(RENDER_BLEND_SIGMA)
    pad = 2 * hmax + 2                                        # a centre may lie hmax px outside
    Wp = W + 2 * pad
    Hp = H + 2 * pad
    # compiled passes (CPU): per-surfel coefficients in one loop, the surfel lists stay lists (no
    # footprint buckets)
    compiled = kernels.use_compiled(cfg, dev)
    if compiled:
        n, conf, coef, half, base, stab, c4 = _coefficients_compiled(store, vis, cam, cfg, q_scale, k_pow, pad, Wp)
    else:
        n, conf, coef, monos, half, base, stab, c4 = _coefficients_torch(store, vis, cam, cfg, q_scale, k_pow, pad, Wp)
        ncoef = coef.shape[0]
        nblk = len(monos)
        ids = torch.arange(V, device=dev)[None, :]              # surfel ids of the z-buffer keys

    def make_buckets(subset: torch.Tensor | None) -> list:
        """Per footprint-size bucket (a few, not a loop over surfels) of the surfels ``subset``
        (indices into the visible set; None = all): their coefficients and the monomials of the
        offsets.  The compiled passes take the surfel list as it is (one "bucket")."""
        if compiled:
            return [torch.arange(V) if subset is None else subset]
        hs = half if subset is None else half.index_select(0, subset)
        counts = torch.bincount(hs, minlength=hmax + 1).tolist()
        out = []
        for h in range(hmax + 1):
            if counts[h] == 0:
                continue
            if subset is None and counts[h] == V:
                sel, per = None, (coef, base, ids, stab, c4)
            else:
                sel = (hs == h).nonzero().squeeze(1)
                if subset is not None:
                    sel = subset.index_select(0, sel)
                per = tuple(x.index_select(1, sel) for x in (coef, base, ids, stab, c4))
            out.append((sel, per, *offset_basis(h)))
        return out

    @functools.lru_cache(maxsize=None)
    def offset_basis(h: int):
        """Monomials of the ``(2h + 1)^2`` pixel offsets, their padded-pixel offsets and count
        (shared by every bucket of half size ``h``)."""
        off = torch.arange(-h, h + 1, device=dev, dtype=torch.float32)
        oy, ox = torch.meshgrid(off, off, indexing="ij")
        ox, oy = ox.reshape(-1), oy.reshape(-1)
        k2 = ox.numel()
        table = {"1": torch.ones_like(ox), "x": ox, "y": oy, "rr": ox * ox + oy * oy}
        basis = torch.zeros(nblk * k2, ncoef, device=dev)
        col = 0
        for bi, ms in enumerate(monos):
            basis[bi * k2:(bi + 1) * k2, col:col + len(ms)] = torch.stack([table[m] for m in ms], 1)
            col += len(ms)
        offs = (oy.long() * Wp + ox.long())[:, None]
        return basis, offs, k2

    def chunks(b):
        S = b[1][0].shape[1]
        step = max(1, _CHUNK // b[4])
        return ((s0, min(S, s0 + step)) for s0 in range(0, S, step))

    def entries(b, s0, s1):
        """Entries of surfels ``[s0, s1)`` of bucket ``b``, all ``(k2, S)``: ``t`` clamped at 0,
        inverse depth, 1/0 inside/outside the footprint, padded pixel."""
        _, (cf, bs, _, _, _), basis, offs, k2 = b
        out = torch.mm(basis, cf[:, s0:s1])                    # (nblk k2, S)
        t = out[:k2].clamp_min_(0.0)
        t[k2 // 2].clamp_min_(1e-6)                            # centre pixel
        inside = torch.ceil(t)
        # inverse depth; <= 0 behind the camera (never covers), capped below the stable offset
        qf = out[k2:2 * k2].clamp_(0.0, float(_Q_MAX))
        return t, qf, inside, bs[:, s0:s1] + offs

    # ---- pass 1: front surface (z-buffer) --------------------------------------------------------
    buf = torch.zeros(Hp * Wp, dtype=torch.long, device=dev)

    def front_pass(bks: list) -> None:
        if compiled:
            for order in bks:
                kernels.splat_front(buf.numpy(), Wp, order.numpy(), *per_surfel, float(_Q_MAX))
            return
        for b in bks:
            _, (_, _, idk, stb, _), _, _, _ = b
            for s0, s1 in chunks(b):
                _, qf, inside, pix = entries(b, s0, s1)
                zv = (qf + stb[:, s0:s1]).mul_(inside).long()        # 0 off the footprint
                key = torch.add(idk[:, s0:s1], zv, alpha=1 << 32)    # z-buffer value << 32 | surfel
                buf.scatter_reduce_(0, pix.view(-1), key.view(-1), reduce="amax")

    if compiled:
        per_surfel = (base[0].contiguous().numpy(), half.contiguous().numpy(), coef.contiguous().numpy(),
                      stab[0].contiguous().numpy())

    stable = stab[0] > 0                                      # (stab: the stable surfels' key offset)
    n_stable = int(stable.sum())
    if cull_hidden_unstable and 0 < n_stable < V:
        # stable surfels first; an unstable surfel whose footprint stable ones cover (its centre
        # pixel and the 8 pixels at its corners and edge midpoints) would not show: not splatted
        buckets = make_buckets(stable.nonzero().squeeze(1))
        front_pass(buckets)
        unst = (~stable).nonzero().squeeze(1)
        ub = take(base[0], unst)
        uh = take(half, unst)
        hidden = torch.ones_like(unst, dtype=torch.bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                hidden &= (take(buf, ub + uh * (dy * Wp + dx)) >> 32) > _Q_MAX
        unst = take(unst, (~hidden).nonzero().squeeze(1))
        if unst.numel():
            rest = make_buckets(unst)
            front_pass(rest)
            buckets += rest
    else:
        buckets = make_buckets(None)
        front_pass(buckets)
    # ---- pass 2: blend the surfels of the front surface ---------------------------------------------
    # an entry takes part when its z-buffer value exceeds the pixel's threshold
    # (2^30 if the front is stable) + q_front * z_front / (z_front + tol),
    # tol = max(tol_mm, tol_rel * z_front): same class as the front, at most tol behind it
    zbuf = buf >> 32
    q_front = zbuf & _Q_MAX
    z_front = q_scale / q_front.clamp_min(1).float()
    tol = torch.clamp_min(RENDER_DEPTH_TOL_REL * z_front, RENDER_DEPTH_TOL_MM)
    thr = torch.where(q_front > 0, (zbuf - q_front).float() + q_scale / (z_front + tol), float("inf"))

    def blend(with_colour: bool) -> torch.Tensor:
        """Per padded pixel ``(C, Hp * Wp)`` sums of the blending weights ``w``, then ``w rgb``
        (with colour)."""
        colors = to_columns(take(store.color, slots)) if with_colour else None   # (3, V)
        acc = torch.zeros(1 + (3 if with_colour else 0), Hp * Wp, device=dev)
        if compiled:
            sums = torch.zeros(Hp * Wp, 4)                  # w, w rgb per pixel, interleaved
            cols = (colors if colors is not None else torch.zeros(3, V)).contiguous().numpy()
            root, thr_np = c4[0].contiguous().numpy(), thr.contiguous().numpy()
            for order in buckets:
                kernels.splat_blend(sums.numpy(), Wp, order.numpy(), *per_surfel, root, k_pow, thr_np, cols)
            keep = [0] + ([1, 2, 3] if with_colour else [])
            return torch.stack([sums[:, c] for c in keep])
        for b in buckets:
            sel, (_, _, _, stb, cq), _, _, _ = b
            cs = None if colors is None else (colors if sel is None else colors.index_select(1, sel))
            for s0, s1 in chunks(b):
                t, qf, inside, pix = entries(b, s0, s1)
                pix = pix.view(-1)
                zv = (qf + stb[:, s0:s1]).mul_(inside)
                front = zv.sub_(take(thr, pix).view(zv.shape)).sign_().clamp_min_(0.0)
                w = _int_pow_(t.mul_(front).mul_(cq[:, s0:s1]), k_pow)   # (k2, S)
                acc[0].scatter_add_(0, pix, w.view(-1))
                for c in range(3 if cs is not None else 0):
                    acc[1 + c].scatter_add_(0, pix, (w * cs[c:c + 1, s0:s1]).view(-1))
        return acc

    def crop(x: torch.Tensor) -> torch.Tensor:
        """``(C, Hp * Wp)`` padded buffer -> ``(C, H * W)``."""
        return x.view(x.shape[0], Hp, Wp)[:, pad:pad + H, pad:pad + W].reshape(x.shape[0], -1)

    buf = crop(buf[None])[0]
    zbuf = buf >> 32
    valid = zbuf > 0
    vidx = buf & _ID_MASK
    wslots = take(slots, vidx)
    z_front = q_scale / (zbuf & _Q_MAX).clamp_min(1).float()
    depth = torch.where(valid, z_front, 0.0)
    acc = crop(blend(True)) if colour else None
    edits = store.edits

    def colour_of(acc: torch.Tensor | None) -> torch.Tensor:
        if acc is None:
            if store.edits != edits:
                raise RuntimeError("the surfel map changed since this view was rendered: render it again")
            acc = crop(blend(True))
        wsum = acc[0]
        return torch.where(wsum > 1e-30, acc[-3:] / wsum.clamp_min(1e-30),
                           to_columns(take(store.color, wslots)) * valid).reshape(3, H, W)

    vm = valid[:, None].float()
    normals = take(n, vidx) * vm
    confidence = take(conf, vidx) * valid
    index = torch.where(valid, wslots, -1)
    view = ModelView(color=torch.zeros(3, H, W, device=dev), depth=depth.reshape(H, W),
                     normals=to_columns(normals).reshape(3, H, W), confidence=confidence.reshape(H, W),
                     valid=valid.reshape(H, W), index=index.reshape(H, W))
    if colour:
        view.color = colour_of(acc)
    else:   # the blending pass on demand (ModelView.with_colour)
        view.pending_colour = lambda: colour_of(None)
    return view


def render(store: SurfelStore, cfg: MapConfig, K, T_wc, height: int, width: int,
           stable_only: bool = False, colour: bool = True, *,
           cull_hidden_unstable: bool = RENDER_CULL_HIDDEN_UNSTABLE, seen_from: int | None = None,
           seen_before: int | None = None) -> tuple[ModelView, int]:
    """Render the store from ``T_wc``; returns the view and the number of visible surfels
    (``cull_hidden_unstable``: see :func:`splat`; ``seen_from``, ``seen_before``: only the
    surfels last fused in that frame range, see :func:`visible_set`)."""
    cam = Camera.make(K, T_wc, height, width, store.device)
    if store.n == 0 or store.num_alive == 0:
        return ModelView.empty(height, width, store.device), 0
    # right after fusing a frame at this very view, its visible set (plus the new surfels) is reused
    cached = store.scratch.get("view")
    candidates = None
    # (the fusion's set holds every surfel seen since its frame's window start: not the inactive ones)
    if cached is not None and cached[0] == cam.key and cached[1] == store.version and seen_before is None:
        candidates = cached[2]
    vis = visible_set(store, cam, NEAR_MM, FAR_MM, margin_px=float(SPLAT_MAX_HALF),
                      stable_threshold=cfg.stable_confidence if stable_only else None, candidates=candidates,
                      compiled=kernels.use_compiled(cfg, store.device), seen_from=seen_from, seen_before=seen_before)
    return splat(store, vis, cam, cfg, colour, cull_hidden_unstable=cull_hidden_unstable), len(vis)
