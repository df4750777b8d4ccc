"""Runs one job of tools/compare_baselines.py in this process: ``JOB.json`` in, ``RESULT.json`` out.
The code lives in benchmarks/baselines_open3d.py (compare_baselines starts it as
``python -m benchmarks.baselines_open3d JOB.json RESULT.json``)."""
import sys

from benchmarks.baselines_open3d import main

if __name__ == "__main__":
    sys.exit(main())
