"""``slam run``: open the dataset, build the pipeline and logger, run, print a summary."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from slam.config import SlamConfig
from slam.pipeline import Pipeline, RunResult


def default_out_dir(data: str | Path, mode: str) -> Path:
    path = Path(data).resolve()
    return Path("runs") / f"{path.stem if path.is_file() else path.name}_{mode}"


def make_logger(config: SlamConfig, dataset):
    """A rerun logger when asked for, else None (rerun is then not imported at all)."""
    if not (config.logging.rerun or config.logging.spawn):
        return None
    from slam.rerun_log import RerunLogger

    return RerunLogger(config.logging, dataset.camera, name=dataset.path.name,
                       gt_poses=dataset.gt_poses, R1=dataset.R1)


def run_from_config(data: str | Path, config: SlamConfig, out: str | Path | None = None,
                    frames: str | None = None, print_summary: bool = True,
                    on_frame: Callable[[int], None] | None = None) -> RunResult:
    """Run one sequence end to end with a resolved config; ``metrics.json`` records the run's
    provenance (``slam.provenance``). ``on_frame``: see ``Pipeline.run``."""
    from slam.datasets import open_dataset
    from slam.provenance import provenance

    dataset = open_dataset(Path(data), config.data)
    if frames:
        dataset = dataset.select(frames)
    out_dir = Path(out) if out else default_out_dir(data, config.tracking.mode)
    logger = make_logger(config, dataset)
    pipeline = Pipeline(config, dataset, out_dir, logger=logger, provenance=provenance(config, frames))
    result = pipeline.run(progress=config.logging.progress, on_frame=on_frame)
    if print_summary:
        print(summary_text(result))
    return result


def summary_text(result: RunResult) -> str:
    m = result.metrics
    lines = [f"{'interrupted after' if result.interrupted else 'processed'} {m['frames']} frames "
             f"({m.get('mode')}), {len(m['failed_frames'])} failed, {len(m.get('flagged_frames', []))} flagged, "
             f"{m['fps']:.1f} fps"]
    if "ate_rmse_mm" in m:
        lines.append(f"ATE-RMSE {m['ate_rmse_mm']:.3f} mm | RPE-trans {m['rpe_trans_mm']:.3f} ± {m['rpe_trans_std_mm']:.3f} mm"
                     f" | RPE-rot {m['rpe_rot_deg']:.4f} ± {m['rpe_rot_std_deg']:.4f} deg")
    if m.get("map_points"):
        lines.append(f"map: {m['map_points']} points")
    lines.append("outputs: " + ", ".join(f"{k}={v}" for k, v in result.files.items()))
    return "\n".join(lines)
