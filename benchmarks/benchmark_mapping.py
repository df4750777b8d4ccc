"""Benchmark of the surfel map: fuse + render per frame with a map of about a million surfels.

For each resolution a map is built by fusing a raster scan of a large synthetic tissue-like
height field (exact depth by ray casting, analytic texture) until it holds ``--surfels`` surfels;
then ``--frames`` further frames revisiting the mapped area are fused and rendered, timing every
stage.  Prints a table of median milliseconds per stage.  ``render`` is the depth-only model view
(depth, normals, confidence: the coverage test of every frame); ``render_rgb`` also blends the
colour (what frame2model computes the flow against).

    .venv/bin/python tools/benchmark_mapping.py                      # 320x256 and 640x512, 2 threads
    .venv/bin/python tools/benchmark_mapping.py --sizes 320x256 --threads 1 --surfels 300000
"""
from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import torch

from mapping import MapConfig, SurfelMap

STAGES = ["measure", "maintain", "cull", "index_map", "associate", "update", "free_space", "add", "clean"]


def height(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Tissue-like height field (mm): broad folds plus finer ripples, around 80 mm from z = 0."""
    return (80.0 + 5.0 * torch.sin(x / 15.0) * torch.cos(y / 20.0)
            + 1.0 * torch.sin(x / 4.0 + 0.5) * torch.sin(y / 5.0))


def texture(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return torch.stack([0.55 + 0.3 * torch.sin(x / 2.0), 0.35 + 0.2 * torch.cos(y / 3.0),
                        0.3 + 0.15 * torch.sin((x + y) / 4.0)]).clamp(0, 1)


def pose(cx: float, cy: float, cz: float, yaw: float = 0.0) -> torch.Tensor:
    """Camera looking along +z (down onto the surface), rotated by ``yaw`` about its axis."""
    T = torch.eye(4, dtype=torch.float64)
    c, s = math.cos(yaw), math.sin(yaw)
    T[:2, :2] = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    T[:3, 3] = torch.tensor([cx, cy, cz], dtype=torch.float64)
    return T


def ray_cast(T_wc: torch.Tensor, K: torch.Tensor, H: int, W: int, iters: int = 30):
    """Exact depth (H, W) and colour (3, H, W) of the height field by fixed-point ray marching."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                          indexing="ij")
    d = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    dw = d @ T_wc[:3, :3].T
    o = T_wc[:3, 3]
    t = (80.0 - o[2]) / dw[..., 2]
    for _ in range(iters):
        t = (height(o[0] + t * dw[..., 0], o[1] + t * dw[..., 1]) - o[2]) / dw[..., 2]
    x, y = o[0] + t * dw[..., 0], o[1] + t * dw[..., 1]
    return t.float(), texture(x, y).float()


def intrinsics(W: int, H: int) -> torch.Tensor:
    f = 0.875 * W   # ~60 deg horizontal field of view
    return torch.tensor([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]], dtype=torch.float64)


def scan_path(step: float, lane: float, width: float):
    """Boustrophedon raster scan over [0, width]^2 at 70 mm from the surface (endless generator)."""
    y = 0.0
    direction = 1
    while True:
        xs = np.arange(0.0, width + 1e-9, step)
        for x in (xs if direction > 0 else xs[::-1]):
            yield pose(float(x), y, 10.0, 0.05 * math.sin(x / 30.0))
        y += lane
        direction = -direction


def build(H: int, W: int, target: int, cfg: MapConfig, device: str):
    K = intrinsics(W, H)
    m = SurfelMap(cfg, device=device)
    view_w = 70.0 * W / K[0, 0].item()        # footprint width at 70 mm
    step = 0.1 * view_w
    lane = 0.6 * view_w
    width = math.sqrt(target / (0.8 * (K[0, 0].item() / 70.0) ** 2))    # side of the square to scan
    path = scan_path(step, lane, width)
    frame = 0
    t0 = time.perf_counter()
    while len(m) < target:
        T = next(path)
        depth, color = ray_cast(T, K, H, W)
        m.fuse(depth.to(device), color.to(device), K, T, frame)
        frame += 1
        if frame % 50 == 0:
            print(f"  [{W}x{H}] built {frame} frames, {len(m)} surfels "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
    return m, K, frame, width


def bench(H: int, W: int, target: int, n_frames: int, device: str, cfg: MapConfig) -> dict:
    m, K, frame, width = build(H, W, target, cfg, device)
    built = len(m)
    # revisit the mapped area: a slow diagonal sweep through its middle
    poses = [pose(0.3 * width + 0.4 * width * i / n_frames, 0.35 * width + 0.3 * width * i / n_frames,
                  10.0 + 3.0 * math.sin(i / 5.0), 0.1 * math.sin(i / 7.0)) for i in range(n_frames + 3)]
    frames = [ray_cast(T, K, H, W) for T in poses]
    m.profile = True
    rows = []
    for i, (T, (depth, color)) in enumerate(zip(poses, frames)):
        d, c = depth.to(device), color.to(device)
        c0 = time.process_time()
        t0 = time.perf_counter()
        stats = m.fuse(d, c, K, T, frame + i)
        fuse_t = dict(m.last_timings)
        t1 = time.perf_counter()
        view = m.render(K, T, H, W, colour=False)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t2 = time.perf_counter()
        c2 = time.process_time()
        m.render(K, T, H, W, colour=True)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t3 = time.perf_counter()
        if i >= 3:     # warm-up frames excluded
            row = {k: fuse_t.get(k, 0.0) for k in STAGES}
            row.update(fuse=(t1 - t0) * 1e3, render=(t2 - t1) * 1e3, total=(t2 - t0) * 1e3,
                       render_rgb=(t3 - t2) * 1e3, total_rgb=(t1 - t0 + t3 - t2) * 1e3,
                       cpu=(c2 - c0) * 1e3,
                       visible=stats["visible"], rendered=m.last_timings.get("render_visible", 0.0),
                       coverage=view.coverage(), matched=stats["matched"], added=stats["added"])
            rows.append(row)
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    med.update(size=f"{W}x{H}", surfels=len(m), built=built, build_frames=frame)
    return med


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="320x256,640x512", help="comma-separated WxH list")
    ap.add_argument("--surfels", type=int, default=1_000_000, help="map size to build before timing")
    ap.add_argument("--frames", type=int, default=20, help="timed frames (median reported)")
    ap.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--kernels", default="auto", choices=["auto", "compiled", "torch"],
                    help="MapConfig.kernels: compiled (numba, CPU) or torch code")
    ap.add_argument("--json", default="", help="also write the per-size medians to this JSON file")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = MapConfig(kernels=args.kernels)
    results = []
    for size in args.sizes.split(","):
        W, H = (int(v) for v in size.lower().split("x"))
        print(f"building a {args.surfels}-surfel map at {W}x{H} ...", flush=True)
        results.append(bench(H, W, args.surfels, args.frames, args.device, cfg))

    print(f"\nsurfel map benchmark: device={args.device}, kernels={args.kernels}, torch threads={args.threads}, "
          f"median over {args.frames} frames (ms; stages are the parts of 'fuse', 'total' = fuse + "
          f"render wall time, 'cpu' = process CPU time of fuse + render, all threads; '_rgb': rendering the "
          f"colour too)")
    cols = ["size", "surfels", "visible"] + STAGES + ["fuse", "render", "total", "render_rgb", "total_rgb", "cpu", "rendered",
                                                "coverage"]
    hdr = " | ".join(f"{c:>10}" for c in cols)
    print(hdr)
    print("-" * len(hdr))
    for r in results:
        cells = []
        for c in cols:
            v = r[c]
            if isinstance(v, str):
                cells.append(f"{v:>10}")
            elif c in ("surfels", "visible", "rendered"):
                cells.append(f"{int(v):>10d}")
            elif c == "coverage":
                cells.append(f"{v:>10.3f}")
            else:
                cells.append(f"{v:>10.1f}")
        print(" | ".join(cells))
    if args.json:
        settings = {"device": args.device, "kernels": args.kernels, "threads": args.threads, "frames": args.frames}
        with open(args.json, "w") as fh:
            json.dump({"settings": settings, "results": results}, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
