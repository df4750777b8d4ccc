"""Configuration of the surfel map (one concern: how depth frames are fused, rendered and exported).

Units are millimetres and pixels throughout; defaults suit a stereo endoscope observing tissue
20-200 mm away at 320x256 - 640x512 pixels.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


def fixed(why: str, default):
    """A field a person does not set: the application's configuration refuses it (its analysis
    tools may change it); the map reads it like any other."""
    return field(default=default, metadata={"fixed": why})


class MapConfigError(ValueError):
    """A map setting out of range or unknown (the application reports it as a config error)."""


@dataclass
class MapConfig:
    """User settings of :class:`mapping.SurfelMap` (ElasticFusion-style surfel fusion).

    Every other parameter of the map is a named constant of the module that uses it
    (:mod:`mapping.fusion`, :mod:`mapping.render`, :mod:`mapping.surfels`, :mod:`mapping.export`),
    with its value's justification.

    Attributes:
        min_depth_mm: input depths below this are ignored (not fused, no free-space test).
        max_depth_mm: input depths above this are ignored.
        stable_confidence: surfels whose accumulated confidence reaches this are *stable*.
        max_confidence: confidence is clamped to this (keeps a long-lived surfel able to adapt).
        unstable_window: an unstable surfel still unstable ``unstable_window`` frames after its
            creation is removed (ElasticFusion's time window).
        free_space_mm: minimum free-space margin: a visible surfel that lies in front of the
            measured surface along its pixel's ray by more than the margin violates free space
            (the margin is ``max(free_space_mm, mapping.fusion.FREE_SPACE_REL * depth)`` and never
            below the association tolerance).
        kernels: how the fusion, the view culling and the splatting passes run: ``torch`` =
            vectorised torch code on the map's device (CPU or GPU); ``compiled`` = the numba
            kernels of :mod:`mapping.kernels` (CPU only; one loop per surfel instead of many tensor
            passes: with a million surfels fusion 15 against 27-45 ms, the colour render 14
            against 22-25 ms); ``auto`` = ``compiled`` for a CPU map when numba is installed, else
            ``torch``.
    """

    stable_confidence: float = 3.0
    unstable_window: int = 20
    min_depth_mm: float = fixed("the map's input range (the tracker's is depth.min/max_depth_mm)", 20.0)
    max_depth_mm: float = fixed("the map's input range (the tracker's is depth.min/max_depth_mm)", 200.0)
    max_confidence: float = fixed("ElasticFusion's clamp of a surfel's confidence", 100.0)
    free_space_mm: float = fixed("the free-space margin, with mapping.fusion.FREE_SPACE_REL", 3.0)
    kernels: Literal["auto", "compiled", "torch"] = fixed("an analysis switch (analysis.map_kernels)", "auto")

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise :class:`MapConfigError` on a value out of range."""
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise MapConfigError(f"map: {msg}")

        need(0 < self.min_depth_mm < self.max_depth_mm, "need 0 < min_depth_mm < max_depth_mm")
        need(self.stable_confidence > 0, "map.stable_confidence must be > 0")
        need(self.max_confidence >= self.stable_confidence, "map.stable_confidence must be <= max_confidence (100)")
        need(self.unstable_window >= 1, "map.unstable_window must be >= 1")
        need(self.free_space_mm > 0, "free_space_mm must be > 0")
        need(self.kernels in ("auto", "compiled", "torch"), "kernels must be 'auto', 'compiled' or 'torch'")
