"""The tracking regression reference: short synthetic runs in the default config whose poses
``tests/test_regression.py`` compares with the current code's (every pose within 1e-3 mm, every
ATE within 0.5 %: float sums reorder across machines and thread counts).

    .venv/bin/python tools/record_regression.py [--out tests/fixtures/regression_reference.json]

A change that alters tracking on purpose re-records the reference in the same commit and says
why in its message. The runs cover each path the default config takes: a still camera (a
keyframe and the filtered depth), a moving camera (the paper's previous-frame reference),
frame2model against the map, and a refinement pass against the model.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.runs import one_thread_config, pipeline, synthetic

SIZE = (160, 128)
SEED = 4242
FRAMES = 20
# name -> (scenario, config overrides)
RUNS = {
    "breathing_frame2frame": ("breathing", []),
    "scanning_frame2frame": ("scanning", []),
    "scanning_frame2model": ("scanning", ["tracking.mode=frame2model"]),
    "rigid_frame2model_refined": ("rigid", ["tracking.mode=frame2model", "tracking.refine_passes=1"]),
}
DEFAULT_OUT = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "regression_reference.json"


def sequence(root: Path, scenario: str) -> Path:
    """The synthetic sequence of ``scenario`` (written under ``root`` on first use)."""
    return synthetic(root / f"{scenario}_s{SEED}", scenario, frames=FRAMES, size=SIZE, seed=SEED, progress=False)


def run(name: str, root: Path) -> dict:
    """Run ``name`` of :data:`RUNS` on one torch thread: ``poses`` ``(N, 4, 4)`` mm (left camera to
    world) and ``ate_rmse_mm``."""
    scenario, overrides = RUNS[name]
    result = pipeline(one_thread_config(overrides), sequence(root, scenario), root / "runs" / name).run(progress=False)
    return {"poses": np.stack([r.pose for r in result.records]), "ate_rmse_mm": result.metrics["ate_rmse_mm"],
            "failed_frames": result.metrics["failed_frames"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    reference = {"size": list(SIZE), "seed": SEED, "frames": FRAMES, "runs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for name in RUNS:
            out = run(name, Path(tmp))
            reference["runs"][name] = {"poses": out["poses"].round(9).tolist(), "ate_rmse_mm": out["ate_rmse_mm"],
                                       "failed_frames": out["failed_frames"]}
            print(f"{name}: ATE {out['ate_rmse_mm']:.4f} mm, {len(out['poses'])} poses", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(reference, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
