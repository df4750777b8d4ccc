"""Many synthetic sequences on the batch engine (``slam synth`` with several scenarios or seeds,
``slam train``'s training and validation sets): one task per sequence, run where ``slam
evaluate``'s tasks run; a sequence already rendered with the same parameters is kept."""
from __future__ import annotations

from slam.batch.runner import BatchOptions, run_batch
from slam.batch.tasks import SynthTask
from slam.errors import ConfigError, DataError


def parse_seeds(items: list[str]) -> list[int]:
    """Seeds from ``N`` and ``A-B`` (inclusive) items, in the order given."""
    seeds: list[int] = []
    for item in items:
        text = str(item).strip()
        try:
            if "-" in text.lstrip("-"):
                a, b = text.split("-", 1)
                lo, hi = int(a), int(b)
                if hi < lo:
                    raise ValueError
                seeds += range(lo, hi + 1)
            else:
                seeds.append(int(text))
        except ValueError:
            raise ConfigError(f"--seed {text}: expected N or A-B (A <= B)") from None
    if any(s < 0 for s in seeds):
        raise ConfigError("--seed: seeds are >= 0")
    return list(dict.fromkeys(seeds))


def synthesize(tasks: list[SynthTask], options: BatchOptions) -> tuple[dict, bool]:
    """Render the sequences of ``tasks`` that are not there yet; returns ``{label: outcome}`` of
    those that ran (``status`` ``ok`` | ``error`` | ...) and whether it was interrupted."""
    options.validate()
    todo = [t for t in tasks if options.force or not t.is_done()]
    todo.sort(key=lambda t: -t.frames * t.size[0] * t.size[1])
    if not todo:
        return {}, False

    def describe(k: int, outcome: dict) -> str:
        t = todo[k]
        if outcome.get("status") != "ok":
            return f"{t.label}: {outcome.get('status', 'error').upper()} {outcome.get('message', '')}"
        return f"{t.label}: {t.frames} frames ({t.scenario}, seed {t.seed}) in {outcome.get('seconds', 0):.1f} s"

    outcomes, interrupted, _ = run_batch(todo, options, describe)
    return {todo[k].label: o for k, o in outcomes.items()}, interrupted


def synthesize_or_fail(tasks: list[SynthTask], options: BatchOptions) -> None:
    """:func:`synthesize`, raising a DataError naming the first sequence that failed."""
    outcomes, interrupted = synthesize(tasks, options)
    if interrupted:
        raise KeyboardInterrupt
    failed = [(label, o) for label, o in outcomes.items() if o.get("status") != "ok"]
    if failed:
        label, o = failed[0]
        raise DataError(f"{label}: {o.get('message', o.get('status'))}"
                        + (f" (and {len(failed) - 1} more)" if len(failed) > 1 else ""))
