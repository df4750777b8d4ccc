"""Dense correspondence backends: temporal optical flow and stereo parallax flow."""
from __future__ import annotations

from vo.config import CorrespondenceConfig, lr_check_preset
from vo.correspondence.base import FlowEstimator
from vo.correspondence.dis import DisFlow


def make_flow_estimators(config: CorrespondenceConfig, device: str = "cpu") -> tuple[FlowEstimator, FlowEstimator]:
    """The temporal and the stereo flow estimators of ``config`` (they may be the same object)."""
    if config.backend == "dis":
        return (DisFlow(config.dis_preset, exposure=config.dis_match_exposure),
                DisFlow(config.dis_stereo_preset, exposure=config.dis_match_exposure))
    if config.backend == "raft":
        from vo.correspondence.raft_backend import RaftFlow

        raft = RaftFlow(config.raft_checkpoint or None, iters=config.raft_iters, device=device)
        return raft, raft
    raise ValueError(f"unknown correspondence.backend '{config.backend}' (dis, raft)")


def make_lr_check_flow(config: CorrespondenceConfig, stereo: FlowEstimator, width: int) -> FlowEstimator:
    """The estimator of the left-right check's flow back for images ``width`` px wide: DIS at
    ``dis_lr_check_preset`` (:func:`vo.config.lr_check_preset`; the stereo estimator itself where
    that is its preset, and with RAFT)."""
    preset = lr_check_preset(config.dis_lr_check_preset, width)
    if config.backend == "dis" and preset != config.dis_stereo_preset:
        return DisFlow(preset, exposure=config.dis_match_exposure)
    return stereo


__all__ = ["FlowEstimator", "DisFlow", "make_flow_estimators", "make_lr_check_flow"]
