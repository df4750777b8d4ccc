"""Rerun logging (slam/app/rerun_log.py): entities and per-frame counts in a saved .rrd, the encoded
images and depth read back, the trajectory logged in parts, ``logging.rerun_every``, the file's
size per frame on a real run, the flow and weight colour codes, the blueprint, and that rerun
stays unimported unless asked for."""
from __future__ import annotations

import collections
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

rr = pytest.importorskip("rerun")

from slam.config import LoggingConfig, SlamConfig  # noqa: E402
from slam.app.pipeline import FrameRecord  # noqa: E402
import slam.app.rerun_log as rl  # noqa: E402
from slam.app.rerun_log import RerunLogger, colormap_u8, decode_depth_png, flow_to_rgb  # noqa: E402
from vo.camera import StereoCamera  # noqa: E402
from vo.odometry import TrackResult, View  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RERUN_CLI = Path(sys.executable).parent / "rerun"
H, W, N = 48, 64, 5

IMAGE = "/world/camera/image"
DEPTH = "/world/camera/depth"
FLOW = "/world/camera/flow"
W2D = "/world/camera/weights/w2d"
W3D = "/world/camera/weights/w3d"
VALID = "/world/camera/valid"
CAMERA = "/world/camera"
EST = "/world/trajectory/estimate/part_0000"
GT = "/world/trajectory/ground_truth/part_0000"
MAP = "/world/map"


def _camera() -> StereoCamera:
    K = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
    return StereoCamera(K=K, baseline_mm=4.0, width=W, height=H)


def _pose(k: int) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(0.02 * k), np.sin(0.02 * k)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = [2.0 * k, -0.5 * k, 1.0 + 0.3 * k]  # mm
    return T


class FakeMap:
    """The part of mapping.SurfelMap the logger uses."""

    def __init__(self, n: int = 200):
        rng = np.random.default_rng(1)
        self.pos = rng.normal(size=(n, 3)) * 10.0 + [0.0, 0.0, 80.0]
        self.col = rng.random((n, 3))

    def points(self, stable_only: bool = True) -> dict:
        n = len(self.pos)
        return {"positions": self.pos, "normals": np.tile([0.0, 0.0, -1.0], (n, 1)), "colors": self.col,
                "radii": np.full(n, 0.5), "confidence": np.ones(n), "t_init": np.zeros(n), "t_last": np.zeros(n)}

    def __len__(self) -> int:
        return len(self.pos)


def _view(gen: torch.Generator) -> View:
    depth = 50.0 + 50.0 * torch.rand(1, 1, H, W, generator=gen)
    valid = torch.rand(1, 1, H, W, generator=gen) > 0.2
    return View(image=torch.rand(1, 3, H, W, generator=gen), gray=np.zeros((H, W), np.uint8),
                depth=torch.where(valid, depth, torch.zeros_like(depth)), valid=valid,
                parallax=torch.zeros(1, 2, H, W))


def _track(gen: torch.Generator, failed: bool) -> TrackResult:
    return TrackResult(relative=np.eye(4), failed=failed, reason="diverged" if failed else "", iterations=7,
                       cost=0.25, valid_pixels=H * W, flow=torch.randn(1, 2, H, W, generator=gen) * 3.0,
                       w2d=torch.rand(1, 1, H, W, generator=gen), w3d=torch.rand(1, 1, H, W, generator=gen),
                       timings_ms={"flow": 10.0, "solver": 5.0})


def _run_logger(path: Path, gt: bool = True, map_every: int = 2, n: int = N, rerun_every: int = 1,
                gt_poses: np.ndarray | None = None, final_est: np.ndarray | None = None) -> dict:
    """Log ``n`` frames (frame 3 failed) and the final map into ``path``; return what was logged.
    ``gt_poses``: instead of the default ground truth; ``final_est``: the poses ``log_final`` gets
    (as from loop closure), default those logged per frame."""
    gen = torch.Generator().manual_seed(0)
    camera = _camera()
    if gt_poses is None and gt:
        gt_poses = np.stack([_pose(k) for k in range(n)])
    R1 = np.eye(3)
    logger = RerunLogger(LoggingConfig(rerun=str(path), map_every=map_every, rerun_every=rerun_every), camera,
                         name="fake_seq", gt_poses=gt_poses, R1=R1)
    fmap = FakeMap()
    est, views = [], []
    for k in range(n):
        failed = k == 3
        track = None if k == 0 else _track(gen, failed)
        pose = _pose(k)
        pose[:3, 3] += 0.1 * k  # drift: the first estimate is the first ground-truth pose
        est.append(pose)
        record = FrameRecord(index=10 + k, timestamp=0.1 * k, pose=pose, failed=failed,
                             reason="diverged" if failed else "", reference="first" if k == 0 else "previous_frame",
                             iterations=0 if k == 0 else 7, cost=float("nan") if k == 0 else 0.25,
                             health={} if k == 0 else {"support": 0.9, "nees": float("nan") if k == 1 else 5.0})
        frame = SimpleNamespace(index=10 + k, timestamp=0.1 * k, left=None, right=None, mask=None)
        views.append(_view(gen))
        logger.log_frame(k, frame, views[-1], track, record, fmap, camera, pose)
    est = np.stack(est)
    logger.log_final(fmap, est if final_est is None else final_est,
                     None if gt_poses is None else gt_poses[np.all(np.isfinite(gt_poses[:, :3, 3]), axis=1)])
    assert path.is_file() and path.stat().st_size > 0
    return {"est": est, "gt": gt_poses, "map": fmap, "views": views}


def _frames_per_entity(path: Path) -> dict:
    """{(entity, component): sorted list of `frame` values of the non-null rows} of the recording,
    read back with rerun's own chunk reader (rows summed over however many chunks were written)."""
    from rerun.chunk import RrdReader

    out = collections.defaultdict(list)
    for chunk in RrdReader(path).stream():
        if chunk.is_static or "frame" not in chunk.timeline_names:
            continue
        batch = chunk.to_record_batch()
        frames = batch.column("frame").to_pylist()
        for name in batch.schema.names:
            if ":" not in name:
                continue  # row id / timelines
            col = batch.column(name)
            out[(chunk.entity_path, name)] += [f for f, ok in zip(frames, col.is_valid().to_pylist()) if ok]
    return {key: sorted(v) for key, v in out.items()}


def _static_components(path: Path) -> dict:
    from rerun.chunk import RrdReader

    out = collections.defaultdict(set)
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            out[chunk.entity_path] |= {n for n in chunk.to_record_batch().schema.names if ":" in n}
    return out


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rerun") / "run.rrd"
    logged = _run_logger(path)
    return path, logged


def test_rrd_print_lists_entities(recording):
    path, _ = recording
    assert RERUN_CLI.is_file(), f"rerun CLI not found at {RERUN_CLI}"
    res = subprocess.run([str(RERUN_CLI), "rrd", "print", str(path)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    # summary lines: "Chunk(<id>) with <n> rows (<size>) - <entity> - data columns: [<Archetype:field> ...]"
    rows = collections.Counter()
    for m in re.finditer(r"^Chunk\(\S+\) with (\d+) rows \([^)]*\) - (\S+) - data columns: \[([^\]]*)\]", res.stdout,
                         re.MULTILINE):
        for column in m.group(3).split():
            rows[(m.group(2), column)] += int(m.group(1))
    entities = {entity for entity, _ in rows}
    for entity in (IMAGE, DEPTH, FLOW, W2D, W3D, VALID, CAMERA, EST, GT, MAP, "/metrics/fps",
                   "/metrics/solver_iterations", "/metrics/solver_cost", "/metrics/translation_error_mm",
                   "/metrics/failed"):
        assert entity in entities, f"{entity} not in the recording: {sorted(entities)}"
    # the same counts as the chunk reader below, from the CLI's row counts
    assert rows[(IMAGE, "EncodedImage:blob")] == N
    assert rows[(DEPTH, "EncodedDepthImage:blob")] == N
    assert rows[(FLOW, "EncodedImage:blob")] == N - 1
    assert rows[(CAMERA, "Transform3D:translation")] == N
    assert rows[(CAMERA, "Pinhole:image_from_camera")] == 1
    assert rows[(EST, "LineStrips3D:strips")] == N
    assert rows[(GT, "LineStrips3D:strips")] == N
    # verify: the file is a complete, loadable recording
    res = subprocess.run([str(RERUN_CLI), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]


def test_one_entry_per_processed_frame(recording):
    path, _ = recording
    frames = _frames_per_entity(path)
    every = list(range(N))
    tracked = list(range(1, N))  # the first frame has no flow / weights
    assert frames[(IMAGE, "EncodedImage:blob")] == every
    assert frames[(IMAGE, "EncodedImage:media_type")] == every
    assert frames[(DEPTH, "EncodedDepthImage:blob")] == every
    assert frames[(DEPTH, "EncodedDepthImage:meter")] == every
    assert frames[(VALID, "SegmentationImage:buffer")] == every
    assert frames[(CAMERA, "Transform3D:translation")] == every
    assert frames[(EST, "LineStrips3D:strips")] == every
    assert frames[(GT, "LineStrips3D:strips")] == every
    assert frames[(FLOW, "EncodedImage:blob")] == tracked
    assert frames[(W2D, "EncodedImage:blob")] == tracked
    assert frames[(W3D, "EncodedImage:blob")] == tracked
    # nothing raw but the valid mask (a segmentation, for its annotation context)
    assert not [key for key in frames if key[1] in ("Image:buffer", "DepthImage:buffer")]
    assert frames[("/metrics/failed", "Scalars:scalars")] == every
    assert frames[("/metrics/solver_iterations", "Scalars:scalars")] == every
    assert frames[("/metrics/translation_error_mm", "Scalars:scalars")] == every
    assert frames[("/metrics/solver_cost", "Scalars:scalars")] == tracked  # NaN cost of frame 0 skipped
    assert frames[("/metrics/fps", "Scalars:scalars")] == tracked
    # the health figures as time series, a frame's nan left out
    assert frames[("/health/support", "Scalars:scalars")] == tracked
    assert frames[("/health/nees", "Scalars:scalars")] == tracked[1:]
    # map every 2 frames (0, 2, 4) and the final map (at the last frame)
    assert frames[(MAP, "Points3D:positions")] == [0, 2, 4, 4]
    static = _static_components(path)
    assert "Pinhole:image_from_camera" in static["/world/camera"]


def _column(path: Path, entity: str, name: str) -> list:
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            if name in batch.schema.names:
                rows += list(zip(batch.column("frame").to_pylist(), batch.column(name).to_pylist()))
    return [v for _, v in sorted(rows, key=lambda r: r[0])]


def test_values_in_metres(recording):
    path, logged = recording
    strips = _column(path, EST, "LineStrips3D:strips")
    last = np.asarray(strips[-1][0], dtype=np.float64)  # one strip of N points
    np.testing.assert_allclose(last, logged["est"][:, :3, 3] / 1000.0, rtol=0, atol=1e-6)
    assert [len(s[0]) for s in strips] == list(range(1, N + 1))
    gt_last = np.asarray(_column(path, GT, "LineStrips3D:strips")[-1][0])
    np.testing.assert_allclose(gt_last, logged["gt"][:, :3, 3] / 1000.0, atol=1e-6)
    err = [v[0] for v in _column(path, "/metrics/translation_error_mm", "Scalars:scalars")]
    expected = np.linalg.norm(logged["est"][:, :3, 3] - logged["gt"][:, :3, 3], axis=1)
    np.testing.assert_allclose(err, expected, rtol=1e-5, atol=1e-6)
    failed = [v[0] for v in _column(path, "/metrics/failed", "Scalars:scalars")]
    assert failed == [0.0, 0.0, 0.0, 1.0, 0.0]
    t = np.asarray(_column(path, CAMERA, "Transform3D:translation")[-1]).reshape(3)
    np.testing.assert_allclose(t, logged["est"][-1][:3, 3] / 1000.0, atol=1e-6)
    pts = np.asarray(_column(path, MAP, "Points3D:positions")[-1])
    np.testing.assert_allclose(pts, logged["map"].pos / 1000.0, rtol=1e-6, atol=1e-6)
    meter = _column(path, DEPTH, "EncodedDepthImage:meter")[0]
    assert np.ravel(meter)[0] == pytest.approx(10000.0)  # depth units (0.1 mm) per metre
    assert _column(path, DEPTH, "EncodedDepthImage:media_type")[0] == ["image/png"]


def test_blueprint_is_saved(recording):
    from rerun.chunk import RrdReader

    path, _ = recording
    reader = RrdReader(path)
    assert len(reader.recordings()) == 1
    assert len(reader.blueprints()) == 1
    origins = set()
    for chunk in reader.stream(store=reader.blueprints()[0]):
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if name.endswith("space_origin"):
                origins |= {str(v[0] if isinstance(v, list) else v).strip("/") for v in batch.column(name).to_pylist()}
    for origin in ("/world", IMAGE, DEPTH, FLOW, W2D, W3D, "/metrics/fps"):
        assert origin.strip("/") in origins, (origin, origins)


def test_without_ground_truth_and_map_only_at_the_end(tmp_path):
    path = tmp_path / "nogt.rrd"
    _run_logger(path, gt=False, map_every=0)
    frames = _frames_per_entity(path)
    assert frames[(IMAGE, "EncodedImage:blob")] == list(range(N))
    assert (GT, "LineStrips3D:strips") not in frames
    assert ("/metrics/translation_error_mm", "Scalars:scalars") not in frames
    assert frames[(MAP, "Points3D:positions")] == [N - 1]


def test_the_recording_is_written_beside_and_renamed_when_it_closes(tmp_path, monkeypatch):
    path = tmp_path / "rec.rrd"
    logger = RerunLogger(LoggingConfig(rerun=str(path)), _camera(), name="x")
    assert not path.exists() and logger.writing.is_file() and logger.writing.parent == tmp_path
    logger.close()
    assert path.is_file() and path.stat().st_size > 0 and not logger.writing.exists()
    # a rename that fails: one warning naming the recording, no partial file left
    def refuse(src, dst):
        raise PermissionError(13, "Permission denied")
    monkeypatch.setattr(rl.os, "replace", refuse)
    path2 = tmp_path / "refused.rrd"
    logger = RerunLogger(LoggingConfig(rerun=str(path2)), _camera(), name="y")
    logger.close()
    assert not path2.exists() and not logger.writing.exists()


def test_spawn_failure_falls_back_to_the_file(tmp_path, monkeypatch):
    import slam.app.rerun_log as rl

    def no_viewer(**kwargs):
        raise RuntimeError("no viewer here")

    monkeypatch.setattr(rl.rr, "spawn", no_viewer)
    path = tmp_path / "spawn.rrd"
    logger = RerunLogger(LoggingConfig(rerun=str(path)), _camera(), name="x", spawn=True)
    logger.log_final(None, np.zeros((0, 4, 4)), None)  # nothing logged: closes cleanly
    logger.close()  # idempotent
    assert path.is_file() and path.stat().st_size > 0
    # no file and no viewer: logging is a no-op (nothing buffered in memory)
    logger = RerunLogger(LoggingConfig(rerun=""), _camera(), name="y", spawn=True)
    gen = torch.Generator().manual_seed(0)
    record = FrameRecord(index=0, timestamp=0.0, pose=np.eye(4), failed=False)
    logger.log_frame(0, None, _view(gen), None, record, FakeMap(), _camera(), np.eye(4))
    assert logger.positions == []
    logger.log_final(None, np.eye(4)[None], None)


# ------------------------------------------------------------------------------------------------
# what the recording holds, read back
def _rows(path: Path, entity_prefix: str) -> list:
    """``[(entity, frame, row id, strip points or None for a Clear)]`` of the entities under
    ``entity_prefix`` (row ids: big-endian TUIDs, which sort as they were logged)."""
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(path).stream():
        if chunk.is_static or not chunk.entity_path.startswith(entity_prefix):
            continue
        batch = chunk.to_record_batch()
        names = batch.schema.names
        frames = batch.column("frame").to_pylist()
        ids = batch.column(0).to_pylist()
        assert batch.schema.names[0] == "rerun.controls.RowId"
        none = [None] * len(frames)
        strips = batch.column("LineStrips3D:strips").to_pylist() if "LineStrips3D:strips" in names else none
        clears = batch.column("Clear:is_recursive").to_pylist() if "Clear:is_recursive" in names else none
        for f, row_id, strip, clear in zip(frames, ids, strips, clears):
            if strip is not None:
                rows.append((chunk.entity_path, f, row_id, np.asarray(strip[0], dtype=np.float64).reshape(-1, 3)))
            elif clear is not None:
                rows.append((chunk.entity_path, f, row_id, None))
    return rows


def _path_at(rows: list, frame: int) -> np.ndarray:
    """The polyline the viewer shows at ``frame``: the latest-at strip of every part, in order,
    each part's first point (the join to the part before) dropped after the first part. Rows at
    the same frame resolve by row id, as in the viewer."""
    latest = {}
    for entity, f, _, pts in sorted(rows, key=lambda r: (r[1], r[2])):
        if f <= frame:
            latest[entity] = pts
    parts = [latest[e] for e in sorted(latest) if latest[e] is not None and len(latest[e])]
    if not parts:
        return np.zeros((0, 3))
    return np.concatenate([parts[0]] + [p[1:] for p in parts[1:]])


def _blobs(path: Path, entity: str, name: str) -> dict:
    """{frame: the blob's bytes} of an ``EncodedImage`` / ``EncodedDepthImage`` entity."""
    from rerun.chunk import RrdReader

    out = {}
    for chunk in RrdReader(path).stream():
        if chunk.entity_path != entity or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        for f, value in zip(batch.column("frame").to_pylist(), batch.column(name)):
            if value.is_valid:
                out[f] = value.values[0].values.to_numpy(zero_copy_only=False).tobytes()
    return out


def test_depth_png_round_trip_in_tenth_mm():
    depth = np.array([[0.0, 20.04, 20.06, 250.0], [np.nan, np.inf, -3.0, rl.DEPTH_MAX_MM + 1.0]], np.float32)
    back = decode_depth_png(rl.encode_depth_png(depth))
    assert back.dtype == np.float32 and back.shape == depth.shape
    np.testing.assert_allclose(back[0], [0.0, 20.0, 20.1, 250.0], atol=1e-4)
    assert np.all(back[1] == 0.0)  # no depth: non-finite, negative, beyond the uint16 range
    edge = decode_depth_png(rl.encode_depth_png(np.full((2, 2), rl.DEPTH_MAX_MM, np.float32)))
    assert np.allclose(edge, rl.DEPTH_MAX_MM)


def test_encoded_depth_decodes_to_the_logged_mm(recording):
    path, logged = recording
    blobs = _blobs(path, DEPTH, "EncodedDepthImage:blob")
    assert sorted(blobs) == list(range(N))
    for k, blob in blobs.items():
        depth = logged["views"][k].depth[0, 0].numpy()
        back = decode_depth_png(blob)
        assert back.shape == (H, W)
        np.testing.assert_allclose(back, depth, rtol=0, atol=0.5 / rl.DEPTH_UNITS_PER_MM + 1e-4)
        assert np.array_equal(back > 0, depth > 0)


def test_depth_coloured_over_the_scene_s_range(recording):
    """The depth view's colours span the scene's own depths (each recorded frame's 2nd to 98th
    percentile in the PNG's 0.1 mm, widened frame by frame), not a uint16 image's 0-65535 the viewer
    guesses without a range (one saturated colour over the tissue)."""
    from rerun.chunk import RrdReader

    path, logged = recording
    ranges = {}
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == DEPTH and not chunk.is_static:
            batch = chunk.to_record_batch()
            for f, value in zip(batch.column("frame").to_pylist(), batch.column("EncodedDepthImage:depth_range")
                                .to_pylist()):
                if value is not None:
                    ranges[f] = tuple(value[0])
    assert sorted(ranges) == list(range(N))
    lo, hi = np.inf, -np.inf
    for k in range(N):
        depth = logged["views"][k].depth[0, 0].numpy()
        p2, p98 = np.percentile(depth[depth > 0], [2, 98]) * rl.DEPTH_UNITS_PER_MM
        lo, hi = min(lo, p2), max(hi, p98)
        assert ranges[k] == pytest.approx((lo, hi))
    assert 500 < ranges[0][0] < ranges[0][1] < 1000      # the fake views' 50-100 mm


def test_trajectory_logged_in_parts(tmp_path, monkeypatch):
    """Each frame logs only the part of the path it extends (bounded data per frame, not the
    whole path), the parts at any frame make the path so far (ground truth with a gap too), and
    log_final's different poses (loop closure) replace it once, clearing parts beyond it."""
    monkeypatch.setattr(rl, "TRAJ_PART_FRAMES", 4)
    n = 14
    gt = np.stack([_pose(k) for k in range(n)])
    gt[3:6, :3, 3] = np.nan  # unknown ground truth across the first part boundary
    final = np.stack([_pose(k) for k in range(n - 3)])
    final[:, :3, 3] += [5.0, 0.0, 0.0]  # fewer poses, moved: the last part must go
    path = tmp_path / "parts.rrd"
    logged = _run_logger(path, n=n, gt_poses=gt, final_est=final, map_every=0)
    est_rows = _rows(path, "/world/trajectory/estimate/")
    assert sorted({e for e, _, _, _ in est_rows}) == [f"/world/trajectory/estimate/part_{i:04d}" for i in range(4)]
    per_frame = collections.Counter()
    for _, f, _, pts in est_rows:
        per_frame[f] += 0 if pts is None else len(pts)
    # bounded: a frame logs at most a part and its join (the last frame: also log_final's 11)
    assert all(per_frame[k] <= 4 + 1 for k in range(n - 1)), per_frame
    assert sum(per_frame[k] for k in range(n - 1)) < 3 * n  # the whole path each frame: 91
    for k in range(n - 1):
        np.testing.assert_allclose(_path_at(est_rows, k), logged["est"][: k + 1, :3, 3] / 1000.0, atol=1e-6)
        truth = gt[: k + 1, :3, 3]
        truth = truth[np.all(np.isfinite(truth), axis=1)] / 1000.0
        np.testing.assert_allclose(_path_at(_rows(path, "/world/trajectory/ground_truth/"), k), truth, atol=1e-6)
    # at the last frame: the final poses, the parts beyond them cleared
    np.testing.assert_allclose(_path_at(est_rows, n - 1), final[:, :3, 3] / 1000.0, atol=1e-6)
    last = sorted(((row_id, pts) for e, f, row_id, pts in est_rows if e.endswith("part_0003") and f == n - 1),
                  key=lambda r: r[0])
    assert last[-1][1] is None  # cleared after its strip


def test_trajectory_not_relogged_when_final_poses_agree(recording):
    path, _ = recording
    frames = _frames_per_entity(path)
    assert frames[(EST, "LineStrips3D:strips")] == list(range(N))  # one row a frame, none more at the end
    assert frames[(GT, "LineStrips3D:strips")] == list(range(N))


def test_rerun_every_records_every_kth_frame(tmp_path):
    path = tmp_path / "every3.rrd"
    _run_logger(path, n=8, rerun_every=3, map_every=0)
    frames = _frames_per_entity(path)
    recorded = [0, 3, 6]
    for entity, name in ((IMAGE, "EncodedImage:blob"), (DEPTH, "EncodedDepthImage:blob"),
                         (VALID, "SegmentationImage:buffer"), (CAMERA, "Transform3D:translation")):
        assert frames[(entity, name)] == recorded, entity
    for entity in (FLOW, W2D, W3D):
        assert frames[(entity, "EncodedImage:blob")] == [3, 6]
    every = list(range(8))
    assert frames[(EST, "LineStrips3D:strips")] == every  # the trajectory stays complete
    assert frames[(GT, "LineStrips3D:strips")] == every
    assert frames[("/metrics/failed", "Scalars:scalars")] == every


def test_rerun_every_is_validated():
    from slam.config import load_config
    from slam.errors import ConfigError

    assert load_config(None, ["logging.rerun_every=4"]).logging.rerun_every == 4
    with pytest.raises(ConfigError, match="logging.rerun_every must be >= 1"):
        load_config(None, ["logging.rerun_every=0"])


# ------------------------------------------------------------------------------------------------
# a real run on a synthetic sequence
SYNTH_FRAMES = 12
# measured at 160x128 (scanning, 12 frames, frame2model): 29.7 kB a frame for the per-frame
# entities (~23 kB the images; in 12 frames the chunks' schemas weigh), against ~220 kB with the
# raw images of before; the bound leaves 50 % for other machines and sequences
MAX_KB_PER_FRAME_160 = 45


class _CapturingLogger(RerunLogger):
    """A RerunLogger that keeps what it was given to log: the depth (mm) and the image (uint8)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.logged: dict = {}

    def log_frame(self, k, frame, view, track, record, *args, **kwargs):
        self.logged[k] = (rl._hw(view.depth).astype(np.float32).copy(), rl.image_to_u8(view.image))
        super().log_frame(k, frame, view, track, record, *args, **kwargs)


def _synth_run(data: Path, out: Path, overrides: list) -> tuple:
    from slam.config import load_config
    from slam.io.datasets import open_dataset
    from slam.app.pipeline import Pipeline

    config = load_config(None, ["tracking.mode=frame2model", "threads=1", f"logging.rerun={out / 'run.rrd'}", *overrides])
    dataset = open_dataset(data, config.data)
    logger = _CapturingLogger(config.logging, dataset.camera, name=data.name, gt_poses=dataset.gt_poses, R1=dataset.R1)
    result = Pipeline(config, dataset, out, logger=logger).run(progress=False)
    return out / "run.rrd", logger.logged, result


@pytest.fixture(scope="module")
def synth_recording(synth_dir, tmp_path_factory):
    data = synth_dir("scanning", SYNTH_FRAMES, (160, 128))
    return _synth_run(data, tmp_path_factory.mktemp("synth_rrd"), ["logging.map_every=0"])


def test_synth_run_encoded_views_read_back(synth_recording):
    import cv2

    path, logged, _ = synth_recording
    frames = _frames_per_entity(path)
    every = list(range(SYNTH_FRAMES))
    assert frames[(IMAGE, "EncodedImage:blob")] == every
    assert frames[(DEPTH, "EncodedDepthImage:blob")] == every
    assert frames[(VALID, "SegmentationImage:buffer")] == every
    for entity in (FLOW, W2D, W3D):
        assert frames[(entity, "EncodedImage:blob")] == every[1:]
    depths = _blobs(path, DEPTH, "EncodedDepthImage:blob")
    images = _blobs(path, IMAGE, "EncodedImage:blob")
    for k in every:
        depth, image = logged[k]
        back = decode_depth_png(depths[k])
        assert np.count_nonzero(depth) > 0.5 * depth.size
        np.testing.assert_allclose(back, depth, rtol=0, atol=0.5 / rl.DEPTH_UNITS_PER_MM + 1e-3)
        # the JPEG is the image, in RGB order (cv2 decodes to BGR)
        rgb = cv2.imdecode(np.frombuffer(images[k], np.uint8), cv2.IMREAD_COLOR)[..., ::-1].astype(float)
        err = np.abs(rgb - image).mean()
        assert err < 3.0, err
        assert err < 0.5 * np.abs(rgb[..., ::-1] - image).mean()


def test_synth_run_file_per_frame(synth_recording):
    """What the per-frame entities (camera and images, trajectories, scalars) take in the file,
    per frame, stays below a measured bound: their bytes are the file's size minus that of the
    file rerun writes without them."""
    path, _, _ = synth_recording
    per_frame = sorted({entity for entity, _ in _frames_per_entity(path)} - {MAP})
    assert IMAGE in per_frame and "/metrics/failed" in per_frame and EST in per_frame
    rest = path.with_name("rest.rrd")
    cmd = [str(RERUN_CLI), "rrd", "filter", str(path), "-o", str(rest)]
    for entity in per_frame:
        cmd += ["--drop-entity", entity]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    kb = (path.stat().st_size - rest.stat().st_size) / SYNTH_FRAMES / 1000.0
    assert 1.0 < kb < MAX_KB_PER_FRAME_160, f"{kb:.1f} kB a frame"


def test_synth_run_rerun_every(synth_dir, tmp_path):
    from slam.app.cli import main

    data = synth_dir("scanning", SYNTH_FRAMES, (160, 128))
    path = tmp_path / "every.rrd"
    assert main(["run", str(data), "--mode", "frame2model", "--out", str(tmp_path / "run"), "--rerun", str(path),
                 "--set", "threads=1", "--set", "logging.rerun_every=5", "--quiet"]) == 0
    frames = _frames_per_entity(path)
    assert frames[(IMAGE, "EncodedImage:blob")] == [0, 5, 10]
    assert frames[(DEPTH, "EncodedDepthImage:blob")] == [0, 5, 10]
    assert frames[(FLOW, "EncodedImage:blob")] == [5, 10]
    assert frames[(EST, "LineStrips3D:strips")] == list(range(SYNTH_FRAMES))
    est = _path_at(_rows(path, "/world/trajectory/estimate/"), SYNTH_FRAMES - 1)
    from slam.io.tum import read_tum

    _, poses = read_tum(tmp_path / "run" / "trajectory.txt")
    np.testing.assert_allclose(est, poses[:, :3, 3] / 1000.0, atol=1e-5)


# ------------------------------------------------------------------------------------------------
def _hue(rgb: np.ndarray) -> float:
    import colorsys

    return colorsys.rgb_to_hsv(*(rgb.astype(float) / 255.0))[0]


def test_flow_to_rgb_zero_is_black_and_direction_is_hue():
    zero = flow_to_rgb(np.zeros((H, W, 2), np.float32))
    assert zero.shape == (H, W, 3) and zero.dtype == np.uint8
    assert zero.max() == 0
    flow = np.zeros((2, 8, 8), np.float32)  # channel-first like a (1, 2, H, W) tensor
    flow[0, :, :4] = 2.0   # right
    flow[0, :, 4:] = -2.0  # left
    rgb = flow_to_rgb(torch.from_numpy(flow)[None])
    right, left = rgb[0, 0], rgb[0, -1]
    assert right.max() > 200 and left.max() > 200  # full magnitude: bright
    assert abs(_hue(right) - _hue(left)) == pytest.approx(0.5, abs=0.02)  # opposite directions
    up = flow_to_rgb(np.dstack([np.zeros((4, 4)), -np.ones((4, 4))]))[0, 0]
    assert min(abs(_hue(up) - _hue(right)), abs(_hue(up) - _hue(left))) > 0.2
    # magnitude -> value, normalised by a robust max (the outlier does not darken everything)
    ramp = np.zeros((1, 1001, 2), np.float32)
    ramp[0, :1000, 0] = np.linspace(0.0, 1.0, 1000)
    ramp[0, 1000, 0] = 1000.0
    value = flow_to_rgb(ramp, percentile=99.0).max(axis=-1)[0]
    assert np.all(np.diff(value[:1000].astype(int)) >= 0) and value[0] == 0 and value[999] == 255
    assert flow_to_rgb(ramp, max_magnitude=2.0).max(axis=-1)[0, 999] == pytest.approx(128, abs=2)
    nan = np.full((2, 2, 2), np.nan, np.float32)
    assert flow_to_rgb(nan).max() == 0


def test_colormap_min_dark_max_bright():
    w = np.linspace(0.3, 7.0, 64, dtype=np.float32).reshape(8, 8)
    rgb = colormap_u8(torch.from_numpy(w)[None, None])
    lum = rgb.astype(float) @ [0.299, 0.587, 0.114]
    assert rgb.shape == (8, 8, 3)
    assert lum.flat[0] == lum.min() and lum.flat[-1] == lum.max() and lum.max() - lum.min() > 150
    const = colormap_u8(np.ones((4, 4)))
    assert const.shape == (4, 4, 3) and np.all(const == const[0, 0])


def _reference_flow_to_rgb(flow: np.ndarray) -> np.ndarray:
    """The colour code in float numpy (HSV -> RGB by hand), what flow_to_rgb approximates."""
    u, v = flow[..., 0].astype(np.float64), flow[..., 1].astype(np.float64)
    mag = np.hypot(u, v)
    value = np.clip(mag / np.percentile(mag[mag > 0], 99.0), 0.0, 1.0)
    h6 = ((np.arctan2(v, u) / (2.0 * np.pi)) % 1.0) * 6.0
    i = np.floor(h6).astype(np.int64) % 6
    f = h6 - np.floor(h6)
    p, q, t = np.zeros_like(value), value * (1.0 - f), value * f
    rgb = np.stack([np.choose(i, [value, q, p, p, t, value]), np.choose(i, [t, value, value, q, p, p]),
                    np.choose(i, [p, p, t, value, value, q])], axis=-1)
    return (rgb * 255.0 + 0.5).astype(np.uint8)


def test_colour_codes_match_a_float_reference_and_leave_the_input():
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:96, 0:128].astype(np.float32)
    flow = np.dstack([np.cos(xx / 9.0) * 4.0, np.sin(yy / 7.0) * 3.0]) + rng.normal(0, 0.3, (96, 128, 2))
    flow = flow.astype(np.float32)
    before = flow.copy()
    diff = np.abs(flow_to_rgb(flow).astype(int) - _reference_flow_to_rgb(flow).astype(int))
    assert diff.max() <= 12 and diff.mean() < 1.0, (diff.max(), diff.mean())  # hue in 256 steps
    w = (rng.random((96, 128)) * 5.0).astype(np.float32)
    w[0, 0] = np.nan
    x = np.clip((w - np.nanmin(w)) / (np.nanmax(w) - np.nanmin(w)), 0.0, 1.0) * (len(rl._VIRIDIS) - 1)
    x = np.nan_to_num(x)
    i0 = np.minimum(np.floor(x).astype(np.int64), len(rl._VIRIDIS) - 2)
    reference = rl._VIRIDIS[i0] * (1.0 - (x - i0)[..., None]) + rl._VIRIDIS[i0 + 1] * (x - i0)[..., None]
    got = colormap_u8(w)
    assert np.abs(got[1:].astype(float) - reference[1:]).max() <= 2.0
    assert np.all(got[0, 0] == 0)  # non-finite: black
    assert np.array_equal(flow, before)
    assert np.isnan(w[0, 0]) and np.count_nonzero(np.isnan(w)) == 1


# ------------------------------------------------------------------------------------------------
def test_rerun_not_imported_unless_asked():
    code = (
        "import sys\n"
        "import slam.app.runner, slam.app.pipeline\n"
        "from types import SimpleNamespace\n"
        "from slam.config import SlamConfig\n"
        "assert slam.app.runner.make_logger(SlamConfig(), SimpleNamespace()) is None\n"
        "bad = sorted(m for m in sys.modules if m == 'rerun' or m.startswith(('rerun.', 'rerun_bindings')))\n"
        "assert not bad, bad\n"
        "print('ok')\n"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and "ok" in res.stdout, res.stderr[-3000:]


def test_make_logger_builds_a_rerun_logger(tmp_path):
    from slam.app.runner import make_logger

    config = SlamConfig()
    config.logging.rerun = str(tmp_path / "out" / "run.rrd")
    dataset = SimpleNamespace(camera=_camera(), path=tmp_path / "seq", gt_poses=None, R1=np.eye(3))
    logger = make_logger(config, dataset)
    assert isinstance(logger, RerunLogger)
    logger.close()
    assert (tmp_path / "out" / "run.rrd").is_file()
