"""The accuracy gate: the working tree against a base commit on the real SCARED sequence and the
generator, each case run several times in a moved world frame to know its own spread; one table,
one verdict (exit 1 on a regression). The code lives in benchmarks/check_accuracy.py (``--help``
for the options; docs/benchmarks.md, "How to compare versions")."""
import sys

from benchmarks.check_accuracy import main

if __name__ == "__main__":
    sys.exit(main())
