"""The application's configuration: one schema of typed dataclasses (``slam.schema``), loaded
from YAML, overridden with ``--set a.b=value``, checked, and saved with every run.

``configs/default.yaml`` lists every key a person may set, each documented once, in the class
that holds it. An unknown or mistyped key is a one-line ``ConfigError`` naming it (with a
suggestion); a key that was removed names what replaces it (:data:`REMOVED`). The ``analysis``
section holds the switches the analysis tools set (exact depth, known poses, the
forward-backward check, ...): not in ``default.yaml``, not for tracking.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import yaml

from mapping.config import MapConfig
from slam.errors import ConfigError
from slam.io.datasets.config import DataConfig
from slam.schema import parse_into, rebuild, user_dict
from vo.config import CorrespondenceConfig, DepthConfig, SolverConfig, VOConfig, WeightsConfig, fixed, need

#: frame2model: below this fraction of the last frame's valid pixels covered by the model view the
#: previous frame is the reference for that step (the start, fast motion). A partly covered view is
#: filled with the last frame's pixels, which sit at the true last pose while the render sits at the
#: estimated one: the seam between them pulls the flow, so the bar is high.
MIN_MODEL_COVERAGE = 0.95


@dataclass
class TrackingConfig:
    """How the pipeline tracks.

    Attributes:
        mode: ``frame2frame`` (reference = previous frame) or ``frame2model`` (reference = the
            surfel map rendered at the last pose, its colour relit to the last frame's shading, as
            the paper: the flow then ties the new frame to the map itself).
        refine_passes: frame2model: after tracking against the model view at the last pose,
            render the model at the new estimate and track the frame against that view again,
            this many times (ElasticFusion re-associates at each iteration's pose). The view is
            then nearly at the frame's pose: short flow, the same parts of the surface seen, no
            disocclusions. Each pass costs a colour render, a flow, the weights and a solve
            (one pass: frame2model ATE -13 % at 0.7x the fps on the synthetic rigid and loop
            sequences; two passes tracked worse than one; docs/experiments.md).
        keyframe_gap: frame2frame: a tracked frame becomes the reference (keyframe) of the
            frames after it once it is this many frames after the current keyframe; the frames
            in between are tracked against the keyframe, not against the frame before them. 1
            is the paper's: every frame against the previous one (``configs/paper.yaml``). With
            the default 5, while the camera is still (``keyframe_still_mm``, 0.1 mm per frame at
            25 fps), a static camera's pose is chained a fifth as often and the reference stands
            further from the current frame (the tissue's motion in between rises above the depth
            noise); a moving camera's frames are each tracked against the one before it. The
            networks are trained on pairs 1-5 frames apart. The depth filter
            (``depth.temporal_gain``) still runs from each frame to the one before it. A failed
            frame makes the last tracked frame the keyframe (docs/experiments.md).
        model_every: frame2model with the cross-check: the largest gap between model frames, the
            frames registered against the map's view (and fused). The frames between keep the
            cross-check's estimate against the last frame as their pose, their spread the filter's
            ``P`` summed since the last model frame (``slam.tracking.model_frames``); a frame whose
            chain is unconfirmed or uncertain is a model frame at once. 1: every frame (the paper's
            frame2model).
        keyframe_still_mm: (fixed) keep a keyframe only while the last tracked motion moved the
            camera less than this (mm per frame at 25 fps; 0: the gap applies to every frame).
        min_model_coverage: (fixed) :data:`MIN_MODEL_COVERAGE`.
    """

    mode: Literal["frame2frame", "frame2model"] = "frame2frame"
    refine_passes: int = 0
    keyframe_gap: int = 5
    model_every: int = 5
    keyframe_still_mm: float = fixed("a constant scaled by the frame rate (at_frame_rate)", 0.1)
    min_model_coverage: float = fixed("the model view's coverage below which the last frame is the reference",
                                      MIN_MODEL_COVERAGE)

    def __post_init__(self):
        need(0 <= self.refine_passes <= 5, "tracking.refine_passes must be in 0..5")
        need(self.keyframe_gap >= 1, "tracking.keyframe_gap must be >= 1 (1 = every frame against the previous one)")
        need(self.model_every >= 1, "tracking.model_every must be >= 1 (1 = every frame against the map)")
        need(self.keyframe_still_mm >= 0, "tracking.keyframe_still_mm must be >= 0 (0 = keyframes for a moving camera too)")
        need(0.0 <= self.min_model_coverage <= 1.0, "tracking.min_model_coverage must be in [0, 1]")


@dataclass
class HealthConfig:
    """Tracking health.

    Attributes:
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
        covariance_scale_frame: (fixed; ``analysis.covariance_scale_frame``) ``s`` of the pose
            covariance ``s * sigma^2 * H^-1`` against a camera frame (the previous frame or a
            keyframe). The residuals of neighbouring pixels are correlated (one flow field, one
            stereo match), so the textbook covariance (``s = 1``) is overconfident. Fitted by
            ``tools/calibrate_covariance.py`` on randomised validation sequences so that the NEES
            of the 6-dof relative pose averages 6 (6343 on 590 frames of rigid and scanning
            validation sequences at 320x256: median NEES 5.3, 93 % of frames inside the 95 %
            chi-square bound).
        covariance_scale_model: (fixed; ``analysis.covariance_scale_model``) the same against the
            model view (frame2model; fitted 774: median NEES 3.3, 88 % inside the bound).
    """

    cross_check: float = 22.5
    flag_mm: float = 1.5
    covariance_scale_frame: float = fixed("fitted by tools/calibrate_covariance.py (analysis.covariance_scale_frame)",
                                          6300.0)
    covariance_scale_model: float = fixed("fitted by tools/calibrate_covariance.py (analysis.covariance_scale_model)",
                                          770.0)

    def __post_init__(self):
        need(self.cross_check >= 0, "health.cross_check must be >= 0 (0 = no cross-check)")
        need(self.flag_mm > 0, "health.flag_mm must be > 0")


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

    def __post_init__(self):
        need(self.keyframe_mm > 0 and self.keyframe_deg > 0, "graph.keyframe_mm and keyframe_deg must be > 0")
        need(self.inactive_after >= 1, "graph.inactive_after must be >= 1")


@dataclass
class LoggingConfig:
    """The rerun recording and the map's exports besides the trajectory.

    Attributes:
        rerun: path of a rerun recording (``.rrd``) to save; empty = none (``slam run --rerun``;
            ``--spawn`` opens the viewer).
        map_every: log the map to rerun every N frames (0 = only the final map).
        rerun_every: record the camera and its image views (image, depth, flow, weights, valid
            mask) of every N-th frame only (1 = every frame; each costs ~0.2 MB at 640x512); the
            trajectories and the metrics keep every frame, the map follows ``map_every``.
        export_map: fuse a map in frame2frame too (without tracking against it) and write it
            (``--export-map``; frame2model always writes its map).
        mesh: also write a surface mesh of the map (``--mesh``).
    """

    rerun: str = ""
    map_every: int = 10
    rerun_every: int = 1
    export_map: bool = False
    mesh: bool = False

    def __post_init__(self):
        need(self.map_every >= 0, "logging.map_every must be >= 0 (0 = only the final map)")
        need(self.rerun_every >= 1, "logging.rerun_every must be >= 1 (1 = every frame)")


@dataclass
class AnalysisConfig:
    """Switches for the analysis tools (``tools/``), not for tracking: each replaces an input or
    a constant to measure what it costs. Not in ``configs/default.yaml``; empty values keep the
    default. A run records them in its ``config.yaml``.

    Attributes:
        depth_source: ``stereo``, or ``groundtruth``: the synthetic generator's exact depth
            instead of the stereo depth (``tools/error_attribution.py``).
        poses: ``estimated``, or ``groundtruth``: no tracking; the map is fused at the dataset's
            ground-truth poses (the map's accuracy apart from tracking; with learned weights each
            frame is still matched to the previous one for its w3D fusion weight).
        fb_check_px: > 0: drop temporal flows whose forward-backward round trip misses by more
            (pixels; costs a second temporal flow).
        round_trip: compute each tracked pair's flow back for the ``round_trip_px`` figure of
            ``tracking.csv`` (it ranks wrong poses less well than the cost and ``sigma_t_mm``:
            docs/experiments.md).
        inpaint_px, match_exposure: the highlights' inpainting radius and the exposure matching
            before DIS (``correspondence``; 0 / false: the recipe of ``weights_3d.pt``).
        solver_kernel, map_kernels: ``compiled`` (numba) or ``torch`` normal equations and map
            passes (``tools/check_gpu.py`` runs the code a GPU runs on the CPU).
        covariance_scale_frame, covariance_scale_model: the pose covariance's scales
            (``health``; ``tools/calibrate_covariance.py``).
    """

    depth_source: Literal["stereo", "groundtruth"] = "stereo"
    poses: Literal["estimated", "groundtruth"] = "estimated"
    fb_check_px: Optional[float] = None
    round_trip: Optional[bool] = None
    inpaint_px: Optional[float] = None
    match_exposure: Optional[bool] = None
    solver_kernel: Optional[Literal["auto", "compiled", "torch"]] = None
    map_kernels: Optional[Literal["auto", "compiled", "torch"]] = None
    covariance_scale_frame: Optional[float] = None
    covariance_scale_model: Optional[float] = None

    #: where each switch lands: (section, field)
    TARGETS = {"fb_check_px": ("correspondence", "fb_check_px"), "round_trip": ("correspondence", "round_trip"),
               "inpaint_px": ("correspondence", "inpaint_px"), "match_exposure": ("correspondence", "dis_match_exposure"),
               "solver_kernel": ("solver", "kernel"), "map_kernels": ("map", "kernels"),
               "covariance_scale_frame": ("health", "covariance_scale_frame"),
               "covariance_scale_model": ("health", "covariance_scale_model")}


@dataclass
class SlamConfig:
    """Everything a run needs.

    Attributes:
        device: torch device of the VO and the map (``cpu``, ``cuda``, ...).
        threads: the cores a run may use (0 = all of this process's; more than it has: capped to
            them, with a warning): torch's pool gets every one but the read-ahead thread's (at
            least 1), OpenCV's all of them, during the frames (restored afterwards;
            ``slam.app.thread_use.ThreadBudget``). On a 2-core machine 1
            torch thread with the stereo ahead ran 10.1 / 7.7 fps (frame2frame / frame2model,
            320x256) where 2 threads ran 8.7 / 6.1.
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
    analysis: AnalysisConfig = field(default_factory=AnalysisConfig)

    def __post_init__(self):
        need(self.threads >= 0, "threads must be >= 0 (0 = every core)")

    def vo(self) -> VOConfig:
        """The VO core's part of the configuration."""
        return VOConfig(correspondence=self.correspondence, depth=self.depth, solver=self.solver, weights=self.weights)


#: keys that are gone: what replaces them (or why they are gone)
REMOVED = {
    "tracking.flow_reference": "is gone: frame2model flows against the model's relit colour ('rendered'); "
                               "the last frame lost (0.554 against 0.242 mm, docs/experiments.md)",
    "tracking.fuse_weight": "is gone: fusion is weighed by the learned w3D where there is one ('uniform' lost on "
                            "deforming tissue, docs/experiments.md)",
    "tracking.read_ahead": "is gone: the next frame's view is always made ahead (the same results, faster)",
    "tracking.export_map": "is now logging.export_map (the option --export-map)",
    "logging.spawn": "is now the option --spawn",
    "tracking.poses": "is now analysis.poses (mapping at known poses is an analysis)",
    "tracking.min_model_coverage": "is gone: a constant (slam.config.MIN_MODEL_COVERAGE)",
    "tracking.keyframe_still_mm": "is gone: a constant scaled by the frame rate (0.1 mm per frame at 25 fps)",
    "depth.source": "is now analysis.depth_source",
    "depth.temporal_gate_mm": "is gone: a constant scaled by the frame rate",
    "depth.temporal_still_mm": "is gone: a constant scaled by the frame rate (0.1 mm per frame at 25 fps)",
    "correspondence.fb_check_px": "is now analysis.fb_check_px",
    "correspondence.round_trip": "is now analysis.round_trip",
    "correspondence.inpaint_px": "is now analysis.inpaint_px",
    "correspondence.dis_match_exposure": "is now analysis.match_exposure",
    "correspondence.raft_iters": "is gone: RAFT runs the 12 iterations its checkpoints were trained with",
    "correspondence.max_vertical_parallax_px": "is gone: a constant (2 px)",
    "solver.kernel": "is now analysis.solver_kernel",
    "solver.init": "is gone: the solver starts at the identity",
    "solver.max_pixels": "is gone: a constant (16384 pixels)",
    "solver.max_translation_mm": "is gone: a constant scaled by the frame rate (20 mm per frame at 25 fps)",
    "solver.max_rotation_deg": "is gone: a constant (15 degrees)",
    "solver.min_valid_pixels": "is gone: a constant (200 pixels)",
    "map.kernels": "is now analysis.map_kernels",
    "map.min_depth_mm": "is gone: a constant (20 mm)",
    "map.max_depth_mm": "is gone: a constant (200 mm)",
    "map.max_confidence": "is gone: a constant (100)",
    "map.free_space_mm": "is gone: a constant (3 mm)",
    "data.specular_threshold": "is gone: a constant (0.96)",
    "data.specular_dilate_px": "is gone: a constant (3 px)",
    "data.dark_threshold": "is gone: a constant (0.04)",
    "health.covariance_scale_frame": "is now analysis.covariance_scale_frame",
    "health.covariance_scale_model": "is now analysis.covariance_scale_model",
    "logging.progress": "is now the option --quiet",
}


def read_yaml(path: str | Path) -> dict:
    """A YAML file's mapping; ConfigError naming the file (and the line) otherwise."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        line = getattr(getattr(err, "problem_mark", None), "line", None)
        raise ConfigError(f"{path}{f':{line + 1}' if line is not None else ''}: not valid YAML") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of sections")
    return data


def override_tree(item: str) -> dict:
    """``a.b=value`` as ``{"a": {"b": value}}`` (the value parsed as a YAML scalar)."""
    if "=" not in item:
        raise ConfigError(f"--set {item}: expected key=value")
    key, raw = item.split("=", 1)
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    tree: dict = {}
    cursor = tree
    parts = key.strip().split(".")
    for part in parts[:-1]:
        cursor = cursor.setdefault(part, {})
    cursor[parts[-1]] = value
    return tree


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> SlamConfig:
    """Defaults, then the YAML file, then ``key=value`` overrides; checked, with the analysis
    switches applied to the sections they replace a constant of."""
    config = SlamConfig()
    if path:
        parse_into(config, read_yaml(path), str(path), REMOVED)
    return with_overrides(config, overrides or [])


def with_overrides(config: SlamConfig, overrides: list[str], source: str = "--set") -> SlamConfig:
    """A copy of ``config`` with ``key=value`` overrides, checked (ConfigError naming ``source``)."""
    config = copy.deepcopy(config)
    for item in overrides:
        parse_into(config, override_tree(item), source, REMOVED)
    config = rebuild(config)
    apply_analysis(config)
    return config


def apply_analysis(config) -> None:
    """Copy the analysis switches that are set onto the constants they replace."""
    for name, (section, key) in AnalysisConfig.TARGETS.items():
        value = getattr(config.analysis, name)
        if value is not None and hasattr(config, section):     # (a training config has no health)
            setattr(getattr(config, section), key, value)




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


def default_tree() -> dict:
    """What ``configs/default.yaml`` lists: every key a person may set, at its default."""
    return user_dict(SlamConfig(), skip=("analysis",))


def save_config(config: SlamConfig, path: str | Path) -> None:
    """Write the resolved configuration as YAML: what a person may set, and the analysis
    switches where one is set (``slam run --config`` reads it back)."""
    tree = user_dict(config, skip=("analysis",))
    analysis = {k: v for k, v in user_dict(config.analysis).items()
                if v is not None and v != getattr(AnalysisConfig(), k)}
    if analysis:
        tree["analysis"] = analysis
    Path(path).write_text(yaml.safe_dump(tree, sort_keys=False))
