"""Configuration of the surfel map (one concern: how depth frames are fused, rendered and exported).

Units are millimetres and pixels throughout; defaults suit a stereo endoscope observing tissue
20-200 mm away at 320x256 - 640x512 pixels.
"""
from __future__ import annotations

from dataclasses import dataclass, fields



class MapConfigError(ValueError):
    """A map setting out of range or unknown (the application reports it as a config error)."""


@dataclass
class MapConfig:
    """Tunables of :class:`mapping.SurfelMap` (ElasticFusion-style surfel fusion).

    Attributes:
        min_depth_mm: input depths below this are ignored (not fused, no free-space test).
        max_depth_mm: input depths above this are ignored.
        near_mm: near clipping distance of the renderer / view culling.
        far_mm: far clipping distance of the renderer / view culling.

        normal_max_jump_rel: a central-difference normal is only computed where both neighbours
            along x and y are valid and their depth differs from the centre pixel by at most this
            fraction of the centre depth (depth discontinuities get no normal and are not fused).
            0.03 admits surfaces inclined up to ~75-80 deg to the view at 150-600 px focal length.
        radius_min_cos: clamp of ``|n . ray|`` in the surfel radius
            ``r = sqrt(2) * depth / f / max(|n . ray|, radius_min_cos)`` (``|n . ray| = |n_z|`` on the
            optical axis); with the default 0.5 the radius of a grazing surfel is at most twice the
            fronto-parallel one (ElasticFusion's ``min(2 r, r / |n_z|)``).
        radius_scale: extra factor on the radius (1 = ElasticFusion's ``sqrt(2) * depth / f``).
        radial_sigma: sigma of the radial Gaussian confidence weight
            ``exp(-d^2 / (2 sigma^2))``, ``d`` = distance from the principal point normalised by the
            distance of the farthest image corner (ElasticFusion: 0.6). 0 disables the weighting.
        min_fuse_weight: pixels whose fusion weight (input weight x radial weight) is at most this
            are neither fused nor used for the free-space test (weight-0 pixels: instruments,
            specularities, deforming tissue).

        index_scale: super-sampling of the index map used for projective data association
            (ElasticFusion: 4, i.e. 4x4 index-map cells per pixel, each holding the nearest surfel).
        assoc_depth_mm: minimum depth tolerance of a match (surfel depth vs measured depth).
        assoc_depth_rel: depth tolerance of a match as a fraction of the measured depth; the
            tolerance is ``max(assoc_depth_mm, assoc_depth_rel * depth)``.
        assoc_normal_deg: maximum angle between the measured normal and the surfel normal of a match.
        assoc_conf_tie_rel: among the candidates of a pixel the most confident one wins; candidates
            whose confidence is within this fraction of the best are considered tied and the one
            closest to the pixel's viewing ray wins (Keller et al. 2013).
        radius_update_ratio: a matched measurement updates position, normal, colour and radius only
            when its radius is below ``radius_update_ratio`` x the surfel's radius (ElasticFusion's
            rule: coarser measurements never blur finer surfels); confidence and last-seen are
            always updated.
        merge_radius_factor: a candidate that matches a pixel but loses to a more confident one is
            merged into the winner (and removed) when their centres are closer than this times the
            smaller radius (Keller et al. 2013); 0 disables merging.

        skip_covered: a fusable pixel that matched no surfel but lies within half a radius (about a
            pixel) of a surfel centred in a neighbouring pixel, within the association's depth and
            normal tolerances, adds no new surfel (it is already represented: the renderer shows
            that surfel there).
            Association only pairs a pixel with the surfels whose centre falls inside it, and on
            a mapped surface about one pixel in eight holds none: without this each would add a
            duplicate surfel every frame (12 % of a scanning frame's pixels).
        stable_confidence: surfels whose accumulated confidence reaches this are *stable*.
        max_confidence: confidence is clamped to this (keeps a long-lived surfel able to adapt).
        unstable_window: an unstable surfel still unstable ``unstable_window`` frames after its
            creation is removed (ElasticFusion's time window).
        free_space_mm: minimum free-space margin: a visible surfel that lies in front of the
            measured surface along its pixel's ray by more than the margin violates free space.
        free_space_rel: free-space margin as a fraction of the measured depth; the margin is
            ``max(free_space_mm, free_space_rel * depth)`` and never below the association
            tolerance.
        free_space_decay: confidence factor applied to a stable surfel violating free space; an
            unstable violator is removed at once.

        initial_capacity: surfel slots allocated up front.
        growth_factor: capacity growth factor when the store is full (geometric growth).
        chunk_size: surfels per spatial chunk; each chunk keeps a bounding box so that view culling
            touches only the chunks inside the frustum (cost follows the visible surfels).  A frame's
            new surfels are appended in image-tile order (tiles of ~sqrt(chunk_size) pixels), so a
            chunk covers a compact patch of surface.
        compact_fraction: the store is compacted (removed slots squeezed out, order kept) once
            this fraction of its slots are dead.
        sort_cell_mm: cell size of the Z-order curve along which surfels past their unstable window
            are re-ordered in blocks (compact chunks, tight culling); 0 disables the re-ordering.

        splat_max_half: the renderer splats a surfel into at most a
            ``(2 * splat_max_half + 1)^2`` pixel footprint (3 -> 7x7).
        splat_round: footprint half-size is ``floor(R + splat_round)`` pixels for a footprint
            radius ``R`` (0.5 = every pixel the footprint can touch; smaller is faster, the
            neighbouring discs of a surface seen at its fusion resolution still close every gap).
        render_exact_discs: footprint of a surfel in the renderer: False = the circle of the same
            area as the disc's image ellipse, ``R = r_px * sqrt(|n . ray|)`` around the projected
            centre (``r_px`` the projected radius; cheap, depth still exact on the disc's plane),
            True = the exact ray/disc intersection test (the disc's image ellipse, ``R = r_px``;
            about 2x the per-surfel work).
        render_min_cos: surfels whose disc is seen at ``|n . ray|`` below this are splatted only
            into their centre pixel (ray-disc intersection is ill-conditioned at grazing angles).
        render_depth_tol_mm: the renderer z-buffers the footprints (stable surfels take precedence
            over unstable ones), then blends, per pixel, the surfels of the front's class whose
            depth on their plane lies within ``max(render_depth_tol_mm, render_depth_tol_rel *
            depth)`` behind the front depth (the surfels of the visible surface; occluded surfaces
            lie farther behind).
        render_depth_tol_rel: see ``render_depth_tol_mm``.
        render_blend_sigma: width of the renderer's blending kernel relative to the footprint
            radius ``R``: a surfel's weight at a pixel is ``(1 - d^2 / R^2)^k`` (``d`` the distance
            from the pixel centre to the surfel's projected centre, ``k = round(1 / (2 sigma^2))``),
            about a Gaussian of ``sigma * R`` pixels with compact support.  The colour and depth of
            a pixel are the normalised blend of the surfels centred near it; smaller is sharper
            but approaches nearest-surfel sampling (jagged), larger blurs.
        render_depth: ``front``: a pixel's depth is that of the front surfel's plane along the
            pixel's ray (exact sub-pixel depth of the disc the pixel sees); ``blended``: the same
            blend as the colour. Measured on our frame2model runs, ``front`` tracks at least as
            well (mean ATE 0.43 vs 0.47 mm over four sequences) and a depth-only render then
            needs no blending pass (half the render cost).
        render_cull_hidden_unstable: unstable surfels show only where no stable one covers a pixel;
            with this, those whose footprint stable surfels cover (its centre pixel and the 8
            pixels at its corners and edge midpoints) are not splatted at all. On a scanning run
            half of the visible surfels are unstable (measurements that did not associate), most
            of them under the stable surface: about 15 % less render time (paired runs).
        kernels: how the fusion, the view culling and the splatting passes run: ``torch`` =
            vectorised torch code on the map's device (CPU or GPU); ``compiled`` = the numba
            kernels of :mod:`mapping.kernels` (CPU only; one loop per surfel instead of many tensor
            passes: with a million surfels fusion 15 against 27-45 ms, the colour render 14
            against 22-25 ms); ``auto`` = ``compiled`` for a CPU map when numba is installed, else
            ``torch``. (``render_exact_discs`` footprints are splatted by torch either way.)

        mesh_density_quantile: Poisson vertices whose density is below this quantile are trimmed.
        mesh_trim_radius_factor: Poisson vertices farther than this many median surfel radii from
            the nearest stable surfel are trimmed (Poisson extrapolates over holes and borders).
    """

    # input range
    min_depth_mm: float = 20.0
    max_depth_mm: float = 200.0
    near_mm: float = 5.0
    far_mm: float = 400.0

    # per-pixel measurements
    normal_max_jump_rel: float = 0.03
    radius_min_cos: float = 0.5
    radius_scale: float = 1.0
    radial_sigma: float = 0.6
    min_fuse_weight: float = 0.0

    # data association and fusion
    index_scale: int = 4
    assoc_depth_mm: float = 2.0
    assoc_depth_rel: float = 0.02
    assoc_normal_deg: float = 35.0
    assoc_conf_tie_rel: float = 0.05
    radius_update_ratio: float = 1.5
    merge_radius_factor: float = 1.0
    skip_covered: bool = True

    # confidence and removal
    stable_confidence: float = 3.0
    max_confidence: float = 100.0
    unstable_window: int = 20
    free_space_mm: float = 3.0
    free_space_rel: float = 0.04
    free_space_decay: float = 0.5

    # storage
    initial_capacity: int = 1 << 16
    growth_factor: float = 2.0
    chunk_size: int = 256
    compact_fraction: float = 0.25
    sort_cell_mm: float = 1.0

    # rendering
    splat_max_half: int = 3
    splat_round: float = 0.25
    render_exact_discs: bool = False
    render_min_cos: float = 0.05
    render_depth_tol_mm: float = 1.0
    render_depth_tol_rel: float = 0.02
    render_blend_sigma: float = 0.35
    render_depth: str = "front"
    render_cull_hidden_unstable: bool = True

    # implementation
    kernels: str = "auto"

    # export
    mesh_density_quantile: float = 0.02
    mesh_trim_radius_factor: float = 6.0

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise :class:`MapConfigError` on a value out of range."""
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise MapConfigError(f"mapping: {msg}")

        need(0 < self.min_depth_mm < self.max_depth_mm, "need 0 < min_depth_mm < max_depth_mm")
        need(0 < self.near_mm < self.far_mm, "need 0 < near_mm < far_mm")
        need(self.normal_max_jump_rel > 0, "normal_max_jump_rel must be > 0")
        need(0 < self.radius_min_cos <= 1, "radius_min_cos must be in (0, 1]")
        need(self.radius_scale > 0, "radius_scale must be > 0")
        need(self.radial_sigma >= 0, "radial_sigma must be >= 0")
        need(0 <= self.min_fuse_weight < 1, "min_fuse_weight must be in [0, 1)")
        need(int(self.index_scale) == self.index_scale and 1 <= self.index_scale <= 8,
             "index_scale must be an integer in [1, 8]")
        need(self.assoc_depth_mm > 0 and self.assoc_depth_rel >= 0, "association tolerances must be > 0")
        need(0 < self.assoc_normal_deg <= 90, "assoc_normal_deg must be in (0, 90]")
        need(0 <= self.assoc_conf_tie_rel < 1, "assoc_conf_tie_rel must be in [0, 1)")
        need(self.radius_update_ratio >= 1, "radius_update_ratio must be >= 1")
        need(self.merge_radius_factor >= 0, "merge_radius_factor must be >= 0")
        need(self.stable_confidence > 0, "stable_confidence must be > 0")
        need(self.max_confidence >= self.stable_confidence, "max_confidence must be >= stable_confidence")
        need(self.unstable_window >= 1, "unstable_window must be >= 1")
        need(self.free_space_mm > 0 and self.free_space_rel >= 0, "free-space margins must be > 0")
        need(0 <= self.free_space_decay < 1, "free_space_decay must be in [0, 1)")
        need(self.initial_capacity >= 1, "initial_capacity must be >= 1")
        need(self.growth_factor > 1, "growth_factor must be > 1")
        need(self.chunk_size >= 64, "chunk_size must be >= 64")
        need(self.sort_cell_mm >= 0, "sort_cell_mm must be >= 0")
        need(0 < self.compact_fraction <= 1, "compact_fraction must be in (0, 1]")
        need(0 <= self.splat_max_half <= 8, "splat_max_half must be in [0, 8]")
        need(0 <= self.splat_round <= 1, "splat_round must be in [0, 1]")
        need(0 <= self.render_min_cos < 1, "render_min_cos must be in [0, 1)")
        need(self.render_depth_tol_mm > 0 and self.render_depth_tol_rel >= 0,
             "render_depth_tol_mm must be > 0 and render_depth_tol_rel >= 0")
        need(0.1 <= self.render_blend_sigma <= 0.75, "render_blend_sigma must be in [0.1, 0.75]")
        need(self.render_depth in ("front", "blended"), "render_depth must be 'front' or 'blended'")
        need(self.kernels in ("auto", "compiled", "torch"), "kernels must be 'auto', 'compiled' or 'torch'")
        need(0 <= self.mesh_density_quantile < 1, "mesh_density_quantile must be in [0, 1)")
        need(self.mesh_trim_radius_factor > 0, "mesh_trim_radius_factor must be > 0")

    @classmethod
    def from_dict(cls, values: dict | None) -> "MapConfig":
        """Build from a plain mapping (e.g. a YAML section); unknown keys raise MapConfigError."""
        values = dict(values or {})
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise MapConfigError(f"mapping: unknown key(s) {', '.join(unknown)}")
        out = {}
        for k, v in values.items():
            typ = type(getattr(cls, k))
            if typ is str:
                out[k] = str(v)
                continue
            if typ is bool:
                if not isinstance(v, bool):
                    raise MapConfigError(f"mapping: {k} must be true or false, got {v!r}")
                out[k] = v
                continue
            try:
                fv = float(v)
                if typ is int and fv != int(fv):
                    raise ValueError
                out[k] = int(fv) if typ is int else fv
            except (TypeError, ValueError):
                raise MapConfigError(f"mapping: {k} must be a {typ.__name__}, got {v!r}") from None
        return cls(**out)
