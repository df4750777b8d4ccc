"""Progress a person can read: a bar on a terminal, a line now and then in a log file.

On a terminal (standard error is a TTY) :class:`Progress` draws a tqdm bar and routes the
project's log records around it, so a warning gets a line of its own instead of being glued onto
the bar. Redirected to a file it prints one plain line every tenth of the way (at least every
``max_every`` items), never carriage returns. Disabled (``--quiet``) it prints nothing.
"""
from __future__ import annotations

import contextlib
import sys
import time


def on_terminal() -> bool:
    """Whether standard error is a terminal (bars there; plain lines elsewhere)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


class Progress:
    """Progress over ``total`` items; use as a context manager, :meth:`update` after each item.

    Args:
        total: the number of items.
        desc: what is counted, e.g. ``track`` (the line's prefix).
        unit: the item's name, e.g. ``frame``.
        enabled: False prints nothing.
        max_every: the longest stretch of items between two lines off a terminal.
    """

    def __init__(self, total: int, desc: str, unit: str = "frame", enabled: bool = True, max_every: int = 500):
        self.total = int(total)
        self.desc = desc
        self.unit = unit
        self.enabled = bool(enabled)
        self.every = max(1, min(max_every, -(-self.total // 10)))
        self.done = 0
        self._bar = None
        self._stack = contextlib.ExitStack()
        self._t0 = time.perf_counter()

    def __enter__(self) -> "Progress":
        self._t0 = time.perf_counter()
        if self.enabled and on_terminal():
            from tqdm import tqdm
            from tqdm.contrib.logging import logging_redirect_tqdm

            self._bar = tqdm(total=self.total, desc=self.desc, unit=self.unit, dynamic_ncols=True, leave=False)
            self._stack.enter_context(logging_redirect_tqdm())   # the console handler writes around the bar
        return self

    def update(self, n: int = 1, **postfix) -> None:
        """``n`` more items done; ``postfix`` figures (e.g. ``fps=...``) shown beside the count."""
        self.done += n
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.update(n)
            if postfix:
                self._bar.set_postfix(**postfix)
            return
        if self.done % self.every == 0 or self.done == self.total:
            rate = self.done / max(time.perf_counter() - self._t0, 1e-9)
            figures = ", ".join(f"{k} {v}" for k, v in postfix.items()) or f"{rate:.1f} {self.unit}s/s"
            print(f"{self.desc}: {self.done}/{self.total} {self.unit}s ({figures})", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        self._stack.close()

    def __exit__(self, *exc) -> None:
        self.close()


def progress_line(text: str, enabled: bool = True) -> None:
    """An informational line on standard error (nothing when ``enabled`` is False)."""
    if enabled:
        print(text, file=sys.stderr, flush=True)
