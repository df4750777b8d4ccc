"""``slam synth``: synthetic stereo-endoscopy sequences with ground truth (StereoMIS layouts).

Modules: ``scene`` (tissue height field + albedo, via ``texture`` and ``noise``), ``camera_paths``
(trajectories), ``deformation`` (breathing, indentation), ``instrument``, ``cameras`` (rectified and
raw stereo rigs), ``render`` (ray casting), ``shading`` (light and sensor), ``writer`` (file layout),
``generate`` (the entry point).
"""
from slam.synth.generate import SCENARIOS, VERSION, generate

__all__ = ["generate", "SCENARIOS", "VERSION"]
