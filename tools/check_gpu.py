"""Checks the GPU path (torch kernels) against the CPU's numba kernels, pose by pose.
The code lives in benchmarks/check_gpu.py (``--help`` for the options)."""
import sys

from benchmarks.check_gpu import main

if __name__ == "__main__":
    sys.exit(main())
