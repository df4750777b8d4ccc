"""The loss of eq. 7 of weight-network checkpoints on a training config's validation pairs, per
scenario: compares checkpoints on the same held-out pairs (e.g. which network should weigh model
views, ``configs/train_model.yaml``), with constant weights w = 1 as the reference row.

    .venv/bin/python tools/validation_loss.py --config configs/train_model.yaml \\
        --checkpoints vo/checkpoints/weights_2d3d_model.pt runs/trainX/weights_2d3d.pt [--set KEY=VALUE] [--out DIR]

The validation pairs are those ``slam train`` holds out with the same config and overrides (the
pair cache is shared). Prints a markdown table and writes ``validation_loss.{md,json}`` to ``--out``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from slam.errors import SlamError
from slam.training.trainer import by_scenario, evaluate_loss, load_train_config, training_data
from vo.weights import load_weight_networks


def losses(nets, samples: list[dict], cfg, constant: tuple[float, float] | None = None) -> dict:
    """``{"all": loss, SCENARIO: loss, ...}`` (mean L1 pose loss over the pairs whose solve succeeded)."""
    groups = {"all": samples} | by_scenario(samples)
    return {name: evaluate_loss(nets, group, cfg, constant=constant)[0] for name, group in groups.items()}


def parse_constant(text: str) -> tuple[float, float]:
    """``"W2D,W3D"`` -> ``(w2d, w3d)``; a one-line :class:`SlamError` otherwise."""
    try:
        w2, w3 = (float(v) for v in text.split(","))
    except ValueError:
        raise SlamError(f"--constants: expected W2D,W3D (e.g. 1,0.01), got {text!r}") from None
    if min(w2, w3) < 0 or max(w2, w3) <= 0:
        raise SlamError(f"--constants: {text!r}: weights must be non-negative and not both 0")
    return w2, w3


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", required=True)
    ap.add_argument("--checkpoints", nargs="+", required=True)
    ap.add_argument("--constants", nargs="*", default=[], metavar="W2D,W3D",
                    help="extra rows of constant weights, e.g. 1,0.01 (the default config's balance)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    try:
        constants = [parse_constant(c) for c in args.constants]
        cfg = load_train_config(args.config, args.set)
        if cfg.optim.threads > 0:
            torch.set_num_threads(cfg.optim.threads)
        _, _, val = training_data(cfg, progress=False)
        rows = {"w = 1": losses(None, val, cfg, constant=(1.0, 1.0))}
        for w2, w3 in constants:
            rows[f"w2D = {w2:g}, w3D = {w3:g}"] = losses(None, val, cfg, constant=(w2, w3))
        for path in args.checkpoints:
            if not Path(path).is_file():
                raise SlamError(f"{path}: checkpoint not found")
            nets, _ = load_weight_networks(path, cfg.residuals)     # (in eval mode)
            rows[path] = losses(nets, val, cfg)
    except SlamError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    names = [n for n in rows["w = 1"] if n != "all"]
    lines = [f"| checkpoint ({len(val)} validation pairs) | all | {' | '.join(names)} |",
             "|---|" + "---|" * (len(names) + 1)]
    for label, row in rows.items():
        lines.append(f"| {label} | {row['all']:.5f} | " + " | ".join(f"{row[n]:.5f}" for n in names) + " |")
    table = "\n".join(lines)
    print(table)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "validation_loss.md").write_text(table + "\n")
        (out / "validation_loss.json").write_text(json.dumps({"config": args.config, "overrides": args.set,
                                                              "pairs": len(val), "loss": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
