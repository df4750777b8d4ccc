"""The LM solver's normal equations as one compiled loop over the pixels (numba, CPU).

``vo.solver.normal_equations`` builds the Gauss-Newton system with ~100 vectorised torch ops per
evaluation; on a CPU with 16k pixels their cost is the traffic of the intermediates, not the
arithmetic. This kernel does the same sums in one pass, in float64 throughout (the torch code
accumulates the 2D block in the data's float32), so the two agree to float32 rounding, not bit
for bit. Selected by ``solver.kernel`` (``vo.config.SolverConfig``); numba is compiled on first
use and cached on disk.
"""
from __future__ import annotations

import functools
import importlib.util

import numpy as np
import torch

AVAILABLE = importlib.util.find_spec("numba") is not None


def _normal_equations_loop(T, pc, tgt, pr, w2, w3, K, s2, s3, H, g, cost):
    B, N = w2.shape
    for b in range(B):
        R00, R01, R02, t0 = T[b, 0, 0], T[b, 0, 1], T[b, 0, 2], T[b, 0, 3]
        R10, R11, R12, t1 = T[b, 1, 0], T[b, 1, 1], T[b, 1, 2], T[b, 1, 3]
        R20, R21, R22, t2 = T[b, 2, 0], T[b, 2, 1], T[b, 2, 2], T[b, 2, 3]
        fx, fy, cx, cy = K[b, 0, 0], K[b, 1, 1], K[b, 0, 2], K[b, 1, 2]
        fxs, fys = fx * s2, fy * s2
        h = np.zeros((6, 6))
        gg = np.zeros(6)
        c = 0.0
        sw = 0.0
        sY = np.zeros(3)
        sYY = np.zeros((3, 3))
        ju = np.zeros(6)
        jv = np.zeros(6)
        for n in range(N):
            a, bb, cc = float(pc[b, 0, n]), float(pc[b, 1, n]), float(pc[b, 2, n])
            Y0 = R00 * a + R01 * bb + R02 * cc + t0
            Y1 = R10 * a + R11 * bb + R12 * cc + t1
            Y2 = R20 * a + R21 * bb + R22 * cc + t2
            wa = float(w2[b, n])
            if wa != 0.0:
                z = Y2 if Y2 > 1e-6 else 1e-6
                iz = 1.0 / z
                xz, yz = Y0 * iz, Y1 * iz
                eu = (fx * xz + cx - float(tgt[b, 0, n])) * s2
                ev = (fy * yz + cy - float(tgt[b, 1, n])) * s2
                ju[0], ju[1], ju[2] = fxs * iz, 0.0, -fxs * xz * iz
                ju[3], ju[4], ju[5] = -fxs * xz * yz, fxs * (1.0 + xz * xz), -fxs * yz
                jv[0], jv[1], jv[2] = 0.0, fys * iz, -fys * yz * iz
                jv[3], jv[4], jv[5] = -fys * (1.0 + yz * yz), fys * xz * yz, fys * xz
                for i in range(6):
                    gg[i] += wa * (ju[i] * eu + jv[i] * ev)
                    for j in range(i, 6):
                        h[i, j] += wa * (ju[i] * ju[j] + jv[i] * jv[j])
                c += wa * (eu * eu + ev * ev)
            wb = float(w3[b, n])
            if wb != 0.0:
                e0 = (Y0 - float(pr[b, 0, n])) * s3
                e1 = (Y1 - float(pr[b, 1, n])) * s3
                e2 = (Y2 - float(pr[b, 2, n])) * s3
                c += wb * (e0 * e0 + e1 * e1 + e2 * e2)
                sw += wb
                sY[0] += wb * Y0
                sY[1] += wb * Y1
                sY[2] += wb * Y2
                sYY[0, 0] += wb * Y0 * Y0
                sYY[0, 1] += wb * Y0 * Y1
                sYY[0, 2] += wb * Y0 * Y2
                sYY[1, 1] += wb * Y1 * Y1
                sYY[1, 2] += wb * Y1 * Y2
                sYY[2, 2] += wb * Y2 * Y2
                # g3 = s3 * sum w [e; Y x e]
                gg[0] += s3 * wb * e0
                gg[1] += s3 * wb * e1
                gg[2] += s3 * wb * e2
                gg[3] += s3 * wb * (Y1 * e2 - Y2 * e1)
                gg[4] += s3 * wb * (Y2 * e0 - Y0 * e2)
                gg[5] += s3 * wb * (Y0 * e1 - Y1 * e0)
        sYY[1, 0], sYY[2, 0], sYY[2, 1] = sYY[0, 1], sYY[0, 2], sYY[1, 2]
        for i in range(6):
            for j in range(i):
                h[i, j] = h[j, i]
        # 3D block: s3^2 [[sw I, -[sY]x], [[sY]x, tr(sYY) I - sYY]]
        k = s3 * s3
        tr = sYY[0, 0] + sYY[1, 1] + sYY[2, 2]
        for i in range(3):
            h[i, i] += k * sw
            for j in range(3):
                h[3 + i, 3 + j] += k * ((tr if i == j else 0.0) - sYY[i, j])
        # [a]x = [[0, -a2, a1], [a2, 0, -a0], [-a1, a0, 0]]
        sk = np.array([[0.0, -sY[2], sY[1]], [sY[2], 0.0, -sY[0]], [-sY[1], sY[0], 0.0]])
        for i in range(3):
            for j in range(3):
                h[i, 3 + j] -= k * sk[i, j]
                h[3 + i, j] += k * sk[i, j]
        H[b] = h
        g[b] = gg
        cost[b] = c


@functools.lru_cache(maxsize=None)
def _kernel():
    """The loop compiled by numba on first use (importing this module does not load numba)."""
    import numba

    return numba.njit(cache=True, nogil=True, error_model="numpy")(_normal_equations_loop)


def normal_equations_compiled(T: torch.Tensor, prob) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(H, g, cost)`` of ``vo.solver.normal_equations`` for a CPU problem without gradients:
    ``H`` ``(B, 6, 6)``, ``g`` ``(B, 6)``, ``cost`` ``(B,)``, float64."""
    B = prob.w2d.shape[0]
    H = np.empty((B, 6, 6))
    g = np.empty((B, 6))
    cost = np.empty(B)
    arr = lambda t: np.ascontiguousarray(t.detach().numpy())  # noqa: E731
    _kernel()(T.detach().double().numpy(), arr(prob.points_cur), arr(prob.target_px), arr(prob.points_ref),
              arr(prob.w2d), arr(prob.w3d), np.ascontiguousarray(prob.K.detach().double().expand(B, 3, 3).numpy()),
              float(prob.s2), float(prob.s3), H, g, cost)
    return torch.from_numpy(H), torch.from_numpy(g), torch.from_numpy(cost)
