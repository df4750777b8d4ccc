"""What the benchmarks share to run the pipeline: synthetic sequences rendered once, the pipeline
on one torch thread, worker processes that share the cores, and the table they print and write."""
from __future__ import annotations

import json
import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path


def synthetic(path: str | Path, scenario: str, **options) -> Path:
    """The synthetic sequence of ``scenario`` in ``path``, rendered with ``slam.synth.generate``
    (keyword ``options``: frames, size, seed, appearance, ...) unless it is there already and
    finished (a generation interrupted half-way is rendered again)."""
    from slam.synth.writer import is_finished

    path = Path(path)
    if not is_finished(path):
        from slam.synth import generate

        generate(path, scenario, **options)
    return path


def one_thread_config(overrides: list[str], extra: list[str] = ()):
    """The config of ``overrides``, ``threads=1`` (one torch thread during the run) and then
    ``extra`` (a benchmark's ``--set``)."""
    from slam.config import load_config

    return load_config(None, [*overrides, "threads=1", *extra])


def pipeline(config, data: str | Path, out: str | Path, logger=None, frames: str | None = None):
    """The pipeline of ``config`` on the sequence ``data`` (read as ``config.data`` says; ``frames``:
    the selection of ``--frames``, e.g. ``::5``), writing to ``out``; ``.run(progress=False)`` runs it."""
    from slam.app.pipeline import Pipeline
    from slam.io.datasets import open_dataset

    dataset = open_dataset(Path(data), config.data)
    return Pipeline(config, dataset.select(frames) if frames else dataset, Path(out), logger=logger)


def _one_torch_thread() -> None:
    import torch

    torch.set_num_threads(1)


def run_in_workers(function, jobs: list, workers: int) -> list:
    """``[function(job) for job in jobs]`` in ``workers`` fresh (spawned) processes with one torch
    thread each (the workers share the cores); ``function`` is a module-level function."""
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_one_torch_thread) as pool:
        return list(pool.map(function, jobs))


def write_report(out: str | Path, name: str, table: str, data, indent: int = 2) -> None:
    """Print ``table`` and write it to ``out/NAME.md``, and ``data`` to ``out/NAME.json``."""
    print(table)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.md").write_text(table + "\n")
    (out / f"{name}.json").write_text(json.dumps(data, indent=indent))
