"""Poses of the rectified left camera, ``T_wc`` ``(4, 4)`` float64 numpy arrays in mm: the few
operations the tracking layer composes them with, named.

``T_wc`` maps camera coordinates to world coordinates; a relative pose ``T_ab = T_wa^-1 T_wb``
maps frame ``b``'s camera coordinates to frame ``a``'s (the VO core's ``relative``: current to
reference).
"""
from __future__ import annotations

import numpy as np

IDENTITY = np.eye(4)


def relative(T_wa: np.ndarray, T_wb: np.ndarray) -> np.ndarray:
    """``T_ab = T_wa^-1 T_wb``: frame ``b``'s pose seen from frame ``a``."""
    return np.linalg.inv(T_wa) @ T_wb


def translation_mm(T: np.ndarray) -> float:
    """The length of ``T``'s translation (mm)."""
    return float(np.linalg.norm(T[:3, 3]))


def moved_less_than(T_ab: np.ndarray, still_mm: float) -> bool:
    """Whether the motion ``T_ab`` translated the camera less than ``still_mm`` (always True
    when that is 0 or less: no threshold)."""
    return still_mm <= 0 or translation_mm(T_ab) < still_mm
