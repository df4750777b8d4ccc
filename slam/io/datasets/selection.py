"""Frame selection: which frames of a sequence are processed.

``parse_frames(spec, n)`` turns a user's spec into frame indices:

* ``None`` or ``""``: all frames;
* ``N`` (int or ``"N"``): the first N frames (all of them if the sequence is shorter);
* ``"A:B"`` / ``"A:B:S"``: Python slice semantics over ``range(n)`` (any part may be empty,
  negative values count from the end), e.g. ``"2:8:2"`` -> 2, 4, 6; ``"::5"`` every 5th frame;
* segments joined by commas, in time order: ``"0:100:5,100:180:20,180::5"`` every 5th frame with
  every 20th from 100 to 180 (a stretch of faster motion).

A spec that is malformed, has a zero or negative step, selects nothing, or whose segments overlap
or go back in time raises ConfigError.
"""
from __future__ import annotations

from slam.errors import ConfigError


def parse_frames(spec: str | int | None, n: int) -> list[int]:
    """Frame indices selected by ``spec`` out of ``n`` frames (see the module docstring)."""
    n = int(n)
    if spec is None:
        return list(range(n))
    if isinstance(spec, bool):
        raise ConfigError(f"frames: expected a count or 'start:stop:step', got {spec!r}")
    if isinstance(spec, int):
        if spec <= 0:
            raise ConfigError(f"frames: the number of frames must be positive, got {spec}")
        return list(range(min(spec, n)))
    text = str(spec).strip()
    if not text:
        return list(range(n))
    if "," in text:
        return _segments(text, n)
    if ":" not in text:
        try:
            count = int(text)
        except ValueError:
            raise ConfigError(f"frames: expected a count or 'start:stop:step', got '{text}'") from None
        return parse_frames(count, n)
    parts = text.split(":")
    if len(parts) > 3:
        raise ConfigError(f"frames: expected 'start:stop:step', got '{text}'")
    values: list[int | None] = []
    for part in parts:
        part = part.strip()
        if not part:
            values.append(None)
            continue
        try:
            values.append(int(part))
        except ValueError:
            raise ConfigError(f"frames: '{part}' in '{text}' is not an integer") from None
    while len(values) < 3:
        values.append(None)
    start, stop, step = values
    if step is not None and step <= 0:
        raise ConfigError(f"frames: the step must be positive, got {step} in '{text}'")
    indices = list(range(n))[slice(start, stop, step)]
    if not indices:
        raise ConfigError(f"frames: '{text}' selects no frames of the {n} in the sequence")
    return indices


def _segments(text: str, n: int) -> list[int]:
    """The frames of comma-separated segments, each a spec of its own, strictly in time order."""
    indices: list[int] = []
    for part in text.split(","):
        if not part.strip():
            raise ConfigError(f"frames: an empty segment in '{text}'")
        segment = parse_frames(part.strip(), n)
        if indices and segment[0] <= indices[-1]:
            raise ConfigError(f"frames: segment '{part.strip()}' in '{text}' starts at frame {segment[0]}, "
                              f"not after the last one selected ({indices[-1]})")
        indices += segment
    return indices
