"""``slam train``: learn the weight networks end to end through the pose optimum (paper Sec. 2.2).

Data: sequences with ground truth (by default the project's own synthetic sequences, generated
on first use into the cache), pairs 1..``max_gap`` frames apart balanced between moving and
static camera, split 80/20 into training and validation by sequence (the validation loss is then
taken on tissue and motion the networks have not seen) or by pair. For each pair the correspondences and
the network inputs are computed once and cached: the weight networks' inputs at 1/``downscale``
resolution, and the pose problem at ``pixels_per_pair`` randomly drawn valid pixels (the weight
maps are smooth, so their bilinear upsampling evaluated at those pixels is exact and training
needs no full-resolution tensors).

Loss: L1 between the declarative layer's optimum p* and the ground-truth relative pose in se(3),
translation in the solver's normalised units (eq. 7). Adam, early stopping on the validation loss.
Under ``torchrun`` with several processes the networks are wrapped in DistributedDataParallel
and each rank takes its share of every epoch's batches (standard torch.distributed API).
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import random
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from mapping import MapConfig
from slam.app.frame_view import frame_view
from slam.app.progress import on_terminal
from slam.config import AnalysisConfig
from slam.errors import ConfigError, DataError, SlamError
from slam.io.rectification import original_to_rect_pose
from slam.synth.appearance import appearance_tag, parse_appearance
from slam.synth.generate import SCENARIOS
from vo.config import CorrespondenceConfig, DepthConfig, SolverConfig, VOConfig, WeightsConfig
from vo.ddn import declarative_pose
from vo.geometry import backproject
from vo.lie import se3_exp, se3_log
from vo.odometry import StereoOdometry, View
from vo.residuals import PoseProblem
from vo.weights import (IN_CHANNELS, INPUT_VERSION, WeightInputs, WeightNetworks, load_weight_networks,
                        network_inputs, sample_weights)

log = logging.getLogger("slam.train")


@dataclass
class TrainDataConfig:
    """Where the training pairs come from.

    Attributes:
        scenarios, seeds: synthetic sequences generated for training (every scenario x seed).
            Keep these seeds apart from every evaluation seed (tools/benchmark_scenarios.py).
        frames: frames per synthetic sequence.
        width, height: image size of training (and of the checkpoint's intended use).
        sequences: extra folders with ground truth (any supported layout).
        cache_dir: generated sequences and cached pairs.
        pairs_per_sequence: pairs drawn per sequence.
        max_gap: pairs are 1..max_gap frames apart.
        moving_threshold_mm, moving_threshold_deg: a pair whose ground-truth motion exceeds either
            is "moving", else "static"; the two classes are balanced.
        pixels_per_pair: pose-problem pixels kept per pair.
        breathing_follows_tissue: passed to the generator (correlation of the breathing amplitude
            with the tissue's look; 0 = independent).
        appearance: how the synthetic sequences look (``slam synth --appearance``): empty for the
            generator's own look, ``random`` for one look per sequence drawn from the ranges of
            :func:`slam.synth.appearance.random_appearance` (texture from rich to nearly none,
            highlights, smoke, exposure changes, vignetting, tissue colour) with the seed
            :func:`appearance_seed` of its scenario and seed, or ``KEY=VALUE,...`` for one look.
        reference: what a pair's reference view is: ``frame`` (the camera frame, as in
            frame2frame) or ``model`` (the surfel map fused from the frames up to the reference
            frame at their ground-truth poses, rendered at the reference frame's pose, as
            frame2model tracks against; trains the networks of ``weights.checkpoint_model``).
        min_model_coverage: ``model``: a pair whose render covers less of the reference frame's
            valid pixels is left out (tracking falls back to the previous frame there).
        workers: processes that render the missing synthetic sequences at once (``slam.batch``'s
            local workers; 0: one per core, 1: in this process).
        chain_length: 1: independent pairs (eq. 7 per pair). ``L > 1``: the pairs come in chains of
            ``L`` consecutive frame pairs (one frame apart, as frame2frame tracks) and the loss of
            eq. 7 is taken on the chain's composed pose: the per-pair loss weighs each pair's
            noise, while what makes a trajectory drift is the bias that consecutive pairs share
            (breathing, a push), which grows ``L`` times along a chain and the noise only
            ``sqrt(L)`` times. Every consecutive pair of a sequence is cached; each epoch draws
            ``pairs_per_sequence // L`` chains per training sequence afresh (random starts, so
            the chains differ from epoch to epoch: a fixed set of a few hundred chains is learnt
            by heart within a few epochs; not balanced by camera motion: the scenarios are, moving
            in rigid, scanning and loop, still in breathing and deforming); validation takes each sequence's chains end to end
            from its first frame (fixed). ``optim.batch_size`` still counts pairs (``batch_size //
            L`` chains, at least one, per step).
    """

    scenarios: list = field(default_factory=lambda: ["rigid", "breathing", "scanning", "deforming", "loop"])
    seeds: list = field(default_factory=lambda: [1000, 1001, 1002, 1003])
    frames: int = 80
    width: int = 320
    height: int = 256
    sequences: list = field(default_factory=list)
    cache_dir: str = "cache/train"
    pairs_per_sequence: int = 60
    max_gap: int = 5
    moving_threshold_mm: float = 0.1
    moving_threshold_deg: float = 0.1
    pixels_per_pair: int = 4096
    breathing_follows_tissue: float = 0.0
    appearance: str = ""
    reference: Literal["frame", "model"] = "frame"
    min_model_coverage: float = 0.95
    chain_length: int = 1
    workers: int = 0


@dataclass
class OptimConfig:
    """Optimisation.

    Attributes:
        epochs: maximum epochs.
        batch_size: pairs per step.
        lr: Adam learning rate.
        patience: epochs without validation improvement before stopping.
        val_fraction: share held out for validation.
        split: ``sequence`` holds out whole sequences (that share of each scenario's sequences,
            so the validation loss measures tissue, breathing and motion the networks have not
            seen; falls back to ``pair`` when no scenario has two sequences) or ``pair`` (that
            share of all pairs, drawn from the training sequences themselves).
        seed: seeds sampling, splitting, initialisation and shuffling.
        grad_tol: the forward pass must reach |grad f| / f below this to contribute a gradient.
        threads: torch threads (0 = torch's default).
        init: a checkpoint to start from instead of a random initialisation (fine-tuning, e.g. on
            other data or another reference kind); its residuals, input layout, width and
            downscale must be the config's.
    """

    epochs: int = 40
    batch_size: int = 8
    lr: float = 3e-4
    patience: int = 6
    val_fraction: float = 0.2
    split: Literal["sequence", "pair"] = "sequence"
    seed: int = 0
    grad_tol: float = 1e-3
    threads: int = 0
    init: str = ""


@dataclass
class TrainConfig:
    """Everything ``slam train`` needs."""

    residuals: Literal["2d3d", "2d", "3d"] = "2d3d"
    downscale: int = 8
    base: int = 16
    # the networks' input layout (vo.weights.network_inputs); 1 reproduces the shipped 3D checkpoint
    inputs: int = INPUT_VERSION
    data: TrainDataConfig = field(default_factory=TrainDataConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    correspondence: CorrespondenceConfig = field(default_factory=CorrespondenceConfig)
    # each frame's own stereo depth unless told otherwise (``--set depth.temporal_gain=0.05`` trains
    # the networks tracking uses on a still camera's filtered depth; docs/training.md)
    depth: DepthConfig = field(default_factory=lambda: DepthConfig(temporal_gain=1.0, temporal_still_mm=0.0))
    map: MapConfig = field(default_factory=MapConfig)    # the model references' map (data.reference: model)
    # the declarative layer's forward solve (its tolerance: vo.solver.DECLARATIVE)
    solver: SolverConfig = field(default_factory=lambda: SolverConfig(max_iters=25))
    # what the analysis tools switch (slam.config.AnalysisConfig): the generator's exact depth
    # (depth_source), the inpainting and exposure matching of the shipped 3D checkpoint's recipe
    analysis: AnalysisConfig = field(default_factory=AnalysisConfig)


def load_train_config(path: str | Path, overrides: list[str] | None = None) -> TrainConfig:
    """Defaults, then the YAML file, then ``key=value`` overrides, validated like the run config."""
    from slam.config import REMOVED, apply_analysis, override_tree, read_yaml
    from slam.schema import parse_into, rebuild

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: training config not found")
    cfg = TrainConfig()
    parse_into(cfg, read_yaml(path), str(path), REMOVED)
    for item in overrides or []:
        parse_into(cfg, override_tree(item), "--set", REMOVED)
    cfg = rebuild(cfg)
    apply_analysis(cfg)
    try:
        parse_appearance(cfg.data.appearance, 0)
    except DataError as err:
        raise ConfigError(f"{path}: data.appearance: {err}") from None
    if not isinstance(cfg.data.chain_length, int) or cfg.data.chain_length < 1:
        raise ConfigError(f"{path}: 'data.chain_length' must be a whole number >= 1")
    if cfg.data.chain_length > 1 and cfg.data.reference != "frame":
        raise ConfigError(f"{path}: 'data.chain_length' > 1 needs 'data.reference: frame' (frame2frame chains)")
    if cfg.inputs not in IN_CHANNELS:
        raise ConfigError(f"{path}: 'inputs' must be one of {', '.join(map(str, IN_CHANNELS))} (weight-network input versions)")
    if cfg.optim.init:
        check_init_checkpoint(cfg, path)
    return cfg


# ------------------------------------------------------------------------------------- data
def training_sequences(cfg: TrainConfig, progress: bool = True) -> list[Path]:
    """The training sequence folders, rendering the missing synthetic ones into the cache (in
    ``data.workers`` processes on the batch engine, ``slam.batch.synth``)."""
    from slam.batch.runner import BatchOptions
    from slam.batch.synth import synthesize_or_fail
    from slam.batch.tasks import SynthTask
    from slam.synth import generate

    root = Path(cfg.data.cache_dir) / "sequences"
    look = cfg.data.appearance.strip()
    follows = cfg.data.breathing_follows_tissue
    tag = (f"_ft{follows:g}" if follows else "") + appearance_tag(look)
    tasks = [SynthTask(out_dir=str(root / f"{scenario}_s{seed}_{cfg.data.width}x{cfg.data.height}_n{cfg.data.frames}{tag}"),
                       scenario=scenario, seed=seed, frames=cfg.data.frames, size=(cfg.data.width, cfg.data.height),
                       appearance=look, appearance_seed=appearance_seed(scenario, seed), breathing_follows_tissue=follows)
             for scenario in cfg.data.scenarios for seed in cfg.data.seeds]
    missing = [t for t in tasks if not t.is_done()]
    if cfg.data.workers == 1 or len(missing) == 1:
        for t in missing:
            log.info("generating %s", t.out_dir)
            generate(t.out_dir, t.scenario, frames=t.frames, size=t.size, seed=t.seed, progress=progress,
                     breathing_follows_tissue=follows, appearance=t.look())
    elif missing:
        log.info("generating %d training sequences in %s", len(missing), root)
        synthesize_or_fail(missing, BatchOptions(executor="local", workers=cfg.data.workers, progress=progress))
    return [Path(t.out_dir) for t in tasks] + [Path(p) for p in cfg.data.sequences]


def appearance_seed(scenario: str, seed: int) -> int:
    """The seed of a training sequence's random look: its own seed, offset per scenario so that the
    scenarios of one seed look different (``slam synth --appearance random --seed`` this value
    draws the same look)."""
    return SCENARIOS.index(scenario) * 100_000 + int(seed)


def relative_rect_transform(gt: np.ndarray, R1: np.ndarray, i: int, j: int) -> np.ndarray:
    """Ground-truth transform from rectified camera j to rectified camera i (mm)."""
    M = np.eye(4)
    M[:3, :3] = R1
    return M @ np.linalg.inv(gt[i]) @ gt[j] @ M.T


def sample_pairs(gt: np.ndarray, R1: np.ndarray, cfg: TrainDataConfig, rng: random.Random) -> list[tuple[int, int, bool]]:
    """Draw ``(reference i, current j, moving)`` pairs balanced between moving and static camera."""
    moving, static = [], []
    for i in range(len(gt)):
        for gap in range(1, cfg.max_gap + 1):
            j = i + gap
            if j >= len(gt):
                break
            T = relative_rect_transform(gt, R1, i, j)
            angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
            is_moving = np.linalg.norm(T[:3, 3]) > cfg.moving_threshold_mm or angle > cfg.moving_threshold_deg
            (moving if is_moving else static).append((i, j, is_moving))
    n = cfg.pairs_per_sequence
    if moving and static:
        picks = rng.sample(moving, min(n // 2, len(moving))) + rng.sample(static, min(n - n // 2, len(static)))
    else:
        pool = moving or static
        picks = rng.sample(pool, min(n, len(pool)))
    return sorted(picks)


def chain_runs(samples: list[dict]) -> list[list[int]]:
    """Indices of ``samples`` that are consecutive frame pairs (``chain_length`` > 1 samples carry
    their sequence ``seq`` and reference frame ``link``), grouped into runs of unbroken
    succession (a pair left out for too few valid pixels, or held out, breaks a run)."""
    by_seq: dict[str, list[int]] = {}
    for k, smp in enumerate(samples):
        by_seq.setdefault(smp["seq"], []).append(k)
    runs = []
    for idx in by_seq.values():
        idx.sort(key=lambda k: samples[k]["link"])
        run = [idx[0]]
        for k in idx[1:]:
            if samples[k]["link"] == samples[run[-1]]["link"] + 1:
                run.append(k)
            else:
                runs.append(run)
                run = [k]
        runs.append(run)
    return runs


def chains_of(samples: list[dict], length: int) -> list[list[int]]:
    """The fixed chains of ``samples`` (validation): each run of consecutive pairs cut into
    chains of ``length`` links end to end from its start (a shorter rest is left out).
    ``length`` 1: every sample alone, in order."""
    if length == 1:
        return [[k] for k in range(len(samples))]
    return [run[a:a + length] for run in chain_runs(samples) for a in range(0, len(run) - length + 1, length)]


def draw_chains(samples: list[dict], length: int, per_sequence: int, rng: random.Random) -> list[list[int]]:
    """``per_sequence`` chains of ``length`` consecutive pairs per sequence with random starts
    (chains may overlap), in the order drawn (training: a fresh draw every epoch)."""
    by_seq: dict[str, list[list[int]]] = {}
    for run in chain_runs(samples):
        by_seq.setdefault(samples[run[0]]["seq"], []).extend(run[a:a + length] for a in range(len(run) - length + 1))
    chains = []
    for seq in sorted(by_seq):
        candidates = by_seq[seq]
        chains.extend(rng.sample(candidates, min(per_sequence, len(candidates))))
    return chains


def chain_pose_loss(p: torch.Tensor, p_gt: torch.Tensor, ok: torch.Tensor, length: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 7 on chains: ``|log(T_1 ... T_L) - log(T_1^gt ... T_L^gt)|_1`` per chain; for
    ``length`` 1 eq. 7 per pair, ``|p* - p_gt|_1`` (the pair recipe, computed as such).

    Args:
        p, p_gt: ``(C * length, 6)`` solved and true poses of the links (current -> reference,
            translation normalised), chain by chain in link order.
        ok: ``(C * length,)`` links whose forward pass reached a minimum.
    Returns:
        per-chain loss ``(C,)`` and ``(C,)`` bool chains whose every link is ok.
    """
    if length == 1:
        return (p - p_gt).abs().sum(1), ok
    C = p.shape[0] // length
    ok_chain = ok.view(C, length).all(1)
    p = torch.where(ok[:, None], p, p_gt.to(p.dtype))        # a failed link: no value, no gradient
    T = se3_exp(p.double()).view(C, length, 4, 4)
    T_gt = se3_exp(p_gt.double()).view(C, length, 4, 4)
    est, gt = T[:, 0], T_gt[:, 0]
    for k in range(1, length):
        est, gt = est @ T[:, k], gt @ T_gt[:, k]
    return (se3_log(est) - se3_log(gt)).abs().sum(1), ok_chain


def _cache_key(cfg: TrainConfig, path: Path) -> str:
    """What the samples of one sequence depend on (not on which other sequences are trained)."""
    data = asdict(cfg.data)
    for name in ("breathing_follows_tissue", "appearance", "scenarios", "seeds", "sequences", "cache_dir", "workers"):
        data.pop(name)  # the sequence itself is named by its path (the coupling is in the folder name)
    data.pop("chain_length")    # ("pairs" below marks the caches of every consecutive pair)
    if cfg.data.reference == "frame":
        for name in ("reference", "min_model_coverage"):
            data.pop(name)
    depth = asdict(cfg.depth)
    depth.pop("temporal_still_mm")      # the pair cache filters every frame (tracking decides per frame)
    depth["source"] = cfg.analysis.depth_source
    if cfg.depth.temporal_gain >= 1.0:
        for name in ("temporal_gain", "temporal_gate_mm"):
            depth.pop(name)
    relevant = {"seq": str(path.resolve()), "data": data, "corr": asdict(cfg.correspondence),
                "depth": depth, "downscale": cfg.downscale, "seed": cfg.optim.seed, "v": 3,
                "inputs": cfg.inputs}
    if cfg.data.reference == "model":
        relevant["map"] = asdict(cfg.map)
    if cfg.data.chain_length > 1:
        relevant["pairs"] = "consecutive"     # every consecutive pair, whatever the chain length (drawn in training)
    return hashlib.sha1(json.dumps(relevant, sort_keys=True).encode()).hexdigest()[:12]


def build_pair_samples(path: Path, cfg: TrainConfig) -> list[dict]:
    """Compute (or load from the cache) the samples of one sequence (seeded by the training seed
    and the sequence's name, so a cached and a fresh run draw the same pairs)."""
    rng = random.Random(f"{cfg.optim.seed}:{path.name}")
    from slam.io.datasets import DataConfig, open_dataset

    cache = Path(cfg.data.cache_dir) / "pairs" / f"{path.name}_{_cache_key(cfg, path)}.pt"
    if cache.is_file():
        return torch.load(cache, weights_only=False)
    dataset = open_dataset(path, DataConfig(width=cfg.data.width, height=cfg.data.height))
    if dataset.gt_poses is None:
        raise SlamError(f"{path}: training needs ground truth (groundtruth.txt)")
    vo_cfg = VOConfig(correspondence=cfg.correspondence, depth=cfg.depth, solver=cfg.solver,
                      weights=WeightsConfig(mode="constant"))
    odo = StereoOdometry(dataset.camera, vo_cfg)
    dmax = cfg.depth.max_depth_mm
    H, W = dataset.camera.height, dataset.camera.width
    views: dict[int, object] = {}
    last_filtered: list = [-1, None]    # frames made in order (the filter): the last one, its view

    def view(k):
        if k not in views:
            if cfg.depth.temporal_gain < 1.0:
                # each frame filtered against the one before it, as tracking with every frame does
                m, prev = last_filtered
                if k <= m:
                    raise AssertionError(f"{path}: frame {k} asked for after frame {m} (pairs are sorted)")
                for n in range(m + 1, k + 1):
                    v = frame_view(odo, dataset.frame(n), path, depth_source=cfg.analysis.depth_source)
                    if prev is not None:
                        v = odo.filter_depth(v, prev, odo.correspondences(v, prev, round_trip=False))
                    views[n] = prev = v
                last_filtered[:] = [k, prev]
            else:
                views[k] = frame_view(odo, dataset.frame(k), path, depth_source=cfg.analysis.depth_source)
        return views[k]

    model = ModelReference(cfg, odo, dataset) if cfg.data.reference == "model" else None
    samples = []
    g = torch.Generator().manual_seed(rng.randrange(2**31))
    chained = cfg.data.chain_length > 1     # every consecutive pair: chains are drawn from them per epoch
    pairs = ([(i, i + 1, None) for i in range(len(dataset.gt_poses) - 1)] if chained else
             sample_pairs(dataset.gt_poses, dataset.R1, cfg.data, rng))
    for i, j, moving in pairs:
        cur = view(j)
        ref = model.view_at(i, view) if model is not None else view(i)
        if ref is None:
            continue
        corr = odo.correspondences(cur, ref, round_trip=False)    # as tracking computes them
        target, valid, valid3, points_ref = odo.residual_problem(cur, ref, corr)
        _, x3 = network_inputs(WeightInputs(cur.image, cur.depth / dmax, corr.flow, cur.parallax,
                                            ref.image, ref.depth / dmax, ref.parallax, valid),
                               cfg.downscale, cfg.inputs)
        idx = valid.flatten().nonzero().squeeze(1)
        n = cfg.data.pixels_per_pair
        if idx.numel() < 64:
            continue
        idx = idx[torch.randperm(idx.numel(), generator=g)[:n]]
        pad = n - idx.numel()
        keep = torch.ones(n, dtype=torch.bool)
        if pad > 0:
            keep[idx.numel():] = False
            idx = torch.cat([idx, idx[:1].expand(pad)])
        pts = backproject(cur.depth / dmax, odo.K).flatten(2)[0][:, idx]
        T = torch.as_tensor(relative_rect_transform(dataset.gt_poses, dataset.R1, i, j))
        T[:3, 3] /= dmax
        pix = torch.stack([idx % W, idx // W]).float()
        samples.append({
            "x3": x3[0].half(),
            "pix": pix,
            "points_cur": pts.float(),
            "target": target.flatten(2)[0][:, idx].float(),
            "points_ref": points_ref.flatten(2)[0][:, idx].float(),
            "valid2": keep & valid.flatten()[idx],
            "valid3": keep & valid3.flatten()[idx],
            "p_gt": se3_log(T[None])[0].float(),
            "K": odo.K.float(),
            "size": (H, W),
            "moving": moving,
            "source": f"{path.name}:{i}->{j}",
        } | ({"seq": path.name, "link": i} if chained else {}))
        for k in [k for k in views if k < i]:
            del views[k]  # pairs are sorted by i: earlier views are not needed again
    cache.parent.mkdir(parents=True, exist_ok=True)
    # written aside and renamed: two trainings sharing the cache (2d3d and 2d side by side) must
    # never read a half-written file
    tmp = cache.with_name(f"{cache.name}.{os.getpid()}.tmp")
    torch.save(samples, tmp)
    tmp.replace(cache)
    return samples


class ModelReference:
    """The references of frame2model for one sequence: a surfel map fused from its frames at their
    ground-truth poses (each frame with the same weight: the learned fusion weight tracking uses
    is not there yet), rendered at a frame's pose and made a view as tracking makes it.

    Args:
        cfg: the training config (``map``, ``data.min_model_coverage``).
        odo: the odometry the views come from.
        dataset: the sequence (with ground truth).
    """

    def __init__(self, cfg: TrainConfig, odo: StereoOdometry, dataset):
        from mapping import SurfelMap
        from slam.tracking.map_fusion import FusionExposure

        self.cfg, self.odo = cfg, odo
        self.map = SurfelMap(cfg.map)
        self.exposure = FusionExposure()
        self.poses = torch.as_tensor(original_to_rect_pose(dataset.gt_poses, dataset.R1), dtype=torch.float32)
        self.size = (dataset.camera.height, dataset.camera.width)
        self.fused = -1
        self.last: tuple[int, View | None] | None = None   # (frame, its model view): pairs share references

    def view_at(self, i: int, view) -> View | None:
        """The model view at frame ``i``'s pose after fusing frames ``0..i`` (``view(k)`` gives frame
        ``k``'s view; ``i`` must not decrease between calls), or None where the render covers
        less than ``data.min_model_coverage`` of frame ``i``'s valid pixels."""
        from slam.tracking.references import model_coverage

        if self.last is not None and self.last[0] == i:
            return self.last[1]     # the map has not changed since: the same render
        frame = view(i)
        mv = self._render(i, view)
        ref = None
        if model_coverage(mv.valid, frame.valid[0, 0]) >= self.cfg.data.min_model_coverage:
            mv.with_colour()
            ref = self.odo.view_from_render(mv.color, mv.depth, mv.valid, background=frame)
        self.last = (i, ref)
        return ref

    def _render(self, i: int, view):
        while self.fused < i:
            k = self.fused + 1
            v = view(k)
            self.map.fuse(v.depth[0, 0], self.exposure.colour(v), self.odo.K, self.poses[k], frame_index=k,
                          valid=v.valid[0, 0])
            self.fused = k
        return self.map.render(self.odo.K, self.poses[i], *self.size, colour=False)


def collate(samples: list[dict]) -> dict:
    out = {k: torch.stack([s[k] for s in samples]) for k in
           ("x3", "pix", "points_cur", "target", "points_ref", "valid2", "valid3", "p_gt", "K")}
    out["x3"] = out["x3"].float()
    out["size"] = samples[0]["size"]
    return out


def training_data(cfg: TrainConfig, progress: bool = True) -> tuple[list[Path], list[dict], list[dict]]:
    """Sequences, training samples and validation samples (deterministic by ``optim.seed``)."""
    from tqdm import tqdm

    rng = random.Random(cfg.optim.seed)
    sequences = training_sequences(cfg, progress=progress)
    per_sequence = [build_pair_samples(path, cfg)
                    for path in tqdm(sequences, desc="pairs", disable=not (progress and on_terminal()), leave=False)]
    samples = [s for seq in per_sequence for s in seq]
    if len(samples) < 2:
        raise SlamError("training: fewer than 2 usable pairs")
    held_out = held_out_sequences(cfg, len(sequences), rng) if cfg.optim.split == "sequence" else set()
    if held_out and any(per_sequence[k] for k in held_out) and any(
            per_sequence[k] for k in range(len(sequences)) if k not in held_out):
        train_set = [s for k, seq in enumerate(per_sequence) if k not in held_out for s in seq]
        val = [s for k in sorted(held_out) for s in per_sequence[k]]
        log.info("validation: %d held-out sequences (%s)", len(held_out),
                 ", ".join(sequences[k].name for k in sorted(held_out)))
        return sequences, train_set, val
    if cfg.optim.split == "sequence":
        log.warning("validation: no scenario has two sequences to hold one out; validating on a share of "
                    "the pairs of the training sequences")
    units = chains_of(samples, cfg.data.chain_length)    # whole chains (single pairs when chain_length is 1)
    order = list(range(len(units)))
    rng.shuffle(order)
    n_val = max(1, int(round(cfg.optim.val_fraction * len(units))))
    return (sequences, [samples[m] for k in order[n_val:] for m in units[k]],
            [samples[m] for k in order[:n_val] for m in units[k]])


def sequence_name(sample: dict) -> str:
    """The name of the sequence a pair sample was drawn from (its ``source`` is ``NAME:i->j``)."""
    return sample["source"].rsplit(":", 1)[0]


def scenario_of(sample: dict) -> str:
    """The scenario a pair comes from: its sequence folder's name up to the first underscore
    (``SCENARIO_sSEED_WxH_nN`` for the synthetic sequences)."""
    return sequence_name(sample).split("_")[0]


def by_scenario(samples: list[dict]) -> dict[str, list[dict]]:
    """``samples`` grouped by :func:`scenario_of`, in order of first appearance."""
    groups: dict[str, list[dict]] = {}
    for s in samples:
        groups.setdefault(scenario_of(s), []).append(s)
    return groups


def held_out_sequences(cfg: TrainConfig, n_sequences: int, rng: random.Random) -> set[int]:
    """Indices (into ``training_sequences``) of the validation sequences: in every scenario, the
    ``val_fraction`` share of its seeds (rounded; none when it has one), drawn by ``rng``; of the
    extra ``data.sequences`` likewise, as one group."""
    n_seeds = len(cfg.data.seeds)
    groups = [list(range(k * n_seeds, (k + 1) * n_seeds)) for k in range(len(cfg.data.scenarios))]
    groups.append(list(range(len(cfg.data.scenarios) * n_seeds, n_sequences)))
    held: set[int] = set()
    for group in groups:
        if len(group) >= 2:
            n = int(round(cfg.optim.val_fraction * len(group)))
            held.update(rng.sample(group, min(max(n, 1), len(group) - 1)))
    return held


# ------------------------------------------------------------------------------------- model
def pose_from_batch(nets: WeightNetworks, batch: dict, cfg: TrainConfig, n2d: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights from the networks, then the declarative pose: ``(p* (B, 6), ok (B,))``.
    ``n2d``: channels of the 2D network's input (default: the networks' own)."""
    H, W = batch["size"]
    x3 = batch["x3"]
    module = nets.module if hasattr(nets, "module") else nets
    n2d = module.in_channels_2d if n2d is None else n2d
    w2_low, w3_low = module.low_res(x3[:, :n2d], x3)
    w2 = sample_weights(w2_low, batch["pix"], H, W) * batch["valid2"]
    w3 = sample_weights(w3_low, batch["pix"], H, W) * batch["valid3"]
    s2, s3 = PoseProblem.scales(H, W)
    prob = PoseProblem(batch["points_cur"], batch["target"], batch["points_ref"], w2, w3, batch["K"], s2, s3)
    return declarative_pose(w2, w3, prob, cfg.solver, cfg.optim.grad_tol)


def evaluate_loss(nets, samples: list[dict], cfg: TrainConfig, n2d: int | None = None,
                  constant: tuple[float, float] | None = None) -> tuple[float, int]:
    """Mean L1 pose loss over ``samples`` (over their chains, ``data.chain_length`` > 1) and the
    number of failed forward passes (chains), with the networks' weights or, when ``constant =
    (w2d, w3d)`` is given, constant weights."""
    total, count, failed = 0.0, 0, 0
    L = cfg.data.chain_length
    chains = chains_of(samples, L)
    bs = max(1, cfg.optim.batch_size // L)      # chains per batch (pairs when L = 1)
    with torch.no_grad():
        for k in range(0, len(chains), bs):
            batch = collate([samples[m] for chain in chains[k:k + bs] for m in chain])
            if constant is not None:
                H, W = batch["size"]
                s2, s3 = PoseProblem.scales(H, W)
                w2 = batch["valid2"].float() * (constant[0] if cfg.residuals != "3d" else 0.0)
                w3 = batch["valid3"].float() * (constant[1] if cfg.residuals != "2d" else 0.0)
                prob = PoseProblem(batch["points_cur"], batch["target"], batch["points_ref"], w2, w3, batch["K"], s2, s3)
                p, ok = declarative_pose(w2, w3, prob, cfg.solver, cfg.optim.grad_tol)
            else:
                p, ok = pose_from_batch(nets, batch, cfg, n2d)
            per, ok = chain_pose_loss(p, batch["p_gt"], ok, L)
            total += float((per * ok).sum())
            count += int(ok.sum())
            failed += int((~ok).sum())
    return total / max(count, 1), failed


def train(cfg: TrainConfig, out_dir: str | Path, progress: bool = True) -> Path:
    """Run the training; returns the path of the best checkpoint."""
    from tqdm import tqdm

    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    if world > 1:
        import torch.distributed as dist

        dist.init_process_group(backend="nccl" if torch.cuda.is_available() else "gloo")
    if cfg.optim.threads > 0:
        torch.set_num_threads(cfg.optim.threads)
    random.seed(cfg.optim.seed)
    torch.manual_seed(cfg.optim.seed)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    sequences, train_set, val = training_data(cfg, progress=progress and rank == 0)
    val_sequences = sorted({sequence_name(s) for s in val} - {sequence_name(s) for s in train_set})  # held out whole

    nets = initial_networks(cfg)
    model = nets
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel

        model = DistributedDataParallel(nets)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.optim.lr)

    baseline, _ = evaluate_loss(nets, val, cfg, constant=(1.0, 1.0))
    best_val, _ = evaluate_loss(nets, val, cfg)
    best_state = {k: v.clone() for k, v in nets.state_dict().items()}
    best_epoch, stale = 0, 0
    history = [{"epoch": 0, "val": best_val}]
    bar = tqdm(range(1, cfg.optim.epochs + 1), desc=f"train {cfg.residuals}",
               disable=not (progress and on_terminal()) or rank != 0)
    bar.set_postfix(val=f"{best_val:.5f}", const=f"{baseline:.5f}")
    t0 = time.time()
    L = cfg.data.chain_length
    chains = chains_of(train_set, L)
    per_step = max(1, cfg.optim.batch_size // L)      # chains per step (pairs when L = 1)
    for epoch in bar:
        nets.train()
        if L > 1:   # fresh chains every epoch
            chains = draw_chains(train_set, L, max(1, cfg.data.pairs_per_sequence // L),
                                 random.Random(f"{cfg.optim.seed}:chains:{epoch}"))
        perm = list(range(len(chains)))
        random.Random(cfg.optim.seed + epoch).shuffle(perm)
        perm = perm[rank::world]
        losses, failed = [], 0
        for k in range(0, len(perm), per_step):
            idx = [m for c in perm[k:k + per_step] for m in chains[c]]
            batch = collate([train_set[m] for m in idx])
            p, ok = pose_from_batch(model, batch, cfg)
            per, ok = chain_pose_loss(p, batch["p_gt"], ok, L)  # eq. 7 per pair, or per chain
            failed += int((~ok).sum())
            loss = (per * ok).sum() / ok.sum().clamp(min=1)     # mean over the successful pairs / chains
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
        nets.eval()
        val_loss, val_failed = evaluate_loss(nets, val, cfg)
        history.append({"epoch": epoch, "train": float(np.mean(losses)), "val": val_loss,
                        "train_failed": failed, "val_failed": val_failed})
        bar.set_postfix(train=f"{np.mean(losses):.5f}", val=f"{val_loss:.5f}", const=f"{baseline:.5f}")
        if val_loss < best_val:
            best_val, best_epoch, stale = val_loss, epoch, 0
            best_state = {k: v.clone() for k, v in nets.state_dict().items()}
            if rank == 0:  # an interrupted training keeps its best checkpoint
                save_checkpoint(out_dir / f"weights_{cfg.residuals}.pt", cfg, best_state, sequences, len(train_set),
                                len(val), best_epoch, best_val, baseline, history, t0, final=False,
                                val_sequences=val_sequences)
        else:
            stale += 1
            if stale >= cfg.optim.patience:
                break
    ckpt_path = out_dir / f"weights_{cfg.residuals}.pt"
    if rank == 0:
        save_checkpoint(ckpt_path, cfg, best_state, sequences, len(train_set), len(val), best_epoch, best_val,
                        baseline, history, t0, final=True, val_sequences=val_sequences)
        print(f"best validation loss {best_val:.5f} at epoch {best_epoch} (constant weights w=1: {baseline:.5f}); "
              f"checkpoint {ckpt_path}")
    if world > 1:
        import torch.distributed as dist

        dist.destroy_process_group()
    return ckpt_path


def check_init_checkpoint(cfg: TrainConfig, config_path: Path) -> None:
    """Raise :class:`ConfigError` unless ``optim.init`` is a checkpoint of the config's layout."""
    path = Path(cfg.optim.init)
    if not path.is_file():
        raise ConfigError(f"{config_path}: optim.init checkpoint {path} not found")
    meta = torch.load(path, map_location="cpu", weights_only=False).get("meta", {})
    theirs = {"residuals": meta.get("residuals"), "inputs": int(meta.get("inputs", 1)),
              "base": int(meta.get("base", 16)), "downscale": int(meta.get("downscale", 8))}
    ours = {"residuals": cfg.residuals, "inputs": cfg.inputs, "base": cfg.base, "downscale": cfg.downscale}
    if theirs != ours:
        diff = ", ".join(f"{k} {theirs[k]} (config: {ours[k]})" for k in ours if theirs[k] != ours[k])
        raise ConfigError(f"{path}: optim.init checkpoint has another layout: {diff}")


def initial_networks(cfg: TrainConfig) -> WeightNetworks:
    """Networks of the config's layout (checked by :func:`load_train_config`): randomly initialised
    (seeded by the caller) or, with ``optim.init``, the weights of that checkpoint."""
    nets = WeightNetworks(downscale=cfg.downscale, residuals=cfg.residuals, base=cfg.base, inputs=cfg.inputs)
    if cfg.optim.init:
        nets.load_state_dict(load_weight_networks(cfg.optim.init, cfg.residuals)[0].state_dict())
    return nets


def save_checkpoint(path: Path, cfg: TrainConfig, state: dict, sequences: list, n_train: int, n_val: int,
                    best_epoch: int, best_val: float, baseline: float, history: list, t0: float, final: bool,
                    val_sequences: list | None = None) -> None:
    """Write the weights with everything needed to reproduce and use them. ``val_sequences``: the
    names of the sequences held out whole for validation (empty when pairs were split)."""
    meta = {
        "residuals": cfg.residuals, "reference": cfg.data.reference, "downscale": cfg.downscale, "base": cfg.base,
        "inputs": cfg.inputs,
        "correspondence": asdict(cfg.correspondence), "image_size": [cfg.data.width, cfg.data.height],
        "max_depth_mm": cfg.depth.max_depth_mm, "train_config": asdict(cfg),
        "data": {"sequences": [str(p) for p in sequences], "pairs_train": n_train, "pairs_val": n_val,
                 "validation_sequences": list(val_sequences or [])},
        "best_epoch": best_epoch, "val_loss": best_val, "val_loss_constant_w1": baseline,
        "history": history, "minutes": (time.time() - t0) / 60.0, "finished": final,
    }
    tmp = path.with_suffix(".tmp")
    torch.save({"state_dict": state, "meta": meta}, tmp)
    tmp.replace(path)
    (path.parent / f"train_log_{cfg.residuals}.json").write_text(json.dumps(meta, indent=2, default=str))


def train_from_config(config_path: str | Path, out: str | Path | None, overrides: list[str] | None = None,
                      progress: bool = True) -> Path:
    cfg = load_train_config(config_path, overrides)
    return train(cfg, out or Path("runs") / "train", progress=progress)
