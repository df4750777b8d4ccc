"""Regenerates which input makes a pose wrong: stereo depth, flow or weights (``error_attribution.md`` / ``.json``).
The code lives in benchmarks/error_attribution.py (``--help`` for the options)."""
from benchmarks.error_attribution import main

if __name__ == "__main__":
    main()
