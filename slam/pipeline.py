"""The SLAM pipeline: read frames, track (frame2frame | frame2model), fuse, log, write results.

The pipeline owns progress, evaluation and result files; the VO core and the map own none of them.
Poses: the VO core tracks the *rectified* left camera; rows written are those of the original left
camera, ``T_wc = T_wc_rect @ [[R1, 0], [0, 1]]`` (ARCHITECTURE.md, Conventions). The world frame is
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
from typing import Optional

import numpy as np
import torch

from slam.config import SlamConfig, save_config
from slam.datasets.base import StereoFrame
from slam.errors import DataError, SlamError
from slam.frame_view import frame_view
from slam.prefetch import Prefetcher
from slam.tum import TumStreamWriter
from vo.odometry import StereoOdometry, TrackResult, View, moved_less_than

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


def model_coverage(model_valid: torch.Tensor, frame_valid: torch.Tensor) -> float:
    """The fraction of a frame's valid pixels ``(H, W)`` bool that the model view ``(H, W)`` bool
    rendered at its pose covers (the whole image's fraction when the frame has none).

    Measured on what the camera saw, not on the whole image: pixels without stereo depth (the
    border the right view does not see) or masked out (instruments, highlights) are left out.
    """
    n = int(frame_valid.sum())
    if n == 0:
        return float(model_valid.float().mean())
    return int((model_valid & frame_valid).sum()) / n


def normalised_fusion_weight(w3d: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The per-pixel fusion weight of a frame from its learned 3D weight.

    Where the tracker weighed the pixel (``w3d > 0``): ``w3d`` divided by its median over those
    pixels, clamped to [0, 1]. The optimum does not fix the weights' scale, so a typical pixel
    counts as one observation (the map's confidence keeps ElasticFusion's meaning and a surface
    becomes stable after a few frames) and a pixel the network trusts k times less than typical
    counts 1/k. Valid pixels the tracker could not weigh (no reference depth there: tissue coming
    into view, outside the model view) count fully: leaving them out would keep new tissue out of
    the map until the tracker next falls back to the previous frame.
    Invalid pixels (no stereo depth, instruments, highlights) are 0.

    Args:
        w3d: ``(H, W)`` learned 3D weight, 0 where the tracker did not weigh the pixel;
        valid: ``(H, W)`` bool valid pixels of the frame.
    """
    weighed = valid & (w3d > 0)
    vals = w3d[weighed]
    if vals.numel() == 0:
        return valid.to(w3d.dtype)
    ref = vals.float()[:: max(1, vals.numel() // 20000)].median().clamp(min=1e-12)   # (quantile: 8x slower)
    return torch.where(weighed, (w3d / ref).clamp(0, 1), valid.to(w3d.dtype))


def mean_brightness(view: View) -> float:
    """Mean grey level (0-255) of ``view``'s valid pixels (of all pixels when under 1 % are valid:
    a dark frame may have no stereo depth at all)."""
    gray = torch.from_numpy(view.gray)
    valid = view.valid[0, 0].cpu()
    if valid.shape == gray.shape and int(valid.sum()) >= 0.01 * valid.numel():
        gray = gray[valid]
    return float(gray.float().mean()) if gray.numel() else 0.0


def exposure_gain(brightness: float, level: float, lo: float = 0.25, hi: float = 8.0) -> float:
    """The gain that brings a frame of mean ``brightness`` to the map's exposure ``level`` (both
    0-255 grey), clamped to ``[lo, hi]``: exposure is a global factor on the image (the light's
    intensity, the exposure time), so the fused colour is ``image x gain``."""
    return float(min(max(level / max(brightness, 0.5), lo), hi))


class FusionExposure:
    """The colour each view is fused with: as it is, or (``normalised``) brought to the map's
    exposure, the mean brightness of the first fused frame that is not black (:func:`exposure_gain`)."""

    def __init__(self, mode: str):
        self.normalised = mode == "normalised"
        self.level: Optional[float] = None

    def colour(self, view: View) -> torch.Tensor:
        """``view``'s ``(3, H, W)`` colour to fuse."""
        colour = view.image[0]
        if not self.normalised:
            return colour
        brightness = mean_brightness(view)
        if self.level is None and brightness >= 8.0:     # (not a black frame)
            self.level = brightness
        gain = exposure_gain(brightness, self.level) if self.level else 1.0
        return (colour * gain).clamp_(0.0, 1.0) if gain != 1.0 else colour


class Pipeline:
    """One run over a dataset.

    Args:
        config: the resolved configuration.
        dataset: a ``StereoDataset`` view (frames already selected).
        out_dir: where results go.
        logger: a frame logger (``slam.rerun_log.RerunLogger``) or None.
    """

    def __init__(self, config: SlamConfig, dataset, out_dir: Path, logger=None):
        self.config = config
        self.dataset = dataset
        self.out_dir = Path(out_dir)
        self.logger = logger
        self.camera = dataset.camera
        self.R1 = _R1_4x4(dataset.R1)
        self.odometry = StereoOdometry(self.camera, config.vo(), device=config.device)
        mode = config.tracking.mode
        self.map = None
        self.gt_poses_only = config.tracking.poses == "groundtruth"
        if self.gt_poses_only and dataset.gt_poses is None:
            raise SlamError(f"{dataset.path}: tracking.poses=groundtruth needs a ground-truth trajectory")
        # layout-4 weight networks compare each reference with the map: frame2frame keeps one too
        self.map_depth_for_weights = self.odometry.needs_map_depth()
        if mode == "frame2model" or config.tracking.export_map or self.gt_poses_only or self.map_depth_for_weights:
            from mapping import SurfelMap

            self.map = SurfelMap(config.map, device=config.device)
            self.map.warm_up()      # compiled kernels loaded now, not in the first frame's time
        tc = config.tracking
        # frame2model reference: the flow goes against the last real frame (last_frame, chained)
        # or the model's colour (rendered, chained), which only then is rendered
        self.flow_against_last_frame = tc.flow_reference in ("last_frame", "chained")
        self.render_colour = tc.flow_reference != "last_frame"
        self.chain_gain = tc.chain_gain if tc.flow_reference == "chained" else 0.0
        # the learned w3D weighs fusion where there is one (not with constant weights or 2D only)
        self.learned_fusion_weight = (tc.fuse_weight == "w3d" and self.odometry.weight_networks is not None
                                      and config.weights.residuals != "2d")
        self.timings: dict[str, list[float]] = {}
        self.fallbacks = 0
        self.exposure = FusionExposure(tc.fuse_exposure)
        self.velocity = np.eye(4)   # the last tracked relative motion: solver.init=constant_velocity's start
        # frame2frame's reference with tracking.keyframe_gap > 1: (frame position, view, rectified pose)
        self.keyframe_gap = tc.keyframe_gap if tc.mode == "frame2frame" else 1
        self._keyframe: Optional[tuple[int, View, np.ndarray]] = None
        self._ahead_view: Optional[View] = None   # the read-ahead thread's last view (tracking.flow_ahead)
        self._waiting_for = -1      # the frame the main thread waits for (-1: none; tracking.flow_ahead)

    # --------------------------------------------------------------------------------------
    def _initial_rect_pose(self) -> np.ndarray:
        gt = self.dataset.gt_poses
        T0 = gt[0] if gt is not None else np.eye(4)
        return T0 @ self.R1.T  # T_wc_rect = T_wc_orig @ R1^T

    def _time(self, stage: str, ms: float) -> None:
        self.timings.setdefault(stage, []).append(ms)

    def _reference(self, last_view: View, pose_rect: np.ndarray) -> tuple[View, Optional[View], str]:
        """The reference view for the next frame and the view the flow is computed against."""
        if self.config.tracking.mode != "frame2model" or self.map is None:
            return last_view, None, "previous_frame"
        t0 = time.perf_counter()
        K = self.odometry.K
        # depth first: the colour's blending pass is only run when the view is used
        mv = self.map.render(K, torch.as_tensor(pose_rect, dtype=torch.float32), self.camera.height, self.camera.width,
                             colour=False)
        coverage = model_coverage(mv.valid, last_view.valid[0, 0])
        if coverage < self.config.tracking.min_model_coverage:
            self._time("render", (time.perf_counter() - t0) * 1000.0)
            self.fallbacks += 1
            log.info("the model view covers %.0f%% of what the last frame saw: tracking against the previous frame",
                     100 * coverage)
            return last_view, None, "previous_frame"
        if self.render_colour:
            mv.with_colour()
        self._time("render", (time.perf_counter() - t0) * 1000.0)
        ref = self.odometry.view_from_render(mv.color if self.render_colour else None, mv.depth, mv.valid,
                                             background=last_view)
        return ref, (last_view if self.flow_against_last_frame else None), "model"

    def _refine(self, view: View, pose_rect: np.ndarray, track: TrackResult) -> tuple[np.ndarray, TrackResult]:
        """``tracking.refine_passes`` x: track ``view`` against the model rendered at its
        estimated ``pose_rect`` and compose the correction. Returns the pose and the last
        successful tracking result (its weight maps weigh the fusion)."""
        for _ in range(self.config.tracking.refine_passes):
            t0 = time.perf_counter()
            # depth first, as in _reference: the colour's blending pass only for a view that is used
            mv = self.map.render(self.odometry.K, torch.as_tensor(pose_rect, dtype=torch.float32),
                                 self.camera.height, self.camera.width, colour=False)
            if model_coverage(mv.valid, view.valid[0, 0]) < self.config.tracking.min_model_coverage:
                self._time("render", (time.perf_counter() - t0) * 1000.0)
                break
            mv.with_colour()
            self._time("render", (time.perf_counter() - t0) * 1000.0)
            # the current frame fills the few uncovered pixels (no residual there: it sits at the
            # true pose, the render at the estimate) and gives the render its shading
            ref = self.odometry.view_from_render(mv.color, mv.depth, mv.valid, background=view,
                                                 background_matchable=False)
            refined = self.odometry.track(view, ref, model_reference=True)
            for stage, ms in refined.timings_ms.items():
                self._time(stage, ms)
            if refined.failed:
                break
            pose_rect, track = pose_rect @ refined.relative, refined
        return pose_rect, track

    def _fuse(self, view: View, w3d: Optional[torch.Tensor], pose_rect: np.ndarray, index: int) -> None:
        """Fuse ``view`` at ``pose_rect``, weighted by its ``(1, 1, H, W)`` learned ``w3d`` if given."""
        if self.map is None:
            return
        t0 = time.perf_counter()
        valid = view.valid[0, 0]
        weight = None
        if w3d is not None and self.learned_fusion_weight:
            weight = normalised_fusion_weight(w3d[0, 0], valid)
        pose = torch.as_tensor(pose_rect, dtype=torch.float32)
        self.map.fuse(view.depth[0, 0], self.exposure.colour(view), self.odometry.K, pose, frame_index=index,
                      weight=weight, valid=valid)
        self._time("fusion", (time.perf_counter() - t0) * 1000.0)
        if self.map_depth_for_weights:      # the view is the next reference: its standing off the map
            t0 = time.perf_counter()
            mv = self.map.render(self.odometry.K, pose, self.camera.height, self.camera.width, colour=False)
            view.model_depth = torch.where(mv.valid, mv.depth, torch.zeros_like(mv.depth)).reshape(view.depth.shape)
            self._time("render", (time.perf_counter() - t0) * 1000.0)

    # --------------------------------------------------------------------------------------
    def run(self, progress: bool = True) -> RunResult:
        """Process every frame; write trajectory rows as they come; never lose finished work."""
        from tqdm import tqdm

        self.out_dir.mkdir(parents=True, exist_ok=True)
        save_config(self.config, self.out_dir / "config.yaml")
        result = RunResult(out_dir=self.out_dir)
        pose_rect = self._initial_rect_pose()
        last_view: Optional[View] = None
        n = len(self.dataset)
        writer = TumStreamWriter(self.out_dir / "trajectory.txt")
        bar = tqdm(total=n, unit="frame", disable=not progress, dynamic_ncols=True, leave=False)
        self._ahead_view = None
        self._keyframe = None
        reader = Prefetcher(self._read_view, n)
        threads_before = torch.get_num_threads()
        torch.set_num_threads(self._torch_threads())
        t_start = time.perf_counter()
        try:
            for k in range(n):
                t_frame = time.perf_counter()
                index = int(self.dataset.indices[k])
                stamp = float(self.dataset.timestamps[k])
                record, pose_rect, last_view = self._step(k, index, stamp, last_view, pose_rect, reader)
                if record.failed:
                    log.warning("frame %d: %s (pose carried over)", index, record.reason)
                writer.write(stamp, record.pose)
                result.records.append(record)
                self._time("total", (time.perf_counter() - t_frame) * 1000.0)
                bar.update(1)
                elapsed = time.perf_counter() - t_start
                bar.set_postfix(fps=f"{(k + 1) / max(elapsed, 1e-9):.1f}", fail=sum(r.failed for r in result.records))
        except KeyboardInterrupt:
            result.interrupted = True
            log.warning("interrupted after %d frames; results so far are written", len(result.records))
        finally:
            reader.close()
            bar.close()
            writer.close()
            torch.set_num_threads(threads_before)
        wall = time.perf_counter() - t_start
        self._finish(result, wall)
        return result

    def _stereo_ahead(self) -> bool:
        return self.config.tracking.stereo_ahead and self.odometry.stereo_flow is not self.odometry.temporal_flow

    def _torch_threads(self) -> int:
        """``threads``, or with 0 every core but the read-ahead thread's (torch's default without it)."""
        if self.config.threads > 0:
            return self.config.threads
        if not self._stereo_ahead():
            return torch.get_num_threads()
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        return max(1, cores - 1)

    def _flow_ahead(self) -> bool:
        """Whether the read-ahead thread also computes the temporal flow against the previous
        frame (``tracking.flow_ahead``): only where tracking flows against the previous frame."""
        tc = self.config.tracking
        return (tc.flow_ahead and self._stereo_ahead() and self.odometry.can_flow_ahead()
                and (self.learned_fusion_weight if self.gt_poses_only
                     else tc.mode != "frame2model" or self.flow_against_last_frame))

    def _read_view(self, k: int) -> tuple[StereoFrame, Optional[View], dict]:
        """Frame ``k`` and, with ``tracking.stereo_ahead``, its view and the view's timings (the
        read-ahead thread runs this, for one frame after another). With ``tracking.flow_ahead``
        the view also carries its temporal flow against the view this thread made before (the
        previous frame's, unless that one could not be read); tracking takes it only if that
        view is its reference. Raises what reading the frame raises."""
        frame = self.dataset.frame(k)
        timings: dict = {}
        if not self._stereo_ahead():
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

    def _step(self, k: int, index: int, stamp: float, last_view: Optional[View],
              pose_rect: np.ndarray, reader: Prefetcher) -> tuple[FrameRecord, np.ndarray, Optional[View]]:
        """Read, track and fuse one frame.

        Returns the frame's record and the new (rectified pose, last good view); a frame that cannot
        be read or tracked makes a failed record and leaves both unchanged.
        """
        try:
            t0 = time.perf_counter()
            self._waiting_for = k
            try:
                frame, view, timings = reader.get(k)   # read ahead in a thread: the time spent waiting for it
            finally:
                self._waiting_for = -1
            self._time("read", (time.perf_counter() - t0) * 1000.0)
        except DataError as err:
            return FrameRecord(index, stamp, pose_rect @ self.R1, True, f"unreadable frame: {err}"), pose_rect, last_view
        if view is None:
            timings = {}
            view = self._make_view(frame, timings)
        for stage, ms in timings.items():
            self._time(stage, ms)
        if self.gt_poses_only:
            pose_rect = frame.gt_pose @ self.R1.T
            rec = FrameRecord(index, stamp, frame.gt_pose, False, reference="groundtruth")
            self._fuse(view, self._fusion_weight_only(view, last_view), pose_rect, index)
            self._log(k, frame, view, None, pose_rect, rec)
            return rec, pose_rect, view
        if last_view is None:
            rec = FrameRecord(index, stamp, pose_rect @ self.R1, False, reference="first")
            self._fuse(view, None, pose_rect, index)
            self._log(k, frame, view, None, pose_rect, rec)
            self._keyframe = (k, view, pose_rect) if self.keyframe_gap > 1 else None
            return rec, pose_rect, view
        ref, flow_ref, kind = self._reference(last_view, pose_rect)
        ref_pose = pose_rect
        T_init = self.velocity if self.config.solver.init == "constant_velocity" else None
        if self._keyframe is not None and self._keyframe[1] is not last_view:   # an earlier frame is the reference
            ref, ref_pose, kind = self._keyframe[1], self._keyframe[2], "keyframe"
            if T_init is not None:      # the motion since the keyframe, continued by one frame's
                T_init = np.linalg.inv(ref_pose) @ pose_rect @ self.velocity
        track = self.odometry.track(view, ref, flow_ref, T_init=T_init,
                                    chain_gain=self.chain_gain if kind == "model" else 0.0,
                                    model_reference=kind == "model",
                                    camera_still=self.odometry.camera_still(self.velocity),
                                    filter_ref=last_view if kind == "keyframe" else None)
        for stage, ms in track.timings_ms.items():
            self._time(stage, ms)
        if track.failed:
            rec = FrameRecord(index, stamp, pose_rect @ self.R1, True, track.reason, kind, track.iterations, track.cost)
            self._log(k, frame, view, track, pose_rect, rec)
            self._keyframe = None       # the next frame goes against the last tracked one, and becomes the keyframe
            return rec, pose_rect, last_view
        new_pose = ref_pose @ track.relative
        if kind == "model":
            new_pose, track = self._refine(view, new_pose, track)
        self.velocity = np.linalg.inv(pose_rect) @ new_pose
        rec = FrameRecord(index, stamp, new_pose @ self.R1, False, "", kind, track.iterations, track.cost)
        self._fuse(view, track.w3d, new_pose, index)
        self._log(k, frame, view, track, new_pose, rec)
        if self.keyframe_gap > 1 and (self._keyframe is None or k - self._keyframe[0] >= self.keyframe_gap
                                      or not self._keeps_keyframe()):
            self._keyframe = (k, view, new_pose)    # (a moving camera: the next frame goes against this one)
        return rec, new_pose, view

    def _keeps_keyframe(self) -> bool:
        """Whether the last tracked motion leaves the camera still enough to keep the keyframe
        (``tracking.keyframe_still_mm``; always with 0)."""
        return moved_less_than(self.velocity, self.config.tracking.keyframe_still_mm)

    def _fusion_weight_only(self, view: View, last_view: Optional[View]) -> Optional[torch.Tensor]:
        """With known poses, the learned ``(1, 1, H, W)`` w3D of ``view`` against the previous frame.

        The learned w3D is what keeps badly matched depth, moving tissue and instruments out of the
        map, so a map fused with ground-truth poses still wants it; no pose is solved for.
        Returns None where there is none (constant weights, 2D only, first frame).
        """
        if last_view is None or not self.learned_fusion_weight:
            return None
        timings: dict = {}
        _, w3d = self.odometry.weight_maps(view, last_view, timings)
        for stage, ms in timings.items():
            self._time(stage, ms)
        return w3d

    def _log(self, k, frame, view, track, pose_rect, record) -> None:
        if self.logger is not None:
            t0 = time.perf_counter()
            self.logger.log_frame(k, frame, view, track, record, self.map, self.odometry.camera, pose_rect)
            self._time("logging", (time.perf_counter() - t0) * 1000.0)

    # --------------------------------------------------------------------------------------
    def _finish(self, result: RunResult, wall_s: float) -> None:
        from slam.evaluation import evaluate
        from slam.plots import plot_trajectory

        records = result.records
        done = len(records)
        est = np.stack([r.pose for r in records]) if records else np.zeros((0, 4, 4))
        metrics: dict = {
            "frames": done,
            "failed_frames": [r.index for r in records if r.failed],
            "failures": {str(r.index): r.reason for r in records if r.failed},
            "fps": done / wall_s if wall_s > 0 else 0.0,
            "timings_ms": {k: float(np.mean(v)) for k, v in self.timings.items()},
            "mode": self.config.tracking.mode,
            "model_fallbacks": self.fallbacks,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        }
        if result.interrupted:
            metrics["interrupted"] = True
            metrics["stopped_before_frame"] = int(self.dataset.indices[done]) if done < len(self.dataset) else None
        gt = self.dataset.gt_poses
        gt_sel = gt[:done] if gt is not None else None
        if gt_sel is not None and done >= 2:
            metrics.update(evaluate(gt_sel, est))
        files = {"trajectory": str(self.out_dir / "trajectory.txt"), "config": str(self.out_dir / "config.yaml")}
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
        if done >= 2:
            plot_trajectory(self.out_dir / "trajectory.png", est, gt_sel, np.array([r.timestamp for r in records]),
                            title=f"{self.dataset.path.name} ({self.config.tracking.mode})")
            files["plot"] = str(self.out_dir / "trajectory.png")
        (self.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
        files["metrics"] = str(self.out_dir / "metrics.json")
        if self.logger is not None:
            self.logger.log_final(self.map, est, gt_sel)
        result.metrics = metrics
        result.files = files
