"""Stereo visual odometry: a stereo pair in, the relative pose to a reference view out.

``StereoOdometry.make_view`` turns a rectified stereo pair into a ``View`` (image, depth from the
stereo parallax flow, validity, parallax). ``track`` estimates the pose of a current view relative
to a reference view (the previous frame in frame2frame, a rendered model view in frame2model):
temporal flow, residuals, weight maps, NLLS. ``register`` is the frame2frame loop in one call.
"""
from __future__ import annotations

import logging
import time
import weakref
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from vo.camera import StereoCamera
from vo.config import CorrespondenceConfig, DepthConfig, SolverConfig, WeightsConfig
from vo.correspondence import make_flow_estimators
from vo.correspondence.dis import DisFlow, to_gray_u8
from vo.depth import (depth_from_parallax, filter_depth_and_velocity_along_flow, flow_consistency, parallax_from_depth,
                      vertical_parallax_ok)
from vo.geometry import backproject, flow_grid, lands_inside, pixel_grid, sample_by_flow, sample_valid_by_flow
from vo.lie import rotation_angle_deg
from vo.motion_memory import relative_residual, update_memory
from vo.residuals import PoseProblem, residuals
from vo.solver import solve_pose
from vo.weights import (WeightInputs, WeightNetworks, constant_weights, load_weight_networks, rigid_prior_flow,
                        model_reference_checkpoint, uses_map_depth, uses_motion_memory, uses_rigid_flow)

log = logging.getLogger(__name__)


@dataclass
class VOConfig:
    """The VO core's configuration, one section per concern."""

    correspondence: CorrespondenceConfig = field(default_factory=CorrespondenceConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    weights: WeightsConfig = field(default_factory=WeightsConfig)


@dataclass
class View:
    """One view as the VO core uses it (batch of 1).

    Attributes:
        image: ``(1, 3, H, W)`` float32 RGB in [0, 1].
        gray: ``(H, W)`` uint8 grey image (for the classical flow backend).
        depth: ``(1, 1, H, W)`` depth in mm, 0 where invalid.
        valid: ``(1, 1, H, W)`` bool pixels with a valid depth and not masked.
        parallax: ``(1, 2, H, W)`` stereo parallax flow left -> right (pixels).
        matchable: ``(1, 1, H, W)`` bool, the pixels a correspondence may land on, or None (all).
            A rendered view whose uncovered pixels were filled from a view at another pose
            marks only its covered pixels (those fill pixels give no residual).
        masked: ``(H, W)`` bool numpy, the pixels the frame's mask excludes (specular
            highlights, instruments, dark corners), or None (no mask given).
        rendered: the view's image is the model's colour (it shows no highlights or
            instruments); False for a real frame and for a model view seen with a real frame's
            pixels.
        flow_input: the image and grey image with the masked pixels inpainted, kept once
            computed (:meth:`StereoOdometry._flow_input`: a frame is flowed against a model
            view in its tracking pass, its refinement passes and, chained, as the last frame).
        model_depth: ``(1, 1, H, W)`` depth in mm of the map rendered at this view's pose after it
            was fused (0 where the map does not cover it), or None: the input of layout-4 weight
            networks when the view is a reference (:meth:`StereoOdometry.needs_map_depth`).
        flow_ahead: the temporal flow of this view against an earlier real view, computed
            before it was needed (:meth:`StereoOdometry.flow_ahead`): a weak reference to that
            view, the flow and the forward-backward mask; taken once by the tracking that uses it.
        stereo_depth: the view's own stereo depth once ``depth`` holds it filtered along the flow
            (``depth.temporal_gain`` < 1, :meth:`StereoOdometry.filter_depth`), else None.
        motion_memory: ``(1, 4, H, W)`` where the tissue seen in this view has been moving
            (:mod:`vo.motion_memory`), set when it was tracked against a camera frame for
            layout-5 weight networks (:meth:`StereoOdometry.remember_motion`), else None.
        depth_velocity: ``(1, 1, H, W)`` mm per frame, the filter's depth velocity where ``depth`` was
            filtered with ``depth.temporal_velocity_gain`` > 0, else None.
    """

    image: torch.Tensor
    gray: np.ndarray
    depth: torch.Tensor
    valid: torch.Tensor
    parallax: torch.Tensor
    matchable: torch.Tensor | None = None
    masked: np.ndarray | None = None
    rendered: bool = False
    flow_input: tuple[torch.Tensor, np.ndarray] | None = field(default=None, repr=False)
    model_depth: torch.Tensor | None = field(default=None, repr=False)
    flow_ahead: tuple[weakref.ref, torch.Tensor, torch.Tensor | None] | None = field(default=None, repr=False)
    stereo_depth: torch.Tensor | None = field(default=None, repr=False)
    motion_memory: torch.Tensor | None = field(default=None, repr=False)
    depth_velocity: torch.Tensor | None = field(default=None, repr=False)


@dataclass
class TrackResult:
    """The outcome of tracking one view against a reference.

    Attributes:
        relative: ``(4, 4)`` float64 transform current camera -> reference camera, mm; identity
            when the frame failed.
        failed: the pose could not be trusted (see ``reason``).
        reason: why it failed ('' otherwise).
        iterations, cost: solver figures.
        valid_pixels: pixels with a non-zero weight.
        flow: ``(1, 2, H, W)`` temporal flow current -> reference.
        w2d, w3d: ``(1, 1, H, W)`` weight maps used.
        timings_ms: per-stage wall time.
    """

    relative: np.ndarray
    failed: bool
    reason: str
    iterations: int
    cost: float
    valid_pixels: int
    flow: torch.Tensor
    w2d: torch.Tensor
    w3d: torch.Tensor
    timings_ms: dict


def image_tensor(rgb: np.ndarray, device: str | torch.device = "cpu") -> torch.Tensor:
    """``(H, W, 3)`` uint8 RGB -> ``(1, 3, H, W)`` float32 in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(rgb)).to(device).permute(2, 0, 1)[None].float().div_(255.0)


class StereoOdometry:
    """The paper's VO: learned (or constant) per-pixel weights on 2D and 3D geometric residuals.

    Args:
        camera: the rectified stereo camera (all views share it).
        config: VO configuration.
        device: torch device.
        weight_networks: networks to use in ``learned`` mode (loaded from the config's checkpoint
            when None).
        weight_hook: optional ``hook(cur, ref, flow, w2d, w3d) -> (w2d, w3d)`` applied to the weight
            maps before every solve (analysis: ``tools/oracle_weights.py`` masks them with ground
            truth); ``(1, 1, H, W)`` maps, ``flow`` the temporal flow ``(1, 2, H, W)``.
    """

    def __init__(self, camera: StereoCamera, config: VOConfig, device: str = "cpu",
                 weight_networks: WeightNetworks | None = None,
                 weight_hook: Callable[..., tuple[torch.Tensor, torch.Tensor]] | None = None):
        self.weight_hook = weight_hook
        self.camera = camera
        self.config = config
        self.device = torch.device(device)
        self.K = camera.K_tensor(self.device)
        self.temporal_flow, self.stereo_flow = make_flow_estimators(config.correspondence, device)
        self.weight_networks = None
        self.model_weight_networks = None   # against views rendered from the map (None: the same)
        self.unfiltered_weight_networks = None  # for frames left unfiltered (depth.temporal_still_mm; None: the same)
        self.weight_meta: dict = {}
        if config.weights.mode == "learned":
            wcfg = config.weights
            if weight_networks is None:
                weight_networks, self.weight_meta = load_weight_networks(
                    wcfg.checkpoint, wcfg.residuals, device, filtered_depth=config.depth.temporal_gain < 1.0)
                model_path = model_reference_checkpoint(wcfg.checkpoint, wcfg.checkpoint_model, wcfg.residuals)
                if model_path is not None:
                    self.model_weight_networks = load_weight_networks(model_path, wcfg.residuals, device)[0].to(self.device).eval()
                if config.depth.temporal_gain < 1.0 and config.depth.temporal_still_mm > 0 and not wcfg.checkpoint:
                    self.unfiltered_weight_networks = load_weight_networks("", wcfg.residuals, device)[0].to(self.device).eval()
            self.weight_networks = weight_networks.to(self.device).eval()
            warn_depth_filter_mismatch(self.weight_meta, config.depth.temporal_gain, wcfg.checkpoint)
        elif config.weights.mode != "constant":
            raise ValueError(f"unknown weights.mode '{config.weights.mode}' (learned, constant)")
        self._ahead_flow_estimator = None   # the look-ahead thread's own temporal flow (flow_ahead)
        self.reference: View | None = None
        self.pose = np.eye(4)  # T_wc of the rectified left camera, mm
        self.previous_relative = np.eye(4)

    # ---------------------------------------------------------------- views
    def _flow(self, estimator, a_img: torch.Tensor, a_gray: np.ndarray, b_img: torch.Tensor, b_gray: np.ndarray) -> torch.Tensor:
        if isinstance(estimator, DisFlow):
            f = estimator.flow_gray(a_gray, b_gray)
            return torch.from_numpy(f).permute(2, 0, 1)[None].to(self.device)
        return estimator.flow(a_img, b_img)

    def make_view(self, left: np.ndarray, right: np.ndarray, mask: np.ndarray | None = None,
                  gt_depth: np.ndarray | None = None, timings: dict | None = None,
                  specular: np.ndarray | None = None) -> View:
        """A view from a rectified stereo pair.

        Args:
            left, right: ``(H, W, 3)`` uint8 RGB.
            mask: ``(H, W)`` bool valid tissue pixels, or None.
            gt_depth: ``(H, W)`` float depth in mm to use instead of stereo depth (error budget).
            specular: ``(2, H, W)`` bool specular highlights of the left and right views, or
                None; inpainted for the stereo match (``correspondence.stereo_inpaint_px``).
        """
        t0 = time.perf_counter()
        img_l = image_tensor(left, self.device)
        gray_l = to_gray_u8(img_l[0])
        valid_mask = None if mask is None else torch.from_numpy(np.ascontiguousarray(mask)).to(self.device)[None, None]
        fxb = self.camera.depth_from_disparity_scale()
        dcfg = self.config.depth
        if gt_depth is not None:
            depth = torch.from_numpy(np.ascontiguousarray(gt_depth, dtype=np.float32)).to(self.device)[None, None]
            valid = (depth >= dcfg.min_depth_mm) & (depth <= dcfg.max_depth_mm)
            if valid_mask is not None:
                valid &= valid_mask
            depth = torch.where(valid, depth, torch.zeros_like(depth))
            parallax = parallax_from_depth(depth, fxb)
        else:
            img_r = image_tensor(right, self.device)
            gray_r = to_gray_u8(img_r[0])
            ccfg = self.config.correspondence
            st_l, st_r = (img_l, gray_l), (img_r, gray_r)
            if specular is not None and ccfg.stereo_inpaint_px > 0:
                need_image = not isinstance(self.stereo_flow, DisFlow)
                if specular[0].any():
                    st_l = inpaint_masked(img_l, gray_l, specular[0], ccfg.stereo_inpaint_px, need_image)
                if specular[1].any():
                    st_r = inpaint_masked(img_r, gray_r, specular[1], ccfg.stereo_inpaint_px, need_image)
            parallax = self._flow(self.stereo_flow, *st_l, *st_r)
            depth, valid = depth_from_parallax(parallax, fxb, dcfg, valid_mask)
            if specular is not None and ccfg.stereo_inpaint_px > 0 and specular[1].any():
                # a match that lands on the right view's highlight found no tissue there
                seen_r = torch.from_numpy(~np.asarray(specular[1], dtype=bool)).to(self.device)[None, None]
                valid &= sample_valid_by_flow(seen_r, parallax)
            if ccfg.max_vertical_parallax_px > 0:
                valid &= vertical_parallax_ok(parallax, ccfg.max_vertical_parallax_px)
            if ccfg.lr_check_px > 0:
                back = self._flow(self.stereo_flow, *st_r, *st_l)
                valid &= flow_consistency(parallax, back, ccfg.lr_check_px)
            depth = torch.where(valid, depth, torch.zeros_like(depth))
        if timings is not None:
            timings["stereo"] = (time.perf_counter() - t0) * 1000.0
        masked = None if mask is None else ~np.asarray(mask, dtype=bool)
        return View(image=img_l, gray=gray_l, depth=depth, valid=valid, parallax=parallax,
                    masked=masked if masked is not None and masked.any() else None)

    def view_from_render(self, color: torch.Tensor | None, depth: torch.Tensor, valid: torch.Tensor,
                         background: View | None = None, background_matchable: bool = True) -> View:
        """A reference view from a rendered model view.

        Args:
            color: ``(3, H, W)`` RGB in [0, 1], or None: the image is the background's (the view is
                then the model's geometry seen with the last real frame's pixels, which is all that
                tracking with the flow against the last frame uses).
            depth: ``(H, W)`` mm; valid: ``(H, W)`` bool.
            background: a real view at the same pose (the last frame) whose colour fills the
                pixels the model does not cover, so that the flow has no artificial edge there
                (those pixels get 2D residuals only: the reference depth comes from the model),
                and whose shading the render is relit to (:func:`relight`, over the pixels valid
                in both: the background's highlights and instruments are not in the model).
            background_matchable: False when the background sits at another pose than the
                render (the current frame filling a render at its own estimated pose): the
                filled pixels are then not :attr:`View.matchable`.
        """
        dcfg = self.config.depth
        depth = depth[None, None].to(self.device).float()
        covered = valid[None, None].to(self.device)
        valid = covered & (depth >= dcfg.min_depth_mm) & (depth <= dcfg.max_depth_mm)
        depth = torch.where(valid, depth, torch.zeros_like(depth))
        if color is None:
            if background is None:
                raise ValueError("view_from_render: without colour a background view is needed")
            image, gray = background.image, background.gray
        else:
            image = color[None].to(self.device).float().clamp(0, 1)
            if background is not None:
                image = torch.where(covered, relight(image, background.image, covered & background.valid), background.image)
            gray = to_gray_u8(image[0])
        return View(image=image, gray=gray, depth=depth, valid=valid,
                    parallax=parallax_from_depth(depth, self.camera.depth_from_disparity_scale()),
                    matchable=None if background is None or background_matchable else covered,
                    rendered=color is not None)

    # ---------------------------------------------------------------- tracking
    def _weights(self, cur: View, ref: View, flow: torch.Tensor, problem: tuple,
                 model_reference: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """``problem``: :meth:`build_problem`'s ``(target, valid, valid3, points_ref)``."""
        wcfg = self.config.weights
        valid = problem[1]
        if self.weight_networks is None:
            return constant_weights(valid, wcfg.w2d, wcfg.w3d, wcfg.residuals)
        networks = self.model_weight_networks if model_reference and self.model_weight_networks is not None \
            else self.weight_networks
        if not model_reference and cur.stereo_depth is None and self.unfiltered_weight_networks is not None:
            networks = self.unfiltered_weight_networks      # a moving camera's frame keeps its stereo depth
        dmax = self.config.depth.max_depth_mm
        rigid = self.rigid_flow(cur, flow, problem) if uses_rigid_flow(networks.inputs) else None
        model_depth = None
        if uses_map_depth(networks.inputs):   # a reference without a map view (a first frame, a model view): no deviation
            model_depth = torch.zeros_like(ref.depth) if ref.model_depth is None else ref.model_depth / dmax
        inp = WeightInputs(image_cur=cur.image, depth_cur=cur.depth / dmax, flow=flow, parallax_cur=cur.parallax,
                           image_ref=ref.image, depth_ref=ref.depth / dmax, parallax_ref=ref.parallax, valid=valid,
                           rigid_flow=rigid, model_depth_ref=model_depth,
                           motion_memory_ref=ref.motion_memory if uses_motion_memory(networks.inputs) else None)
        with torch.inference_mode():
            return networks(inp)

    def keeps_motion_memory(self) -> bool:
        """Some frame-reference weight networks take the reference's motion memory (layout 5)."""
        return any(n is not None and uses_motion_memory(n.inputs)
                   for n in (self.weight_networks, self.unfiltered_weight_networks))

    def remember_motion(self, cur: View, ref: View, flow: torch.Tensor, problem: tuple, T: torch.Tensor,
                        points_cur: torch.Tensor | None = None) -> None:
        """Set ``cur.motion_memory``: ``ref``'s carried along ``flow`` plus the 3D residual of every
        pixel at the pose ``T`` ``(1, 4, 4)`` (current -> reference, translation normalised by
        ``depth.max_depth_mm``); ``problem`` is :meth:`build_problem`'s; ``points_cur`` ``(1, 3, H,
        W)`` ``cur``'s normalised points if already computed. Between camera frames only (a model
        view's depth is the map's, not the tissue as this frame saw it)."""
        if cur.rendered or ref.rendered:
            return
        _, _, valid3, points_ref = problem
        if points_cur is None:
            points_cur = backproject(cur.depth / self.config.depth.max_depth_mm, self.K)
        residual = relative_residual(points_cur, points_ref, T, valid3)
        cur.motion_memory = update_memory(ref.motion_memory, flow, residual, valid3)

    def needs_map_depth(self) -> bool:
        """The frame-reference weight networks take the map's depth at the reference's pose
        (layout 4): whoever keeps a map sets ``View.model_depth`` on each reference."""
        return self.weight_networks is not None and uses_map_depth(self.weight_networks.inputs)

    def rigid_flow(self, cur: View, flow: torch.Tensor, problem: tuple) -> torch.Tensor:
        """``(1, 2, H, W)``: the flow of the rigid motion solved with the constant weights
        (``weights.w2d`` / ``w3d``, both residuals), the input of layout-3 weight networks; the
        measured flow itself (a zero residual) where that solve has too few pixels or fails."""
        target, valid, valid3, points_ref = problem
        wcfg, scfg = self.config.weights, self.config.solver
        dmax = self.config.depth.max_depth_mm
        w2, w3 = constant_weights(valid, wcfg.w2d, wcfg.w3d, "2d3d")
        points_cur = backproject(cur.depth / dmax, self.K)
        prob = self._pose_problem(points_cur, target, points_ref, w2, w3 * valid3)
        if prob.w2d.shape[1] < scfg.min_valid_pixels:
            return flow
        T = solve_pose(prob.subsample(scfg.max_pixels), scfg).T
        if not bool(torch.isfinite(T).all()):
            return flow
        return rigid_prior_flow(points_cur, flow, T, self.K)

    def _pose_problem(self, points_cur: torch.Tensor, target: torch.Tensor, points_ref: torch.Tensor,
                      w2d: torch.Tensor, w3d: torch.Tensor) -> PoseProblem:
        """The objective over every pixel with a non-zero weight: ``points_cur``, ``points_ref``
        ``(1, 3, H, W)`` (normalised), ``target`` ``(1, 2, H, W)`` pixels, weights ``(1, 1, H, W)``."""
        s2, s3 = PoseProblem.scales(*target.shape[-2:])
        return PoseProblem(points_cur=points_cur.flatten(2), target_px=target.flatten(2),
                           points_ref=points_ref.flatten(2), w2d=w2d.flatten(1), w3d=w3d.flatten(1),
                           K=self.K[None], s2=s2, s3=s3).compact()

    def build_problem(self, cur: View, ref: View, flow: torch.Tensor, flow_valid: torch.Tensor | None = None):
        """The pose problem of ``cur`` against ``ref`` given the temporal flow.

        Returns:
            (problem, valid ``(1, 1, H, W)`` bool, valid3d ``(1, 1, H, W)`` bool)
        """
        _, _, H, W = flow.shape
        dmax = self.config.depth.max_depth_mm
        target = pixel_grid(H, W, flow.device, flow.dtype) + flow
        valid = cur.valid & lands_inside(flow, target)
        if flow_valid is not None:
            valid &= flow_valid
        grid = flow_grid(flow, target)      # one sampling grid for the three maps drawn by the flow
        if ref.matchable is not None:
            valid &= sample_valid_by_flow(ref.matchable, flow, grid)
        valid3 = valid & sample_valid_by_flow(ref.valid, flow, grid)
        points_ref = sample_by_flow(backproject(ref.depth / dmax, self.K), flow, grid=grid)
        return target, valid, valid3, points_ref

    def track(self, cur: View, ref: View, flow_ref: View | None = None, T_init: np.ndarray | None = None,
              chain_gain: float = 0.0, model_reference: bool = False, camera_still: bool = True,
              filter_ref: View | None = None) -> TrackResult:
        """Estimate the transform from ``cur``'s camera to ``ref``'s camera.

        Args:
            cur: the current view.
            ref: the reference view (its depth gives the 3D residual's reference points).
            flow_ref: the view the temporal flow is computed against (default ``ref``); in
                frame2model it can be the last real frame, which sits at the reference pose.
            T_init: ``(4, 4)`` mm initial guess (identity when None).
            chain_gain: with ``flow_ref``, follow the temporal flow ``cur -> flow_ref`` on by
                ``chain_gain`` x the (smoothed) flow ``flow_ref -> ref``, so that correspondences
                move towards the pixels of ``ref`` that show the same surface points. In
                frame2model the last real frame and the model view share the *estimated* pose, but
                the real frame was taken at the true one: without the chain its pose error is
                handed on to the next frame; the short flow between two views of the same pose
                measures it, and a gain below 1 removes it over a few frames while damping the
                render's flow noise (a complementary filter). 0: no chain.
            model_reference: ``ref`` is a view rendered from the map: the weights come from the
                model-reference networks (``weights.checkpoint_model``) and the robust 3D step uses
                ``solver.robust_3d_model_mm`` instead of ``solver.robust_3d_mm``.
            camera_still: the last tracked motion moved the camera less than
                ``depth.temporal_still_mm`` (:meth:`camera_still`; the caller keeps the motion):
                only then is ``cur``'s depth filtered (:meth:`filter_depth`).
            filter_ref: the real frame ``cur``'s depth is filtered against when that is not
                ``ref`` (a keyframe reference, ``tracking.keyframe_gap``: the filter runs from one
                frame to the next, as in training, and the tracking against the keyframe sees the
                filtered depths' change over the gap); None: ``ref``.
        """
        timings: dict = {}
        t0 = time.perf_counter()
        against = filter_ref if filter_ref is not None and self.filters_depth(cur, filter_ref, camera_still) else ref
        # the flow to another frame first: _correspondences hands the read-ahead flow on only once
        filter_flow = self._flow_against(cur, against) if against is not ref else None
        flow, fb_ok = self._correspondences(cur, ref, flow_ref, chain_gain)
        f_flow, f_ok = filter_flow if filter_flow is not None else (flow, fb_ok)
        self.filter_depth(cur, against, f_flow, f_ok, camera_still)
        t1 = time.perf_counter()
        problem = self.build_problem(cur, ref, flow, fb_ok)
        target, valid, valid3, points_ref = problem
        w2d, w3d = self._weights(cur, ref, flow, problem, model_reference)
        w3d = w3d * valid3
        if self.weight_hook is not None:
            w2d, w3d = self.weight_hook(cur, ref, flow, w2d, w3d)
        t2 = time.perf_counter()
        dmax = self.config.depth.max_depth_mm
        points_cur = backproject(cur.depth / dmax, self.K)
        prob = self._pose_problem(points_cur, target, points_ref, w2d, w3d)
        n_valid = int(prob.w2d.shape[1])
        prob = prob.subsample(self.config.solver.max_pixels)
        scfg = self.config.solver
        init = None
        if T_init is not None:
            Ti = torch.as_tensor(T_init, dtype=torch.float32, device=self.device).clone()
            Ti[:3, 3] /= dmax
            init = Ti[None]
        failed, reason = False, ""
        result = None
        if n_valid < scfg.min_valid_pixels:
            failed, reason = True, f"only {n_valid} valid pixels"
        else:
            result = solve_pose(prob, scfg, init)
            robust_mm = scfg.robust_3d_model_mm if model_reference else scfg.robust_3d_mm
            if robust_mm > 0 and bool(torch.isfinite(result.T).all()):
                robust = prob.with_weights(prob.w2d, prob.w3d * cauchy_weights_3d(prob, result.T, dmax, robust_mm))
                result = solve_pose(robust, scfg, result.T)
        t3 = time.perf_counter()
        relative = np.eye(4)
        if result is not None:
            T = result.T[0].double().cpu()
            if not bool(torch.isfinite(T).all()):
                failed, reason = True, "non-finite pose"
            else:
                trans_mm = float(T[:3, 3].norm()) * dmax
                rot_deg = float(rotation_angle_deg(T[None])[0])
                if trans_mm > scfg.max_translation_mm:
                    failed, reason = True, f"implausible motion {trans_mm:.1f} mm"
                elif rot_deg > scfg.max_rotation_deg:
                    failed, reason = True, f"implausible rotation {rot_deg:.1f} deg"
                else:
                    relative = T.numpy().copy()
                    relative[:3, 3] *= dmax
                    if not model_reference and self.keeps_motion_memory():
                        self.remember_motion(cur, ref, flow, problem, result.T, points_cur)
        timings.update(flow=(t1 - t0) * 1000.0, weights=(t2 - t1) * 1000.0, solve=(t3 - t2) * 1000.0)
        return TrackResult(relative=relative, failed=failed, reason=reason,
                           iterations=0 if result is None else result.iterations,
                           cost=float("nan") if result is None else float(result.cost[0]),
                           valid_pixels=n_valid, flow=flow, w2d=w2d, w3d=w3d, timings_ms=timings)

    def camera_still(self, last_relative: np.ndarray) -> bool:
        """Whether the last tracked motion, ``(4, 4)`` mm, moved the camera less than
        ``depth.temporal_still_mm`` (always True when that is 0): :meth:`track`'s ``camera_still``."""
        return moved_less_than(last_relative, self.config.depth.temporal_still_mm)

    def filters_depth(self, cur: View, ref: View, filter_on: bool = True) -> bool:
        """Whether :meth:`filter_depth` filters ``cur`` against ``ref`` (the filter on, two camera frames)."""
        return self.config.depth.temporal_gain < 1.0 and filter_on and not (cur.rendered or ref.rendered)

    def filter_depth(self, cur: View, ref: View, flow: torch.Tensor, flow_ok: torch.Tensor | None,
                     filter_on: bool = True) -> None:
        """With ``depth.temporal_gain`` < 1 and ``filter_on``, replace ``cur.depth`` by its stereo
        depth filtered along ``flow`` (``cur -> ref``) against ``ref``'s depth
        (:func:`vo.depth.filter_depth_along_flow`) and keep the stereo depth in
        ``cur.stereo_depth`` (None: ``cur.depth`` is the stereo depth). Only between two camera
        frames: a model view's depth is fused already, and a real frame tracked against one keeps
        its own stereo depth. Tracking ``cur`` again starts from its stereo depth, never the filtered one."""
        dcfg = self.config.depth
        if cur.stereo_depth is not None:
            cur.depth, cur.stereo_depth = cur.stereo_depth, None
        cur.depth_velocity = None
        if not self.filters_depth(cur, ref, filter_on):
            return
        cur.stereo_depth = cur.depth
        cur.depth, cur.depth_velocity = filter_depth_and_velocity_along_flow(
            cur.stereo_depth, cur.valid, ref.depth, ref.valid, flow, flow_ok, dcfg.temporal_gain,
            dcfg.temporal_gate_mm, ref.depth_velocity, dcfg.temporal_velocity_gain)

    def _flow_input(self, view: View, against: View) -> tuple[torch.Tensor, np.ndarray]:
        """``view``'s image and grey image for a temporal flow to ``against``: a real frame's
        masked pixels inpainted when ``against`` is a model view
        (``correspondence.inpaint_masked_px``), else as they are."""
        radius = self.config.correspondence.inpaint_masked_px
        if not against.rendered or view.rendered or view.masked is None or radius <= 0:
            return view.image, view.gray
        if view.flow_input is None:
            view.flow_input = inpaint_masked(view.image, view.gray, view.masked, radius,
                                             need_image=not isinstance(self.temporal_flow, DisFlow))
        return view.flow_input

    def _pair_flow(self, estimator, cur: View, against: View) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The temporal flow ``cur -> against`` and, with ``correspondence.fb_check_px``, the
        ``(1, 1, H, W)`` bool mask of flows that passed the forward-backward check (else None)."""
        cur_img, cur_gray = self._flow_input(cur, against=against)
        flow = self._flow(estimator, cur_img, cur_gray, against.image, against.gray)
        fb_ok = None
        if self.config.correspondence.fb_check_px > 0:
            back = self._flow(estimator, against.image, against.gray, cur_img, cur_gray)
            fb_ok = flow_consistency(flow, back, self.config.correspondence.fb_check_px)
        return flow, fb_ok

    def can_flow_ahead(self) -> bool:
        """Whether :meth:`flow_ahead` can run in another thread (a classical backend: a second
        estimator of the same settings; one RAFT model is not shared between threads)."""
        return self.config.correspondence.backend == "dis"

    def flow_ahead(self, cur: View, against: View) -> None:
        """Compute the temporal flow ``cur -> against`` now, with an estimator of its own (safe in
        a read-ahead thread while :meth:`track` runs in another), and keep it on ``cur``: a
        later :meth:`track` whose flow goes against ``against`` takes it instead of computing it
        (same settings, same inputs: the same flow bit for bit). Both must be real frames."""
        if cur.rendered or against.rendered:
            raise ValueError("flow_ahead: only between real frames")
        if self._ahead_flow_estimator is None:
            self._ahead_flow_estimator = make_flow_estimators(self.config.correspondence, self.device)[0]
        flow, fb_ok = self._pair_flow(self._ahead_flow_estimator, cur, against)
        cur.flow_ahead = (weakref.ref(against), flow, fb_ok)

    def _flow_against(self, cur: View, against: View) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The temporal flow ``cur -> against`` (:meth:`_pair_flow`): the one :meth:`flow_ahead`
        kept on ``cur`` when it goes against that view, else computed now."""
        ahead = cur.flow_ahead
        if ahead is not None and ahead[0]() is against:
            return ahead[1], ahead[2]
        return self._pair_flow(self.temporal_flow, cur, against)

    def _correspondences(self, cur: View, ref: View, flow_ref: View | None,
                         chain_gain: float) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The temporal flow ``cur -> ref`` (through ``flow_ref``, see :meth:`track`) and the
        ``(1, 1, H, W)`` bool mask of flows that passed the checks (None: no check ran)."""
        chain = chain_gain > 0 and flow_ref is not None and flow_ref is not ref
        flow_ref = flow_ref or ref
        flow, fb_ok = self._flow_against(cur, flow_ref)
        cur.flow_ahead = None
        if chain:
            last_img, last_gray = self._flow_input(flow_ref, against=ref)
            to_ref = self._flow(self.temporal_flow, last_img, last_gray, ref.image, ref.gray)
            # a pose offset moves a smooth surface smoothly: keep the field's low frequencies only
            # (the render's blur and shading make the per-pixel flow noisy)
            to_ref = masked_blur(to_ref, ref.valid & flow_ref.valid, 0.05) * chain_gain
            flow, on_ref = chain_flows(flow, to_ref, ref.valid)
            fb_ok = on_ref if fb_ok is None else fb_ok & on_ref
        return flow, fb_ok

    def weight_maps(self, cur: View, ref: View, timings: dict | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The ``(1, 1, H, W)`` weight maps ``(w2d, w3d)`` of ``cur`` against ``ref`` as :meth:`track`
        computes them, without solving for the pose (mapping with known poses)."""
        t0 = time.perf_counter()
        flow, fb_ok = self._correspondences(cur, ref, None, 0.0)
        t1 = time.perf_counter()
        problem = self.build_problem(cur, ref, flow, fb_ok)
        w2d, w3d = self._weights(cur, ref, flow, problem)
        valid3 = problem[2]
        if timings is not None:
            timings.update(flow=(t1 - t0) * 1000.0, weights=(time.perf_counter() - t1) * 1000.0)
        return w2d, w3d * valid3

    # ---------------------------------------------------------------- frame2frame
    def register(self, left: np.ndarray, right: np.ndarray, mask: np.ndarray | None = None,
                 gt_depth: np.ndarray | None = None, specular: np.ndarray | None = None) -> TrackResult | None:
        """Frame-to-frame odometry step: track the new pair against the previous one and chain.

        Returns None for the first frame (it becomes the reference). On failure the pose and the
        reference are kept (the next frame is tracked against the last good one).
        """
        timings: dict = {}
        view = self.make_view(left, right, mask, gt_depth, timings, specular)
        if self.reference is None:
            self.reference = view
            return None
        T_init = self.previous_relative if self.config.solver.init == "constant_velocity" else None
        result = self.track(view, self.reference, T_init=T_init, camera_still=self.camera_still(self.previous_relative))
        result.timings_ms = {**timings, **result.timings_ms}
        if not result.failed:
            self.pose = self.pose @ result.relative
            self.previous_relative = result.relative
            self.reference = view
        return result


def moved_less_than(relative: np.ndarray, still_mm: float) -> bool:
    """Whether the ``(4, 4)`` mm motion ``relative`` translated the camera less than ``still_mm``
    (always True when that is 0 or less: no threshold)."""
    return still_mm <= 0 or float(np.linalg.norm(relative[:3, 3])) < still_mm


def warn_depth_filter_mismatch(meta: dict, temporal_gain: float, checkpoint: str) -> None:
    """Log a warning when the weight networks were trained on depth filtered with another
    ``depth.temporal_gain`` than tracking uses (their weights then suit another depth noise)."""
    trained = (meta.get("train_config") or {}).get("depth", {}).get("temporal_gain", 1.0)
    if abs(float(trained) - float(temporal_gain)) > 1e-9:
        log.warning("the weight networks (%s) were trained with depth.temporal_gain=%g, tracking uses %g: "
                    "their 3D weights suit another depth noise (README, \"Temporal depth filter\")",
                    checkpoint or "packaged", float(trained), float(temporal_gain))


def cauchy_weights_3d(prob: PoseProblem, T: torch.Tensor, max_depth_mm: float, scale_mm: float) -> torch.Tensor:
    """``(B, N)`` Cauchy weights ``1 / (1 + (r / scale_mm)^2)`` of the 3D residuals ``r`` (mm)
    of ``prob`` at the poses ``T`` ``(B, 4, 4)`` (translation in the problem's normalised units)."""
    _, e3, _ = residuals(T.to(prob.points_cur.dtype), prob)
    r_mm = e3.norm(dim=1) * (max_depth_mm / prob.s3)
    return 1.0 / (1.0 + (r_mm / scale_mm) ** 2)


def inpaint_masked(image: torch.Tensor, gray: np.ndarray, masked: np.ndarray, radius: float,
                   need_image: bool = True) -> tuple[torch.Tensor, np.ndarray]:
    """Fill the ``masked`` pixels of a real frame from their surroundings (OpenCV Telea).

    A model view shows the tissue without the frame's specular highlights and instruments (they
    are never fused); left in the frame, their edges pull the flow of every patch that overlaps
    them towards their own motion (a highlight rides with the light, on the endoscope).

    Args:
        image: ``(1, 3, H, W)`` RGB in [0, 1]; gray: ``(H, W)`` uint8; masked: ``(H, W)`` bool.
        radius: inpainting radius (pixels).
        need_image: also inpaint ``image`` (flow backends that read the colour); else it is
            returned as it is.
    Returns:
        ``(image, gray)`` with the masked pixels filled.
    """
    import cv2

    mask_u8 = masked.astype(np.uint8)
    gray = cv2.inpaint(gray, mask_u8, float(radius), cv2.INPAINT_TELEA)
    if need_image:
        rgb = (image[0].permute(1, 2, 0).clamp(0, 1) * 255.0).round().to(torch.uint8).cpu().numpy()
        rgb = cv2.inpaint(np.ascontiguousarray(rgb), mask_u8, float(radius), cv2.INPAINT_TELEA)
        image = torch.from_numpy(rgb).to(image.device).permute(2, 0, 1)[None].float().div_(255.0)
    return image, gray


def relight(image: torch.Tensor, target: torch.Tensor, covered: torch.Tensor, sigma_frac: float = 0.03) -> torch.Tensor:
    """Match the low-frequency shading of ``image`` to ``target`` (a view at the same pose).

    A rendered model view averages colours seen under lights at other positions (the light rides
    on the endoscope); a smooth per-channel gain, the ratio of the two images blurred over
    ``covered`` pixels (normalised convolution), gives it the current light without moving edges.

    Args:
        image, target: ``(1, 3, H, W)`` RGB in [0, 1]; covered: ``(1, 1, H, W)`` bool.
    """
    both = masked_blur(torch.cat([target, image], 1), covered, sigma_frac)
    gain = (both[:, :3] + 1e-3) / (both[:, 3:] + 1e-3)
    return (image * gain.clamp(0.25, 4.0)).clamp(0, 1)


def masked_blur(x: torch.Tensor, mask: torch.Tensor, sigma_frac: float) -> torch.Tensor:
    """Gaussian blur of ``x`` ``(B, C, H, W)`` over the pixels of ``mask`` ``(B, 1, H, W)`` only
    (normalised convolution), sigma ``sigma_frac`` of the image's larger side.

    The result is smooth by construction, so it is computed on a grid pooled to ~sigma / 2 and
    upsampled bilinearly: the cost stays a few ms at any image size.
    """
    import kornia

    H, W = x.shape[-2:]
    sigma = max(1.0, sigma_frac * max(H, W))
    step = max(1, int(sigma // 2))
    m = mask.to(x.dtype)
    xm, mm = x * m, m
    if step > 1:
        xm = torch.nn.functional.avg_pool2d(xm, step, ceil_mode=True, count_include_pad=False)
        mm = torch.nn.functional.avg_pool2d(mm, step, ceil_mode=True, count_include_pad=False)
    s = sigma / step
    k = int(2 * round(3 * s) + 1)
    blur = lambda t: kornia.filters.gaussian_blur2d(t, (k, k), (s, s), border_type="replicate")
    out = blur(xm) / blur(mm).clamp_min(1e-3)
    if step > 1:
        out = torch.nn.functional.interpolate(out, size=(H, W), mode="bilinear", align_corners=False)
    return out


def chain_flows(a_to_b: torch.Tensor, b_to_c: torch.Tensor, c_valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Compose two flows: ``x -> x + a_to_b(x) -> that + b_to_c(that)``.

    Args:
        a_to_b: ``(B, 2, H, W)`` flow on view a's grid into view b.
        b_to_c: ``(B, 2, H, W)`` flow on view b's grid into view c.
        c_valid: ``(B, 1, H, W)`` bool valid pixels of view c.

    Returns:
        (``(B, 2, H, W)`` flow on a's grid into c, ``(B, 1, H, W)`` bool where the chain stays inside
        both images and lands on valid pixels of c).
    """
    flow = a_to_b + sample_by_flow(b_to_c, a_to_b)
    return flow, lands_inside(a_to_b) & sample_valid_by_flow(c_valid, flow)
