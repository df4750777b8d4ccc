"""Regenerates the speed table of the whole pipeline and the map's cost (``speed.md`` / ``.json``).
The code lives in benchmarks/benchmark_speed.py (``--help`` for the options)."""
from benchmarks.benchmark_speed import main

if __name__ == "__main__":
    main()
