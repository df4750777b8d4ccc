"""Regenerates the tracking regression reference (``tests/fixtures/regression_reference.json``).
The code lives in benchmarks/record_regression.py (``--help`` for the options)."""
import sys

from benchmarks.record_regression import main

if __name__ == "__main__":
    sys.exit(main())
