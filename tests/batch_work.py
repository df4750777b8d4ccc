"""Worker functions for the executor tests (imported by name in the worker processes, so they
live in a module of their own, not in a test file)."""
from __future__ import annotations

import ctypes
import os
import time


def work(payload, report):
    """``("ok", v)`` returns v; ``("crash", _)`` segfaults; ``("raise", _)`` raises;
    ``("sleep", n)`` reports a frame a tenth of a second for n tenths, returning what it did
    when interrupted."""
    kind, value = payload
    if kind == "crash":
        ctypes.string_at(0)
    if kind == "raise":
        raise ValueError("a bad\nsequence")
    if kind == "sleep":
        done = 0
        try:
            for done in range(1, value + 1):
                time.sleep(0.1)
                report("frames", done)
        except KeyboardInterrupt:
            return {"status": "interrupted", "frames": done}
        return {"status": "ok", "frames": done}
    return {"status": "ok", "value": value, "pid": os.getpid(), "omp": os.environ.get("OMP_NUM_THREADS"),
            "nice": os.nice(0)}
