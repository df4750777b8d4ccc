"""Stopping a command cleanly: SIGTERM taken as Ctrl-C, and blocks a signal may not cut short.

A scheduler, ``timeout`` or Ray stops a process with SIGTERM, a person with Ctrl-C (SIGINT). Both
end a run the same way: the frames done are kept, the results written, and the command exits
with ``128 + signal`` (130 for SIGINT, 143 for SIGTERM). Python turns SIGINT into
``KeyboardInterrupt``; :func:`terminate_as_interrupt` makes SIGTERM raise :class:`Terminated`,
a ``KeyboardInterrupt`` too, so one ``except KeyboardInterrupt`` handles both.

:class:`SignalGate` protects what must be written once the frames stop (``metrics.json``):
there a signal is held, and it only cuts short the slow outputs a person may skip (map,
mesh, plot). Signal handlers belong to the main thread; elsewhere both helpers do nothing.
"""
from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C."""

    signum = signal.SIGTERM


def signal_of(err: BaseException) -> int:
    """The signal a ``KeyboardInterrupt`` stands for (SIGINT unless it is :class:`Terminated`)."""
    return int(getattr(err, "signum", signal.SIGINT))


def exit_code(signum: int) -> int:
    """The shell's exit code of a process stopped by ``signum``: 130 for SIGINT, 143 for SIGTERM."""
    return 128 + int(signum)


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Inside the block SIGTERM raises :class:`Terminated` (and SIGINT ``KeyboardInterrupt``, as
    Python's default does); the previous handlers are restored afterwards."""
    if not _in_main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class SignalGate:
    """A run's signals, from its first frame to its last output.

    SIGINT and SIGTERM raise (``KeyboardInterrupt``, :class:`Terminated`) only inside
    :meth:`interruptible` blocks: the frames, then each slow output a person may skip (map,
    mesh, plot). A signal raises once; one that comes while no block is open (the small files
    being written, or right after another signal) is held, and the next interruptible block
    raises it at its start. So a first Ctrl-C stops the frames and a second one, whenever it
    comes, skips the slow outputs not written yet. Use as a context manager; the handlers in
    place before are restored afterwards.

    Attributes:
        received: the signals that came, in order.
    """

    def __init__(self):
        self.received: list[int] = []
        self._held: list[int] = []
        self._open = False
        self._previous: dict = {}

    def __enter__(self) -> "SignalGate":
        if _in_main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in STOP_SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous = {}

    def _handle(self, signum, frame) -> None:
        self.received.append(int(signum))
        if not self._open:
            self._held.append(int(signum))
            return
        self._open = False      # a signal right behind this one is held, not raised mid-cleanup
        self._raise(signum)

    @staticmethod
    def _raise(signum: int) -> None:
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[None]:
        """A block a signal may cut short (KeyboardInterrupt, or :class:`Terminated`); a held
        signal raises at its start."""
        if self._held:
            self._raise(self._held.pop(0))
        self._open = True
        try:
            yield
        finally:
            self._open = False
