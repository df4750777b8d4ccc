"""View culling, the splatting renderer and the super-sampled index map.

Everything is vectorised over surfels: the visible set is found by testing the chunk bounding
boxes of :class:`mapping.surfels.SurfelStore` against the frustum, then the surfels of the
surviving chunks individually.  The renderer expands every visible surfel into the pixels of its
projected footprint (at most ``(2 h + 1)^2``, grouped by footprint size), takes the depth of each
pixel from the ray's intersection with the surfel's plane (exact, sub-pixel), and z-buffers with
one ``scatter_reduce`` on an int64 key ``quantised inverse depth << 32 | surfel``; the winner's
attributes are gathered per pixel.  The index map used by the fusion is a super-sampled depth
buffer z-tested the same way.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .config import MapConfig
from .surfels import SurfelStore, take

KEY_EMPTY = torch.iinfo(torch.int64).max
_ID_MASK = (1 << 32) - 1


@dataclass
class ModelView:
    """The map rendered from one camera.

    Attributes:
        color: ``(3, H, W)`` float32 RGB in [0, 1] (0 where empty).
        depth: ``(H, W)`` float32 depth along the optical axis, mm (0 where empty).
        normals: ``(3, H, W)`` float32 unit normals in the camera frame (0 where empty).
        confidence: ``(H, W)`` float32 confidence of the visible surfel (0 where empty).
        valid: ``(H, W)`` bool, True where a surfel covers the pixel.
        index: ``(H, W)`` int64 slot of the visible surfel, -1 where empty (valid until the
            map is next modified).
    """

    color: torch.Tensor
    depth: torch.Tensor
    normals: torch.Tensor
    confidence: torch.Tensor
    valid: torch.Tensor
    index: torch.Tensor

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


def cull_chunks(store: SurfelStore, cam: Camera, near: float, far: float, margin_px: float) -> torch.Tensor:
    """Bool mask over the used chunks whose bounding box may intersect the view frustum.

    The frustum is the image rectangle grown by ``margin_px`` on each side between ``near`` and
    ``far``; a box is culled when all 8 corners lie outside one of its 6 planes.
    """
    nch = store.num_chunks
    lo, hi = store.box_lo[:nch], store.box_hi[:nch]
    finite = torch.isfinite(lo).all(dim=1) & torch.isfinite(hi).all(dim=1)
    lo = torch.where(finite[:, None], lo, 0.0)
    hi = torch.where(finite[:, None], hi, 0.0)
    sel = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=torch.bool,
                       device=lo.device)
    corners = torch.where(sel[None], hi[:, None, :], lo[:, None, :])          # (B, 8, 3)
    c = cam.to_cam(corners)
    x, y, z = c.unbind(-1)
    xmin = (-0.5 - margin_px - cam.cx) / cam.fx
    xmax = (cam.width - 0.5 + margin_px - cam.cx) / cam.fx
    ymin = (-0.5 - margin_px - cam.cy) / cam.fy
    ymax = (cam.height - 0.5 + margin_px - cam.cy) / cam.fy
    outside = ((z < near).all(1) | (z > far).all(1)
               | (x < xmin * z).all(1) | (x > xmax * z).all(1)
               | (y < ymin * z).all(1) | (y > ymax * z).all(1))
    return finite & ~outside


def visible_set(store: SurfelStore, cam: Camera, near: float, far: float, margin_px: float = 0.0,
                stable_threshold: float | None = None, candidates: torch.Tensor | None = None) -> VisibleSet:
    """Live surfels whose centre projects inside the image grown by ``margin_px``, depth in [near, far].

    ``stable_threshold``: keep only surfels with at least this confidence.
    ``candidates``: slots known to contain every such surfel (skips the chunk culling).
    """
    dev = store.device
    if store.n == 0:
        e = torch.zeros(0, device=dev)
        return VisibleSet(torch.zeros(0, dtype=torch.long, device=dev), torch.zeros(0, 3, device=dev), e, e)
    if candidates is None:
        slots = store.chunk_candidates(cull_chunks(store, cam, near, far, margin_px))
    else:
        slots = take(candidates, take(store.alive, candidates).nonzero().squeeze(1))
    if stable_threshold is not None and slots.numel():
        slots = take(slots, (take(store.conf, slots) >= stable_threshold).nonzero().squeeze(1))
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


def splat(store: SurfelStore, vis: VisibleSet, cam: Camera, cfg: MapConfig) -> ModelView:
    """Z-buffered disc splatting of the visible surfels into a ``(H, W)`` view.

    Every surfel is expanded into the ``(2h + 1)^2`` pixel offsets ``(ox, oy)`` around its centre
    pixel (``h`` from its projected radius, surfels grouped by ``h``).  For an offset, the inverse
    depth of the pixel ray's intersection with the surfel's plane is affine in ``(ox, oy)``
    (exact sub-pixel depth on the disc's plane), and the footprint test is a quadratic in
    ``(ox, oy)``: by default the circle of the projected radius around the projected centre
    (``render_exact_discs=False``), or the exact image conic of the disc ``|X - p| <= r``.
    Their coefficients are computed once per surfel, and one small matrix product against the
    monomials of the footprint offsets evaluates every entry.  The z-buffer is one
    ``scatter_reduce(amax)`` over int64 keys ``quantised inverse depth << 32 | surfel``; the
    winner's attributes are gathered per pixel.  The centre pixel of every surfel is always
    written, so no surfel vanishes between pixel centres.  The buffer is padded so no bounds tests
    are needed per entry.
    """
    H, W = cam.height, cam.width
    dev = store.device
    if len(vis) == 0:
        return ModelView.empty(H, W, dev)
    hmax = int(cfg.splat_max_half)
    V = len(vis)
    slots = vis.slots
    n = cam.rot_to_cam(take(store.normal, slots))
    r = take(store.radius, slots)
    # per-surfel quantities as contiguous rows (structure of arrays)
    px, py, pz = vis.p.T.contiguous()
    nx, ny, nz = n.T.contiguous()
    uc = torch.round(vis.u)
    vc = torch.round(vis.v)
    rx0 = (uc - cam.cx) / cam.fx                              # centre pixel ray (rx0, ry0, 1)
    ry0 = (vc - cam.cy) / cam.fy
    # inverse depth at pixel offset (ox, oy) = (n . ray) / (n . p), affine in (ox, oy); scaled to
    # the z-buffer's 31-bit integer range right away (depth >= near / 4 fits)
    q_scale = float(2 ** 31 - 1) * cfg.near_mm * 0.25
    den0 = torch.addcmul(torch.addcmul(nz, nx, rx0), ny, ry0)
    ndp = torch.addcmul(torch.addcmul(nz * pz, nx, px), ny, py)
    # grazing surfels (|n . ray| small at the centre pixel): centre pixel only, at the centre depth
    good = den0.abs() >= cfg.render_min_cos * torch.sqrt(torch.addcmul(torch.addcmul(
        torch.ones_like(rx0), rx0, rx0), ry0, ry0))
    scale = torch.where(good, q_scale / ndp, 0.0)
    L0 = torch.where(good, den0 * scale, q_scale / pz)
    L1 = nx * scale * (1.0 / cam.fx)
    L2 = ny * scale * (1.0 / cam.fy)
    r_px = r * cam.f / pz

    if cfg.render_exact_discs:
        # orthonormal tangent basis (e1, e2) of each disc (Duff et al. 2017, branchless)
        sign = torch.where(nz >= 0, 1.0, -1.0)
        a = -1.0 / (sign + nz)
        b = nx * ny * a
        e1 = (1.0 + sign * nx * nx * a, sign * b, -sign * nx)
        e2 = (b, sign + ny * ny * a, -ny)

        def plane_coef(e):
            # in-plane coordinate of the ray/plane intersection times inverse depth, affine in
            # (ox, oy): (ray . e) * i - (p . e) * i, with ray . e affine and i as above
            ex, ey, ez = e
            pe = torch.addcmul(torch.addcmul(ez * pz, ex, px), ey, py)
            lin0 = torch.addcmul(torch.addcmul(ez, ex, rx0), ey, ry0)
            return (q_scale * lin0 - pe * L0, (q_scale / cam.fx) * ex - pe * L1,
                    (q_scale / cam.fy) * ey - pe * L2)

        g1, g2 = plane_coef(e1), plane_coef(e2)
        gr = (L0 * r, L1 * r, L2 * r)
        # g1^2 + g2^2 - (r i)^2 <= 0: the 6 coefficients of the quadratic in (ox, oy)
        rows = []
        for i, j, w in ((0, 0, 1.0), (0, 1, 2.0), (0, 2, 2.0), (1, 1, 1.0), (1, 2, 2.0), (2, 2, 1.0)):
            c = torch.addcmul(torch.addcmul(g1[i] * g1[j], g2[i], g2[j]), gr[i], gr[j], value=-1.0)
            if w != 1.0:
                c = c * w
            rows.append(torch.where(good, c, 1.0) if i == j == 0 else c * good)
        monos = ("1", "x", "y", "xx", "xy", "yy")
    else:
        # circle of the projected radius around the projected centre:
        # (ox - du)^2 + (oy - dv)^2 - r_px^2 = ox^2 + oy^2 - 2 du ox - 2 dv oy + du^2 + dv^2 - r_px^2
        du = vis.u - uc
        dv = vis.v - vc
        c0 = torch.addcmul(torch.addcmul(r_px * r_px, du, du, value=-1.0), dv, dv, value=-1.0)
        rows = [torch.where(good, -c0, 1.0), -2.0 * du, -2.0 * dv]
        monos = ("1", "x", "y")                               # + ox^2 + oy^2 as a constant column
    nq = len(rows)
    coef = torch.stack(rows + [L0, L1, L2])                   # (nq + 3, V)

    half = torch.where(good, torch.floor(r_px + cfg.splat_round), 0.0).clamp(0, hmax).long()
    pad = 2 * hmax + 2                                        # a centre may lie hmax px outside
    Wp = W + 2 * pad
    Hp = H + 2 * pad
    base = (vc.long() + pad) * Wp + (uc.long() + pad)          # padded linear pixel of the centre
    buf = torch.zeros(Hp * Wp, dtype=torch.long, device=dev)  # keys > 0 where a surfel wins
    counts = torch.bincount(half, minlength=hmax + 1).tolist()
    for h in range(hmax + 1):      # a few footprint-size buckets, not a loop over surfels
        if counts[h] == 0:
            continue
        if counts[h] == V:
            sel, cf, bs = torch.arange(V, device=dev), coef, base
        else:
            sel = (half == h).nonzero().squeeze(1)
            cf, bs = coef.index_select(1, sel), take(base, sel)
        off = torch.arange(-h, h + 1, device=dev, dtype=torch.float32)
        oy, ox = torch.meshgrid(off, off, indexing="ij")
        ox, oy = ox.reshape(-1), oy.reshape(-1)
        k2 = ox.numel()
        table = {"1": torch.ones_like(ox), "x": ox, "y": oy, "xx": ox * ox, "xy": ox * oy, "yy": oy * oy}
        basis = torch.zeros(2 * k2, nq + 3, device=dev)
        basis[:k2, :nq] = torch.stack([table[m] for m in monos], 1)
        basis[k2:, nq:] = torch.stack([table["1"], ox, oy], 1)
        bias = torch.zeros(2 * k2, 1, device=dev)
        if not cfg.render_exact_discs:
            bias[:k2, 0] = ox * ox + oy * oy
        out = torch.addmm(bias, basis, cf)                     # (2 k2, S): footprint test | inv. depth
        ok = out[:k2] <= 0
        ok[k2 // 2] = True                                     # centre pixel
        q = (out[k2:] * ok).long()                             # 0 where the pixel is off the disc
        key = torch.add(sel[None, :], q, alpha=1 << 32)        # q << 32 | surfel
        pix = bs[None, :] + (oy.long() * Wp + ox.long())[:, None]
        buf.scatter_reduce_(0, pix.view(-1), key.view(-1), reduce="amax")
    buf = buf.view(Hp, Wp)[pad:pad + H, pad:pad + W].reshape(-1)
    qbuf = buf >> 32
    valid = qbuf > 0
    vidx = buf & _ID_MASK
    depth = torch.where(valid, q_scale / qbuf.clamp_min(1).double(), 0.0).float()
    wslots = take(slots, vidx)
    vm = valid[:, None].float()
    color = take(store.color, wslots) * vm
    normals = take(n, vidx) * vm
    conf = take(store.conf, wslots) * valid
    index = torch.where(valid, wslots, -1)
    return ModelView(color=color.T.reshape(3, H, W), depth=depth.reshape(H, W),
                     normals=normals.T.reshape(3, H, W), confidence=conf.reshape(H, W),
                     valid=valid.reshape(H, W), index=index.reshape(H, W))


def render(store: SurfelStore, cfg: MapConfig, K, T_wc, height: int, width: int,
           stable_only: bool = False) -> tuple[ModelView, int]:
    """Render the store from ``T_wc``; returns the view and the number of visible surfels."""
    cam = Camera.make(K, T_wc, height, width, store.device)
    if store.n == 0 or store.num_alive == 0:
        return ModelView.empty(height, width, store.device), 0
    # right after fusing a frame at this very view, its visible set (plus the new surfels) is reused
    cached = store.scratch.get("view")
    candidates = None
    if cached is not None and cached[0] == cam.key and cached[1] == store.version:
        candidates = cached[2]
    vis = visible_set(store, cam, cfg.near_mm, cfg.far_mm, margin_px=float(cfg.splat_max_half),
                      stable_threshold=cfg.stable_confidence if stable_only else None, candidates=candidates)
    return splat(store, vis, cam, cfg), len(vis)
