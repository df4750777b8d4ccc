"""The frame prefetcher returns what a synchronous read would, errors included, in any order of gets."""
from __future__ import annotations

import threading

import pytest

from slam.prefetch import Prefetcher


def test_prefetcher_reads_ahead_in_one_thread_and_reraises():
    threads, calls = set(), []

    def read(k):
        threads.add(threading.get_ident())
        calls.append(k)
        if k == 3:
            raise ValueError(f"frame {k} unreadable")
        return k * 10

    with Prefetcher(read, 6) as reader:
        assert [reader.get(k) for k in range(3)] == [0, 10, 20]
        with pytest.raises(ValueError, match="frame 3"):
            reader.get(3)
        assert reader.get(5) == 50          # skipping ahead works too
    assert len(threads) == 1 and threading.get_ident() not in threads
    assert {0, 1, 2, 3, 5} <= set(calls) <= set(range(6))   # never past the end (4 may be cancelled)


def test_prefetcher_disabled_reads_synchronously():
    seen = []
    reader = Prefetcher(lambda k: seen.append(threading.get_ident()) or k, 3, enabled=False)
    assert [reader.get(k) for k in range(3)] == [0, 1, 2]
    assert set(seen) == {threading.get_ident()}
    reader.close()
