"""The generator's appearance options: texture strength, highlights, smoke, exposure, colour."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from slam.errors import DataError
from slam.synth import generate
from slam.synth.appearance import RANDOM_RANGES, Appearance, parse_appearance, random_appearance
from slam.synth.scene import TEX_RES_MM
from slam.synth.texture import make_albedo

SIZE = (160, 128)
SEED = 9401


def _frames(folder: Path, side: str = "l") -> list[np.ndarray]:
    files = sorted((folder / "video_frames").glob(f"*{side}.png"))
    return [cv2.imread(str(f), cv2.IMREAD_COLOR).astype(np.float32) for f in files]


def _render(tmp_path: Path, name: str, frames: int = 1, **look) -> list[np.ndarray]:
    out = generate(tmp_path / name, "rigid", frames=frames, size=SIZE, seed=SEED, appearance=Appearance(**look))
    return _frames(out)


def _fine_structure(rgb: np.ndarray) -> float:
    """Std of the band-pass (0.3-3 mm) of an albedo texture's green channel."""
    g = rgb[..., 1].astype(np.float32)
    mm = 1.0 / TEX_RES_MM
    band = cv2.GaussianBlur(g, (0, 0), 0.3 * mm) - cv2.GaussianBlur(g, (0, 0), 3 * mm)
    return float(band.std())


def test_the_default_appearance_is_the_generators_own_look(tmp_path):
    plain = _frames(generate(tmp_path / "plain", "rigid", frames=2, size=SIZE, seed=SEED))
    explicit = _render(tmp_path, "explicit", frames=2, texture=1.0, highlights=0.0, haze=0.0, vignetting=3.0)
    for a, b in zip(plain, explicit):
        assert np.array_equal(a, b)
    meta = json.loads((tmp_path / "explicit" / "synth.json").read_text())
    assert meta["appearance"] == Appearance().as_dict()


def test_texture_strength_scales_the_fine_structure_of_the_same_vessels():
    size = 600  # 60 mm of texture
    rich = make_albedo(np.random.default_rng([5, 2]), size, TEX_RES_MM, texture=1.0)
    weak = make_albedo(np.random.default_rng([5, 2]), size, TEX_RES_MM, texture=0.0)
    half = make_albedo(np.random.default_rng([5, 2]), size, TEX_RES_MM, texture=0.5)
    s_rich, s_half, s_weak = (_fine_structure(t) for t in (rich, half, weak))
    assert s_weak < 0.5 * s_rich
    assert s_weak < s_half < s_rich
    # the same tissue: its large-scale pattern (fat patches, red and pale regions) is kept
    low = [cv2.GaussianBlur(t[..., 1].astype(np.float32), (0, 0), 40).ravel() for t in (rich, weak)]
    assert np.corrcoef(low[0], low[1])[0, 1] > 0.8


def test_highlights_cover_up_to_a_fifth_of_the_view(tmp_path):
    dry = _render(tmp_path, "dry", texture=0.0)[0]
    wet = _render(tmp_path, "wet", texture=0.0, highlights=1.0)[0]
    saturated = [float((im.max(axis=2) >= 250).mean()) for im in (dry, wet)]
    assert saturated[0] < 0.06
    assert 0.12 < saturated[1] < 0.35


def test_smoke_veils_the_view_and_drifts(tmp_path):
    clear = _render(tmp_path, "clear", frames=2)
    smoky = _render(tmp_path, "smoky", frames=2, haze=0.6)
    gray = [cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in (clear[0], smoky[0])]
    assert gray[1].std() < 0.8 * gray[0].std()           # contrast lost
    assert gray[1].min() > gray[0].min()                  # the veil lifts the dark
    veil0, veil1 = (s - c for s, c in zip(smoky, clear))
    assert np.abs(veil0 - veil1).mean() > 1.0             # and it moves between frames


def test_exposure_changes_move_both_views_together(tmp_path):
    out = generate(tmp_path / "auto", "rigid", frames=12, size=SIZE, seed=SEED,
                   appearance=Appearance(exposure_jitter=0.15))
    fixed = _frames(generate(tmp_path / "fixed", "rigid", frames=12, size=SIZE, seed=SEED))
    left, right = _frames(out, "l"), _frames(out, "r")
    ratio_l = np.array([a.mean() / b.mean() for a, b in zip(left, fixed)])
    fixed_r = _frames(tmp_path / "fixed", "r")
    ratio_r = np.array([a.mean() / b.mean() for a, b in zip(right, fixed_r)])
    assert ratio_l.std() > 0.03
    np.testing.assert_allclose(ratio_l, ratio_r, atol=0.02)


def test_tint_and_vignetting(tmp_path):
    base = _render(tmp_path, "base", texture=0.5)[0]
    pale = _render(tmp_path, "pale", texture=0.5, tint=0.7)[0]
    dark_rim = _render(tmp_path, "rim", texture=0.5, vignetting=7.0)[0]
    red_share = [im[..., 2].mean() / im.mean() for im in (base, pale)]  # BGR: channel 2 is red
    assert red_share[1] < red_share[0] - 0.05
    corner = (slice(0, 16), slice(0, 16))
    assert dark_rim[corner].mean() < 0.8 * base[corner].mean()


def test_random_appearance_is_drawn_per_seed_within_its_ranges():
    looks = [random_appearance(s) for s in range(40)]
    assert random_appearance(3) == looks[3]
    assert len({lk.texture for lk in looks}) == 40
    for name, (lo, hi) in RANDOM_RANGES.items():
        values = [getattr(lk, name) for lk in looks]
        assert lo <= min(values) and max(values) <= hi
    assert sum(lk.texture < 0.5 for lk in looks) >= 10


def test_parse_appearance():
    assert parse_appearance(None, 1) == Appearance()
    assert parse_appearance("random", 4) == random_appearance(4)
    assert parse_appearance("texture=0.1, highlights=1", 0) == Appearance(texture=0.1, highlights=1.0)
    for bad, word in [("texture", "KEY=VALUE"), ("gloss=1", "KEY=VALUE"), ("texture=a", "not a number"),
                      ("texture=2", "outside")]:
        with pytest.raises(DataError, match=word):
            parse_appearance(bad, 0)


def test_synth_command_takes_an_appearance(tmp_path):
    out = tmp_path / "cli"
    done = subprocess.run([sys.executable, "-m", "slam", "synth", str(out), "--scenario", "rigid", "--frames", "1",
                           "--size", "64x48", "--appearance", "texture=0.2,haze=0.3"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert json.loads((out / "synth.json").read_text())["appearance"]["haze"] == 0.3
    bad = subprocess.run([sys.executable, "-m", "slam", "synth", str(tmp_path / "bad"), "--scenario", "rigid",
                          "--frames", "1", "--size", "64x48", "--appearance", "texture=5"], capture_output=True, text=True)
    assert bad.returncode != 0
    assert len(bad.stderr.strip().splitlines()) == 1 and "texture" in bad.stderr
