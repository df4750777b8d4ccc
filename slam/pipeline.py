"""The SLAM pipeline: read frames, track (frame2frame | frame2model), fuse, log, write results.

The pipeline owns progress, evaluation and result files; the VO core and the map own none of them.
Poses: the VO core tracks the *rectified* left camera; rows written are those of the original left
camera, ``T_wc = T_wc_rect @ [[R1, 0], [0, 1]]`` (docs/method.md, Conventions). The world frame is
the ground truth's when it exists (first estimate = first ground-truth pose), else the first camera's.
"""
from __future__ import annotations

import json
import logging
import os
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from slam.config import SlamConfig, at_frame_rate, save_config
from slam.datasets.base import StereoFrame
from slam.errors import DataError, SlamError
from slam.frame_view import frame_view
from slam.prefetch import Prefetcher
from slam.health import health_summary, nees, relative_error
from slam.tracker import FrameResult, Tracker
from slam.tracking_csv import TrackingCsvWriter
from slam.tum import TumStreamWriter
from vo.odometry import View

log = logging.getLogger("slam")


@dataclass
class FrameRecord:
    """What the pipeline keeps of one processed frame (small: no images)."""

    index: int
    timestamp: float
    pose: np.ndarray  # T_wc of the original left camera, mm
    failed: bool
    reason: str = ""
    reference: str = ""  # previous_frame | keyframe (an earlier frame, tracking.keyframe_gap) | model | first
    iterations: int = 0
    cost: float = float("nan")
    health: dict = field(default_factory=dict)   # slam.health.FIGURES of the frame
    reference_position: Optional[int] = None      # the processed frame it was tracked against
    flagged: bool = False   # an inconsistent or uncertain pose (slam.tracker.FrameResult.flagged)


@dataclass
class RunResult:
    """The outcome of ``run_sequence``."""

    out_dir: Path
    records: list = field(default_factory=list)
    metrics: dict = field(default_factory=dict)
    interrupted: bool = False
    map_points: int = 0
    files: dict = field(default_factory=dict)


def _R1_4x4(R1: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = R1
    return M


class Pipeline:
    """One run over a dataset.

    Args:
        config: the resolved configuration.
        dataset: a ``StereoDataset`` view (frames already selected).
        out_dir: where results go.
        logger: a frame logger (``slam.rerun_log.RerunLogger``) or None.
        provenance: what the results depend on (``slam.provenance.provenance``), written into
            ``metrics.json``; None writes none.
    """

    def __init__(self, config: SlamConfig, dataset, out_dir: Path, logger=None, provenance: Optional[dict] = None):
        self.config = config
        self.provenance = provenance
        self.dataset = dataset
        self.out_dir = Path(out_dir)
        self.logger = logger
        self.camera = dataset.camera
        self.R1 = _R1_4x4(dataset.R1)
        if config.tracking.poses == "groundtruth" and dataset.gt_poses is None:
            raise SlamError(f"{dataset.path}: tracking.poses=groundtruth needs a ground-truth trajectory")
        # thresholds on the motion per frame, at the frames' own rate (a frame selection's too)
        self.frame_rate = dataset.fps
        self.tracker = Tracker(at_frame_rate(config, self.frame_rate), self.camera, self._initial_rect_pose())
        self.timings: dict[str, list[float]] = {}
        self._ahead_view: Optional[View] = None   # the read-ahead thread's last view (tracking.read_ahead)
        self._waiting_for = -1      # the frame the main thread waits for (-1: none)
        self._rect_poses: list[np.ndarray] = []     # estimated rectified T_wc per processed frame

    @property
    def odometry(self):
        """The tracker's VO core."""
        return self.tracker.odometry

    @property
    def map(self):
        """The tracker's surfel map (None when the run fuses none)."""
        return self.tracker.map

    # --------------------------------------------------------------------------------------
    def _initial_rect_pose(self) -> np.ndarray:
        gt = self.dataset.gt_poses
        T0 = gt[0] if gt is not None and np.all(np.isfinite(gt[0])) else np.eye(4)
        if gt is not None and not np.all(np.isfinite(gt[0])):
            log.warning("%s: the first frame has no ground-truth pose: the world frame is its camera's", self.dataset.path)
        return T0 @ self.R1.T  # T_wc_rect = T_wc_orig @ R1^T

    def _time(self, stage: str, ms: float) -> None:
        self.timings.setdefault(stage, []).append(ms)

    # --------------------------------------------------------------------------------------
    def run(self, progress: bool = True, on_frame: Optional[Callable[[int], None]] = None) -> RunResult:
        """Process every frame; write trajectory rows as they come; never lose finished work.

        Args:
            progress: show a progress bar.
            on_frame: called with the number of frames done after each frame (e.g. to report
                progress to a batch driver).
        """
        from tqdm import tqdm

        self.out_dir.mkdir(parents=True, exist_ok=True)
        save_config(self.config, self.out_dir / "config.yaml")
        result = RunResult(out_dir=self.out_dir)
        n = len(self.dataset)
        writer = TumStreamWriter(self.out_dir / "trajectory.txt")
        health_csv = TrackingCsvWriter(self.out_dir / "tracking.csv")
        bar = tqdm(total=n, unit="frame", disable=not progress, dynamic_ncols=True, leave=False)
        self._ahead_view = None
        reader = Prefetcher(self._read_view, n)
        threads_before = torch.get_num_threads()
        torch.set_num_threads(self._torch_threads())
        t_start = time.perf_counter()
        try:
            for k in range(n):
                t_frame = time.perf_counter()
                record = self._step(k, reader)
                if record.failed:
                    log.warning("frame %d: %s (pose carried over)", record.index, record.reason)
                elif record.flagged:
                    log.warning("frame %d flagged: %s (not fused)", record.index, record.reason)
                writer.write(record.timestamp, record.pose)
                health_csv.write(record.index, record.timestamp, record.failed, record.flagged, record.reason,
                                 record.reference, self._reference_frame(record), record.health)
                result.records.append(record)
                self._time("total", (time.perf_counter() - t_frame) * 1000.0)
                bar.update(1)
                elapsed = time.perf_counter() - t_start
                bar.set_postfix(fps=f"{(k + 1) / max(elapsed, 1e-9):.1f}", fail=sum(r.failed for r in result.records),
                                flag=sum(r.flagged for r in result.records))
                if on_frame is not None:
                    on_frame(k + 1)
        except KeyboardInterrupt:
            result.interrupted = True
            log.warning("interrupted after %d frames; results so far are written", len(result.records))
        finally:
            reader.close()
            bar.close()
            writer.close()
            health_csv.close()
            torch.set_num_threads(threads_before)
        wall = time.perf_counter() - t_start
        self._finish(result, wall)
        return result

    def _read_ahead(self) -> bool:
        """Whether views are made in the read-ahead thread (``tracking.read_ahead``, and a stereo
        flow of its own: not one RAFT model shared with the temporal flow)."""
        odo = self.odometry
        return self.config.tracking.read_ahead and odo.stereo_flow is not odo.temporal_flow

    def _torch_threads(self) -> int:
        """``threads``, or with 0 every core but the read-ahead thread's (torch's default without it)."""
        if self.config.threads > 0:
            return self.config.threads
        if not self._read_ahead():
            return torch.get_num_threads()
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        return max(1, cores - 1)

    def _flow_ahead(self) -> bool:
        """Whether the read-ahead thread also computes the temporal flow against the previous
        frame: only where tracking flows against the previous frame."""
        return self._read_ahead() and self.odometry.can_flow_ahead() and self.tracker.flows_against_previous_frame()

    def _read_view(self, k: int) -> tuple[StereoFrame, Optional[View], dict]:
        """Frame ``k`` and, with ``tracking.read_ahead``, its view and the view's timings (the
        read-ahead thread runs this, for one frame after another). The view also carries its
        temporal flow against the view this thread made before (the previous frame's, unless
        that one could not be read) where tracking flows against the previous frame; tracking
        takes it only if that view is its reference. Raises what reading the frame raises."""
        frame = self.dataset.frame(k)
        timings: dict = {}
        if not self._read_ahead():
            return frame, None, timings
        view = self._make_view(frame, timings)
        previous, self._ahead_view = self._ahead_view, view
        if previous is not None and self._flow_ahead() and self._waiting_for != k:
            t0 = time.perf_counter()
            self.odometry.flow_ahead(view, previous)
            timings["flow_ahead"] = (time.perf_counter() - t0) * 1000.0
        return frame, view, timings

    def _make_view(self, frame: StereoFrame, timings: dict) -> View:
        """Stereo depth (or the ground-truth depth of ``depth.source: groundtruth``) of ``frame``."""
        return frame_view(self.odometry, frame, self.dataset.path, timings)

    def _step(self, k: int, reader: Prefetcher) -> FrameRecord:
        """Read frame ``k``, have the tracker track it, log it; a frame that cannot be read makes a
        failed record and leaves the tracker as it was."""
        index = int(self.dataset.indices[k])
        stamp = float(self.dataset.timestamps[k])
        try:
            t0 = time.perf_counter()
            self._waiting_for = k
            try:
                frame, view, timings = reader.get(k)   # read ahead in a thread: the time spent waiting for it
            finally:
                self._waiting_for = -1
            self._time("read", (time.perf_counter() - t0) * 1000.0)
        except DataError as err:
            self._rect_poses.append(self.tracker.pose)
            return FrameRecord(index, stamp, self.tracker.pose @ self.R1, True, f"unreadable frame: {err}")
        if view is None:
            timings = {}
            view = self._make_view(frame, timings)
        for stage, ms in timings.items():
            self._time(stage, ms)
        gt_pose = frame.gt_pose @ self.R1.T if self.tracker.known_poses else None
        result = self.tracker.track(k, view, gt_pose)
        for stage, ms in result.timings:
            self._time(stage, ms)
        track = result.track
        pose = frame.gt_pose if self.tracker.known_poses else result.pose @ self.R1
        self._rect_poses.append(np.asarray(result.pose))
        record = FrameRecord(index, stamp, pose, result.failed, result.reason, result.reference,
                             track.iterations if track is not None else 0,
                             track.cost if track is not None else float("nan"), dict(result.health),
                             result.reference_position, result.flagged)
        record.health["nees"] = self._nees(k, result)
        self._log(k, frame, view, track, result.pose, record)
        return record

    def _nees(self, k: int, result: FrameResult) -> float:
        """The NEES of frame ``k``'s motion from its reference frame against the ground truth's
        (nan without a covariance or a ground-truth pose of both frames)."""
        gt, ref = self.dataset.gt_poses, result.reference_position
        if result.covariance is None or result.failed or gt is None or ref is None or ref < 0:
            return float("nan")
        if not (np.all(np.isfinite(gt[k])) and np.all(np.isfinite(gt[ref]))):
            return float("nan")
        truth = np.linalg.inv(gt[ref] @ self.R1.T) @ (gt[k] @ self.R1.T)
        estimate = np.linalg.inv(self._rect_poses[ref]) @ self._rect_poses[k]
        return nees(relative_error(estimate, truth), result.covariance)

    def _reference_frame(self, record: FrameRecord) -> Optional[int]:
        """The dataset index of the frame ``record`` was tracked against, if any."""
        ref = record.reference_position
        return None if ref is None or ref < 0 else int(self.dataset.indices[ref])

    def _log(self, k, frame, view, track, pose_rect, record) -> None:
        if self.logger is not None:
            t0 = time.perf_counter()
            self.logger.log_frame(k, frame, view, track, record, self.map, self.odometry.camera, pose_rect)
            self._time("logging", (time.perf_counter() - t0) * 1000.0)

    def _write_optimised(self, records: list, poses: np.ndarray) -> None:
        """With loop closure: the streamed ``trajectory.txt`` (the poses as tracked) becomes
        ``trajectory_online.txt`` and ``trajectory.txt`` gets the optimised ``poses``."""
        from slam.tum import write_tum

        path = self.out_dir / "trajectory.txt"
        os.replace(path, self.out_dir / "trajectory_online.txt")
        write_tum(path, np.array([r.timestamp for r in records]), poses)

    # --------------------------------------------------------------------------------------
    def _finish(self, result: RunResult, wall_s: float) -> None:
        from slam.evaluation import evaluate
        from slam.plots import plot_trajectory

        records = result.records
        done = len(records)
        est = np.stack([r.pose for r in records]) if records else np.zeros((0, 4, 4))
        online = None
        optimised = self.tracker.optimised_poses(range(done))
        if optimised is not None and done:      # loop closure: the optimised poses are the result
            online, est = est, optimised @ self.R1
            self._write_optimised(records, est)
        metrics: dict = {
            "data": str(self.dataset.path),
            "frames": done,
            "failed_frames": [r.index for r in records if r.failed],
            "failures": {str(r.index): r.reason for r in records if r.failed},
            "flagged_frames": [r.index for r in records if r.flagged],
            "flags": {str(r.index): r.reason for r in records if r.flagged},
            "fps": done / wall_s if wall_s > 0 else 0.0,
            "timings_ms": {k: float(np.mean(v)) for k, v in self.timings.items()},
            "mode": self.config.tracking.mode,
            "frame_rate": self.frame_rate,
            "model_fallbacks": self.tracker.fallbacks,
            "model_rebuilds": self.tracker.rebuilds,
            "health": health_summary([r.health for r in records]),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        }
        if self.provenance is not None:
            metrics["provenance"] = self.provenance
        if result.interrupted:
            metrics["interrupted"] = True
            metrics["stopped_before_frame"] = int(self.dataset.indices[done]) if done < len(self.dataset) else None
        if self.tracker.loops is not None:
            metrics["loop_closure"] = self.tracker.loops.summary(done, float(np.sum(self.timings.get("loop", [0.0]))))
        gt = self.dataset.gt_poses
        gt_sel = gt[:done] if gt is not None else None
        stamps = np.array([r.timestamp for r in records])
        online_sel = online
        if gt_sel is not None:      # frames without a ground-truth pose (associated by time) are left out
            known = np.all(np.isfinite(gt_sel.reshape(len(gt_sel), 16)), axis=1)
            if not known.all():
                metrics["frames_without_groundtruth"] = int((~known).sum())
                gt_sel, est, stamps = gt_sel[known], est[known], stamps[known]
                online_sel = online[known] if online is not None else None
        if gt_sel is not None and len(gt_sel) >= 2:
            metrics.update(evaluate(gt_sel, est))
            if online_sel is not None:
                metrics["online"] = evaluate(gt_sel, online_sel)
        files = {"trajectory": str(self.out_dir / "trajectory.txt"), "config": str(self.out_dir / "config.yaml")}
        if online is not None:
            files["trajectory_online"] = str(self.out_dir / "trajectory_online.txt")
        if self.map is not None:
            ply = self.out_dir / "map.ply"
            # the map lives in the rectified world frame of the VO, which is the world frame: only
            # camera frames are rotated by R1, the world is shared.
            result.map_points = self.map.save_ply(ply)
            metrics["map_points"] = result.map_points
            files["map"] = str(ply)
            if self.config.logging.mesh:
                mesh = self.out_dir / "mesh.ply"
                metrics["mesh_triangles"] = self.map.save_mesh(mesh)
                files["mesh"] = str(mesh)
        if len(est) >= 2:
            plot_trajectory(self.out_dir / "trajectory.png", est, gt_sel, stamps,
                            title=f"{self.dataset.path.name} ({self.config.tracking.mode})")
            files["plot"] = str(self.out_dir / "trajectory.png")
        (self.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
        files["metrics"] = str(self.out_dir / "metrics.json")
        if self.logger is not None:
            edges = None
            if self.tracker.loops is not None:
                kf = self.tracker.loops.keyframe_positions
                edges = [(kf[i], kf[j]) for i, j in self.tracker.loops.graph.loop_edges()]
            self.logger.log_final(self.map, est, gt_sel, online_poses=online, loop_edges=edges)
        result.metrics = metrics
        result.files = files
