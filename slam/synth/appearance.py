"""How a synthetic sequence looks, apart from its geometry: texture strength, highlights, tissue
colour, vignetting, exposure changes, smoke.

The default :class:`Appearance` renders exactly the sequences the generator has always made; each
field moves one physical property away from it. :func:`random_appearance` draws one appearance
per seed from the ranges real endoscopy shows (rich to nearly textureless tissue, highlights up
to about a fifth of the view, smoke), for training and validation sets that are not one look.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np

from slam.errors import DataError

# ranges of every field: (lowest, highest) accepted, and the range random_appearance draws from
LIMITS = {
    "texture": (0.0, 1.0),
    "highlights": (0.0, 1.0),
    "haze": (0.0, 1.0),
    "exposure_jitter": (0.0, 0.5),
    "vignetting": (0.0, 8.0),
    "tint": (0.5, 1.5),
}
RANDOM_RANGES = {
    "texture": (0.0, 1.0),
    "highlights": (0.0, 1.0),
    "haze": (0.0, 0.6),
    "exposure_jitter": (0.0, 0.08),
    "vignetting": (2.0, 6.0),
    "tint": (0.8, 1.2),
}


@dataclass(frozen=True)
class Appearance:
    """Photometric properties of a synthetic sequence.

    Attributes:
        texture: contrast of the tissue's fine structure in [0, 1]. 1: grain, capillaries and the
            full vessel tree; 0: smooth tissue with a few thin vessels over a fifth of it.
        highlights: wet specular film in [0, 1]. 0: small sharp highlights where the tissue is
            wet; 1: broad saturated highlights over about a fifth of a frontal view.
        haze: density of smoke in [0, 1] (a veil of scattered light drifting across the view).
        exposure_jitter: standard deviation of the per-frame log gain of the camera's automatic
            exposure (a mean-reverting random walk; 0: fixed exposure).
        vignetting: exponent of the lens falloff ``cos(theta)^v`` (3: the default optics).
        tint: scale of the tissue's red against its green and blue (1: the default colour;
            below 1 paler, above 1 redder tissue).
    """

    texture: float = 1.0
    highlights: float = 0.0
    haze: float = 0.0
    exposure_jitter: float = 0.0
    vignetting: float = 3.0
    tint: float = 1.0

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            lo, hi = LIMITS[f.name]
            try:
                ok = lo <= float(value) <= hi
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise DataError(f"synthetic appearance: {f.name} {value!r} is outside {lo}..{hi}")

    def as_dict(self) -> dict:
        return asdict(self)


def random_appearance(seed: int) -> Appearance:
    """One appearance drawn from :data:`RANDOM_RANGES` for ``seed`` (uniform per field; texture
    drawn so that half the sequences are weakly textured, below 0.5)."""
    rng = np.random.default_rng([int(seed), 7])
    values = {name: float(rng.uniform(lo, hi)) for name, (lo, hi) in RANDOM_RANGES.items()}
    return Appearance(**{k: round(v, 3) for k, v in values.items()})


def parse_appearance(text: str | None, seed: int) -> Appearance:
    """``Appearance`` from a command-line value: empty or ``default`` (today's look), ``random``
    (:func:`random_appearance` of ``seed``), or ``key=value`` pairs separated by commas
    (``texture=0.1,highlights=1``)."""
    if text is None or text.strip() in ("", "default"):
        return Appearance()
    if text.strip() == "random":
        return random_appearance(seed)
    values = {}
    names = {f.name for f in fields(Appearance)}
    for item in text.split(","):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or key not in names:
            raise DataError(f"appearance '{item.strip()}': expected KEY=VALUE with KEY one of {', '.join(sorted(names))}")
        try:
            values[key] = float(value)
        except ValueError:
            raise DataError(f"appearance '{item.strip()}': {value.strip()!r} is not a number") from None
    return Appearance(**values)


def appearance_tag(text: str | None) -> str:
    """The suffix a sequence folder of the look ``text`` (as :func:`parse_appearance` reads it)
    carries: empty for today's look, else ``_`` and the spec without its separators
    (``texture=0,highlights=1`` -> ``_texture0_highlights1``)."""
    look = (text or "").strip()
    if look in ("", "default"):
        return ""
    return "_" + look.replace("=", "").replace(",", "_")


class ExposureWalk:
    """The camera's automatic exposure: a gain per frame, ``exp(g_t)`` with ``g_t`` a
    mean-reverting random walk of stationary standard deviation ``jitter`` (Ornstein-Uhlenbeck,
    half the deviation restored in about 5 frames)."""

    def __init__(self, jitter: float, seed: int):
        self.jitter = float(jitter)
        self.rng = np.random.default_rng([int(seed), 8])
        self.g = 0.0

    def gain(self) -> float:
        if self.jitter <= 0:
            return 1.0
        a = 0.87  # 0.87^5 = 0.5
        self.g = a * self.g + self.jitter * np.sqrt(1 - a * a) * float(self.rng.standard_normal())
        return float(np.exp(self.g))
