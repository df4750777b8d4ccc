"""Regenerates the validation loss of weight-network checkpoints (``validation_loss.md`` / ``.json``).
The code lives in benchmarks/validation_loss.py (``--help`` for the options)."""
import sys

from benchmarks.validation_loss import main

if __name__ == "__main__":
    sys.exit(main())
