"""Runs the paper's SCARED protocol (Table 3), or a synthetic stand-in of it.
The code lives in benchmarks/evaluate_scared.py (``--help`` for the options)."""
import sys

from benchmarks.evaluate_scared import main

if __name__ == "__main__":
    sys.exit(main())
