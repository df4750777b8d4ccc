"""Whether a stereo pair looks like one: sub-pixel matches between the views, the vertical
disparity a rectified pair must not have, the sign its disparities must have, and the likely cause
when a frame's views give no depth.

A rectified pair's matches lie on one row (vertical disparity 0) and the left view's features lie
to the right of the right view's (positive disparity ``d``, depth ``fx * baseline / d``). These
figures tell apart what people's inputs get wrong: a calibration of other images (vertical
disparity), left and right swapped (negative disparities), a baseline in metres (depths a thousand
times too small), masks that leave nothing (no valid pixel).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slam.errors import DataError

#: a rectified pair's matches lie on one row: below this median |dy| (pixels) the views are row-aligned
ROW_ALIGNED_PX = 0.5
#: above this median |dy| (pixels, at the frames' output size) a rectified pair is refused: the
#: calibration does not describe these frames (made for other images, or a crop of them); a
#: calibration of the frames gives 0.2-0.3 px on the synthetic raw rigs, a crop calibrated without
#: moving its principal points 1.4 px at 256x192 (5 times that at 1280x960)
MAX_VERTICAL_PX = 1.0
#: fewer matches than this say nothing about a pair (textureless, dark, unreadable)
MIN_MATCHES = 20
#: below this share of valid pixels a frame's masks leave (nearly) nothing to track
MIN_VALID_SHARE = 0.01


@dataclass
class Disparities:
    """Stereo matches of one pair: how many, median |vertical disparity|, the share of negative
    horizontal disparities and the median horizontal disparity (px)."""

    matches: int
    vertical_px: float
    negative_share: float
    median_px: float

    def line(self) -> str:
        if self.matches == 0:
            return "no feature matches"
        return (f"{self.matches} matches, median |dy| {self.vertical_px:.2f} px, median disparity "
                f"{self.median_px:.1f} px, {100 * self.negative_share:.0f} % negative")


def disparities(left: np.ndarray, right: np.ndarray, max_corners: int = 800) -> Disparities:
    """Sub-pixel stereo matches between two ``(H, W, 3)`` uint8 RGB views: corners of the left view
    (Shi-Tomasi) followed into the right one with pyramidal Lucas-Kanade and back; a match whose
    round trip misses by over 0.5 px is dropped."""
    gl, gr = (cv2.cvtColor(v, cv2.COLOR_RGB2GRAY) for v in (left, right))
    corners = cv2.goodFeaturesToTrack(gl, max_corners, 0.01, 5)
    if corners is None or len(corners) < 2:
        return Disparities(0, float("nan"), float("nan"), float("nan"))
    lk = dict(winSize=(21, 21), maxLevel=4, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 0.01))
    ahead, ok1, _ = cv2.calcOpticalFlowPyrLK(gl, gr, corners, None, **lk)
    back, ok2, _ = cv2.calcOpticalFlowPyrLK(gr, gl, ahead, None, **lk)
    good = (ok1[:, 0] == 1) & (ok2[:, 0] == 1) & (np.linalg.norm((back - corners)[:, 0], axis=1) < 0.5)
    if not good.any():
        return Disparities(0, float("nan"), float("nan"), float("nan"))
    pl, pr = corners[good, 0], ahead[good, 0]
    dx, dy = pl[:, 0] - pr[:, 0], pl[:, 1] - pr[:, 1]
    return Disparities(int(len(dx)), float(np.median(np.abs(dy))), float(np.mean(dx < 0)), float(np.median(dx)))


def check_rectified_rows(left: np.ndarray, right: np.ndarray, where: str, rectified_here: bool,
                         frame: str = "the first frame") -> Disparities:
    """The disparities of a pair as the pipeline gets it (``(H, W, 3)`` uint8 RGB, rectified or
    taken as rectified); DataError naming ``where`` (the calibration) and ``frame`` when, over at
    least :data:`MIN_MATCHES` matches, its median vertical disparity is above
    :data:`MAX_VERTICAL_PX` (a calibration of other images, or views that are not a pair) or most
    of its disparities are negative (left and right swapped)."""
    found = disparities(left, right)
    if found.matches < MIN_MATCHES:
        return found
    how = "after rectification" if rectified_here else "taken as rectified"
    if found.vertical_px > MAX_VERTICAL_PX:
        raise DataError(f"{where}: {frame}'s views keep a vertical disparity of {found.vertical_px:.1f} px {how} "
                        f"(median over {found.matches} matches; a calibration of these frames leaves at most "
                        f"{MAX_VERTICAL_PX:g} px): the calibration does not fit them (made for other images, or a crop "
                        "of them without its principal points moved), or the views are not a pair; slam inspect "
                        "shows them")
    if found.negative_share > 0.5:
        raise DataError(f"{where}: {100 * found.negative_share:.0f} % of {frame}'s stereo matches have a negative "
                        f"disparity {how}: the left and right views are swapped (or T has the wrong sign)")
    return found


def likely_cause(left: np.ndarray, right: np.ndarray, valid: np.ndarray, fx_px: float, baseline_mm: float,
                 depth_range_mm: tuple[float, float]) -> str:
    """Why a frame's views give too few valid pixels, said with the figure that tells it: masks
    that leave nothing (the share of valid pixels), left and right swapped (negative disparities)
    or mispaired (vertical disparities), a baseline in metres or micrometres (the stereo depth
    outside ``depth_range_mm``). '' when none of these shows.

    Args:
        left, right: ``(H, W, 3)`` uint8 RGB rectified views.
        valid: ``(H, W)`` bool, the frame's valid pixels (instrument masks, highlights, dark).
        fx_px, baseline_mm: the rectified camera's focal length and baseline (depth =
            ``fx_px * baseline_mm / disparity``).
        depth_range_mm: ``(near, far)`` depths the tracking uses (``depth.min_depth_mm``,
            ``depth.max_depth_mm``).
    """
    share = float(np.mean(valid))
    if share < MIN_VALID_SHARE:
        return (f"only {100 * share:.1f} % of the frame's pixels are valid: are its masks empty (non-zero = "
                "tissue), or the frame dark or saturated?")
    found = disparities(left, right)
    if found.matches < MIN_MATCHES:
        return ""
    if found.negative_share > 0.5:
        return (f"{100 * found.negative_share:.0f} % of the stereo matches have a negative disparity: are the left "
                "and right views swapped?")
    if found.vertical_px > MAX_VERTICAL_PX:
        return (f"the views' matches are {found.vertical_px:.1f} px apart vertically (median): are the views "
                "mispaired (frames of different times), or the calibration not theirs?")
    depth = fx_px * baseline_mm / found.median_px if found.median_px > 0 else float("inf")
    near, far = depth_range_mm
    if depth < near:
        return (f"the stereo depth is {depth:.3g} mm (median), nearer than the {near:g} mm tracked: is the "
                f"calibration's baseline ({baseline_mm:.3g}) in metres? calibrations are in mm")
    if depth > far:
        return (f"the stereo depth is {depth:.3g} mm (median), farther than the {far:g} mm tracked: is the "
                f"calibration's baseline ({baseline_mm:.3g}) in micrometres, or its focal length not the frames'?")
    return ""
