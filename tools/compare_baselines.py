"""Regenerates our pipeline against the Open3D baselines (``baselines.md`` / ``.json``).
The code lives in benchmarks/compare_baselines.py (``--help`` for the options)."""
import sys

from benchmarks.compare_baselines import main

if __name__ == "__main__":
    sys.exit(main())
