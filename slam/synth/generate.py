"""``generate``: render a synthetic stereo-endoscopy sequence with ground truth to a folder."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from slam.errors import DataError
from slam.synth.appearance import Appearance, ExposureWalk
from slam.synth.camera_paths import make_path
from slam.synth.cameras import rectified_rig, raw_rig
from slam.synth.deformation import FrameDeformation, make_breathing
from slam.synth.instrument import InstrumentMotion
from slam.synth.render import Renderer
from slam.synth.scene import make_scene
from slam.synth.writer import DEPTH_SCALE_MM, SequenceWriter, prepare_out_dir, write_calibration, write_metadata
from slam.app.progress import Progress
from slam.io.tum import write_tum

VERSION = "1.0.0"
SCENARIOS = ("rigid", "breathing", "scanning", "deforming", "loop")
BREATHES = ("breathing", "scanning", "deforming")
MIN_SIZE, MAX_SIZE = 16, 4096

_DESCRIPTION = {
    "rigid": "camera scans a still tissue (lateral figure-of-eight, depth change, a few degrees of rotation)",
    "breathing": "static camera, tissue breathes (periodic, spatially varying amplitude)",
    "scanning": "camera moves as in rigid while the tissue breathes",
    "deforming": "static camera, breathing tissue pushed by a surgical instrument (masks written)",
    "loop": "camera moves along a closed path and returns to its start at the last frame, tissue still",
}


def _check_args(scenario, frames, size, seed, fps) -> tuple[int, int]:
    if scenario not in SCENARIOS:
        raise DataError(f"unknown synthetic scenario '{scenario}' (choose from {', '.join(SCENARIOS)})")
    if isinstance(size, str):  # "WxH"
        size = tuple(size.lower().split("x"))
        try:
            size = tuple(int(v) for v in size)
        except ValueError:
            raise DataError(f"bad image size {'x'.join(size)!r}: expected WIDTHxHEIGHT, e.g. 640x512") from None
    try:
        w, h = (int(v) for v in size)
        if (w, h) != tuple(size):
            raise ValueError
    except (TypeError, ValueError):
        raise DataError(f"bad image size {size!r}: expected two integers (width, height)") from None
    if not (MIN_SIZE <= w <= MAX_SIZE and MIN_SIZE <= h <= MAX_SIZE):
        raise DataError(f"bad image size {w}x{h}: width and height must be within {MIN_SIZE}..{MAX_SIZE}")
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise DataError(f"bad number of frames {frames!r}: expected an integer >= 1")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise DataError(f"bad seed {seed!r}: expected an integer >= 0")
    if not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0):
        raise DataError(f"bad frame rate {fps!r}: expected a positive number")
    return w, h


def _files_meaning(raw: bool, masks: bool, video: str | None) -> dict:
    files = {
        "StereoCalibration.ini": ("unrectified" if raw else "rectified") + " stereo calibration, StereoMIS keys; "
        "[StereoRight] T_i (mm) and R_i (row-major) with X_r = R X_l + T",
        "groundtruth.txt": "TUM rows (metres, qx qy qz qw) of the left camera pose T_wc (camera to world); "
        "timestamp = frame_index / fps",
    }
    if raw:
        files[video] = "mp4v video; each frame holds the left image on top of the right image (W x 2H), distorted"
    else:
        files["video_frames/%06dl.png"] = "left RGB frame (rectified)"
        files["video_frames/%06dr.png"] = "right RGB frame (rectified)"
        files["depth/%06dl.png"] = "uint16 depth (camera z) of the left view in units of depth_scale_mm; " \
            "instrument pixels hold the instrument depth; 0 = no surface"
        files["nonrigid/%06dl.png"] = "uint16 magnitude of the non-rigid displacement (from the tissue's rest shape) " \
            "of the tissue point seen by each left pixel, units of depth_scale_mm; 0 on rigid scenes and instrument pixels"
    if masks:
        files["masks/%06dl.png"] = "uint8 mask of the left view" + (" (distorted like the video)" if raw else "") + \
            ": 255 = tissue, 0 = instrument"
    return files


def generate(out_dir, scenario: str, frames: int = 150, size: tuple[int, int] = (640, 512), seed: int = 0,
             raw: bool = False, fps: float = 25.0, progress: bool = False,
             breathing_follows_tissue: float = 0.0, camera_speed: float = 1.0, codec: str = "mp4v",
             appearance: Appearance | None = None) -> Path:
    """Render a synthetic stereo sequence with ground truth into ``out_dir``.

    Args:
        out_dir: folder to write (created; must be empty or hold an earlier synthetic sequence).
        scenario: one of :data:`SCENARIOS`.
        frames: number of stereo frames.
        size: ``(width, height)`` of each view (or ``"WxH"``); only changes the sampling, not the scene.
        seed: defines tissue, trajectory, deformation, instrument and noise.
        raw: write the StereoMIS *raw* layout (distorted, unrectified, one mp4) instead of the
            pre-processed one.
        fps: frame rate (timestamps, breathing and instrument speeds are in seconds).
        progress: show a progress bar.
        breathing_follows_tissue: correlation in [0, 1] of the breathing amplitude map with how the
            tissue looks (red parenchyma breathes most; see ``make_breathing``); 0 keeps it
            independent of the image.
        camera_speed: scales the rigid and scanning cameras' motion per frame (1: 0.3-0.9 mm,
            0.1: a camera creeping at 0.03-0.09 mm per frame, below tracking's still threshold).
        codec: the raw video's codec: ``mp4v`` (lossy, ``.mp4``, the StereoMIS raw layout) or
            ``ffv1`` (lossless, ``.avi``, read as a stereo video file).
        appearance: texture strength, highlights, smoke, exposure changes, vignetting and tissue
            colour (:class:`slam.synth.appearance.Appearance`; default: the generator's own look).

    Returns:
        ``out_dir`` as a Path.

    Raises:
        DataError: unknown scenario, bad size/frames/seed/fps, or an unwritable folder.
    """
    width, height = _check_args(scenario, frames, size, seed, fps)
    try:
        follows = float(breathing_follows_tissue)
    except (TypeError, ValueError):
        follows = float("nan")
    if not 0.0 <= follows <= 1.0:
        raise DataError(f"bad breathing_follows_tissue {breathing_follows_tissue!r}: expected a number in [0, 1]")
    try:
        speed = float(camera_speed)
    except (TypeError, ValueError):
        speed = float("nan")
    if not (np.isfinite(speed) and speed > 0):
        raise DataError(f"bad camera_speed {camera_speed!r}: expected a positive number")
    frames, seed, fps = int(frames), int(seed), float(fps)
    out = Path(out_dir)
    prepare_out_dir(out)

    look = appearance if appearance is not None else Appearance()
    scene = make_scene(seed, float(look.texture))
    rig = raw_rig(width, height, seed) if raw else rectified_rig(width, height)
    poses = make_path(scenario, frames, seed, speed)
    breathing = make_breathing(scene, seed, follows) if scenario in BREATHES else None
    instrument = InstrumentMotion(scene, seed, poses[0], breathing) if scenario == "deforming" else None
    renderer = Renderer(scene, breathing, mm_per_px=scene.rest_depth_mm / rig.left.K[0, 0], appearance=look, seed=seed)
    exposure = ExposureWalk(look.exposure_jitter, seed)
    masks = instrument is not None
    writer = SequenceWriter(out, raw, width, height, fps, masks=masks, codec=codec)

    with writer, Progress(frames, f"synth {scenario}", enabled=progress) as bar:
        for i in range(frames):
            t = i / fps
            if instrument is not None:
                deform, capsules = instrument.at(t)
            else:
                deform, capsules = FrameDeformation(t=t, breathing=breathing), None
            T = poses[i]
            light = T[:3, 3]  # the light sits at the left camera's optical centre
            gain = exposure.gain()
            left = renderer.render(rig.left, T, light, deform, capsules, np.random.default_rng([seed, 100, i, 0]), i, gain)
            right = renderer.render(rig.right, T, light, deform, capsules, np.random.default_rng([seed, 100, i, 1]), i, gain)
            writer.write(i, left.rgb, right.rgb,
                         depth=None if raw else left.depth,
                         nonrigid=None if raw else left.nonrigid,
                         tissue=left.tissue if masks else None)
            bar.update(1)

    write_tum(out / "groundtruth.txt", np.arange(frames) / fps, poses)
    write_calibration(out / "StereoCalibration.ini", rig)
    video = writer.video_path.name if writer.video_path is not None else None
    meta = {
        "generator": "slam.synth",
        "version": VERSION,
        "scenario": scenario,
        "description": _DESCRIPTION[scenario],
        "seed": seed,
        "frames": frames,
        "size": [width, height],
        "fps": fps,
        "raw": raw,
        "rectified": not raw,
        "K": rig.left.K.tolist(),
        "dist": rig.left.dist.tolist(),
        "K_right": rig.right.K.tolist(),
        "dist_right": rig.right.dist.tolist(),
        "R": rig.R.tolist(),
        "T_mm": rig.T.tolist(),
        "baseline_mm": rig.baseline_mm,
        "depth_scale_mm": DEPTH_SCALE_MM,
        "has_depth": not raw,
        "has_nonrigid": not raw,
        "has_masks": masks,
        "video": video,
        "units": "millimetres inside the generator; groundtruth.txt in metres (TUM)",
        "world_frame": "tissue frame: camera looks roughly along +z; rest tissue surface z = rest_depth_mm + h(x, y)",
        "rest_depth_mm": scene.rest_depth_mm,
        "light": "point light at the left camera's optical centre",
        "breathing_period_s": breathing.period_s if breathing is not None else None,
        "breathing_follows_tissue": follows,
        "camera_speed": speed,
        "appearance": look.as_dict(),
        "files": _files_meaning(raw, masks, video),
        "notes": ("raw mode: depth/ and nonrigid/ are not written (ground truth is for rectified output only)"
                  if raw else ""),
    }
    write_metadata(out / "synth.json", meta)
    return out
