"""The SLAM pipeline: read frames, track (frame2frame | frame2model), fuse, log, write results.

The pipeline owns progress, evaluation and result files; the VO core and the map own none of them.
Poses: the VO core tracks the *rectified* left camera; rows written are those of the original left
camera, ``T_wc = T_wc_rect @ [[R1, 0], [0, 1]]`` (docs/method.md, Conventions). The world frame is
the ground truth's when it exists (first estimate = first ground-truth pose), else the first camera's.
"""
from __future__ import annotations

import logging
import os
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from slam.config import SlamConfig, at_frame_rate, save_config
from slam.io.datasets.base import StereoFrame
from slam.errors import DataError, SlamError
from slam.app.frame_view import frame_view
from slam.tracking.health import health_summary, nees, relative_error
from slam.app.interrupts import SignalGate, signal_of
from slam.app.prefetch import Prefetcher
from slam.app.progress import Progress
from slam.app.run_folder import complete_ply, native_stderr_silenced, replaced_atomically, write_json_atomically
from slam.app.status import is_result, run_status
from slam.app.thread_use import ThreadBudget, ThreadClock, pool_sizes
from slam.tracking.state import TRUST, FrameResult
from slam.tracking.tracker import KnownPoseMapper, Tracker
from slam.app.tracking_csv import TrackingCsvWriter
from slam.io.tum import TumStreamWriter
from vo.odometry import AheadFlow, View

log = logging.getLogger("slam")


@dataclass
class FrameRecord:
    """What the pipeline keeps of one processed frame (small: no images)."""

    index: int
    timestamp: float
    pose: np.ndarray  # T_wc of the original left camera, mm
    failed: bool
    reason: str = ""
    reference: str = ""  # previous_frame | keyframe (an earlier frame, tracking.keyframe_gap) | model | chain | first
    iterations: int = 0
    cost: float = float("nan")
    health: dict = field(default_factory=dict)   # slam.tracking.health.FIGURES of the frame
    reference_position: Optional[int] = None      # the processed frame it was tracked against
    flagged: bool = False   # an inconsistent or uncertain pose (slam.tracking.tracker.FrameResult.flagged)
    trust: str = ""         # what the pose rests on (slam.tracking.state.TRUST)


@dataclass
class RunResult:
    """The outcome of ``run_sequence``."""

    out_dir: Path
    records: list = field(default_factory=list)
    metrics: dict = field(default_factory=dict)
    interrupted: bool = False
    signum: int = 0          # the signal that stopped it (SIGINT or SIGTERM), 0 when it ran to the end
    map_points: int = 0
    files: dict = field(default_factory=dict)
    output_errors: dict = field(default_factory=dict)   # output -> why it could not be written (one line)


class NoRecording:
    """A run without a rerun recording: frames are not logged."""

    path = None

    def log_frame(self, *args, **kwargs) -> None:
        """(Nothing recorded.)"""


class FlowAhead:
    """The read-ahead thread computes each view's temporal flow against the view it made before
    (where tracking flows against the previous frame, with a classical backend)."""

    def __init__(self, odometry):
        self.odometry = odometry

    def __call__(self, view: View, previous: View, timings: dict) -> AheadFlow:
        t0 = time.perf_counter()
        ahead = self.odometry.flow_ahead(view, previous)
        timings["flow_ahead"] = (time.perf_counter() - t0) * 1000.0
        return ahead


class NoFlowAhead:
    """Every temporal flow is computed where tracking needs it."""

    def __call__(self, view: View, previous: View, timings: dict) -> None:
        return None


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
        logger: a frame logger (``slam.app.rerun_log.RerunLogger``) or None.
        provenance: what the results depend on (``slam.app.provenance.provenance``), written into
            ``metrics.json``; None writes none.
    """

    def __init__(self, config: SlamConfig, dataset, out_dir: Path, logger=None, provenance: Optional[dict] = None):
        self.config = config
        self.provenance = provenance
        self.dataset = dataset
        self.out_dir = Path(out_dir)
        self.logger = logger if logger is not None else NoRecording()
        self.camera = dataset.camera
        self.R1 = _R1_4x4(dataset.R1)
        if config.analysis.poses == "groundtruth" and dataset.gt_poses is None:
            raise SlamError(f"{dataset.path}: analysis.poses=groundtruth needs a ground-truth trajectory")
        # thresholds on the motion per frame, at the frames' own rate (a frame selection's too)
        self.frame_rate = dataset.fps
        self.tracker = self._make_tracker(at_frame_rate(config, self.frame_rate))
        self.timings: dict[str, list[float]] = {}
        self._cpu = ThreadClock()                 # CPU time per frame of the main, read-ahead and mapping threads
        self._pools: dict = {}                    # the libraries' thread pools during the run
        self._ahead_view: Optional[View] = None   # the read-ahead thread's last view
        self._ahead_flow = NoFlowAhead()          # what the read-ahead thread does for the flow (run)
        self._waiting_for = -1      # the frame the main thread waits for (-1: none)
        self._rect_poses: list[np.ndarray] = []     # estimated rectified T_wc per processed frame

    def _make_tracker(self, config: SlamConfig):
        """The tracker, or the mapper at the ground-truth poses (``analysis.poses``)."""
        if config.analysis.poses == "groundtruth":
            return KnownPoseMapper(config, self.camera, self._initial_rect_pose(), self.dataset.gt_poses @ self.R1.T)
        return Tracker(config, self.camera, self._initial_rect_pose())

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

        Ctrl-C or SIGTERM (``slam.app.interrupts``) stops the frames; the results of the frames done
        are written, the small files first, and a second signal skips the slow ones.

        Args:
            progress: show progress (a bar on a terminal, a line now and then otherwise).
            on_frame: called with the number of frames done after each frame (e.g. to report
                progress to a batch driver).
        """
        self.out_dir.mkdir(parents=True, exist_ok=True)
        with replaced_atomically(self.out_dir / "config.yaml") as tmp:
            save_config(self.config, tmp)
        result = RunResult(out_dir=self.out_dir)
        n = len(self.dataset)
        writer = TumStreamWriter(self.out_dir / "trajectory.txt")
        health_csv = TrackingCsvWriter(self.out_dir / "tracking.csv")
        bar = Progress(n, "track", enabled=progress)
        on_frame = on_frame or (lambda done: None)
        self._ahead_view = None
        self._ahead_flow = FlowAhead(self.odometry) if self._flow_ahead() else NoFlowAhead()
        reader = Prefetcher(self._read_view, n, enabled=self._read_ahead())
        budget = ThreadBudget.of(self.config.threads, self._read_ahead())
        with SignalGate() as gate:      # a signal stops the frames; a second one skips the slow outputs
            t_start = time.perf_counter()
            try:
                with budget.applied(), gate.interruptible(), bar:   # (the outputs after: the pools as they were)
                    self._pools = pool_sizes()
                    self._cpu.start()
                    t_start = time.perf_counter()
                    for k in range(n):
                        self._track_frame(k, reader, writer, health_csv, result)
                        bar.update(1, fps=f"{(k + 1) / max(time.perf_counter() - t_start, 1e-9):.1f}",
                                   fail=sum(r.failed for r in result.records), flag=sum(r.flagged for r in result.records))
                        on_frame(k + 1)
            except KeyboardInterrupt as err:
                result.interrupted, result.signum = True, signal_of(err)
                log.warning("interrupted after %d frames: writing the results (a second Ctrl-C skips the map, "
                            "mesh, plot and recording)", len(result.records))
            finally:
                self._record_thread_work(self.tracker.close())     # the last fusion in flight
                self._cpu.stop()
                reader.close()
                writer.close()
                health_csv.close()
            self._finish(result, time.perf_counter() - t_start, gate)
        return result

    def _track_frame(self, k: int, reader: Prefetcher, writer: TumStreamWriter, health_csv: TrackingCsvWriter,
                     result: RunResult) -> None:
        """Frame ``k``: track it, write its rows (``trajectory.txt``, ``tracking.csv``), keep its record."""
        t_frame = time.perf_counter()
        with self._cpu.measure("main"):
            record = self._step(k, reader)
        if record.failed:
            log.warning("frame %d: %s (pose carried over)", record.index, record.reason)
        elif record.flagged:
            log.warning("frame %d flagged: %s%s", record.index, record.reason,
                        "" if "re-anchored" in record.reason or "rebuilt" in record.reason else " (not fused)")
        writer.write(record.timestamp, record.pose)
        health_csv.write(record.index, record.timestamp, record.failed, record.flagged, record.trust, record.reason,
                         record.reference, self._reference_frame(record), record.health)
        result.records.append(record)
        self._time("total", (time.perf_counter() - t_frame) * 1000.0)

    def _record_thread_work(self, result: FrameResult) -> None:
        """The stage times of ``result`` and the CPU time of the other threads handed over with it."""
        for stage, ms in result.timings:
            self._time(stage, ms)
        for thread, ms in result.thread_cpu.items():
            self._cpu.add(thread, ms)

    def _read_ahead(self) -> bool:
        """Whether views are made in the read-ahead thread (a stereo flow of its own: not one RAFT
        model shared with the temporal flow)."""
        odo = self.odometry
        return odo.stereo_flow is not odo.temporal_flow

    def _flow_ahead(self) -> bool:
        """Whether the read-ahead thread also computes the temporal flow against the previous
        frame: only where tracking flows against the previous frame."""
        return self._read_ahead() and self.odometry.can_flow_ahead() and self.tracker.flows_against_previous_frame()

    def _read_view(self, k: int) -> tuple[StereoFrame, View, Optional[AheadFlow], dict]:
        """Frame ``k``, its view, the view's temporal flow against the view made before (the
        previous frame's, unless that one could not be read; computed ahead where tracking flows
        against the previous frame and the main thread is not waiting for this frame, else None)
        and their timings. The read-ahead thread runs this, for one frame after another (the main
        thread where views are not made ahead); tracking takes the flow only where it goes
        against its reference. Raises what reading the frame raises."""
        t_cpu = time.thread_time()
        frame = self.dataset.frame(k)
        timings: dict = {}
        view = self._make_view(frame, timings)
        previous, self._ahead_view = self._ahead_view, view
        ahead = None
        if previous is not None and self._waiting_for != k:
            ahead = self._ahead_flow(view, previous, timings)
        thread = self._cpu.reader_name()
        if thread is not None:     # (in the main thread, the frame's CPU time counts it already)
            self._cpu.add(thread, (time.thread_time() - t_cpu) * 1000.0)
        return frame, view, ahead, timings

    def _make_view(self, frame: StereoFrame, timings: dict) -> View:
        """Stereo depth (or the ground-truth depth of ``analysis.depth_source``) of ``frame``."""
        return frame_view(self.odometry, frame, self.dataset.path, timings, self.config.analysis.depth_source)

    def _step(self, k: int, reader: Prefetcher) -> FrameRecord:
        """Read frame ``k``, have the tracker track it, log it; a frame that cannot be read makes a
        failed record and leaves the tracker as it was."""
        index = int(self.dataset.indices[k])
        stamp = float(self.dataset.timestamps[k])
        try:
            t0 = time.perf_counter()
            self._waiting_for = k
            try:
                frame, view, ahead, timings = reader.get(k)   # read ahead in a thread: the time spent waiting
            finally:
                self._waiting_for = -1
            self._time("read", (time.perf_counter() - t0) * 1000.0)
        except DataError as err:
            self._rect_poses.append(self.tracker.pose)
            return FrameRecord(index, stamp, self.tracker.pose @ self.R1, True, f"unreadable frame: {err}", trust="failed")
        for stage, ms in timings.items():
            self._time(stage, ms)
        result = self.tracker.track(k, view, ahead)
        self._record_thread_work(result)
        track = result.track
        pose = result.pose @ self.R1
        self._rect_poses.append(np.asarray(result.pose))
        record = FrameRecord(index, stamp, pose, result.failed, result.reason, result.reference,
                             track.iterations if track is not None else 0,
                             track.cost if track is not None else float("nan"), dict(result.health),
                             result.reference_position, result.flagged, result.trust)
        record.health["nees"] = self._nees(k, result)
        self._log(k, frame, result.view or view, track, result.pose, record)
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
        t0 = time.perf_counter()
        self.logger.log_frame(k, frame, view, track, record, self.map, self.odometry.camera, pose_rect)
        self._time("logging", (time.perf_counter() - t0) * 1000.0)

    # --------------------------------------------------------------------------------------
    def _finish(self, result: RunResult, wall_s: float, gate: SignalGate) -> None:
        """The run's results: first the small files (the final trajectory, ``metrics.json``),
        then the slow ones (map, mesh, plot, recording), of which a signal (``gate``) skips those
        not written yet; ``metrics.json`` then lists them."""
        estimate, online = self._final_trajectory(result)
        result.metrics = self._metrics(result, wall_s, estimate, online)
        result.files = {name: str(self.out_dir / file) for name, file in (
            ("trajectory", "trajectory.txt"), ("tracking", "tracking.csv"), ("config", "config.yaml"),
            ("metrics", "metrics.json"))}
        if online is not None:
            result.files["trajectory_online"] = str(self.out_dir / "trajectory_online.txt")
        write_json_atomically(self.out_dir / "metrics.json", result.metrics)
        skipped = self._write_slow_outputs(result, estimate, online, gate)
        if gate.received and not result.interrupted:     # the first signal came after the last frame
            result.interrupted, result.signum = True, gate.received[0]
            result.metrics.update(interrupted=True, stopped_before_frame=None)
        if skipped:
            result.metrics["skipped_outputs"] = skipped
            log.warning("interrupted: skipped %s", ", ".join(skipped))
        if result.output_errors:        # (the command names them in its one error line)
            result.metrics["skipped_outputs"] = skipped + list(result.output_errors)
            result.metrics["output_errors"] = result.output_errors
        write_json_atomically(self.out_dir / "metrics.json", result.metrics)

    def _final_trajectory(self, result: RunResult) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """The poses the run reports ``(N, 4, 4)`` (original left camera, mm) and, where they
        differ from those tracked, the poses as tracked (else None). The repairs of unconfirmed
        stretches (:mod:`slam.tracking.chain_repair`) and loop closure's optimisations make the
        result: ``trajectory.txt`` is rewritten with them, the streamed one kept as
        ``trajectory_online.txt``."""
        records = result.records
        tracked = np.stack([r.pose for r in records]) if records else np.zeros((0, 4, 4))
        optimised = self.tracker.optimised_poses(np.stack(self._rect_poses)) if records else None
        if optimised is None or not records:
            return tracked, None
        from slam.io.tum import write_tum

        estimate = optimised @ self.R1
        path = self.out_dir / "trajectory.txt"
        os.replace(path, self.out_dir / "trajectory_online.txt")
        with replaced_atomically(path) as tmp:
            write_tum(tmp, np.array([r.timestamp for r in records]), estimate)
        return estimate, tracked

    def _metrics(self, result: RunResult, wall_s: float, estimate: np.ndarray, online: Optional[np.ndarray]) -> dict:
        """``metrics.json``'s content (README, Outputs): counts, speed, health, provenance, and
        against the ground truth the accuracy, under ``not_trusted`` when too many frames failed."""
        records = result.records
        done = len(records)
        failed = sum(r.failed for r in records)
        status = run_status(done, failed, sum(r.flagged for r in records))
        metrics: dict = {
            "data": str(self.dataset.path),
            "status": status,
            "frames": done,
            "selected_frames": len(self.dataset),
            "tracked_frames": done - failed,
            "failed_frames": [r.index for r in records if r.failed],
            "failures": {str(r.index): r.reason for r in records if r.failed},
            "flagged_frames": [r.index for r in records if r.flagged],
            "flags": {str(r.index): r.reason for r in records if r.flagged},
            "trust": {name: sum(r.trust == name for r in records) for name in TRUST},
            "fps": (done - failed) / wall_s if wall_s > 0 else 0.0,
            "timings_ms": {k: float(np.mean(v)) for k, v in self.timings.items()},
            "thread_cpu_ms": self._cpu.summary(done),
            "thread_pools": self._pools,
            "mode": self.config.tracking.mode,
            "frame_rate": self.frame_rate,
            "model_fallbacks": self.tracker.fallbacks,
            "model_rebuilds": self.tracker.rebuilds,
            "map_reanchors": self.tracker.reanchors,
            "repaired_frames": self.tracker.repaired_frames,
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
        accuracy = self._accuracy(records, estimate, online)
        cause = self._likely_cause(records) if status != "ok" else ""
        if cause:
            metrics["likely_cause"] = cause
        if is_result(status):
            metrics.update(accuracy)
        elif accuracy:
            metrics["not_trusted"] = accuracy
        return metrics

    def _likely_cause(self, records: list) -> str:
        """Why the frames failed (or were flagged), read off the first such frame that reads
        (:func:`slam.io.stereo_check.likely_cause`); '' when its figures show nothing."""
        from slam.io.stereo_check import likely_cause

        bad = ([k for k, r in enumerate(records) if r.failed and not r.reason.startswith("unreadable")]
               or [k for k, r in enumerate(records) if r.flagged])
        try:
            frame = self.dataset.frame(bad[0]) if bad else None
        except DataError:
            frame = None
        if frame is None:
            return ""
        depth = self.config.depth
        return likely_cause(frame.left, frame.right, frame.mask, self.camera.fx, self.camera.baseline_mm,
                            (depth.min_depth_mm, depth.max_depth_mm))

    def _groundtruth_of(self, records: list) -> tuple[Optional[np.ndarray], np.ndarray]:
        """The ground truth of the processed frames ``(N, 4, 4)`` (None without) and the mask of
        those with a pose (frames associated by time may have none)."""
        gt = self.dataset.gt_poses
        if gt is None:
            return None, np.zeros(len(records), dtype=bool)
        gt = gt[:len(records)]
        return gt, np.all(np.isfinite(gt.reshape(len(gt), 16)), axis=1)

    def _accuracy(self, records: list, estimate: np.ndarray, online: Optional[np.ndarray]) -> dict:
        """ATE and RPE against the ground truth over the frames with a ground-truth pose
        (``evaluated_frames``); with loop closure the tracked poses' under ``online``."""
        from slam.evaluation.metrics import evaluate

        gt, known = self._groundtruth_of(records)
        if gt is None:
            return {}
        out: dict = {}
        if not known.all():
            out["frames_without_groundtruth"] = int((~known).sum())
        if known.sum() < 2:
            return out
        figures = evaluate(gt[known], estimate[known])
        figures["evaluated_frames"] = figures.pop("frames")
        out.update(figures)
        if online is not None:
            out["online"] = evaluate(gt[known], online[known])
            out["online"]["evaluated_frames"] = out["online"].pop("frames")
        return out

    def _write_slow_outputs(self, result: RunResult, estimate: np.ndarray, online: Optional[np.ndarray],
                            gate: SignalGate) -> list[str]:
        """Write the map, the mesh, the plot and the recording's end, in that order; a signal
        (before or during one of them) skips the rest. Returns the names of those skipped. One
        that cannot be written (a full disk) leaves no file and goes to ``result.output_errors``;
        the others are still written."""
        outputs = []
        if self.map is not None:
            outputs.append(("map", self._write_map))
            if self.config.logging.mesh:
                outputs.append(("mesh", self._write_mesh))
        if len(estimate) >= 2:
            outputs.append(("plot", self._write_plot))
        if not isinstance(self.logger, NoRecording):
            outputs.append(("recording", self._end_recording))
        for i, (name, write) in enumerate(outputs):
            try:
                with gate.interruptible():
                    write(result, estimate, online)
            except KeyboardInterrupt:
                if hasattr(self.logger, "close"):
                    self.logger.close()
                return [n for n, _ in outputs[i:]]
            except OSError as err:
                result.output_errors[name] = f"{err.filename}: {err.strerror}" if err.filename else str(err)
        return []

    def _write_map(self, result: RunResult, estimate, online) -> None:
        # the map lives in the rectified world frame of the VO, which is the world frame: only
        # camera frames are rotated by R1, the world is shared.
        path = self.out_dir / "map.ply"
        with replaced_atomically(path, check=complete_ply) as tmp, native_stderr_silenced():
            result.map_points = self.map.save_ply(tmp)
        result.metrics["map_points"] = result.map_points
        result.files["map"] = str(path)

    def _write_mesh(self, result: RunResult, estimate, online) -> None:
        path = self.out_dir / "mesh.ply"
        with replaced_atomically(path, check=complete_ply) as tmp, native_stderr_silenced():
            triangles = self.map.save_mesh(tmp)
        result.metrics["mesh_triangles"] = triangles
        result.files["mesh"] = str(path)

    def _write_plot(self, result: RunResult, estimate, online) -> None:
        from slam.app.plots import plot_trajectory

        gt, known = self._groundtruth_of(result.records)
        if gt is None or known.sum() < 2:
            gt, known = None, np.ones(len(estimate), dtype=bool)
        keep = known
        stamps = np.array([r.timestamp for r in result.records])
        path = self.out_dir / "trajectory.png"
        with replaced_atomically(path) as tmp:
            plot_trajectory(tmp, estimate[keep], None if gt is None else gt[keep], stamps[keep],
                            title=f"{self.dataset.path.name} ({self.config.tracking.mode})")
        result.files["plot"] = str(path)

    def _end_recording(self, result: RunResult, estimate, online) -> None:
        gt, known = self._groundtruth_of(result.records)
        edges = None
        if self.tracker.loops is not None:
            kf = self.tracker.loops.keyframe_positions
            edges = [(kf[i], kf[j]) for i, j in self.tracker.loops.graph.loop_edges()]
        self.logger.log_final(self.map, estimate, gt[known] if gt is not None else None, online_poses=online,
                              loop_edges=edges)
        path = getattr(self.logger, "path", None)      # (a logger that records to no file has none)
        if path is not None:
            result.files["recording"] = str(path)
