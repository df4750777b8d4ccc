"""Regenerates the surfel map's fuse + render timings with a large map.
The code lives in benchmarks/benchmark_mapping.py (``--help`` for the options)."""
import sys

from benchmarks.benchmark_mapping import main

if __name__ == "__main__":
    sys.exit(main())
