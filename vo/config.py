"""Configuration of the VO core, one dataclass per concern.

Choices are ``Literal`` types, range checks live in each class (``__post_init__``). A field whose
metadata says ``fixed`` is a constant a person does not set (the application's configuration
refuses it; its analysis tools may change it through the ``analysis`` section): it is carried
here because the frame rate scales it, or because an analysis tool varies it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

Preset = Literal["ultrafast", "fast", "medium"]


def fixed(why: str, default):
    """A field a person does not set (see the module docstring)."""
    return field(default=default, metadata={"fixed": why})


def need(ok: bool, message: str) -> None:
    """A range check: ``ValueError(message)`` where ``ok`` is False."""
    if not ok:
        raise ValueError(message)


# the left-right check's flow back runs at DIS `fast` where `fast`'s working resolution (a quarter
# of the image) is at least this wide (640x512 and above); 80 px at 320x256 made the check less
# selective. At 640x512 the preset moves frame2frame either way by a third on weak texture (our
# generator: `medium` +35 %; another generator: `fast` +35 %) and frame2model within its spread on
# real video (docs/experiments.md, "Does the left-right check need a `medium` flow back?")
LR_CHECK_FAST_MIN_WIDTH = 128


def lr_check_preset(preset: str, width: int) -> str:
    """The DIS preset of the left-right check's flow back for images ``width`` px wide
    (``auto``: ``fast`` where ``width / 4 >= LR_CHECK_FAST_MIN_WIDTH``, else ``medium``)."""
    if preset != "auto":
        return preset
    return "fast" if width / 4 >= LR_CHECK_FAST_MIN_WIDTH else "medium"


@dataclass
class CorrespondenceConfig:
    """Dense correspondences.

    Attributes:
        backend: ``dis`` (OpenCV DIS optical flow, no weights needed) or ``raft`` (needs
            ``raft_checkpoint``, the published ``raft-things.pth`` layout).
        dis_preset: DIS preset for the temporal flow: ``ultrafast`` | ``fast`` | ``medium``.
        dis_stereo_preset: DIS preset for the stereo parallax flow.
        dis_lr_check_preset: DIS preset for the flow back of the left-right check (right ->
            left, ``lr_check_px``), which only says which depths to keep. ``auto`` (default):
            ``fast`` where its working resolution (a quarter of the image) is at least
            ``LR_CHECK_FAST_MIN_WIDTH`` px wide (640x512 and above), else ``medium``
            (:func:`lr_check_preset`; at 320x256 ``fast`` makes the check less selective). At
            640x512 ``fast`` costs 7 ms against ``medium``'s 38 and is not "within 1 %": on the
            accuracy gate's full panel (56 cases) ``medium`` was worse on 19 and better on 11. On
            the real SCARED sequence ``fast`` gives frame2frame 1.33 mm against 1.38 and, at
            2.5 fps, 2.27 against 3.80 (frame2model 1.18 against 7.38), but the 5-fps map's
            error 0.271 against 0.258 mm; on the generator it is the better in frame2frame on the
            rigid and scanning weak looks, the random look and the raw video (by 6-35 %) and the
            worse on the breathing and deforming weak looks (by 16-41 %); on another generator's weak-texture scene it was the worse
            by 35 % (docs/benchmarks.md, "the left-right check at `medium` against `auto`").
        dis_match_exposure: brighten the darker image of each pair to the other's mean before
            DIS (``vo.correspondence.dis.match_exposure``: exposure jumps between frames).
        raft_checkpoint: path to a RAFT checkpoint (RAFT or RAFT-small, told apart by its tensors).
        raft_iters: RAFT update iterations.
        lr_check_px: left-right stereo consistency threshold (pixels): a pixel whose stereo
            flow, followed there and back (left -> right -> left), misses itself by more is
            invalid (occluded in the right view or mismatched); 0 disables the check. It costs a
            second stereo flow (about 15 ms at 320x256 with DIS) and keeps those depths out of
            the residuals and the map: frame2model ATE -13 % and frame2frame -5 % on the synthetic
            rigid and loop sequences, the learned 2D&3D macro ATE -5 % (docs/experiments.md).
        fb_check_px: forward-backward temporal flow consistency threshold (pixels); 0 disables it
            (it costs a second temporal flow).
        round_trip: also compute each tracked pair's flow back for the forward-backward round-trip
            health figure (``round_trip_px`` in ``tracking.csv``; nan without it). It costs a
            second temporal flow per tracked pair (38 ms at 640x512 with DIS medium) for a figure
            that is reported, not acted on, and that ranks wrong poses less well than the cost and
            ``sigma_t_mm`` do (AUC 0.78 against 0.82 and 0.80, docs/experiments.md). With
            ``fb_check_px`` the flow back is computed anyway and the figure comes with it.
        max_vertical_parallax_px: pixels whose stereo flow has a larger vertical part are invalid
            (rectified views have none); 0 disables the check.
        inpaint_px: radius (pixels) with which specular highlights are inpainted from their
            surroundings (OpenCV Telea) before a match; 0 disables it. A highlight is the light's
            mirror image, not a mark on the tissue, and every patch overlapping it follows it.
            Before the stereo match each view's own highlights are inpainted (the two views show
            them on different tissue: on synthetic rigid sequences the depth within 3 px of a
            highlight was off by 1.0 mm on average, within 6-10 px by 0.63, elsewhere 0.32; the
            highlights' own pixels and the left pixels whose match lands on a right-view highlight
            stay invalid). Before a temporal flow against a model view (frame2model) the frame's
            masked pixels are inpainted too: the model shows tissue there. Never between two real
            frames (both carry highlights; measured worse). 6-12 ms per frame at 320x256 with
            3.5-5 % of the pixels in highlights (docs/experiments.md).
    """

    backend: Literal["dis", "raft"] = "dis"
    dis_preset: Preset = "medium"
    dis_stereo_preset: Preset = "medium"
    dis_lr_check_preset: Literal["auto", "ultrafast", "fast", "medium"] = "auto"
    raft_checkpoint: str = ""
    lr_check_px: float = 1.0
    dis_match_exposure: bool = fixed("an analysis switch (analysis.match_exposure)", True)
    raft_iters: int = fixed("RAFT's update iterations, as the published checkpoints were trained", 12)
    fb_check_px: float = fixed("an analysis switch (analysis.fb_check_px)", 0.0)
    round_trip: bool = fixed("an analysis switch (analysis.round_trip)", False)
    max_vertical_parallax_px: float = fixed("rectified views have no vertical parallax; 2 px of slack", 2.0)
    inpaint_px: float = fixed("an analysis switch (analysis.inpaint_px)", 3.0)

    def __post_init__(self):
        need(self.lr_check_px >= 0, "correspondence.lr_check_px must be >= 0 (0 = no left-right check)")


@dataclass
class DepthConfig:
    """Depth from disparity.

    Attributes:
        min_depth_mm: nearer depths are invalid.
        max_depth_mm: farther depths are invalid; also the normaliser of depth inside the solver
            (paper, Sec. 2.1) and of the weight networks' depth inputs.
        temporal_gain: < 1: each frame's depth is filtered along the temporal flow against its
            reference frame's (already filtered) depth, ``d = d_ref(x + F) + gain (d_stereo -
            d_ref(x + F))`` (:func:`vo.depth.filter_depth_along_flow`), so that the stereo error,
            which is new in every frame, no longer dominates the 3D residual between two frames.
            The filter needs no pose: a point's depth lags its stereo depth by the same amount in
            both frames while the camera's motion is steady, and that common lag cancels in the
            3D residual. 1 = off (each frame's own stereo depth, the paper's; ``configs/paper.yaml``).
            Default 0.05 with ``temporal_still_mm`` 0.1: filtered while the camera is still.
            docs/experiments.md, "Depth filter and keyframe reference".
        temporal_gate_mm: where the stereo depth differs from the filtered reference by more than
            this (a disocclusion, the flow landing on another surface, fast motion in depth), the
            pixel starts again from its own stereo depth.
        temporal_still_mm: > 0: filter only while the camera is still, i.e. the last tracked motion
            moved it less than this (mm per frame); the frames of a moving camera keep their stereo
            depth and are weighed by the networks trained on it (the packaged ones: when no
            ``weights.checkpoint`` is named). Where the camera's motion in depth changes, the
            filter's lag changes with it and biases the 3D residual. 0: filter every frame. The
            default 0.1 mm is below the stereo noise per frame (2.5 mm/s at 25 fps).
    """

    min_depth_mm: float = 20.0
    max_depth_mm: float = 250.0
    temporal_gain: float = 0.05
    temporal_gate_mm: float = fixed("a constant scaled by the frame rate (slam.config.at_frame_rate)", 1.0)
    temporal_still_mm: float = fixed("a constant scaled by the frame rate (slam.config.at_frame_rate)", 0.1)

    def __post_init__(self):
        need(self.max_depth_mm > self.min_depth_mm > 0, "depth: need 0 < min_depth_mm < max_depth_mm")
        need(0.0 < self.temporal_gain <= 1.0, "depth.temporal_gain must be in (0, 1] (1 = off)")
        need(self.temporal_gate_mm > 0, "depth.temporal_gate_mm must be > 0")
        need(self.temporal_still_mm >= 0, "depth.temporal_still_mm must be >= 0 (0 = filter every frame)")


@dataclass
class SolverConfig:
    """The non-linear least-squares pose solver (paper eq. 4).

    Attributes:
        method: ``lm`` (Levenberg-Marquardt with analytic Jacobians) or ``lbfgs`` (as in the
            paper, autograd gradients).
        max_iters: iteration cap.
        max_translation_mm: a relative motion larger than this is a failure.
        max_rotation_deg: a relative rotation larger than this is a failure.
        min_valid_pixels: fewer pixels with non-zero weight is a failure.
        init: ``identity`` or ``constant_velocity`` (start from the previous relative motion).
        max_pixels: the solver uses at most this many valid pixels, evenly spaced over the valid
            set (0 = all). Cost then no longer grows with the image size; see
            tools/benchmark_speed.py for the accuracy it costs.
        robust_3d_mm: > 0: after the solve, each pixel's 3D weight is multiplied by the Cauchy
            weight ``1 / (1 + (r / robust_3d_mm)^2)`` of its 3D residual ``r`` (mm) at the
            solution, and the pose is solved again from there (one IRLS step): tissue that moved
            non-rigidly, and depth the stereo matcher got wrong, are outliers to the rigid motion
            and no longer pull the pose. 0 = off (the paper's objective; the networks are trained
            through it, this step runs after the optimum). Applies when the reference is a
            camera frame (frame2frame, and frame2model's fallback to the last frame); not against
            a model view, whose fused depth carries few of the outliers the step is for (there it
            changed the ATE by 1 % for 20-35 % more frame time; docs/experiments.md).
        kernel: the LM normal equations: ``auto`` (the compiled numba loop for a problem on the
            CPU, torch's vectorised code on any other device), ``compiled`` or ``torch``
            (:class:`vo.solver.Tolerance`; ``tools/check_gpu.py`` forces ``torch`` on the CPU
            to run the code a GPU runs).
    """

    method: Literal["lm", "lbfgs"] = "lm"
    max_iters: int = 30
    robust_3d_mm: float = 0.5
    max_translation_mm: float = fixed("the plausibility check, scaled by the frame rate", 20.0)
    max_rotation_deg: float = fixed("the plausibility check", 15.0)
    min_valid_pixels: int = fixed("the plausibility check", 200)
    init: Literal["identity", "constant_velocity"] = fixed("the solver starts at the identity", "identity")
    max_pixels: int = fixed("the solver's pixel budget (vo.residuals.PoseProblem.compact)", 16384)
    kernel: Literal["auto", "compiled", "torch"] = fixed("an analysis switch (analysis.solver_kernel)", "auto")

    def __post_init__(self):
        need(self.max_iters >= 1, "solver.max_iters must be >= 1")
        need(self.robust_3d_mm >= 0, "solver.robust_3d_mm must be >= 0 (0 = off)")
        need(self.max_translation_mm > 0 and self.max_rotation_deg > 0,
             "solver.max_translation_mm and max_rotation_deg must be > 0")
        need(self.min_valid_pixels >= 1, "solver.min_valid_pixels must be >= 1")


@dataclass
class WeightsConfig:
    """Per-pixel residual weights (paper eqs. 5-6).

    Attributes:
        mode: ``learned`` (weight networks from ``checkpoint``) or ``constant`` (``w2d``, ``w3d``).
        residuals: ``2d3d`` | ``2d`` | ``3d`` (ablation: the other weight is zero).
        w2d, w3d: the constant weights; their defaults come from the sweep of the 2D/3D balance on
            the 1200 training pairs in ``tools/sweep_constant_weights.py`` (docs/experiments.md): w3d/w2d = 0.01 gave the lowest pose error (w = 1 for both: 3.9x higher).
        checkpoint: weight-network checkpoint; empty = the packaged one for ``residuals``
            (``vo/checkpoints/weights_{residuals}.pt``; for 2d3d with the depth filter on,
            ``weights_2d3d_filtered.pt`` weighs the frames whose depth is filtered).
        checkpoint_model: the checkpoint used when the reference is a view rendered from the map
            (frame2model); empty = the packaged ``weights_{residuals}_model.pt`` when
            ``checkpoint`` is empty and that file exists, else the networks of ``checkpoint``
            (docs/training.md).
    """

    mode: Literal["learned", "constant"] = "learned"
    residuals: Literal["2d3d", "2d", "3d"] = "2d3d"
    w2d: float = 1.0
    w3d: float = 0.01
    checkpoint: str = ""
    checkpoint_model: str = ""

    def __post_init__(self):
        need(self.w2d >= 0 and self.w3d >= 0, "weights.w2d/w3d must be >= 0")


@dataclass
class VOConfig:
    """The VO core's configuration, one section per concern."""

    correspondence: CorrespondenceConfig = field(default_factory=CorrespondenceConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    weights: WeightsConfig = field(default_factory=WeightsConfig)
