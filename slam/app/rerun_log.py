"""Rerun logging of a SLAM run (rerun-sdk 0.41): camera, images, depth, flow, weights, trajectories,
the surfel map and per-frame metrics on a ``frame`` timeline, with a one-screen blueprint.

This module imports rerun at import time; ``slam.app.runner.make_logger`` imports it only when a
recording or a viewer is asked for.

Units: the logged world is in metres, like ``map.ply`` and ``trajectory.txt`` (pose translations
and map positions divided by 1000). The depth images are uint16 PNGs in 0.1 mm
(:data:`DEPTH_UNITS_PER_MM`), logged with ``meter=10000``: rerun's ``meter`` (a ``DepthMeter``)
is the depth units per metre, as for ``DepthImage`` (the viewer back-projects ``value / meter``
metres; the ``meter=0.001`` in the ``EncodedDepthImage`` docstring example of 0.41 contradicts
its own default of 1000 for integer depth in mm). :func:`decode_depth_png` reads one back in mm.

Size: the images are compressed (``EncodedImage`` / ``EncodedDepthImage``): a 640x512 frame
costs ~0.2 MB (3.0 MB with the raw images of before); ``logging.rerun_every`` records the images
of every N-th frame only; a frame re-logs only the trajectory part it extends (the whole path
each frame grew quadratically). The map, ~20 bytes a surfel each time it is logged, is then most
of a file at the default ``map_every``. ``tools/benchmark_recording.py`` measures all this.

Entity paths (``frame`` timeline, one entry per processed frame unless noted; "recorded frames":
every ``logging.rerun_every``-th frame, 0, N, 2N, ...):

- ``world``: view coordinates RDF (static).
- ``world/camera``: Transform3D ``T_wc`` of the *rectified* left camera (m) on recorded frames,
  and its Pinhole (rectified ``K``, resolution, RDF; static, re-logged if the intrinsics change),
  so that every image below lies in the camera's image plane and the depth is back-projected in
  3D.
- ``world/camera/image``: the rectified left image, EncodedImage, JPEG (quality
  :data:`IMAGE_JPEG_QUALITY`), recorded frames.
- ``world/camera/depth``: EncodedDepthImage, uint16 PNG in 0.1 mm (0 = no depth),
  ``meter=10000``, coloured over the scene's depths (``depth_range``: :func:`depth_range`),
  recorded frames.
- ``world/camera/flow``: temporal flow, HSV colour-coded, EncodedImage JPEG
  (:data:`CODED_JPEG_QUALITY`), recorded frames but the first.
- ``world/camera/weights/w2d``, ``world/camera/weights/w3d``: weight maps, min..max of the frame
  mapped through a viridis colour map, EncodedImage JPEG, recorded frames but the first.
- ``world/camera/valid``: SegmentationImage of the valid-depth mask (0 invalid, 1 valid; raw
  uint8, which the recording's LZ4 compresses to a few percent), recorded frames.
- ``world/trajectory/estimate/part_NNNN``: LineStrips3D of the estimated positions (original
  left camera, m) of frames ``100 * NNNN`` .. ``100 * NNNN + 99`` (:data:`TRAJ_PART_FRAMES`),
  joined to the last position before them. Each frame re-logs its own part, up to itself: the
  latest-at of every part, i.e. what the viewer shows at a frame, is the whole path so far, and
  what a frame logs is bounded. With loop closure, ``log_final`` re-logs every part once (at the
  last frame) with the optimised positions. ``world/trajectory/ground_truth/part_NNNN``: the same
  for the ground truth (when it exists), ``world/trajectory/as_tracked`` and
  ``world/trajectory/loop_edges`` (loop closure): once, at the end.
- ``world/trajectory/trust/part_NNNN``: Points3D of the same positions, each coloured by what its
  pose rests on (:data:`TRUST_COLORS`: confirmed or tracked green, unconfirmed orange, flagged
  yellow, failed red), logged as the estimate's parts are.
- ``world/map``: coloured Points3D of the stable surfels every ``map_every`` frames and at the end.
- ``metrics/fps`` (from the second frame on), ``metrics/solver_iterations``,
  ``metrics/solver_cost`` (when finite), ``metrics/translation_error_mm`` (with ground truth),
  ``metrics/failed``, ``metrics/flagged`` and ``metrics/unconfirmed`` (0/1, one plot), and the
  ``health/*`` figures: every frame.
"""
from __future__ import annotations

import logging
import os
import time
import uuid
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

log = logging.getLogger("slam")

TIMELINE = "frame"

CAMERA = "world/camera"
IMAGE = "world/camera/image"
DEPTH = "world/camera/depth"
FLOW = "world/camera/flow"
W2D = "world/camera/weights/w2d"
W3D = "world/camera/weights/w3d"
VALID = "world/camera/valid"
TRAJ_EST = "world/trajectory/estimate"
TRAJ_GT = "world/trajectory/ground_truth"
TRAJ_ONLINE = "world/trajectory/as_tracked"
TRAJ_TRUST = "world/trajectory/trust"
LOOP_EDGES = "world/trajectory/loop_edges"
MAP = "world/map"
STATES = ("metrics/failed", "metrics/flagged", "metrics/unconfirmed")
METRICS = ("metrics/fps", "metrics/solver_iterations", "metrics/solver_cost",
           "metrics/translation_error_mm") + STATES

# Encodings (measured on 640x512 synthetic frames, tools/benchmark_recording.py): JPEG at 90 keeps
# the image within 0.5 dB PSNR of 95 at 2/3 of its bytes (~53 kB); the colour codes are views of
# a float map, not data, and take 85 (~13-30 kB each); the depth is lossless uint16 PNG in 0.1 mm
# (~53 kB with the RLE strategy, the fastest and the smallest of zlib's here).
IMAGE_JPEG_QUALITY = 90
CODED_JPEG_QUALITY = 85
DEPTH_UNITS_PER_MM = 10
DEPTH_METER = 1000.0 * DEPTH_UNITS_PER_MM   # rerun's DepthMeter: depth units per metre
DEPTH_MAX_MM = 65535 / DEPTH_UNITS_PER_MM   # deeper (and non-finite, <= 0) pixels are logged as 0
# the depth view's colours span these percentiles of the recorded frames' depths (without a range
# the viewer spans a uint16 image's 0-65535: one saturated colour over the tissue)
DEPTH_PERCENTILES = (2.0, 98.0)
FILE_FLUSH_TICK_S = 5.0  # the rerun batcher's tick when recording to a file only (SDK default 0.2 s)
TRAJ_PART_FRAMES = 100  # frames per trajectory part (the data a frame re-logs is at most this)

EST_COLOR = (255, 140, 0)
GT_COLOR = (40, 200, 80)
ONLINE_COLOR = (160, 160, 160)
LOOP_COLOR = (230, 40, 200)
# what a pose rests on (slam.tracking.state.TRUST): trusted green, unconfirmed orange, flagged
# yellow, failed red
TRUST_COLORS = {"confirmed": (40, 200, 80), "tracked": (40, 200, 80), "known": (40, 200, 80),
                "unconfirmed": (255, 120, 0), "flagged": (255, 220, 0), "failed": (230, 30, 30)}
STATE_COLORS = {"metrics/failed": (255, 0, 0), "metrics/flagged": (255, 220, 0), "metrics/unconfirmed": (255, 120, 0)}

# viridis at 9 evenly spaced stops (enough for a smooth linear interpolation)
_VIRIDIS = np.array([
    [68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
    [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37]], dtype=np.float32)


# ------------------------------------------------------------------------------------------------
# image helpers (numpy only)
def _np(x: Any) -> np.ndarray:
    """A tensor or array as a numpy array on the CPU."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _hw(x: Any) -> np.ndarray:
    """``(1, 1, H, W)`` / ``(1, H, W)`` / ``(H, W)`` -> ``(H, W)``."""
    a = _np(x)
    while a.ndim > 2 and a.shape[0] == 1:
        a = a[0]
    if a.ndim != 2:
        raise ValueError(f"expected a single-channel map, got shape {a.shape}")
    return a


def _hwc(x: Any, channels: int) -> np.ndarray:
    """``(1, C, H, W)`` / ``(C, H, W)`` / ``(H, W, C)`` -> ``(H, W, C)``."""
    a = _np(x)
    while a.ndim > 3 and a.shape[0] == 1:
        a = a[0]
    if a.ndim != 3:
        raise ValueError(f"expected a {channels}-channel map, got shape {a.shape}")
    if a.shape[-1] == channels:
        return a
    if a.shape[0] == channels:
        return np.moveaxis(a, 0, -1)
    raise ValueError(f"expected a {channels}-channel map, got shape {a.shape}")


def image_to_u8(image: Any) -> np.ndarray:
    """A ``(1, 3, H, W)`` float image in [0, 1] (or an ``(H, W, 3)`` uint8 one) -> ``(H, W, 3)`` uint8."""
    a = _hwc(image, 3)
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    return np.ascontiguousarray((np.clip(np.nan_to_num(a.astype(np.float32)), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))


def _planes(x: Any, channels: int) -> list:
    """The channels of an ``(1, C, H, W)`` / ``(C, H, W)`` / ``(H, W, C)`` map as contiguous
    float32 ``(H, W)`` planes (views of ``x`` when they can be: not to be written to)."""
    a = _hwc(x, channels)
    return [np.ascontiguousarray(a[..., c], dtype=np.float32) for c in range(channels)]


def flow_to_rgb(flow: Any, max_magnitude: Optional[float] = None, percentile: float = 99.0) -> np.ndarray:
    """Colour-code a flow field: direction -> hue, magnitude -> value (zero flow is black).

    Args:
        flow: ``(H, W, 2)``, ``(2, H, W)`` or ``(1, 2, H, W)`` (tensor or array), pixels.
        max_magnitude: the magnitude shown at full brightness; default: a robust maximum (the
            ``percentile`` of the finite magnitudes).

    Returns:
        ``(H, W, 3)`` uint8 RGB (hue in 256 steps; OpenCV's polar and HSV conversions, ~14x
        faster than numpy's at 640x512).
    """
    u, v = _planes(flow, 2)
    mag, ang = cv2.cartToPolar(u, v)  # ang: atan2(v, u) in [0, 2 pi)
    finite = np.isfinite(mag) & np.isfinite(ang)
    if not finite.all():
        mag[~finite] = 0.0
        ang[~finite] = 0.0
    if max_magnitude is None:
        vals = mag[mag > 0]
        max_magnitude = float(np.percentile(vals, percentile)) if vals.size else 0.0
    max_magnitude = max(float(max_magnitude), 1e-6)
    hsv = np.empty(mag.shape + (3,), np.uint8)
    hsv[..., 0] = (ang * np.float32(256.0 / (2.0 * np.pi)) + np.float32(0.5)).astype(np.int32) & 255
    hsv[..., 1] = 255
    value = mag * np.float32(255.0 / max_magnitude)
    np.clip(value, 0.0, 255.0, out=value)
    value += 0.5
    hsv[..., 2] = value
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB_FULL)


def _viridis_lut() -> np.ndarray:
    """``(256, 3)`` uint8: :data:`_VIRIDIS` interpolated linearly at 256 steps."""
    x = np.linspace(0.0, 1.0, 256) * (len(_VIRIDIS) - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), len(_VIRIDIS) - 2)
    t = (x - i0)[:, None]
    return (_VIRIDIS[i0] * (1.0 - t) + _VIRIDIS[i0 + 1] * t + 0.5).astype(np.uint8)


_VIRIDIS_LUT = _viridis_lut()


def colormap_u8(values: Any, lo: Optional[float] = None, hi: Optional[float] = None) -> np.ndarray:
    """A scalar map normalised per frame (min -> dark, max -> bright) through viridis.

    Args:
        values: ``(H, W)`` (or with leading unit dims), tensor or array; non-finite -> black.
        lo, hi: the range; default the finite min and max of the map.

    Returns:
        ``(H, W, 3)`` uint8 RGB (the map in 256 steps through a lookup table).
    """
    a = _hw(values).astype(np.float32, copy=False)
    finite = np.isfinite(a)
    all_finite = bool(finite.all())
    vals = a if all_finite else a[finite]
    if lo is None:
        lo = float(vals.min()) if vals.size else 0.0
    if hi is None:
        hi = float(vals.max()) if vals.size else 1.0
    x = (a - np.float32(lo)) * np.float32(255.0 / max(hi - lo, 1e-12))  # a new array
    if not all_finite:
        x[~finite] = 0.0
    np.clip(x, 0.0, 255.0, out=x)
    x += 0.5
    rgb = _VIRIDIS_LUT[x.astype(np.uint8)]
    if not all_finite:
        rgb[~finite] = 0
    return rgb


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    """``(H, W, 3)`` uint8 RGB -> JPEG bytes."""
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


def encode_depth_png(depth_mm: Any) -> bytes:
    """A depth map in mm -> a uint16 PNG in units of ``1 / DEPTH_UNITS_PER_MM`` mm (0 = no depth:
    non-finite, <= 0 or beyond ``DEPTH_MAX_MM``)."""
    d = _hw(depth_mm).astype(np.float64) * DEPTH_UNITS_PER_MM
    ok = np.isfinite(d) & (d > 0) & (d <= 65535.0)
    q = np.where(ok, np.rint(np.where(ok, d, 0.0)), 0.0).astype(np.uint16)
    good, buf = cv2.imencode(".png", q, [cv2.IMWRITE_PNG_COMPRESSION, 1,
                                         cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE])
    if not good:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def depth_range(depth_mm: Any, seen: Optional[tuple[float, float]] = None) -> Optional[tuple[float, float]]:
    """The depth view's colour range in the PNG's units (``1 / DEPTH_UNITS_PER_MM`` mm): the
    frame's depths between :data:`DEPTH_PERCENTILES` (``depth_mm`` ``(H, W)``, 0 = none), widened
    to hold ``seen`` (the scene's range so far); ``seen`` where the frame has no depth."""
    d = _hw(depth_mm).astype(np.float64)
    d = d[np.isfinite(d) & (d > 0) & (d <= DEPTH_MAX_MM)]
    if d.size == 0:
        return seen
    lo, hi = (float(v) * DEPTH_UNITS_PER_MM for v in np.percentile(d, DEPTH_PERCENTILES))
    return (lo, hi) if seen is None else (min(lo, seen[0]), max(hi, seen[1]))


def decode_depth_png(blob: bytes) -> np.ndarray:
    """The inverse of :func:`encode_depth_png`: ``(H, W)`` float32 mm, 0 where there was no depth."""
    q = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_UNCHANGED)
    if q is None or q.dtype != np.uint16 or q.ndim != 2:
        raise ValueError("not a single-channel 16-bit PNG")
    return q.astype(np.float32) / DEPTH_UNITS_PER_MM


def _strip(positions: np.ndarray, color: tuple, label: str) -> "rr.LineStrips3D":
    """One polyline through ``(N, 3)`` positions (m), drawn 2 UI points wide."""
    return rr.LineStrips3D([np.asarray(positions, dtype=np.float32).reshape(-1, 3)], colors=[color],
                           labels=[label], show_labels=False, radii=rr.Radius.ui_points(2.0))


# ------------------------------------------------------------------------------------------------
def make_blueprint() -> rrb.Blueprint:
    """One screen: the 3D world (left), the 2D maps (middle, 2 x 3 grid), the metrics (bottom)."""
    world = rrb.Spatial3DView(
        origin="world", name="world",
        contents=["+ $origin/**", f"- {FLOW}", f"- {W2D}", f"- {W3D}", f"- {VALID}"],
    )
    maps = rrb.Grid(
        rrb.Spatial2DView(origin=IMAGE, name="image"),
        rrb.Spatial2DView(origin=DEPTH, name="depth"),
        rrb.Spatial2DView(origin=FLOW, name="flow"),
        rrb.Spatial2DView(origin=W2D, name="w2d"),
        rrb.Spatial2DView(origin=W3D, name="w3d"),
        rrb.Spatial2DView(origin=VALID, name="valid"),
        grid_columns=3,
    )
    metrics = rrb.Grid(
        rrb.TimeSeriesView(origin="metrics/fps", name="fps"),
        rrb.TimeSeriesView(origin="metrics/translation_error_mm", name="translation error (mm)"),
        rrb.TimeSeriesView(origin="metrics/solver_iterations", name="solver iterations"),
        rrb.TimeSeriesView(origin="metrics/solver_cost", name="solver cost"),
        rrb.TimeSeriesView(origin="metrics", contents=list(STATES), name="failed / flagged / unconfirmed"),
        grid_columns=5,
    )
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(world, maps, column_shares=[2, 3]),
            metrics,
            row_shares=[3, 1],
        ),
        rrb.TimePanel(expanded=True),
        collapse_panels=False,
    )


class RerunLogger:
    """Logs a SLAM run to a rerun recording (``.rrd``) and/or a spawned viewer.

    Args:
        config: ``slam.config.LoggingConfig`` (``rerun`` path, ``map_every``, ``rerun_every``).
        camera: the rectified ``StereoCamera`` (intrinsics of the logged images).
        name: the recording's name (the sequence).
        gt_poses: ``(N, 4, 4)`` ground-truth ``T_wc`` of the original left camera, mm, of the
            selected frames (index ``k``), or None.
        R1: ``(3, 3)`` rectifying rotation of the left camera (kept for reference; positions of the
            original and rectified cameras coincide).
        spawn: also open the rerun viewer.
    """

    def __init__(self, config, camera, name: str = "endoslam", gt_poses: Optional[np.ndarray] = None,
                 R1: Optional[np.ndarray] = None, spawn: bool = False):
        self.config = config
        self.spawn = bool(spawn)
        self.camera = camera
        self.name = str(name)
        self.gt_poses = None if gt_poses is None else np.asarray(gt_poses, dtype=np.float64)
        self.R1 = None if R1 is None else np.asarray(R1, dtype=np.float64)
        self.map_every = int(getattr(config, "map_every", 0) or 0)
        self.rerun_every = max(int(getattr(config, "rerun_every", 1) or 1), 1)
        self.positions: list[np.ndarray] = []  # estimated positions so far, m (the only history kept)
        self.trust_colors: list[tuple] = []     # their colours by trust (TRUST_COLORS)
        self._gt_positions = None if self.gt_poses is None else self.gt_poses[:, :3, 3] / 1000.0
        self._parts: dict[str, int] = {}  # trajectory entity -> parts logged
        self._last_k: Optional[int] = None
        self._last_time: Optional[float] = None
        self._pinhole_key: Optional[tuple] = None
        self.depth_range: Optional[tuple[float, float]] = None   # the scene's depths so far (depth_range)
        self._closed = False
        self.path: Optional[Path] = Path(config.rerun) if getattr(config, "rerun", "") else None
        # the file being written: renamed to ``path`` when the recording closes (a run that stops at
        # frame N still closes it, with frames up to N), so that ``path`` is never a partial file
        self.writing: Optional[Path] = (None if self.path is None
                                        else self.path.with_name(f".{self.path.stem}.partial{self.path.suffix}"))
        # a file alone gathers a few seconds of rows per chunk (each chunk carries ~1 kB of schema:
        # per frame and series at the SDK's 0.2 s); a viewer keeps the SDK's low latency
        batcher = None if self.spawn else rr.ChunkBatcherConfig(flush_tick=FILE_FLUSH_TICK_S)
        self.rec = rr.RecordingStream("endoslam", recording_id=uuid.uuid4(), batcher_config=batcher)
        if not self._connect(make_blueprint()):
            # nothing would ever read the data: do not buffer a whole run in memory
            log.warning("rerun: no recording path and no viewer: rerun logging is off")
            self._closed = True
            self.rec.disconnect()
            return
        self.rec.send_recording_name(self.name)
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self.rec.log(VALID, rr.AnnotationContext([(0, "invalid", (0, 0, 0)), (1, "valid", (255, 255, 255))]),
                     static=True)
        for path, color in (("metrics/fps", (80, 160, 255)), ("metrics/translation_error_mm", (255, 80, 80)),
                            ("metrics/solver_iterations", (200, 200, 200)), ("metrics/solver_cost", (255, 200, 0)),
                            *STATE_COLORS.items()):
            self.rec.log(path, rr.SeriesLines(colors=[color], names=[path.split("/")[-1]]), static=True)
        self._log_pinhole(camera)

    # -------------------------------------------------------------------------------- sinks
    def _connect(self, blueprint: rrb.Blueprint) -> bool:
        """Attach the sinks (viewer and/or file); False when there is none."""
        spawn = self.spawn
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        if spawn:
            try:
                port = 9876
                rr.spawn(port=port, connect=False, recording=self.rec)
                sinks = [rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy")]
                if self.path is not None:
                    sinks.append(rr.FileSink(self.writing))
                self.rec.set_sinks(*sinks, default_blueprint=blueprint)
                return True
            except Exception as err:  # no viewer binary / no display: keep the file
                log.warning("could not spawn the rerun viewer (%s)%s", err,
                            f"; recording to {self.path} only" if self.path else "")
        if self.path is not None:
            self.rec.save(self.writing, default_blueprint=blueprint)
            return True
        return False

    # -------------------------------------------------------------------------------- per frame
    def _log_pinhole(self, camera) -> None:
        if camera is None:
            return
        K = np.asarray(camera.K, dtype=np.float64)
        key = (tuple(np.round(K.ravel(), 9)), int(camera.width), int(camera.height))
        if key == self._pinhole_key:
            return
        self._pinhole_key = key
        self.rec.log(CAMERA, rr.Pinhole(image_from_camera=K, resolution=[int(camera.width), int(camera.height)],
                                        camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.01),
                     static=True)

    def _gt(self, k: int) -> Optional[np.ndarray]:
        if self.gt_poses is None or k >= len(self.gt_poses):
            return None
        T = self.gt_poses[k]
        return T if np.all(np.isfinite(T[:3, 3])) else None

    def log_frame(self, k: int, frame, view, track, record, map=None, camera=None,
                  pose_rect: Optional[np.ndarray] = None) -> None:
        """Log one processed frame ``k`` (see the module doc for what goes where)."""
        if self._closed:
            return
        rec = self.rec
        now = time.perf_counter()
        rec.set_time(TIMELINE, sequence=int(k))
        self._log_pinhole(camera if camera is not None else self.camera)

        # the camera and its images, on every rerun_every-th frame (the pose with them: the image
        # plane and the depth cloud stay where they were seen until the next recorded frame)
        if int(k) % self.rerun_every == 0:
            T = np.asarray(pose_rect if pose_rect is not None else record.pose, dtype=np.float64)
            rec.log(CAMERA, rr.Transform3D(translation=T[:3, 3] / 1000.0, mat3x3=T[:3, :3]))
            rec.log(IMAGE, rr.EncodedImage(contents=encode_jpeg(image_to_u8(view.image), IMAGE_JPEG_QUALITY),
                                           media_type="image/jpeg"))
            self.depth_range = depth_range(view.depth, self.depth_range)
            rec.log(DEPTH, rr.EncodedDepthImage(encode_depth_png(view.depth), media_type="image/png",
                                                meter=DEPTH_METER, depth_range=self.depth_range))
            rec.log(VALID, rr.SegmentationImage(_hw(view.valid).astype(np.uint8)))
            if track is not None:
                for path, value, code in ((FLOW, getattr(track, "flow", None), flow_to_rgb),
                                          (W2D, getattr(track, "w2d", None), colormap_u8),
                                          (W3D, getattr(track, "w3d", None), colormap_u8)):
                    if value is not None:
                        rec.log(path, rr.EncodedImage(contents=encode_jpeg(code(value), CODED_JPEG_QUALITY),
                                                      media_type="image/jpeg"))

        # trajectories (original left camera, m): only the part the frame extends
        pose = np.asarray(record.pose, dtype=np.float64)
        self.positions.append(pose[:3, 3] / 1000.0)
        start = (int(k) // TRAJ_PART_FRAMES) * TRAJ_PART_FRAMES
        self._log_part(TRAJ_EST, self.positions, start, int(k), EST_COLOR, "estimate")
        self.trust_colors.append(TRUST_COLORS.get(getattr(record, "trust", ""), EST_COLOR))
        part = slice(start, int(k) + 1)
        rec.log(f"{TRAJ_TRUST}/part_{start // TRAJ_PART_FRAMES:04d}",
                rr.Points3D(np.asarray(self.positions[part], dtype=np.float32).reshape(-1, 3),
                            colors=np.asarray(self.trust_colors[part], dtype=np.uint8),
                            radii=rr.Radius.ui_points(3.0)))
        gt = self._gt(k)
        if self._gt_positions is not None and k < len(self._gt_positions):
            self._log_part(TRAJ_GT, self._gt_positions, start, int(k), GT_COLOR, "ground truth")

        # map
        if map is not None and self.map_every > 0 and k % self.map_every == 0:
            self._log_map(map)

        # metrics
        if self._last_time is not None:
            dt = now - self._last_time
            if dt > 0:
                rec.log("metrics/fps", rr.Scalars(1.0 / dt))
        elif track is not None and getattr(track, "timings_ms", None):
            total = float(sum(track.timings_ms.values()))
            if total > 0:
                rec.log("metrics/fps", rr.Scalars(1000.0 / total))
        rec.log("metrics/solver_iterations", rr.Scalars(float(getattr(record, "iterations", 0) or 0)))
        cost = float(getattr(record, "cost", float("nan")))
        if np.isfinite(cost):
            rec.log("metrics/solver_cost", rr.Scalars(cost))
        if gt is not None:
            rec.log("metrics/translation_error_mm", rr.Scalars(float(np.linalg.norm(pose[:3, 3] - gt[:3, 3]))))
        rec.log("metrics/failed", rr.Scalars(1.0 if record.failed else 0.0))
        rec.log("metrics/flagged", rr.Scalars(1.0 if getattr(record, "flagged", False) else 0.0))
        rec.log("metrics/unconfirmed", rr.Scalars(1.0 if getattr(record, "trust", "") == "unconfirmed" else 0.0))
        for name, value in (getattr(record, "health", None) or {}).items():   # slam.tracking.health.FIGURES
            if value is not None and np.isfinite(float(value)):
                rec.log(f"health/{name}", rr.Scalars(float(value)))

        self._last_k = int(k)
        self._last_time = now

    def _log_part(self, path: str, positions, start: int, end: int, color: tuple, label: str) -> None:
        """Log part ``start // TRAJ_PART_FRAMES`` of a trajectory: its finite positions of frames
        ``start..end``, joined to the last finite position before ``start``."""
        lo = max(start - TRAJ_PART_FRAMES, 0)
        pts = np.asarray(positions[lo:end + 1], dtype=np.float64).reshape(-1, 3)
        finite = np.all(np.isfinite(pts), axis=1)
        before = np.flatnonzero(finite[: start - lo])
        i0 = int(before[-1]) if before.size else start - lo
        pts = pts[i0:][finite[i0:]]
        part = start // TRAJ_PART_FRAMES
        self.rec.log(f"{path}/part_{part:04d}", _strip(pts, color, label))
        self._parts[path] = max(self._parts.get(path, 0), part + 1)

    def _log_path(self, path: str, positions: np.ndarray, color: tuple, label: str) -> None:
        """Re-log a whole trajectory (at the current time) as parts, clearing parts beyond it."""
        n = len(positions)
        parts = (n + TRAJ_PART_FRAMES - 1) // TRAJ_PART_FRAMES
        logged = self._parts.get(path, 0)
        for part in range(parts):
            start = part * TRAJ_PART_FRAMES
            self._log_part(path, positions, start, min(start + TRAJ_PART_FRAMES, n) - 1, color, label)
        for part in range(parts, logged):
            self.rec.log(f"{path}/part_{part:04d}", rr.Clear(recursive=False))
        self._parts[path] = parts

    def _log_map(self, map) -> None:
        pts = map.points(stable_only=True)
        pos = np.asarray(pts.get("positions", np.zeros((0, 3))), dtype=np.float32).reshape(-1, 3) / 1000.0
        colors = pts.get("colors")
        if colors is not None:
            colors = np.asarray(colors, dtype=np.float32).reshape(-1, 3)
            colors = (np.clip(colors, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        radii = pts.get("radii")
        radii = None if radii is None else np.asarray(radii, dtype=np.float32).reshape(-1) / 1000.0
        self.rec.log(MAP, rr.Points3D(pos, colors=colors, radii=radii))

    # -------------------------------------------------------------------------------- end
    def log_final(self, map, est_poses: Optional[np.ndarray], gt_poses: Optional[np.ndarray] = None,
                  online_poses: Optional[np.ndarray] = None, loop_edges: Optional[list] = None) -> None:
        """The final map and the full trajectories (at the last frame), then close. With loop
        closure ``est_poses`` are the optimised poses, ``online_poses`` those as tracked and
        ``loop_edges`` the ``(i, j)`` frame pairs each accepted loop edge joins."""
        if self._closed:
            return
        k = self._last_k if self._last_k is not None else max(len(est_poses) - 1 if est_poses is not None else 0, 0)
        self.rec.set_time(TIMELINE, sequence=int(k))
        if map is not None:
            self._log_map(map)
        if online_poses is not None and len(online_poses):
            self.rec.log(TRAJ_ONLINE, _strip(np.asarray(online_poses)[:, :3, 3] / 1000.0, ONLINE_COLOR, "as tracked"))
        if loop_edges and est_poses is not None:
            at = np.asarray(est_poses, dtype=np.float64)[:, :3, 3] / 1000.0
            segments = [at[[i, j]].astype(np.float32) for i, j in loop_edges if max(i, j) < len(at)]
            if segments:
                self.rec.log(LOOP_EDGES, rr.LineStrips3D(segments, colors=[LOOP_COLOR] * len(segments),
                                                         radii=rr.Radius.ui_points(1.5)))
        # the per-frame parts already hold the full trajectories when every frame was logged:
        # re-log (all parts, once) only what differs, e.g. the poses loop closure optimised
        if est_poses is not None and len(est_poses):
            est = np.asarray(est_poses, dtype=np.float64)[:, :3, 3] / 1000.0
            if len(est) != len(self.positions) or not np.allclose(est, np.stack(self.positions), equal_nan=True):
                self._log_path(TRAJ_EST, est, EST_COLOR, "estimate")
        if gt_poses is not None and len(gt_poses):
            gt = np.asarray(gt_poses, dtype=np.float64)[:, :3, 3] / 1000.0
            gt = gt[np.all(np.isfinite(gt), axis=1)]
            logged = np.zeros((0, 3)) if self._gt_positions is None or self._last_k is None \
                else self._gt_positions[: self._last_k + 1]
            logged = logged[np.all(np.isfinite(logged), axis=1)]
            if len(gt) != len(logged) or not np.allclose(gt, logged):
                self._log_path(TRAJ_GT, gt, GT_COLOR, "ground truth")
        self.close()

    def close(self) -> None:
        """Flush and close every sink (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.rec.flush()
        except Exception as err:  # e.g. the viewer was closed or never came up: the file is complete
            log.warning("rerun: %s", err)
        finally:
            self.rec.disconnect()
            self._rename_recording()

    def _rename_recording(self) -> None:
        """The finished recording moved to its path (named in one warning where it cannot be)."""
        if self.writing is None or not self.writing.is_file():
            return
        try:
            os.replace(self.writing, self.path)
        except OSError as err:
            log.warning("rerun: could not write %s (%s)", self.path, err.strerror or err)
            self.writing.unlink(missing_ok=True)

    def __enter__(self) -> "RerunLogger":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
