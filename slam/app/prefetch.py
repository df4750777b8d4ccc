"""Read the next frame while the current one is processed.

Decoding, rectifying and masking a frame (OpenCV, which releases the GIL) overlaps the tracking of
the previous one. One worker thread owns all reads, so readers holding a sequential decoder (video)
are used from one thread at a time, in order.
"""
from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Generic, Optional, TypeVar

T = TypeVar("T")


class Prefetcher(Generic[T]):
    """``get(k)`` returns ``read(k)`` (or raises what it raised), having started ``read(k + 1)``.

    Args:
        read: the function reading item ``k``.
        n: number of items; reads past ``n - 1`` are never started.
        enabled: False reads synchronously (no thread).
    """

    def __init__(self, read: Callable[[int], T], n: int, enabled: bool = True):
        self._read = read
        self._n = n
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="frame-reader") if enabled else None
        self._pending: dict[int, Future] = {}

    def _submit(self, k: int) -> None:
        if self._pool is not None and 0 <= k < self._n and k not in self._pending:
            self._pending[k] = self._pool.submit(self._read, k)

    def get(self, k: int) -> T:
        if self._pool is None:
            return self._read(k)
        self._submit(k)
        self._submit(k + 1)
        future = self._pending.pop(k)
        for stale in [j for j in self._pending if j < k]:   # skipped items: drop their reads
            self._pending.pop(stale).cancel()
        return future.result()

    def close(self) -> None:
        if self._pool is not None:
            for future in self._pending.values():
                future.cancel()
            self._pending.clear()
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> "Prefetcher[T]":
        return self

    def __exit__(self, *exc) -> Optional[bool]:
        self.close()
        return None
