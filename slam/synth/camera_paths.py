"""Smooth, seeded camera trajectories (left camera ``T_wc``, millimetres).

A path is a smooth curve traversed at a smoothly varying speed (arc-length parameterised), so
the camera moves 0.1-1.5 mm per frame whatever the number of frames, and stays over the tissue
however long the sequence is (the curves are bounded).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

STATIC = ("breathing", "deforming")


def _pose(p: np.ndarray, euler_deg: np.ndarray, base: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = base @ Rotation.from_euler("xyz", euler_deg, degrees=True).as_matrix()
    T[:3, 3] = p
    return T


def _speed_profile(rng: np.random.Generator, steps: int, mean: float) -> np.ndarray:
    """Per-frame arc lengths: ``mean`` modulated smoothly by +-30 %."""
    if steps <= 0:
        return np.zeros(0)
    i = np.arange(steps)
    period = rng.uniform(60, 140)
    v = 1.0 + 0.3 * np.sin(2 * np.pi * i / period + rng.uniform(0, 2 * np.pi))
    return mean * v


def _arc_length(curve: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])


def _base_rotation(rng: np.random.Generator) -> np.ndarray:
    """The camera looks along +z, tilted by a few degrees."""
    return Rotation.from_euler("xyz", [rng.normal(0, 2.0), rng.normal(0, 2.0), rng.uniform(-10, 10)],
                               degrees=True).as_matrix()


def scanning_path(rng: np.random.Generator, frames: int, speed: float = 1.0) -> np.ndarray:
    """Lateral figure-of-eight scanning with depth change and a few degrees of rotation; ``speed``
    scales the distance per frame along the same curve (1: 0.3-0.9 mm per frame).

    The figure-of-eight ``(Ax sin t, Ay sin 2t)`` never has zero velocity, so the arc-length
    reparameterisation is well defined everywhere.
    """
    base = _base_rotation(rng)
    ax, ay, az = rng.uniform(14, 20), rng.uniform(8, 12), rng.uniform(4, 7)
    wz, pz = rng.uniform(0.6, 0.9), rng.uniform(0, 2 * np.pi)
    rot_amp = rng.uniform(1.5, 3.5, 3)
    rot_w = rng.uniform(0.5, 1.5, 3)
    rot_p = rng.uniform(0, 2 * np.pi, 3)
    t0 = rng.uniform(0, 2 * np.pi)

    def curve(t):
        t = t + t0
        xyz = np.stack([ax * np.sin(t), ay * np.sin(2 * t), az * np.sin(wz * t + pz)], -1)
        eul = rot_amp * np.sin(rot_w * t[:, None] + rot_p)
        return xyz, eul

    steps = _speed_profile(rng, frames - 1, rng.uniform(0.45, 0.7)) * speed
    total = float(steps.sum())
    # dense sampling long enough for the whole distance (the 8 is at least 4*ax long per lap)
    laps = total / (4 * ax) + 1
    t = np.linspace(0, 2 * np.pi * laps, int(4000 * laps) + 2)
    xyz, _ = curve(t)
    s = _arc_length(xyz)
    s_frames = np.concatenate([[0.0], np.cumsum(steps)])
    t_frames = np.interp(s_frames, s, t)
    xyz, eul = curve(t_frames)
    return np.stack([_pose(p, e, base) for p, e in zip(xyz, eul)])


def loop_path(rng: np.random.Generator, frames: int) -> np.ndarray:
    """A closed smooth path (ellipse with depth and rotation wobble) that ends where it starts.

    The loop's length follows the number of frames (about 0.5 mm per frame) up to 180 mm; longer
    sequences go round several times.
    """
    base = _base_rotation(rng)
    if frames < 2:
        return np.stack([_pose(np.zeros(3), np.zeros(3), base)])
    aspect = rng.uniform(1.2, 1.8)
    az, pz = rng.uniform(1.5, 3.0), rng.uniform(0, 2 * np.pi)
    rot_amp = rng.uniform(1.0, 3.0, 3)
    rot_k = rng.integers(1, 3, 3)
    rot_p = rng.uniform(0, 2 * np.pi, 3)
    want = 0.5 * (frames - 1)
    laps = max(1, int(round(want / 180.0)))
    per_lap = want / laps
    t = np.linspace(0, 2 * np.pi, 20001)

    def curve(t, r):
        xyz = np.stack([r * aspect * np.cos(t), r * np.sin(t), az * min(1.0, r / 10) * (np.sin(2 * t + pz) - np.sin(pz))], -1)
        eul = rot_amp * min(1.0, r / 10) * (np.sin(rot_k * t[:, None] + rot_p) - np.sin(rot_p))
        return xyz, eul

    r = per_lap / (2 * np.pi * np.sqrt((1 + aspect ** 2) / 2))
    for _ in range(6):  # fit the radius to the wanted lap length
        r *= per_lap / _arc_length(curve(t, r)[0])[-1]
    xyz, _ = curve(t, r)
    s = _arc_length(xyz)
    steps = _speed_profile(rng, frames - 1, 1.0)
    s_frames = np.concatenate([[0.0], np.cumsum(steps)])
    s_frames *= laps * s[-1] / s_frames[-1]
    lap = np.minimum(np.floor(s_frames / s[-1]), laps - 1)
    t_frames = np.interp(s_frames - lap * s[-1], s, t)
    t_frames[-1] = 2 * np.pi  # close exactly
    xyz, eul = curve(t_frames, r)
    return np.stack([_pose(p, e, base) for p, e in zip(xyz, eul)])


def make_path(scenario: str, frames: int, seed: int, speed: float = 1.0) -> np.ndarray:
    """Left-camera poses ``(frames, 4, 4)`` ``T_wc`` (mm) of a scenario; ``speed`` scales how far
    the rigid and scanning cameras move per frame (a loop always closes over its frames; a static
    camera does not move)."""
    rng = np.random.default_rng([seed, 3])
    if scenario == "loop":
        return loop_path(rng, frames)
    path = scanning_path(rng, max(frames, 2), speed)[:frames]  # rigid and scanning share the path
    if scenario in STATIC:
        return np.repeat(path[:1], frames, axis=0)
    return path
