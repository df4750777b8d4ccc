"""Compiled CPU kernels of the surfel map (numba): one pass per surfel instead of many tensor ops.

The torch code of :mod:`mapping.fusion` and :mod:`mapping.render` is vectorised over surfels and
runs on any device; on a CPU much of its cost is not arithmetic but the traffic of its many small
ops (every intermediate written and read back: a flat profile).  These kernels do the same work
in a few loops that keep the intermediates in registers:

- :func:`associate_and_update`: the fusion's free-space test, index map, projective data
  association, merging of redundant candidates, running averages and chunk-box growth;
- :func:`measure`: the per-pixel points, normals and radii of a frame;
- :func:`cull_chunks` and :func:`visible_surfels`: view culling and the visible set;
- :func:`splat_coefficients`, :func:`splat_front` and :func:`splat_blend`: the renderer's
  per-surfel coefficients and two splatting passes.

They are selected by ``MapConfig.kernels`` (``auto``: for a map on the CPU when numba is
installed); the tests check that both paths give the same results.  The splatting kernels owe
their speed to two things, measured: the footprint loops are specialised to constant sizes
(1x1, 3x3, 5x5: unrolled, 2x faster than a loop to a variable size, which ran no faster than
torch's SIMD passes) and the blend accumulates per pixel into one interleaved row of sums.

Kernels take numpy views of CPU tensors (no copies), edit the store's arrays in place, and are
compiled on first call and cached on disk (``cache=True``).
"""
from __future__ import annotations

import functools
import importlib.util

import numpy as np

AVAILABLE = importlib.util.find_spec("numba") is not None   # optional: without it torch runs


def _compiled_on_first_call(**options):
    """Decorator: the function is compiled by numba when first called, so that importing the
    package (a frame2frame run never fuses) does not load numba and LLVM (~100 MB)."""
    def wrap(fn):
        compiled = None

        @functools.wraps(fn)
        def call(*args):
            nonlocal compiled
            if compiled is None:
                import numba
                for helper in _HELPERS:
                    if not isinstance(globals()[helper.__name__], numba.core.dispatcher.Dispatcher):
                        globals()[helper.__name__] = numba.njit(inline="always", fastmath=True, error_model="numpy")(helper)
                compiled = numba.njit(cache=True, nogil=True, error_model="numpy", **options)(fn)
            return compiled(*args)

        return call
    return wrap


def _inline_helper(fn):
    """Decorator: a helper of the kernels, compiled inline into them.  Until the first kernel
    compiles it is the plain Python function; then its module global becomes the numba function
    (so that importing the package still does not load numba)."""
    _HELPERS.append(fn)
    return fn


_HELPERS: list = []


_jit = _compiled_on_first_call()
_jit_simd = _compiled_on_first_call(fastmath=True)   # branch-free loops: reassociation lets them vectorise


def use_compiled(cfg, device) -> bool:
    """Whether the fusion of a map on ``device`` runs the compiled kernel for ``cfg.kernels``;
    raises ``ValueError`` when ``compiled`` cannot be honoured."""
    mode = getattr(cfg, "kernels", "auto")
    if mode == "torch":
        return False
    cpu = str(device).startswith("cpu")
    if mode == "compiled":
        if not AVAILABLE:
            raise ValueError("mapping.kernels: 'compiled' needs the numba package (pip install numba)")
        if not cpu:
            raise ValueError(f"mapping.kernels: 'compiled' runs on the CPU, the map is on {device}")
        return True
    return AVAILABLE and cpu


@_jit
def associate_and_update(vis_slots, vis_p, vis_u, vis_v,
                         m_points, m_normals, m_radius, m_weight, m_color, m_fuse, m_free_depth,
                         pos, normal, radius, color, conf, t_last, box_lo, box_hi, chunk_size,
                         R_cw, R_wc, t_wc, H, W, s,
                         free_rel, free_mm, assoc_rel, assoc_mm, cos_thr, tie_rel, merge_factor,
                         stable_conf, free_decay, radius_ratio, max_conf, frame, skip_covered, f):
    """Steps 3-5 of :mod:`mapping.fusion` for one frame, on the visible surfels.

    Args:
        vis_slots ``(V,)`` int64, vis_p ``(V, 3)`` camera-frame positions, vis_u, vis_v ``(V,)``:
            the visible set (:class:`mapping.render.VisibleSet`).
        m_*: the frame's :class:`mapping.fusion.Measurement` flattened to ``H*W`` pixels.
        pos, normal, radius, color, conf, t_last: the store's arrays, edited in place.
        box_lo, box_hi ``(chunks, 3)``, chunk_size: the store's chunk boxes, grown in place to
            hold the surfels that moved (:meth:`mapping.surfels.SurfelStore.grow_boxes`).
        R_cw, R_wc ``(3, 3)``, t_wc ``(3,)``: the camera; H, W: image size; s: index-map scale
            (the ``s x s`` cells of a pixel hold exactly the surfels whose centre falls in it, so
            the surfels are grouped by pixel and each pixel's cells are z-tested locally: no
            super-sampled buffer).
        The rest: the constants of :mod:`mapping.fusion` and :class:`mapping.MapConfig` values
        (``cos_thr`` = cos of ``ASSOC_NORMAL_DEG``), ``skip_covered`` the fusion's switch and ``f``
        the mean focal length (for :func:`mapping.fusion.covered_pixels`).

    Returns ``(matched_pix (HW,) bool, covered (HW,) bool, free_kill, merge_kill, touched (int64
    slots), n_decayed, n_visible)``: pixels fused into a surfel; unmatched pixels near a neighbour
    candidate (:func:`mapping.fusion.covered_pixels`; all False unless ``skip_covered``); slots to
    remove (unstable surfels in free space, candidates merged into their pixel's winner); slots
    updated in place; the number of stable surfels whose confidence the free-space test decayed;
    the number of surfels whose centre lies inside the image.
    """
    V = vis_slots.shape[0]
    HW = H * W
    Ws = W * s
    # ---- pass 1, in visible-set order (the store's slot order: cache friendly): pixel and cell of
    # every surfel, free-space test, and the store values the association needs, gathered
    pix = np.full(V, -1, np.int64)            # -1: centre outside the image or in free space
    sub = np.empty(V, np.int64)               # cell within the pixel, cv * s + cu
    z = np.empty(V, np.float32)
    cconf = np.empty(V, np.float32)
    crad = np.empty(V, np.float32)
    ns = np.empty((V, 3), np.float32)         # surfel normal in the camera frame
    count = np.zeros(HW + 1, np.int64)
    free_kill = np.empty(V, np.int64)
    nk = 0
    n_decayed = 0
    n_visible = 0
    for j in range(V):
        fu = vis_u[j] + np.float32(0.5)       # float32 as the torch path (same cells)
        fv = vis_v[j] + np.float32(0.5)
        if fu < 0 or fu >= W or fv < 0 or fv >= H:
            continue
        n_visible += 1
        pu = int(fu)
        pv = int(fv)
        p = pv * W + pu
        zj = vis_p[j, 2]
        slot = vis_slots[j]
        D = m_free_depth[p]
        if D > 0:
            margin = max(max(free_rel * D, free_mm), max(assoc_rel * D, assoc_mm))
            if zj < D - margin:               # seen through: neither occludes nor matches
                if conf[slot] < stable_conf:
                    free_kill[nk] = slot
                    nk += 1
                else:
                    conf[slot] = conf[slot] * free_decay
                    n_decayed += 1
                continue
        pix[j] = p
        cu = min(int(fu * np.float32(s)), Ws - 1) - pu * s
        cv = min(int(fv * np.float32(s)), H * s - 1) - pv * s
        sub[j] = cv * s + cu
        z[j] = zj
        cconf[j] = conf[slot]
        crad[j] = radius[slot]
        for a in range(3):
            ns[j, a] = R_cw[a, 0] * normal[slot, 0] + R_cw[a, 1] * normal[slot, 1] + R_cw[a, 2] * normal[slot, 2]
        count[p + 1] += 1
    # ---- surfels grouped by pixel (counting sort, stable: visible-set order within a pixel)
    for p in range(HW):
        count[p + 1] += count[p]
    fill = count[:HW].copy()
    order = np.empty(count[HW], np.int64)
    for j in range(V):
        p = pix[j]
        if p >= 0:
            order[fill[p]] = j
            fill[p] += 1
    # ---- per pixel: index-map cells (nearest surfel per cell = the candidates), association
    # tests, the winner, and merging of the redundant matching candidates into it
    cellz = np.empty(s * s, np.float32)
    okj = np.zeros(V, np.bool_)
    winner_pix = np.full(V, -1, np.int64)
    merge_kill = np.empty(V, np.int64)
    nm = 0
    acc = np.empty(10)                        # conf-weighted sums: position, normal, colour, radius
    is_cand = np.zeros(V, np.bool_)
    matched_pix = np.zeros(HW, np.bool_)
    for p in range(HW):
        b0 = count[p]
        b1 = count[p + 1]
        if b0 == b1:
            continue
        for k in range(b0, b1):
            cellz[sub[order[k]]] = np.inf
        for k in range(b0, b1):
            j = order[k]
            if z[j] < cellz[sub[j]]:
                cellz[sub[j]] = z[j]
        for k in range(b0, b1):
            j = order[k]
            is_cand[j] = z[j] == cellz[sub[j]]
        if not m_fuse[p]:
            continue
        zm = m_points[p, 2]
        tol = max(assoc_rel * zm, assoc_mm)
        best = np.float32(-1.0)
        for k in range(b0, b1):
            j = order[k]
            if not is_cand[j] or abs(z[j] - zm) > tol:
                continue
            dot = ns[j, 0] * m_normals[p, 0] + ns[j, 1] * m_normals[p, 1] + ns[j, 2] * m_normals[p, 2]
            if dot < cos_thr:
                continue
            okj[j] = True
            if cconf[j] > best:
                best = cconf[j]
        if best < 0:
            continue
        # most confident wins; near-ties go to the candidate closest to the pixel's ray (its cell
        # offset from the pixel centre, in half cells), then to the first
        win = -1
        wkey = np.iinfo(np.int64).max
        for k in range(b0, b1):
            j = order[k]
            if okj[j] and cconf[j] >= best * (1.0 - tie_rel):
                a_off = 2 * (sub[j] % s) - (s - 1)
                b_off = 2 * (sub[j] // s) - (s - 1)
                dray = a_off * a_off + b_off * b_off
                if dray < wkey:
                    wkey = dray
                    win = j
        winner_pix[win] = p
        matched_pix[p] = True
        if merge_factor <= 0:
            continue
        sb = vis_slots[win]
        csum = 0.0
        acc[:] = 0.0
        t_max = -1
        for k in range(b0, b1):
            j = order[k]
            if j == win or not okj[j]:
                continue
            so = vis_slots[j]
            d2 = 0.0
            for a in range(3):
                d = vis_p[j, a] - vis_p[win, a]
                d2 += d * d
            if np.sqrt(d2) > merge_factor * min(radius[so], radius[sb]):
                continue
            co = conf[so]
            csum += co
            for a in range(3):
                acc[a] += co * pos[so, a]
                acc[3 + a] += co * normal[so, a]
                acc[6 + a] += co * color[so, a]
            acc[9] += co * radius[so]
            t_max = max(t_max, np.int64(t_last[so]))
            merge_kill[nm] = so
            nm += 1
        if t_max < 0:
            continue
        ct = conf[sb]
        cs = max(csum + ct, 1e-12)
        nn = 0.0
        for a in range(3):
            pos[sb, a] = (acc[a] + pos[sb, a] * ct) / cs
            normal[sb, a] = (acc[3 + a] + normal[sb, a] * ct) / cs
            color[sb, a] = (acc[6 + a] + color[sb, a] * ct) / cs
            nn += normal[sb, a] * normal[sb, a]
        nn = max(np.sqrt(nn), 1e-12)
        for a in range(3):
            normal[sb, a] = normal[sb, a] / nn
        radius[sb] = (acc[9] + radius[sb] * ct) / cs
        if t_max > t_last[sb]:
            t_last[sb] = t_max
        conf[sb] = min(csum + ct, max_conf)
    # ---- unmatched fusable pixels within half a radius of a candidate centred in a neighbour
    covered = np.zeros(HW, np.bool_)
    if skip_covered:
        for p in range(HW):
            if not m_fuse[p] or matched_pix[p]:
                continue
            pu = p % W
            pv = p // W
            zm = m_points[p, 2]
            tol = max(assoc_rel * zm, assoc_mm)
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    qu = pu + dx
                    qv = pv + dy
                    if (dx == 0 and dy == 0) or qu < 0 or qu >= W or qv < 0 or qv >= H:
                        continue
                    q = qv * W + qu
                    for k in range(count[q], count[q + 1]):
                        j = order[k]
                        if not is_cand[j] or abs(z[j] - zm) > tol:
                            continue
                        du = pu - vis_u[j]
                        dv = pv - vis_v[j]
                        rp = 0.5 * crad[j] * f / z[j]
                        if du * du + dv * dv > rp * rp:
                            continue
                        if ns[j, 0] * m_normals[p, 0] + ns[j, 1] * m_normals[p, 1] + ns[j, 2] * m_normals[p, 2] \
                                < cos_thr:
                            continue
                        covered[p] = True
                        break
                    if covered[p]:
                        break
                if covered[p]:
                    break
    # ---- running averages of the winners, in visible-set order (each surfel has at most one
    # pixel: its centre's)
    touched = np.empty(V, np.int64)
    nt = 0
    for j in range(V):
        p = winner_pix[j]
        if p < 0:
            continue
        slot = vis_slots[j]
        w = m_weight[p]
        c = conf[slot]
        r_old = radius[slot]
        r_new = m_radius[p]
        a = w / max(c + w, 1e-12) if r_new <= radius_ratio * r_old else 0.0
        nn = 0.0
        for k in range(3):
            qw = (R_wc[k, 0] * m_points[p, 0] + R_wc[k, 1] * m_points[p, 1] + R_wc[k, 2] * m_points[p, 2]
                  + t_wc[k])
            pos[slot, k] = pos[slot, k] + a * (qw - pos[slot, k])
            nw = R_wc[k, 0] * m_normals[p, 0] + R_wc[k, 1] * m_normals[p, 1] + R_wc[k, 2] * m_normals[p, 2]
            normal[slot, k] = normal[slot, k] + a * (nw - normal[slot, k])
            nn += normal[slot, k] * normal[slot, k]
            color[slot, k] = color[slot, k] + a * (m_color[p, k] - color[slot, k])
        inv = 1.0 / np.sqrt(max(nn, 1e-24))
        for k in range(3):
            normal[slot, k] = normal[slot, k] * inv
        radius[slot] = r_old + a * (r_new - r_old)
        conf[slot] = min(c + w, max_conf)
        t_last[slot] = frame
        touched[nt] = slot
        nt += 1
        ch = slot // chunk_size
        rr = radius[slot]
        for k in range(3):
            box_lo[ch, k] = min(box_lo[ch, k], pos[slot, k] - rr)
            box_hi[ch, k] = max(box_hi[ch, k], pos[slot, k] + rr)
    return matched_pix, covered, free_kill[:nk], merge_kill[:nm], touched[:nt], n_decayed, n_visible


@_jit_simd
def measure(depth, ok, w, rx, ry, fx, fy, max_jump_rel, min_cos, radius_factor,
            points, normals, radius, weight, fuse, free_depth):
    """Per-pixel measurements of one frame (:func:`mapping.fusion.measure`, same formulas).

    Args:
        depth ``(H, W)`` float32 mm; ok ``(H, W)`` bool (valid depth with a weight above the
        threshold); w ``(H, W)`` float32 fusion weight; rx ``(W,)``, ry ``(H,)`` float32
        normalised image coordinates of the pixel centres; fx, fy; max_jump_rel
        (``NORMAL_MAX_JUMP_REL``), min_cos (``RADIUS_MIN_COS``), radius_factor
        (``RADIUS_SCALE * sqrt(2) / f``) of :mod:`mapping.fusion`.
        Outputs (flattened ``H*W``), written: points ``(HW, 3)``, normals ``(HW, 3)``, radius,
        weight, fuse (bool), free_depth.

    Branch-free float32 rows (selects, no ifs) so that the compiler vectorises them.
    """
    H, W = depth.shape
    zero = np.float32(0.0)
    one = np.float32(1.0)
    half = np.float32(0.5)
    fx32 = np.float32(fx)
    fy32 = np.float32(fy)
    jump = np.float32(max_jump_rel)
    cmin = np.float32(min_cos)
    rf = np.float32(radius_factor)
    z = np.empty((H, W), np.float32)
    for v in range(H):
        for u in range(W):
            z[v, u] = depth[v, u] if ok[v, u] else zero
    for v in range(H):
        interior_row = 0 < v < H - 1
        vt = max(v - 1, 0)
        vb = min(v + 1, H - 1)
        ryv = ry[v]
        for u in range(W):
            i = v * W + u
            ul = max(u - 1, 0)
            ur = min(u + 1, W - 1)
            zc = z[v, u]
            zl = z[v, ul]
            zr = z[v, ur]
            zt = z[vt, u]
            zb = z[vb, u]
            tol = jump * zc
            interior = interior_row and 0 < u < W - 1
            good = (interior and zc > zero and zl > zero and zr > zero and zt > zero and zb > zero
                    and abs(zr - zc) <= tol and abs(zc - zl) <= tol and abs(zb - zc) <= tol
                    and abs(zc - zt) <= tol)
            zu = (zr - zl) * half
            mu = (zr + zl) * half
            zv = (zb - zt) * half
            mv = (zb + zt) * half
            ax = fx32 * zu * mv
            ay = fy32 * mu * zv
            muv = mu * mv
            rxu = rx[u]
            az = -(muv + rxu * ax + ryv * ay)
            inv = one / np.sqrt(max(ax * ax + ay * ay + az * az, np.float32(1e-30)))
            inv = inv if good else zero
            normals[i, 0] = ax * inv
            normals[i, 1] = ay * inv
            normals[i, 2] = az * inv
            cos = muv * inv / np.sqrt(one + rxu * rxu + ryv * ryv)
            cos = cos if interior else one       # (the torch path: 0 inside where not good)
            cos = min(max(cos, cmin), one)
            radius[i] = rf * zc / cos
            points[i, 0] = rxu * zc
            points[i, 1] = ryv * zc
            points[i, 2] = zc
            free_depth[i] = zc
            weight[i] = w[v, u] if ok[v, u] else zero
            fuse[i] = good


@_jit
def visible_surfels(chunks, slots, chunk_size, n, alive, conf, pos, R_cw, t_cw, fx, fy, cx, cy, near, far,
                    umin, umax, vmin, vmax, min_conf):
    """The visible set (:func:`mapping.render.visible_set`) in one pass: the live surfels of the
    ``chunks`` (int64 chunk ids) and of the int64 ``slots`` (either may be empty) with
    confidence >= ``min_conf`` whose camera-frame depth lies in ``[near, far]`` and whose projected
    centre lies in ``[umin, umax) x [vmin, vmax)``.  Returns ``slots (V,)``, camera-frame
    ``p (V, 3)``, ``u, v (V,)`` (float32, as the torch path)."""
    f32 = np.float32
    fx, fy, cx, cy = f32(fx), f32(fy), f32(cx), f32(cy)
    near, far, umin, umax, vmin, vmax = f32(near), f32(far), f32(umin), f32(umax), f32(vmin), f32(vmax)
    total = chunks.shape[0] * chunk_size + slots.shape[0]
    out_slots = np.empty(total, np.int64)
    out_p = np.empty((total, 3), np.float32)
    out_u = np.empty(total, np.float32)
    out_v = np.empty(total, np.float32)
    nch = chunks.shape[0] * chunk_size
    k = 0
    for i in range(total):
        if i < nch:
            s = chunks[i // chunk_size] * chunk_size + i % chunk_size
            if s >= n:
                continue
        else:
            s = slots[i - nch]
        if not alive[s] or conf[s] < min_conf:
            continue
        x = R_cw[0, 0] * pos[s, 0] + R_cw[0, 1] * pos[s, 1] + R_cw[0, 2] * pos[s, 2] + t_cw[0]
        y = R_cw[1, 0] * pos[s, 0] + R_cw[1, 1] * pos[s, 1] + R_cw[1, 2] * pos[s, 2] + t_cw[1]
        z = R_cw[2, 0] * pos[s, 0] + R_cw[2, 1] * pos[s, 1] + R_cw[2, 2] * pos[s, 2] + t_cw[2]
        if z < near or z > far:
            continue
        zs = max(z, f32(1e-6))
        u = x / zs * fx + cx
        v = y / zs * fy + cy
        if u < umin or u >= umax or v < vmin or v >= vmax:
            continue
        out_slots[k] = s
        out_p[k, 0] = x
        out_p[k, 1] = y
        out_p[k, 2] = z
        out_u[k] = u
        out_v[k] = v
        k += 1
    return out_slots[:k], out_p[:k], out_u[:k], out_v[:k]


@_jit
def cull_chunks(box_lo, box_hi, R_cw, t_cw, near, far, xmin, xmax, ymin, ymax):
    """Ids (int64) of the chunks whose box may intersect the frustum (:func:`mapping.render.cull_chunks`,
    same test: a box is culled when its 8 corners all lie outside one of the 6 planes; boxes with a
    non-finite bound - empty chunks - are culled)."""
    nch = box_lo.shape[0]
    out = np.empty(nch, np.int64)
    k = 0
    for c in range(nch):
        finite = True
        for a in range(3):
            finite = finite and np.isfinite(box_lo[c, a]) and np.isfinite(box_hi[c, a])
        if not finite:
            continue
        # per plane: is some corner inside it?
        n_near = n_far = n_l = n_r = n_t = n_b = False
        for corner in range(8):
            px = box_hi[c, 0] if corner & 4 else box_lo[c, 0]
            py = box_hi[c, 1] if corner & 2 else box_lo[c, 1]
            pz = box_hi[c, 2] if corner & 1 else box_lo[c, 2]
            x = R_cw[0, 0] * px + R_cw[0, 1] * py + R_cw[0, 2] * pz + t_cw[0]
            y = R_cw[1, 0] * px + R_cw[1, 1] * py + R_cw[1, 2] * pz + t_cw[1]
            z = R_cw[2, 0] * px + R_cw[2, 1] * py + R_cw[2, 2] * pz + t_cw[2]
            n_near = n_near or z >= near
            n_far = n_far or z <= far
            n_l = n_l or x >= xmin * z
            n_r = n_r or x <= xmax * z
            n_t = n_t or y >= ymin * z
            n_b = n_b or y <= ymax * z
        if n_near and n_far and n_l and n_r and n_t and n_b:
            out[k] = c
            k += 1
    return out[:k]


@_jit_simd
def splat_coefficients(slots, p, u, v, normal, radius, conf, R_cw, fx, fy, cx, cy, f, q_scale, min_cos,
                       splat_round, hmax, stable_conf, inv_k, pad, Wp,
                       n_out, conf_out, coef, half, base, stab, root):
    """The per-surfel quantities of :func:`mapping.render.splat` in one loop.

    Args:
        slots ``(V,)`` int64, p ``(V, 3)`` camera-frame positions, u, v ``(V,)`` projected centres:
            the visible set; normal ``(N, 3)``, radius, conf ``(N,)``: the store's arrays.
        R_cw ``(3, 3)``; fx, fy, cx, cy, f: the camera; q_scale: quantised inverse depth per 1/mm;
        min_cos (``RENDER_MIN_COS``), splat_round (``SPLAT_ROUND``), hmax (``SPLAT_MAX_HALF``), stable_conf, inv_k
        (``1 / k`` of the blending kernel); pad, Wp: the padded buffer.
        Outputs ``(V,)`` unless said: n_out ``(V, 3)`` camera-frame normals, conf_out, coef ``(7,
        V)`` (rows as :func:`splat_front`), half, base (int64), stab, root (the confidence
        factor's k-th root).

    Same formulas as :func:`mapping.render._coefficients_torch`.
    """
    one = np.float32(1.0)
    two = np.float32(2.0)
    zero = np.float32(0.0)
    fx, fy, cx, cy, f = np.float32(fx), np.float32(fy), np.float32(cx), np.float32(cy), np.float32(f)
    q_scale, min_cos, splat_round = np.float32(q_scale), np.float32(min_cos), np.float32(splat_round)
    stable_conf, inv_k = np.float32(stable_conf), np.float32(inv_k)
    for j in range(slots.shape[0]):
        s = slots[j]
        nx = R_cw[0, 0] * normal[s, 0] + R_cw[0, 1] * normal[s, 1] + R_cw[0, 2] * normal[s, 2]
        ny = R_cw[1, 0] * normal[s, 0] + R_cw[1, 1] * normal[s, 1] + R_cw[1, 2] * normal[s, 2]
        nz = R_cw[2, 0] * normal[s, 0] + R_cw[2, 1] * normal[s, 1] + R_cw[2, 2] * normal[s, 2]
        n_out[j, 0] = nx
        n_out[j, 1] = ny
        n_out[j, 2] = nz
        c = conf[s]
        conf_out[j] = c
        px = p[j, 0]
        py = p[j, 1]
        pz = p[j, 2]
        uc = np.rint(u[j])
        vc = np.rint(v[j])
        rx0 = (uc - cx) / fx                               # centre pixel ray (rx0, ry0, 1)
        ry0 = (vc - cy) / fy
        den0 = nz + nx * rx0 + ny * ry0
        ndp = nz * pz + nx * px + ny * py
        cos_v = abs(den0) / np.sqrt(one + rx0 * rx0 + ry0 * ry0)
        good = cos_v >= min_cos
        scale = q_scale / ndp if good else zero
        coef[4, j] = den0 * scale if good else q_scale / pz
        coef[5, j] = nx * scale / fx
        coef[6, j] = ny * scale / fy
        r_fp = radius[s] * f / pz * np.sqrt(min(max(cos_v, min_cos), one))
        du = u[j] - uc
        dv = v[j] - vc
        g = -one / (r_fp * r_fp)
        coef[0, j] = one + g * (du * du + dv * dv)
        coef[1, j] = -two * g * du
        coef[2, j] = -two * g * dv
        coef[3, j] = g
        root[j] = one if c >= stable_conf else (max(c, np.float32(1e-4)) / stable_conf) ** inv_k
        stab[j] = np.float32((1 << 30)) if c >= stable_conf else np.float32(0.0)
        h = int(np.floor(r_fp + splat_round)) if good else 0
        half[j] = min(max(h, 0), hmax)
        base[j] = (np.int64(vc) + pad) * Wp + np.int64(uc) + pad


@_inline_helper
def _footprint_entry(b, Wp, ox, oy, t0, tx, ty, g, l0, l1, l2, q_max):
    """At pixel offset ``(ox, oy)`` of a surfel (coefficients as :func:`splat_front`): the footprint
    value ``t``, the quantised inverse depth clamped to ``[0, q_max]`` and the padded pixel."""
    fx = np.float32(ox)
    fy = np.float32(oy)
    t = t0 + tx * fx + ty * fy + g * (fx * fx + fy * fy)
    q = min(max(l0 + l1 * fx + l2 * fy, np.float32(0.0)), q_max)
    return t, q, b + oy * Wp + ox


@_inline_helper
def _splat_front_entries(buf, Wp, b, h, i, t0, tx, ty, g, l0, l1, l2, st, q_max):
    """The ``(2 h + 1)^2`` entries of surfel ``i`` in :func:`splat_front` (inlined: called with a
    constant ``h`` the loops unroll, twice as fast on the common small footprints)."""
    zero = np.float32(0.0)
    for oy in range(-h, h + 1):
        for ox in range(-h, h + 1):
            t, q, p = _footprint_entry(b, Wp, ox, oy, t0, tx, ty, g, l0, l1, l2, q_max)
            covered = (t > zero) | ((ox == 0) & (oy == 0))       # the centre pixel always
            key = ((np.int64(q + st) << 32) | i) * covered
            buf[p] = max(buf[p], key)


@_jit_simd
def splat_front(buf, Wp, order, base, half, coef, stab, q_max):
    """Pass 1 of :func:`mapping.render.splat`: z-buffer the surfels ``order``.

    Args:
        buf ``(Hp * Wp,)`` int64 padded z-buffer, edited: per pixel the largest key
            ``(z-buffer value) << 32 | surfel``; Wp its row length.
        order ``(S,)`` int64 surfels (indices into the visible set) to splat.
        base ``(V,)`` int64 padded pixel of each surfel's centre pixel; half ``(V,)`` int64
            footprint half-size.
        coef ``(7, V)`` float32 rows ``t0, tx, ty, g, L0, L1, L2``: at pixel offset ``(ox, oy)``
            the footprint value ``t = t0 + tx ox + ty oy + g (ox^2 + oy^2)`` (covered where > 0; the
            centre pixel always) and the quantised inverse depth ``L0 + L1 ox + L2 oy``.
        stab ``(V,)`` float32 offset of stable surfels' values (``2^30``, else 0); q_max the largest
            quantised inverse depth.

    The float32 formulas of the torch pass, without branches per entry.
    """
    qm = np.float32(q_max)
    for j in range(order.shape[0]):
        i = order[j]
        h = half[i]
        b = base[i]
        t0, tx, ty, g, l0, l1, l2 = coef[0, i], coef[1, i], coef[2, i], coef[3, i], coef[4, i], coef[5, i], coef[6, i]
        st = stab[i]
        if h == 1:      # constant sizes: unrolled loops
            _splat_front_entries(buf, Wp, b, 1, i, t0, tx, ty, g, l0, l1, l2, st, qm)
        elif h == 2:
            _splat_front_entries(buf, Wp, b, 2, i, t0, tx, ty, g, l0, l1, l2, st, qm)
        elif h == 0:
            _splat_front_entries(buf, Wp, b, 0, i, t0, tx, ty, g, l0, l1, l2, st, qm)
        else:
            _splat_front_entries(buf, Wp, b, h, i, t0, tx, ty, g, l0, l1, l2, st, qm)


@_inline_helper
def _splat_blend_entries(acc, Wp, b, h, t0, tx, ty, g, l0, l1, l2, st, cq, k_pow, thr, r, gr, bl):
    """The ``(2 h + 1)^2`` entries of one surfel in :func:`splat_blend` (see
    :func:`_splat_front_entries`)."""
    zero = np.float32(0.0)
    tiny = np.float32(1e-6)
    q_max = np.float32((1 << 30) - 1)
    for oy in range(-h, h + 1):
        for ox in range(-h, h + 1):
            t, q, p = _footprint_entry(b, Wp, ox, oy, t0, tx, ty, g, l0, l1, l2, q_max)
            t = max(t, zero)
            t = max(t, tiny) if (ox == 0) & (oy == 0) else t   # the centre pixel always
            zv = (q + st) if t > zero else zero
            x = t * cq if zv > thr[p] else zero                 # in the front surface
            if k_pow == 4:                                      # the default: 15 % faster
                x2 = x * x
                w = x2 * x2
            else:
                w = x
                for _ in range(k_pow - 1):
                    w *= x
            acc[p, 0] += w
            acc[p, 1] += w * r
            acc[p, 2] += w * gr
            acc[p, 3] += w * bl


@_jit_simd
def splat_blend(acc, Wp, order, base, half, coef, stab, weight_root, k_pow, thr, colors):
    """Pass 2 of :func:`mapping.render.splat`: blend the colour of the front surface.

    Args:
        acc ``(Hp * Wp, 4)`` float32, edited: per pixel the sums of the weights ``w`` and
            ``w r, w g, w b`` (pixel-interleaved: one cache line).
        Wp, order, base, half, coef, stab: as :func:`splat_front`.
        weight_root ``(V,)`` float32 k-th root of each surfel's confidence factor; k_pow the
            kernel exponent: ``w = (t * weight_root)^k`` for entries in front.
        thr ``(Hp * Wp,)`` float32: an entry takes part when its z-buffer value exceeds it.
        colors ``(3, V)`` float32 RGB (zeros when the colour is not needed).
    """
    for j in range(order.shape[0]):
        i = order[j]
        h = half[i]
        b = base[i]
        t0, tx, ty, g, l0, l1, l2 = coef[0, i], coef[1, i], coef[2, i], coef[3, i], coef[4, i], coef[5, i], coef[6, i]
        st, cq, r, gr, bl = stab[i], weight_root[i], colors[0, i], colors[1, i], colors[2, i]
        if h == 1:      # constant sizes: unrolled loops
            _splat_blend_entries(acc, Wp, b, 1, t0, tx, ty, g, l0, l1, l2, st, cq, k_pow, thr, r, gr, bl)
        elif h == 2:
            _splat_blend_entries(acc, Wp, b, 2, t0, tx, ty, g, l0, l1, l2, st, cq, k_pow, thr, r, gr, bl)
        elif h == 0:
            _splat_blend_entries(acc, Wp, b, 0, t0, tx, ty, g, l0, l1, l2, st, cq, k_pow, thr, r, gr, bl)
        else:
            _splat_blend_entries(acc, Wp, b, h, t0, tx, ty, g, l0, l1, l2, st, cq, k_pow, thr, r, gr, bl)
