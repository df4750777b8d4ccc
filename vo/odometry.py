"""Stereo visual odometry: a stereo pair in, the relative pose to a reference view out.

``StereoOdometry`` is stateless per call. ``make_view`` turns a rectified stereo pair into a
``View`` (image, depth from the stereo parallax flow, validity, parallax); ``view_from_render``
turns a view rendered from the map into one. ``track`` estimates the pose of a current view
relative to a reference view (the previous frame or a keyframe in frame2frame, a model view in
frame2model) in the paper's steps:

1. correspondences: the temporal flow F_t of the current view against the reference;
2. depth: the current stereo depth D_t, optionally filtered along the flow (a still camera);
3. residual problem: the 2D and 3D residuals of eqs. 1-2 over the pixels the flow can serve;
4. weight maps: w2D, w3D of eqs. 5-6 (learned networks or constants);
5. solve: p* of eq. 4 by non-linear least squares on se(3) (objective of eq. 3, squared terms);
6. check: a pose that is not finite, implausibly large or supported by too few pixels fails.

The per-sequence state (which reference, when to filter, the last motion) belongs to the caller
(``slam.tracking.tracker.Tracker``).
"""
from __future__ import annotations

import dataclasses
import logging
import time
import weakref
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from vo.camera import StereoCamera
from vo.config import VOConfig
from vo.correspondence import make_flow_estimators, make_lr_check_flow
from vo.correspondence.dis import DisFlow, to_gray_u8
from vo.depth import (depth_from_parallax, filter_depth_along_flow, flow_consistency, parallax_from_depth,
                      round_trip_error, vertical_parallax_ok)
from vo.geometry import (backproject, flow_grid, lands_inside, motion_field, pixel_grid, sample_by_flow,
                         sample_valid_by_flow)
from vo.health import PoseFit, pose_fit, weighted_median
from vo.lie import rotation_angle_deg
from vo.residuals import PoseProblem, residuals
from vo.solver import TRACKING, SolverResult, solve_pose
from vo.weights import TrackingNetworks, WeightInputs, constant_weights, load_tracking_networks

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class View:
    """One view as the VO core uses it (batch of 1). Immutable: the read-ahead thread makes it
    while the main thread tracks another; filtering its depth makes a new one
    (:meth:`StereoOdometry.filter_depth`). Compared by identity.

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
        from_model: the view's depth is the map's, rendered at a pose (a model view).
        rendered: the view's image is the model's colour (it shows no highlights or
            instruments); False for a real frame and for a model view seen with a real frame's
            pixels.
        image_of: the real view whose image this one shows (a model view seen with the last
            frame's pixels), whose flows serve this view; else None.
        stereo_depth: the view's own stereo depth where ``depth`` holds it filtered along the
            flow (:meth:`StereoOdometry.filter_depth`), else None.
        base: the view this one was made from by filtering its depth (the same images), else
            None: flows computed for the one serve the other (:attr:`origin`).
    """

    image: torch.Tensor
    gray: np.ndarray
    depth: torch.Tensor
    valid: torch.Tensor
    parallax: torch.Tensor
    matchable: torch.Tensor | None = None
    masked: np.ndarray | None = None
    from_model: bool = False
    rendered: bool = False
    image_of: "View | None" = field(default=None, repr=False)
    stereo_depth: torch.Tensor | None = field(default=None, repr=False)
    base: "View | None" = field(default=None, repr=False)

    @property
    def origin(self) -> "View":
        """The view whose images these are (itself, or the view it was filtered from)."""
        return self.base if self.base is not None else self

    @property
    def unfiltered(self) -> "View":
        """This view with its own stereo depth (itself when it holds it)."""
        return self.base if self.stereo_depth is not None else self


class Correspondences(NamedTuple):
    """The temporal flow of a current view against another view (step 1).

    Attributes:
        flow: ``(1, 2, H, W)`` pixels, current -> other.
        ok: ``(1, 1, H, W)`` bool flows that passed the forward-backward check
            (``correspondence.fb_check_px``), or None (no check ran).
        round_trip: ``(1, 1, H, W)`` forward-backward disagreement ``|F(x) + B(x + F(x))|``
            (pixels) with ``B`` the flow back, or None (not computed): a tracking health figure.
        back_ms: the time the flow back and the round trip took (ms).
    """

    flow: torch.Tensor
    ok: torch.Tensor | None
    round_trip: torch.Tensor | None = None
    back_ms: float = 0.0


class AheadFlow(NamedTuple):
    """A temporal flow computed before it was needed (:meth:`StereoOdometry.flow_ahead`, in the
    read-ahead thread): ``corr`` of the current view against the real view ``against``."""

    against: View
    corr: Correspondences

    def serves(self, against: View) -> bool:
        """Whether it is the flow against ``against`` (the same images)."""
        return self.against.origin is against.origin


class ResidualProblem(NamedTuple):
    """What the residuals of eqs. 1-2 compare, per pixel of the current view (step 3).

    Attributes:
        target: ``(1, 2, H, W)`` pixels ``x + F_t(x)``, where eq. 1 wants the projection.
        valid: ``(1, 1, H, W)`` bool pixels with a 2D residual.
        valid3: ``(1, 1, H, W)`` bool pixels that also have a 3D residual (the flow lands on
            valid reference depth).
        points_ref: ``(1, 3, H, W)`` the reference's points at ``x + F_t(x)``, normalised by
            ``depth.max_depth_mm`` (eq. 2's ``pi_3D(D_{t-1}, x + F_t(x))``).
    """

    target: torch.Tensor
    valid: torch.Tensor
    valid3: torch.Tensor
    points_ref: torch.Tensor


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
        fit: the residuals left at the optimum and the objective's curvature
            (:class:`vo.health.PoseFit`: the pose covariance), None without a finite solution.
        support: the share of the current view's valid pixels that carry a weight.
        round_trip_px: the w2D-weighted median forward-backward disagreement of the temporal
            flow (pixels; nan where it was not computed).
        view: the current view as tracked (its depth filtered where it was).
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
    fit: PoseFit | None = None
    support: float = float("nan")
    round_trip_px: float = float("nan")
    view: View | None = None


def image_tensor(rgb: np.ndarray, device: str | torch.device = "cpu") -> torch.Tensor:
    """``(H, W, 3)`` uint8 RGB -> ``(1, 3, H, W)`` float32 in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(rgb)).to(device).permute(2, 0, 1)[None].float().div_(255.0)


class StereoOdometry:
    """The paper's VO: learned (or constant) per-pixel weights on 2D and 3D geometric residuals.

    Args:
        camera: the rectified stereo camera (all views share it).
        config: VO configuration.
        device: torch device.
        networks: weight networks to use in ``learned`` mode (loaded from the config's
            checkpoints when None).
    """

    def __init__(self, camera: StereoCamera, config: VOConfig, device: str = "cpu",
                 networks: TrackingNetworks | None = None):
        self.camera = camera
        self.config = config
        self.device = torch.device(device)
        self.K = camera.K_tensor(self.device)
        self.temporal_flow, self.stereo_flow = make_flow_estimators(config.correspondence, device)
        self.lr_check_flow = make_lr_check_flow(config.correspondence, self.stereo_flow, camera.width)
        self.networks: TrackingNetworks | None = None
        wcfg, dcfg = config.weights, config.depth
        if wcfg.mode == "learned":
            self.networks = networks.to(self.device) if networks is not None else load_tracking_networks(
                wcfg.checkpoint, wcfg.checkpoint_model, wcfg.residuals, dcfg.temporal_gain, dcfg.temporal_still_mm,
                device)
        elif wcfg.mode != "constant":
            raise ValueError(f"unknown weights.mode '{wcfg.mode}' (learned, constant)")
        self._ahead_flow_estimator = None   # the look-ahead thread's own temporal flow (flow_ahead)
        # a real frame's image with its masked pixels inpainted, for flows against a model view's
        # colour (the frame is flowed against the model in its tracking and refinement passes)
        self._flow_inputs: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

    # ---------------------------------------------------------------- views
    def _flow(self, estimator, a_img: torch.Tensor, a_gray: np.ndarray, b_img: torch.Tensor, b_gray: np.ndarray,
              start: torch.Tensor | None = None) -> torch.Tensor:
        if isinstance(estimator, DisFlow):
            f = estimator.flow_gray(a_gray, b_gray, None if start is None else start[0].permute(1, 2, 0).cpu().numpy())
            return torch.from_numpy(f).permute(2, 0, 1)[None].to(self.device)
        return estimator.flow(a_img, b_img, start)

    def make_view(self, left: np.ndarray, right: np.ndarray, mask: np.ndarray | None = None,
                  gt_depth: np.ndarray | None = None, timings: dict | None = None,
                  specular: np.ndarray | None = None) -> View:
        """A view from a rectified stereo pair.

        Args:
            left, right: ``(H, W, 3)`` uint8 RGB.
            mask: ``(H, W)`` bool valid tissue pixels, or None.
            gt_depth: ``(H, W)`` float depth in mm to use instead of stereo depth (error budget).
            specular: ``(2, H, W)`` bool specular highlights of the left and right views, or
                None; inpainted for the stereo match (``correspondence.inpaint_px``).
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
            if specular is not None and ccfg.inpaint_px > 0:
                need_image = not isinstance(self.stereo_flow, DisFlow)
                if specular[0].any():
                    st_l = inpaint_masked(img_l, gray_l, specular[0], ccfg.inpaint_px, need_image)
                if specular[1].any():
                    st_r = inpaint_masked(img_r, gray_r, specular[1], ccfg.inpaint_px, need_image)
            parallax = self._flow(self.stereo_flow, *st_l, *st_r)
            depth, valid = depth_from_parallax(parallax, fxb, dcfg, valid_mask)
            if specular is not None and ccfg.inpaint_px > 0 and specular[1].any():
                # a match that lands on the right view's highlight found no tissue there
                seen_r = torch.from_numpy(~np.asarray(specular[1], dtype=bool)).to(self.device)[None, None]
                valid &= sample_valid_by_flow(seen_r, parallax)
            if ccfg.max_vertical_parallax_px > 0:
                valid &= vertical_parallax_ok(parallax, ccfg.max_vertical_parallax_px)
            if ccfg.lr_check_px > 0:
                back = self._flow(self.lr_check_flow, *st_r, *st_l)
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
                    from_model=True, rendered=color is not None,
                    image_of=background if color is None else None)

    # ---------------------------------------------------------------- tracking
    def track(self, cur: View, ref: View, init: np.ndarray | None = None,
              filter_against: View | None = None, ahead: AheadFlow | None = None,
              seed: bool = False) -> TrackResult:
        """Estimate the transform from ``cur``'s camera to ``ref``'s camera.

        Args:
            cur: the current view (a real frame).
            ref: the reference view: a camera frame, or a model view (``ref.from_model``: weighed
                by the model-view networks, no robust 3D step).
            init: ``(4, 4)`` mm initial guess (identity when None).
            filter_against: the real frame before ``cur`` to filter ``cur``'s stereo depth
                against along the flow (:meth:`filter_depth`; it may be ``ref``, or the frame
                before ``cur`` when ``ref`` is an older keyframe); None: ``cur`` keeps its own
                stereo depth.
            ahead: ``cur``'s flow computed ahead (:meth:`flow_ahead`), taken where it goes against
                the view a flow is needed to.
            seed: the temporal flow to ``ref`` starts from the motion field of ``init`` (predict,
                then match what is left) instead of from scratch.
        """
        timings: dict = {}
        t0 = time.perf_counter()
        # 1. correspondences (the flow to the filter's frame, when that is not the reference, first)
        filter_corr = None
        if filter_against is not None and filter_against is not ref:
            filter_corr = self.correspondences(cur, filter_against, round_trip=False, ahead=ahead)
        corr = self.correspondences(cur, ref, ahead=ahead, motion=init if seed else None)
        back_ms = 0.0 if ahead is not None and corr is ahead.corr else corr.back_ms   # (timed in its thread)
        # 2. depth
        cur = self.filter_depth(cur, filter_against, corr if filter_corr is None else filter_corr)
        t1 = time.perf_counter()
        # 3. the residual problem (eqs. 1-2) and 4. the weight maps (eqs. 5-6)
        problem = self.residual_problem(cur, ref, corr)
        w2d, w3d = self.weight_maps(cur, ref, corr, problem)
        t2 = time.perf_counter()
        # 5. solve (eq. 4)
        result, n_valid, fit = self.solve(cur, problem, w2d, w3d, init, robust=not ref.from_model)
        t3 = time.perf_counter()
        # 6. check
        relative, reason = self.check(result, n_valid)
        timings.update(flow=(t1 - t0) * 1000.0 - back_ms, flow_back=back_ms, weights=(t2 - t1) * 1000.0,
                       solve=(t3 - t2) * 1000.0)
        n_cur = int(cur.valid.sum())
        fb = float("nan") if corr.round_trip is None else weighted_median(corr.round_trip.flatten(), w2d.flatten())
        return TrackResult(relative=relative, failed=bool(reason), reason=reason,
                           iterations=0 if result is None else result.iterations,
                           cost=float("nan") if result is None else float(result.cost[0]),
                           valid_pixels=n_valid, flow=corr.flow, w2d=w2d, w3d=w3d, timings_ms=timings,
                           fit=None if reason else fit, support=n_valid / n_cur if n_cur else 0.0,
                           round_trip_px=fb, view=cur)

    def correspondences(self, cur: View, against: View, round_trip: bool | None = None,
                        ahead: AheadFlow | None = None, motion: np.ndarray | None = None) -> Correspondences:
        """Step 1: the temporal flow ``cur -> against`` (against the real view whose pixels
        ``against`` shows, if any): ``ahead`` where it goes against that view, else computed now
        (from the motion field of ``motion``, ``(4, 4)`` mm ``cur -> against``, where one is
        given: the flow back from the inverse motion's); with ``round_trip`` (None:
        ``correspondence.round_trip``) its forward-backward disagreement (the flow the pose is
        solved on: a health figure), else the flow back only for ``correspondence.fb_check_px``."""
        shown = against.image_of if against.image_of is not None else against
        if motion is None and ahead is not None and ahead.serves(shown):
            return ahead.corr
        if round_trip is None:
            round_trip = self.config.correspondence.round_trip
        starts = None
        if motion is not None:
            starts = (motion_field(cur.depth, cur.valid, self.K, motion),
                      motion_field(against.depth, against.valid, self.K, np.linalg.inv(motion)))
        return self._pair_flow(self.temporal_flow, cur, shown, round_trip, starts)

    def filters_depth(self) -> bool:
        """Whether the depth filter is on (``depth.temporal_gain`` < 1)."""
        return self.config.depth.temporal_gain < 1.0

    def filter_depth(self, cur: View, against: View | None, corr: Correspondences) -> View:
        """Step 2: with ``against`` (a real frame before ``cur``) and the filter on, the view of
        ``cur`` whose depth is its stereo depth filtered along ``corr`` (``cur -> against``)
        against ``against``'s depth (:func:`vo.depth.filter_depth_along_flow`; the stereo depth
        kept in ``stereo_depth``); else ``cur`` with its own stereo depth. Filtering always starts
        from the stereo depth, never from a filtered one."""
        dcfg = self.config.depth
        cur = cur.unfiltered
        if against is None or not self.filters_depth():
            return cur
        if cur.from_model or against.from_model:
            raise ValueError("filter_depth: only between real frames (a model view's depth is fused already)")
        depth = filter_depth_along_flow(cur.depth, cur.valid, against.depth, against.valid, corr.flow,
                                        corr.ok, dcfg.temporal_gain, dcfg.temporal_gate_mm)
        return dataclasses.replace(cur, depth=depth, stereo_depth=cur.depth, base=cur)

    def residual_problem(self, cur: View, ref: View, corr: Correspondences) -> ResidualProblem:
        """Step 3: what the residuals of eqs. 1-2 compare, given the temporal flow (the pixels
        whose flow lands inside the reference, passed the checks and, for the 3D residual, lands
        on valid reference depth)."""
        flow = corr.flow
        _, _, H, W = flow.shape
        dmax = self.config.depth.max_depth_mm
        target = pixel_grid(H, W, flow.device, flow.dtype) + flow
        valid = cur.valid & lands_inside(flow, target)
        if corr.ok is not None:
            valid &= corr.ok
        grid = flow_grid(flow, target)      # one sampling grid for the three maps drawn by the flow
        if ref.matchable is not None:
            valid &= sample_valid_by_flow(ref.matchable, flow, grid)
        valid3 = valid & sample_valid_by_flow(ref.valid, flow, grid)
        points_ref = sample_by_flow(backproject(ref.depth / dmax, self.K), flow, grid=grid)
        return ResidualProblem(target, valid, valid3, points_ref)

    def weight_maps(self, cur: View, ref: View, corr: Correspondences,
                    problem: ResidualProblem) -> tuple[torch.Tensor, torch.Tensor]:
        """Step 4: the ``(1, 1, H, W)`` weight maps ``(w2d, w3d)`` of eqs. 5-6, zero where the
        residual does not exist (``w3d`` off ``problem.valid3``)."""
        wcfg = self.config.weights
        if self.networks is None:
            w2d, w3d = constant_weights(problem.valid, wcfg.w2d, wcfg.w3d, wcfg.residuals)
        else:
            networks = self.networks.select(model_reference=ref.from_model, filtered_depth=cur.stereo_depth is not None)
            dmax = self.config.depth.max_depth_mm
            inp = WeightInputs(image_cur=cur.image, depth_cur=cur.depth / dmax, flow=corr.flow,
                               parallax_cur=cur.parallax, image_ref=ref.image, depth_ref=ref.depth / dmax,
                               parallax_ref=ref.parallax, valid=problem.valid,
                               # (the reference's depth along the flow: its points' z, sampled already)
                               depth_ref_along_flow=problem.points_ref[:, 2:3], lands_on_ref_depth=problem.valid3)
            with torch.inference_mode():
                w2d, w3d = networks(inp)
        w3d = w3d * problem.valid3
        return w2d, w3d

    def solve(self, cur: View, problem: ResidualProblem, w2d: torch.Tensor, w3d: torch.Tensor,
              init: np.ndarray | None = None, robust: bool = True
              ) -> tuple[SolverResult | None, int, PoseFit | None]:
        """Step 5: ``p* = argmin sum w2D |e2D|^2 + w3D |e3D|^2`` (eq. 4) over at most
        ``solver.max_pixels`` of the weighted pixels, from ``init`` ``(4, 4)`` mm; with ``robust``
        and ``solver.robust_3d_mm`` one Cauchy-reweighted step on the 3D residual follows.

        Returns:
            the solver's result (None when fewer than ``solver.min_valid_pixels`` pixels carry a
            weight), the number of weighted pixels, and the optimum's fit to the problem it
            solved (:func:`vo.health.pose_fit`; None without a finite optimum).
        """
        scfg = self.config.solver
        dmax = self.config.depth.max_depth_mm
        points_cur = backproject(cur.depth / dmax, self.K)
        s2, s3 = PoseProblem.scales(*problem.target.shape[-2:])
        prob = PoseProblem(points_cur=points_cur.flatten(2), target_px=problem.target.flatten(2),
                           points_ref=problem.points_ref.flatten(2), w2d=w2d.flatten(1), w3d=w3d.flatten(1),
                           K=self.K[None], s2=s2, s3=s3)
        prob, n_valid = prob.compact(scfg.max_pixels)
        if n_valid < scfg.min_valid_pixels:
            return None, n_valid, None
        T0 = None
        if init is not None:
            T0 = torch.as_tensor(init, dtype=torch.float32, device=self.device).clone()
            T0[:3, 3] /= dmax
            T0 = T0[None]
        tol = dataclasses.replace(TRACKING, kernel=scfg.kernel)
        result = solve_pose(prob, scfg, T0, tol=tol)
        if robust and scfg.robust_3d_mm > 0 and bool(torch.isfinite(result.T).all()):
            prob = prob.with_weights(prob.w2d, prob.w3d * cauchy_weights_3d(prob, result.T, dmax, scfg.robust_3d_mm))
            result = solve_pose(prob, scfg, result.T, tol=tol)
        fit = pose_fit(prob, result.T, dmax) if bool(torch.isfinite(result.T).all()) else None
        return result, n_valid, fit

    def check(self, result: SolverResult | None, n_valid: int) -> tuple[np.ndarray, str]:
        """Step 6: the relative pose ``(4, 4)`` mm and '' if it can be trusted, else the identity
        and why not (too few pixels, not finite, implausible motion)."""
        if result is None:
            return np.eye(4), f"only {n_valid} valid pixels"
        scfg = self.config.solver
        T = result.T[0].double().cpu()
        if not bool(torch.isfinite(T).all()):
            return np.eye(4), "non-finite pose"
        dmax = self.config.depth.max_depth_mm
        trans_mm = float(T[:3, 3].norm()) * dmax
        rot_deg = float(rotation_angle_deg(T[None])[0])
        if trans_mm > scfg.max_translation_mm:
            return np.eye(4), f"implausible motion {trans_mm:.1f} mm"
        if rot_deg > scfg.max_rotation_deg:
            return np.eye(4), f"implausible rotation {rot_deg:.1f} deg"
        relative = T.numpy().copy()
        relative[:3, 3] *= dmax
        # the solver's rotation is orthonormal to float32 rounding only; projected onto SO(3), so that
        # thousands of chained poses stay rotations (evaluation rejects a drifting rotation part)
        relative[:3, :3] = Rotation.from_matrix(relative[:3, :3]).as_matrix()
        return relative, ""

    # ---------------------------------------------------------------- flows
    def _flow_input(self, view: View, against: View) -> tuple[torch.Tensor, np.ndarray]:
        """``view``'s image and grey image for a temporal flow to ``against``: a real frame's
        masked pixels inpainted when ``against`` is a model view's colour
        (``correspondence.inpaint_px``), else as they are."""
        radius = self.config.correspondence.inpaint_px
        if not against.rendered or view.rendered or view.masked is None or radius <= 0:
            return view.image, view.gray
        view = view.origin
        if view not in self._flow_inputs:
            self._flow_inputs[view] = inpaint_masked(view.image, view.gray, view.masked, radius,
                                                     need_image=not isinstance(self.temporal_flow, DisFlow))
        return self._flow_inputs[view]

    def _pair_flow(self, estimator, cur: View, against: View, round_trip: bool = False,
                   starts: tuple[torch.Tensor, torch.Tensor] | None = None) -> Correspondences:
        """The temporal flow ``cur -> against`` (from ``starts[0]``, where given); with
        ``round_trip`` or ``correspondence.fb_check_px`` the flow back (from ``starts[1]``) and
        their round-trip disagreement (a health figure) and, with the check, the ``(1, 1, H, W)``
        bool mask of flows that passed it (else None)."""
        start, start_back = (None, None) if starts is None else starts
        cur_img, cur_gray = self._flow_input(cur, against=against)
        flow = self._flow(estimator, cur_img, cur_gray, against.image, against.gray, start)
        fb_px = self.config.correspondence.fb_check_px
        if not round_trip and fb_px <= 0:
            return Correspondences(flow, None)
        t0 = time.perf_counter()
        back = self._flow(estimator, against.image, against.gray, cur_img, cur_gray, start_back)
        error = round_trip_error(flow, back)
        return Correspondences(flow, error < fb_px if fb_px > 0 else None, error,
                               (time.perf_counter() - t0) * 1000.0)

    def can_flow_ahead(self) -> bool:
        """Whether :meth:`flow_ahead` can run in another thread (a classical backend: a second
        estimator of the same settings; one RAFT model is not shared between threads)."""
        return self.config.correspondence.backend == "dis"

    def flow_ahead(self, cur: View, against: View) -> AheadFlow:
        """The temporal flow ``cur -> against`` computed now, with an estimator of its own (safe
        in a read-ahead thread while :meth:`track` runs in another): given to a later
        :meth:`track` or :meth:`correspondences` against ``against``, it is taken instead of
        computing it (same settings, same inputs: the same flow bit for bit). Both must be real
        frames."""
        if cur.from_model or against.from_model:
            raise ValueError("flow_ahead: only between real frames")
        if self._ahead_flow_estimator is None:
            self._ahead_flow_estimator = make_flow_estimators(self.config.correspondence, self.device)[0]
        return AheadFlow(against, self._pair_flow(self._ahead_flow_estimator, cur, against,
                                                  self.config.correspondence.round_trip))


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
