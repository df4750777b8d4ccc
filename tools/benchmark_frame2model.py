"""Regenerates the frame2model against frame2frame table (``frame2model.md`` / ``.json``).
The code lives in benchmarks/benchmark_frame2model.py (``--help`` for the options)."""
from benchmarks.benchmark_frame2model import main

if __name__ == "__main__":
    main()
