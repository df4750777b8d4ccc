"""The surfel map facade: fusion, rendering and export over one :class:`SurfelStore`."""
from __future__ import annotations

import numpy as np
import torch

from . import export
from .config import MapConfig
from . import kernels
from .fusion import FREE_SPACE_REL, MIN_FUSE_WEIGHT, SKIP_COVERED, StageTimer, fuse_frame, measure
from .render import FAR_MM, NEAR_MM, Camera, ModelView, render, visible_set
from .surfels import CHUNK_SIZE, COMPACT_FRACTION, INITIAL_CAPACITY, SurfelStore


class SurfelMap:
    """An ElasticFusion-style surfel map in millimetres.

    Poses are 4x4 ``T_wc`` (camera to world, OpenCV axes), ``K`` is the 3x3 pinhole intrinsics;
    depth ``(H, W)`` float32 mm (0 = invalid), colour ``(3, H, W)`` in [0, 1].

    Args:
        config: the user settings (:class:`MapConfig`); defaults when None.
        device: torch device every tensor lives on.
        capacity, chunk_size, compact_fraction: the store's initial capacity, surfels per spatial
            chunk and compaction threshold (:class:`SurfelStore`; defaults
            :data:`mapping.surfels.INITIAL_CAPACITY`, ``CHUNK_SIZE``, ``COMPACT_FRACTION``).
        skip_covered: unmatched pixels on a neighbour's disc add no surfel
            (:data:`mapping.fusion.SKIP_COVERED`).
        min_fuse_weight: pixels of fusion weight at most this are not fused
            (:data:`mapping.fusion.MIN_FUSE_WEIGHT`).

    Attributes:
        profile: when True, ``fuse`` and ``render`` record milliseconds per stage in
            ``last_timings`` (synchronising the device; off by default).
    """

    def __init__(self, config: MapConfig | None = None, device: str | torch.device = "cpu", *,
                 capacity: int = INITIAL_CAPACITY, chunk_size: int = CHUNK_SIZE,
                 compact_fraction: float = COMPACT_FRACTION, skip_covered: bool = SKIP_COVERED,
                 min_fuse_weight: float = MIN_FUSE_WEIGHT) -> None:
        self.config = config if config is not None else MapConfig()
        self.config.validate()
        if not 0 <= min_fuse_weight < 1:
            raise ValueError("SurfelMap: min_fuse_weight must be in [0, 1)")
        self.device = torch.device(device)
        self._options = dict(capacity=capacity, chunk_size=chunk_size, compact_fraction=compact_fraction,
                             skip_covered=skip_covered, min_fuse_weight=min_fuse_weight)
        self.skip_covered = bool(skip_covered)
        self.min_fuse_weight = float(min_fuse_weight)
        self.store = SurfelStore(capacity, chunk_size, compact_fraction=compact_fraction, device=self.device)
        self.profile = False
        self.last_timings: dict[str, float] = {}
        self.frames_fused = 0

    # ------------------------------------------------------------------ fusion
    def fuse(self, depth, color, K, T_wc, frame_index: int, weight=None, valid=None,
             active_from: int | None = None) -> dict:
        """Fuse one frame; returns stats ``matched``, ``added``, ``removed`` (free-space, merged and
        expired surfels; plus ``merged``, ``decayed``: stable surfels whose confidence a free-space
        violation decayed, ``visible``: surfels in view before fusion, ``surfels``: live after).

        Args:
            depth: ``(H, W)`` mm, 0 (or outside ``[min_depth_mm, max_depth_mm]``) = invalid.
            color: ``(3, H, W)`` in [0, 1].
            K: ``(3, 3)`` intrinsics; T_wc: ``(4, 4)`` camera-to-world pose of the frame.
            frame_index: frame counter (non-decreasing), used for the time window.
            weight: optional ``(H, W)`` in [0, 1]; 0 = not fused (instrument, specular, deforming).
            valid: optional ``(H, W)`` bool; False = not fused.
            active_from: only the active model takes part: surfels last fused at this frame
                index or later (ElasticFusion's active/inactive split); the inactive ones are
                neither matched, updated nor carved. None: every surfel.
        """
        timer = StageTimer(self.profile, self.device)
        H, W = depth.shape[-2:]
        cam = Camera.make(K, T_wc, H, W, self.device)
        meas = measure(depth, color, cam, self.config, weight, valid, min_fuse_weight=self.min_fuse_weight)
        timer.lap("measure")
        stats = fuse_frame(self.store, self.config, cam, meas, int(frame_index), timer,
                           skip_covered=self.skip_covered, active_from=active_from)
        self.frames_fused += 1
        if self.profile:
            self.last_timings = dict(timer.times)
        return stats

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the kernels the fusion and the renderer use, by
        fusing and rendering a small plane in a throwaway map with this map's settings and device.
        The first call of a compiled kernel otherwise stalls the first frame by about half a second
        (importing numba, loading the machine code); runs call this before their clock starts.
        This map is not touched."""
        scratch = SurfelMap(self.config, self.device, **self._options)
        H, W = 24, 32
        K = torch.tensor([[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]])
        depth = torch.full((H, W), 0.5 * (self.config.min_depth_mm + self.config.max_depth_mm), device=self.device)
        color = torch.full((3, H, W), 0.5, device=self.device)
        weight = torch.ones(H, W, device=self.device)
        valid = torch.ones(H, W, dtype=torch.bool, device=self.device)
        for i in range(2):
            T = torch.eye(4)
            T[0, 3] = 0.5 * i
            scratch.fuse(depth, color, K, T, i, weight=weight, valid=valid)
            scratch.render(K, T, H, W, colour=False).with_colour()

    # ------------------------------------------------------------------ rendering
    def render(self, K, T_wc, height: int, width: int, stable_only: bool = False, colour: bool = True, *,
               seen_from: int | None = None, seen_before: int | None = None) -> ModelView:
        """Splat the map into a ``height x width`` view from ``T_wc`` (see :class:`ModelView`);
        ``colour=False``: depth, normals and confidence only (the colour is left zero);
        ``seen_from``, ``seen_before``: only the surfels last fused at a frame index in
        ``[seen_from, seen_before)`` (the active model: ``seen_from``; the inactive one:
        ``seen_before``)."""
        timer = StageTimer(self.profile, self.device)
        view, nvis = render(self.store, self.config, K, T_wc, int(height), int(width), stable_only, colour,
                            seen_from=seen_from, seen_before=seen_before)
        timer.lap("render")
        if self.profile:
            self.last_timings = {**self.last_timings, **timer.times, "render_visible": float(nvis)}
        return view

    def forget_view(self, K, T_wc, height: int, width: int, seen_from: int | None = None) -> int:
        """Remove the surfels a ``height x width`` view from ``T_wc`` sees: those that project
        inside the image no further than ``free_space_mm`` behind the rendered surface (the
        surface and what lies in front of it, the part of the map the view would fuse into), so
        that the next fused frame rebuilds that part of the map; ``seen_from``: of the active
        model only (last fused at this frame index or later). Returns how many were removed."""
        view, _ = render(self.store, self.config, K, T_wc, int(height), int(width), False, False, seen_from=seen_from)
        st = self.store
        alive = st.alive[: st.n]
        if seen_from is not None:
            alive = alive & (st.t_last[: st.n] >= int(seen_from))
        alive = alive.nonzero().squeeze(1)
        if alive.numel() == 0:
            return 0
        cam = Camera.make(K, T_wc, height, width, self.device)
        p = cam.to_cam(st.pos[alive])
        z = p[:, 2]
        front = z > 1e-6
        u = torch.round(cam.fx * p[:, 0] / z.clamp(min=1e-6) + cam.cx).long()
        v = torch.round(cam.fy * p[:, 1] / z.clamp(min=1e-6) + cam.cy).long()
        inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        surface = torch.zeros_like(z)
        surface[inside] = view.depth[v[inside], u[inside]]
        seen = inside & (surface > 0) & (z <= surface + self.config.free_space_mm)
        removed = st.kill(alive[seen])
        st.maybe_compact()
        return removed

    # ------------------------------------------------------------------ loop closure
    def last_seen_in_view(self, K, T_wc, height: int, width: int, seen_before: int) -> torch.Tensor:
        """``(V,)`` int64 frame indices at which the surfels a view from ``T_wc`` sees were last
        fused, for those last fused before ``seen_before`` (the inactive model in view)."""
        cam = Camera.make(K, T_wc, height, width, self.device)
        vis = visible_set(self.store, cam, NEAR_MM, FAR_MM, compiled=kernels.use_compiled(self.config, self.device),
                          seen_before=seen_before)
        return self.store.t_last.index_select(0, vis.slots).long()

    def move_surfels(self, corrections: torch.Tensor) -> int:
        """Move every live surfel rigidly with the frame it was last fused at: ``corrections``
        ``(F, 4, 4)`` holds, per frame index, the correction ``T_new T_old^-1`` of that frame's
        pose (a pose-graph optimisation; surfels last fused at a frame index >= F keep their
        place). Positions and normals move; the chunk boxes are rebuilt and the cached view
        dropped. Returns how many surfels moved."""
        st = self.store
        n = st.n
        slots = st.alive[:n].nonzero().squeeze(1)
        if slots.numel() == 0:
            return 0
        t = st.t_last.index_select(0, slots).long()
        inside = t < corrections.shape[0]
        slots, t = slots[inside], t[inside]
        C = corrections.to(device=self.device, dtype=st.pos.dtype).index_select(0, t)      # (M, 4, 4)
        R, tr = C[:, :3, :3], C[:, :3, 3]
        st.pos.index_copy_(0, slots, (R @ st.pos.index_select(0, slots)[:, :, None])[:, :, 0] + tr)
        st.normal.index_copy_(0, slots, (R @ st.normal.index_select(0, slots)[:, :, None])[:, :, 0])
        st.update_boxes(torch.arange(st.num_chunks, device=self.device))
        st.version += 1
        st.edits += 1
        st.scratch.pop("view", None)
        return int(slots.numel())

    def reactivate_view(self, K, T_wc, height: int, width: int, frame_index: int, active_from: int) -> tuple[int, int]:
        """After a loop closure has brought the inactive model in line with the view from
        ``T_wc``: the inactive surfels the view sees (last fused before ``active_from``, on or in
        front of their rendered surface) become active again (last seen at ``frame_index``), and
        the active surfels that duplicate them (within the free-space margin of that surface)
        are merged into them: removed, their confidence added to the surface they duplicate.
        Returns ``(reactivated, merged)``."""
        H, W = int(height), int(width)
        old, _ = render(self.store, self.config, K, T_wc, H, W, False, False, seen_before=active_from)
        st = self.store
        n = st.n
        alive = st.alive[:n].nonzero().squeeze(1)
        if alive.numel() == 0:
            return 0, 0
        cam = Camera.make(K, T_wc, H, W, self.device)
        p = cam.to_cam(st.pos.index_select(0, alive))
        z = p[:, 2]
        zs = z.clamp(min=1e-6)
        u = torch.round(cam.fx * p[:, 0] / zs + cam.cx).long()
        v = torch.round(cam.fy * p[:, 1] / zs + cam.cy).long()
        inside = (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        pix = (v.clamp(0, H - 1) * W + u.clamp(0, W - 1))
        surface = torch.where(inside, old.depth.reshape(-1).index_select(0, pix), torch.zeros_like(z))
        margin = torch.clamp_min(FREE_SPACE_REL * surface, self.config.free_space_mm)
        near_surface = inside & (surface > 0) & ((z - surface).abs() <= margin)
        t_last = st.t_last.index_select(0, alive)
        inactive = t_last < active_from
        revive = alive[near_surface & inactive]
        duplicate = alive[near_surface & ~inactive]
        if duplicate.numel():       # their confidence goes to the old surface at their pixel
            conf = torch.zeros(H * W, dtype=st.conf.dtype, device=self.device)
            conf.index_add_(0, pix[near_surface & ~inactive], st.conf.index_select(0, duplicate))
            gain = conf.index_select(0, pix[near_surface & inactive])
            st.conf.index_copy_(0, revive, (st.conf.index_select(0, revive) + gain).clamp_max(self.config.max_confidence))
        st.t_last.index_fill_(0, revive, int(frame_index))
        merged = st.kill(duplicate)
        st.edits += 1
        st.scratch.pop("view", None)
        st.maybe_compact()
        return int(revive.numel()), merged

    # ------------------------------------------------------------------ queries
    def __len__(self) -> int:
        return self.store.num_alive

    def num_stable(self) -> int:
        return int(self.store.stable_mask(self.config.stable_confidence).sum())

    def points(self, stable_only: bool = True) -> dict:
        """Live (or stable) surfels as numpy arrays: ``positions`` (N, 3) mm, ``normals`` (N, 3),
        ``colors`` (N, 3) in [0, 1], ``radii`` (N,) mm, ``confidence`` (N,), ``t_init``, ``t_last`` (N,)."""
        st = self.store
        n = st.n
        mask = st.stable_mask(self.config.stable_confidence) if stable_only else st.alive[:n]
        idx = mask.nonzero().squeeze(1)

        def np_(x: torch.Tensor) -> np.ndarray:
            return x[idx].detach().cpu().numpy()

        return {"positions": np_(st.pos), "normals": np_(st.normal), "colors": np_(st.color),
                "radii": np_(st.radius), "confidence": np_(st.conf),
                "t_init": np_(st.t_init), "t_last": np_(st.t_last)}

    # ------------------------------------------------------------------ export
    def save_ply(self, path, stable_only: bool = True, scale: float = 1e-3) -> int:
        """Write an open3d point cloud (colours, normals; metres by default) to ``path``; returns
        the number of points."""
        return export.save_ply(self.points(stable_only), path, scale)

    def save_mesh(self, path, scale: float = 1e-3, depth: int = 8) -> int:
        """Mesh the stable points (Poisson of octree ``depth``, density/distance trimmed; ball
        pivoting fallback) and write it to ``path``; returns the triangle count."""
        return export.save_mesh(self.points(True), path, scale, depth)

    def __repr__(self) -> str:
        return (f"SurfelMap({len(self)} surfels, {self.num_stable()} stable, "
                f"capacity {self.store.capacity}, device {self.device})")
