"""Runs the paper's StereoMIS protocol (Tables 1 and 2), or a synthetic stand-in of it.
The code lives in benchmarks/evaluate_stereomis.py (``--help`` for the options)."""
import sys

from benchmarks.evaluate_stereomis import main

if __name__ == "__main__":
    sys.exit(main())
