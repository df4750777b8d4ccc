"""RAFT optical flow (Teed and Deng, ECCV 2020), written for this project in pure torch.

``RAFT(small=False)`` / ``RAFT(small=True)`` load the published ``raft-things.pth`` / ``raft-small.pth``
state dicts unchanged (after stripping DataParallel's ``module.`` prefix); see
:mod:`vo.correspondence.raft_backend` for the ready-to-use flow estimator.
"""
from .corr import CorrBlock, all_pairs_correlation, bilinear_sampler, coords_grid
from .extractor import BasicEncoder, SmallEncoder
from .model import RAFT, convex_upsample, upflow8
from .update import BasicUpdateBlock, SmallUpdateBlock

__all__ = [
    "RAFT",
    "BasicEncoder",
    "SmallEncoder",
    "BasicUpdateBlock",
    "SmallUpdateBlock",
    "CorrBlock",
    "all_pairs_correlation",
    "bilinear_sampler",
    "coords_grid",
    "convex_upsample",
    "upflow8",
]
