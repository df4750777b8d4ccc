"""The health monitor's level bound calibrated on the generator, reported on held-out runs
(``calibrate_health.md`` / ``.json``). The code lives in benchmarks/calibrate_health.py (``--help``
for the options)."""
from benchmarks.calibrate_health import main

if __name__ == "__main__":
    main()
