"""The application's configuration: typed dataclasses per concern, loaded from YAML, validated,
overridden with ``--set a.b=value``, and saved with every run.

An unknown or mistyped key is a one-line ``ConfigError`` naming it (with a suggestion).
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mapping.config import MapConfig
from slam.io.datasets.config import DataConfig
from slam.errors import ConfigError
from vo.config import CorrespondenceConfig, DepthConfig, SolverConfig, WeightsConfig


@dataclass
class TrackingConfig:
    """How the pipeline tracks.

    Attributes:
        mode: ``frame2frame`` (reference = previous frame) or ``frame2model`` (reference = the
            surfel map rendered at the last pose).
        flow_reference: in frame2model, the image the temporal flow is computed against:
            ``rendered`` (the model's colour relit to the last frame's shading, as the paper:
            the flow then ties the new frame to the map itself, which holds the pose to the
            surface seen before) or ``last_frame`` (the last real frame, at the reference pose;
            less noisy per frame, but it hands each frame's pose error on to the next: only
            the depth comes from the map; 0.554 against 0.242 mm on the rigid and loop
            sequences of ``tools/benchmark_frame2model.py``).
        refine_passes: frame2model: after tracking against the model view at the last pose,
            render the model at the new estimate and track the frame against that view again,
            this many times (ElasticFusion re-associates at each iteration's pose). The view is
            then nearly at the frame's pose: short flow, the same parts of the surface seen, no
            disocclusions. Each pass costs a colour render, a flow, the weights and a solve
            (one pass: frame2model ATE -13 % at 0.7x the fps on the synthetic rigid and loop
            sequences; two passes tracked worse than one; docs/experiments.md).
        min_model_coverage: below this fraction of the last frame's valid pixels covered by the
            model view, the previous frame is the reference for that step (the start, fast
            motion). A partly covered view is filled with the last frame's pixels, which sit at
            the true last pose while the render sits at the estimated one: the seam between them
            pulls the flow, so the bar is high.
        fuse_weight: per-pixel fusion weight: ``w3d`` (the learned 3D weight over its per-frame
            median, clamped to 1; pixels the tracker could not weigh count fully, see
            ``slam.app.pipeline.normalised_fusion_weight``; uniform without learned weights) or
            ``uniform`` (every valid pixel counts fully: better on rigid scenes, worse where tissue
            deforms; docs/experiments.md).
        export_map: fuse a map in frame2frame too (without tracking against it) and export it.
        poses: ``estimated`` (track) or ``groundtruth``: take the dataset's ground-truth poses
            and fuse the map with them (mapping on its own, e.g. to measure the map's accuracy
            apart from tracking); needs ground truth, implies ``export_map``. With learned
            weights each frame is still matched to the previous one, for its w3D fusion weight.
        read_ahead: make the next frame's view (stereo depth) in a read-ahead thread while the
            current frame is tracked, and its temporal flow against the frame before it wherever
            tracking will flow against the previous frame (both depend on the frames alone;
            OpenCV and torch release the GIL, so on two cores the two threads overlap). Same
            results either way. With a backend whose temporal and stereo flow are one model
            (RAFT) the view is made in the main thread. The per-stage ``stereo`` and
            ``flow_ahead`` times are then spent in the thread and ``read`` is what the main
            thread waited for.
        keyframe_gap: frame2frame: a tracked frame becomes the reference (keyframe) of the
            frames after it once it is this many frames after the current keyframe; the frames
            in between are tracked against the keyframe, not against the frame before them. 1
            is the paper's: every frame against the previous one (``configs/paper.yaml``). With
            the default 5 (while the camera is still, ``keyframe_still_mm``) a static camera's
            pose is chained a fifth as often (the per-frame noise adds up five times slower) and
            the reference stands further from the current frame (the tissue's motion in between
            rises above the depth noise); the networks are trained on pairs 1-5 frames apart.
            The depth filter (``depth.temporal_gain``) still runs from each frame to the one
            before it. A failed frame makes the last tracked frame the keyframe
            (docs/experiments.md).
        keyframe_still_mm: > 0: keep a keyframe only while the camera is still, i.e. while the
            last tracked motion moved it less than this (mm per frame, as
            ``depth.temporal_still_mm``): a moving camera's frames are each tracked against the
            one before it, the paper's reference. 0: the gap applies to every frame.
    """

    mode: str = "frame2frame"
    flow_reference: str = "rendered"
    refine_passes: int = 0
    min_model_coverage: float = 0.95
    fuse_weight: str = "w3d"
    export_map: bool = False
    poses: str = "estimated"
    read_ahead: bool = True
    keyframe_gap: int = 5
    keyframe_still_mm: float = 0.1


@dataclass
class HealthConfig:
    """Tracking health.

    Attributes:
        covariance_scale_frame: ``s`` of the pose covariance ``s * sigma^2 * H^-1`` against a
            camera frame (the previous frame or a keyframe). The residuals of neighbouring
            pixels are correlated (one flow field, one stereo match), so the textbook covariance
            (``s = 1``) is overconfident. Fitted by ``tools/calibrate_covariance.py`` on
            randomised validation sequences so that the NEES of the 6-dof relative pose averages 6
            (6343 on 590 frames of rigid and scanning validation sequences at 320x256: median NEES
            5.3, 93 % of frames inside the 95 % chi-square bound).
        covariance_scale_model: the same against the model view (frame2model; fitted 774: median
            NEES 3.3, 88 % inside the bound).
        cross_check: frame2model: each frame is also tracked against the last frame with its own
            flow (an estimate independent of the map) and the two are combined by their
            covariances (``slam.tracking.cross_check``: a filter on the pose relative to the map); where
            their squared Mahalanobis distance exceeds this (22.5: the 99.9 % chi-square bound of
            6 dof) the frame is flagged, reports the better-supported estimate and is not fused.
            0: no cross-check (the model view's estimate alone; 1.4x the fps at 320x256, and
            0.822 against 0.557 mm ATE on weak-texture validation sequences, docs/experiments.md).
        flag_mm: a frame is also flagged where the two estimates' positions lie further apart
            than this (frame2model), and in both modes where the positional spread ``sigma_t`` of
            the pose it reports exceeds it (an uncertain pose). A flagged frame is not fused.
    """

    covariance_scale_frame: float = 6300.0
    covariance_scale_model: float = 770.0
    cross_check: float = 22.5
    flag_mm: float = 1.5


@dataclass
class GraphConfig:
    """Frame2model's pose graph and loop closure (``slam.tracking.loop_closure``, ``slam.tracking.pose_graph``).

    Attributes:
        loop_closure: keep a pose graph of keyframes and close loops: tracking and fusion use
            the active model only (surfels fused within the last ``inactive_after`` frames);
            at each new graph keyframe the inactive model is rendered at the pose, the frame is
            registered against it by the dense tracker and, once verified, the loop edge goes
            into the graph (GTSAM, graduated non-convexity against false loops); an accepted
            loop moves the keyframes, the frames' poses and the surfels with them, and the
            inactive surfels in view become active again. ``trajectory.txt`` then holds the
            optimised poses, ``trajectory_online.txt`` the poses as tracked.
        keyframe_mm: a frame becomes a graph keyframe once the camera has moved this far from
            the last one ...
        keyframe_deg: ... or turned this far.
        inactive_after: surfels not fused for this many frames are inactive: they are not
            tracked against nor fused into until a loop closure brings them back.
    """

    loop_closure: bool = False
    keyframe_mm: float = 5.0
    keyframe_deg: float = 5.0
    inactive_after: int = 50


@dataclass
class LoggingConfig:
    """Outputs besides the trajectory.

    Attributes:
        rerun: path of a rerun recording (``.rrd``) to save; empty = none.
        spawn: open the rerun viewer.
        map_every: log the map to rerun every N frames (0 = only the final map).
        rerun_every: record the camera and its image views (image, depth, flow, weights, valid
            mask) of every N-th frame only (1 = every frame; each costs ~0.2 MB at 640x512); the
            trajectories and the metrics keep every frame, the map follows ``map_every``.
        progress: show a progress bar.
        mesh: also write a surface mesh of the map.
    """

    rerun: str = ""
    spawn: bool = False
    map_every: int = 10
    rerun_every: int = 1
    progress: bool = True
    mesh: bool = False


@dataclass
class SlamConfig:
    """Everything a run needs.

    Attributes:
        device: torch device of the VO and the map (``cpu``, ``cuda``, ...).
        threads: torch threads during a run (restored afterwards). 0 = every core but the one
            the read-ahead thread computes the next frame's stereo on (``tracking.read_ahead``),
            at least 1; without it, torch's default. On a 2-core machine 1 torch thread with the
            stereo ahead ran 10.1 / 7.7 fps (frame2frame / frame2model, 320x256) where 2 threads
            ran 8.7 / 6.1.
    """

    device: str = "cpu"
    threads: int = 0
    data: DataConfig = field(default_factory=DataConfig)
    correspondence: CorrespondenceConfig = field(default_factory=CorrespondenceConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    weights: WeightsConfig = field(default_factory=WeightsConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    health: HealthConfig = field(default_factory=HealthConfig)
    map: MapConfig = field(default_factory=MapConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)

    def vo(self):
        """The VO core's part of the configuration."""
        from vo.odometry import VOConfig

        return VOConfig(correspondence=self.correspondence, depth=self.depth, solver=self.solver, weights=self.weights)


# Allowed values of string options, checked at load time.
CHOICES = {
    "data.layout": ("auto", "stereomis", "stereomis_raw", "scared", "plain", "frames", "video"),
    "data.stereo_layout": ("auto", "top-bottom", "side-by-side"),
    "data.rectified": ("auto", "yes", "no"),
    "data.rectify_mode": ("full", "pseudo"),
    "correspondence.backend": ("dis", "raft"),
    "correspondence.dis_preset": ("ultrafast", "fast", "medium"),
    "correspondence.dis_stereo_preset": ("ultrafast", "fast", "medium"),
    "correspondence.dis_lr_check_preset": ("ultrafast", "fast", "medium"),
    "depth.source": ("stereo", "groundtruth"),
    "solver.method": ("lm", "gauss_newton", "lbfgs"),
    "solver.init": ("identity", "constant_velocity"),
    "solver.kernel": ("auto", "compiled", "torch"),
    "weights.mode": ("learned", "constant"),
    "weights.residuals": ("2d3d", "2d", "3d"),
    "tracking.mode": ("frame2frame", "frame2model"),
    "tracking.flow_reference": ("last_frame", "rendered"),
    "tracking.fuse_weight": ("w3d", "uniform"),
    "tracking.poses": ("estimated", "groundtruth"),
}


def _coerce(value: Any, typ: Any, key: str, source: str) -> Any:
    """Check/convert ``value`` to the annotated type ``typ``."""
    origin = typing.get_origin(typ)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(typ) if a is not type(None)]
        if value is None:
            return None
        return _coerce(value, args[0], key, source)
    if typ is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "yes", "on", "1", "false", "no", "off", "0"):
            return value.lower() in ("true", "yes", "on", "1")
        raise ConfigError(f"{source}: '{key}' must be true or false, got {value!r}")
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise ConfigError(f"{source}: '{key}' must be an integer, got {value!r}")
        try:
            return int(value)
        except ValueError:
            raise ConfigError(f"{source}: '{key}' must be an integer, got {value!r}") from None
    if typ is float:
        if isinstance(value, bool):
            raise ConfigError(f"{source}: '{key}' must be a number, got {value!r}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{source}: '{key}' must be a number, got {value!r}") from None
    if typ is str:
        if isinstance(value, (dict, list)):
            raise ConfigError(f"{source}: '{key}' must be a string, got {value!r}")
        if isinstance(value, bool) and "yes" in CHOICES.get(key, ()):
            value = "yes" if value else "no"    # YAML reads an unquoted yes / no as a boolean
        value = "" if value is None else str(value)
        if key in CHOICES and value not in CHOICES[key]:
            raise ConfigError(f"{source}: '{key}' must be one of {', '.join(CHOICES[key])}, got '{value}'")
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{source}: '{key}' must be a list, got {value!r}")
        (inner,) = typing.get_args(typ)[:1] or (Any,)
        return [(_coerce(v, inner, key, source) if inner is not Any else v) for v in value]
    return value


def _merge(obj: Any, data: dict, prefix: str, source: str) -> None:
    """Set the fields of dataclass ``obj`` from ``data`` (nested), validating keys and types."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: '{prefix.rstrip('.') or 'top level'}' must be a mapping, got {data!r}")
    hints = typing.get_type_hints(type(obj))
    names = [f.name for f in dataclasses.fields(obj)]
    for key, value in data.items():
        full = f"{prefix}{key}"
        if key not in names:
            close = difflib.get_close_matches(str(key), names, n=1)
            hint = f" (did you mean '{prefix}{close[0]}'?)" if close else f" (known: {', '.join(names)})"
            raise ConfigError(f"{source}: unknown key '{full}'{hint}")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            _merge(current, value, full + ".", source)
        else:
            setattr(obj, key, _coerce(value, hints[key], full, source))


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> SlamConfig:
    """Defaults, then the YAML file, then ``key=value`` overrides (values parsed as YAML scalars)."""
    config = SlamConfig()
    if path:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"{path}: config file not found")
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as err:
            line = getattr(getattr(err, "problem_mark", None), "line", None)
            where = f":{line + 1}" if line is not None else ""
            raise ConfigError(f"{path}{where}: not valid YAML") from None
        _merge(config, data, "", str(path))
    for item in overrides or []:
        apply_override(config, item)
    validate(config)
    return config


def apply_override(config: Any, item: str) -> None:
    """Apply one ``a.b=value`` override to a configuration dataclass."""
    if "=" not in item:
        raise ConfigError(f"--set {item}: expected key=value")
    key, raw = item.split("=", 1)
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    nested: dict = {}
    cursor = nested
    parts = key.strip().split(".")
    for part in parts[:-1]:
        cursor = cursor.setdefault(part, {})
    cursor[parts[-1]] = value
    _merge(config, nested, "", "--set")


def validate(config: SlamConfig) -> None:
    """Range checks that types alone do not catch."""
    checks = [
        (config.threads >= 0, "threads must be >= 0 (0 = every core but the read-ahead thread's)"),
        (config.depth.max_depth_mm > config.depth.min_depth_mm > 0, "depth: need 0 < min_depth_mm < max_depth_mm"),
        (config.solver.max_iters >= 1, "solver.max_iters must be >= 1"),
        (config.solver.robust_3d_mm >= 0, "solver.robust_3d_mm must be >= 0 (0 = off)"),
        (config.data.width >= 0 and config.data.height >= 0, "data.width/height must be >= 0"),
        ((config.data.width == 0) == (config.data.height == 0), "data.width and data.height: set both or neither"),
        (0.0 <= config.tracking.min_model_coverage <= 1.0, "tracking.min_model_coverage must be in [0, 1]"),
        (0 <= config.tracking.refine_passes <= 5, "tracking.refine_passes must be in 0..5"),
        (config.tracking.keyframe_gap >= 1, "tracking.keyframe_gap must be >= 1 (1 = every frame against the previous one)"),
        (config.tracking.keyframe_still_mm >= 0, "tracking.keyframe_still_mm must be >= 0 (0 = keyframes for a moving camera too)"),
        (config.weights.w2d >= 0 and config.weights.w3d >= 0, "weights.w2d/w3d must be >= 0"),
        (0.0 < config.depth.temporal_gain <= 1.0, "depth.temporal_gain must be in (0, 1] (1 = off)"),
        (config.depth.temporal_gate_mm > 0, "depth.temporal_gate_mm must be > 0"),
        (config.graph.keyframe_mm > 0 and config.graph.keyframe_deg > 0, "graph.keyframe_mm and keyframe_deg must be > 0"),
        (config.graph.inactive_after >= 1, "graph.inactive_after must be >= 1"),
        (config.depth.temporal_still_mm >= 0, "depth.temporal_still_mm must be >= 0 (0 = filter every frame)"),
        (config.logging.rerun_every >= 1, "logging.rerun_every must be >= 1 (1 = every frame)"),
    ]
    for ok, message in checks:
        if not ok:
            raise ConfigError(f"config: {message}")
    try:
        config.map.validate()
    except ValueError as err:
        raise ConfigError(f"config: {err}") from None


#: the frame rate the per-frame motion thresholds of the configuration are given at
REFERENCE_FPS = 25.0


def at_frame_rate(config: SlamConfig, fps: float) -> SlamConfig:
    """``config`` with its per-frame thresholds scaled from ``REFERENCE_FPS`` to a sequence at
    ``fps``, so that 5 and 25 fps mean the same motion per second: the still-camera thresholds
    (``tracking.keyframe_still_mm``, ``depth.temporal_still_mm``) and the plausible motion
    (``solver.max_translation_mm``) by ``REFERENCE_FPS / fps``; the depth filter's gate
    (``depth.temporal_gate_mm``) likewise but never below its value (it also spans the stereo
    noise, which the rate does not change); the keyframe's gap in frames (``tracking.keyframe_gap``)
    and the active model's window (``graph.inactive_after``) by ``fps / REFERENCE_FPS``, at least 1. The map's unstable window stays counted in frames: it
    is how many observations a new surfel gets to become stable (in seconds, 5 fps left it four
    frames: most of the last frame's surfels were removed before the next one was tracked). At
    ``REFERENCE_FPS`` the config itself."""
    if fps <= 0:
        raise ConfigError(f"frame rate must be positive, got {fps}")
    if fps == REFERENCE_FPS:
        return config
    k = REFERENCE_FPS / fps
    out = copy.deepcopy(config)
    out.tracking.keyframe_still_mm *= k
    out.depth.temporal_still_mm *= k
    out.solver.max_translation_mm *= k
    out.depth.temporal_gate_mm *= max(1.0, k)
    out.tracking.keyframe_gap = max(1, int(round(config.tracking.keyframe_gap / k)))
    out.graph.inactive_after = max(1, int(round(config.graph.inactive_after / k)))
    return out


def to_dict(config: Any) -> dict:
    return dataclasses.asdict(config)


def save_config(config: SlamConfig, path: str | Path) -> None:
    """Write the resolved configuration as YAML."""
    Path(path).write_text(yaml.safe_dump(to_dict(config), sort_keys=False))
