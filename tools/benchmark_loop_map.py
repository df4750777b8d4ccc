"""Regenerates the map where a loop closes, with and without loop closure (``loop_map.md`` / ``.json``).
The code lives in benchmarks/benchmark_loop_map.py (``--help`` for the options)."""
from benchmarks.benchmark_loop_map import main

if __name__ == "__main__":
    main()
