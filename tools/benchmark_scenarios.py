"""Regenerates the paper's Table 1 on synthetic sequences (``scenarios.md`` / ``.json``).
The code lives in benchmarks/benchmark_scenarios.py (``--help`` for the options)."""
from benchmarks.benchmark_scenarios import main

if __name__ == "__main__":
    main()
