"""Fast motion and gaps: tracking at 25, 5, 2.5 and 1.25 fps, and after gaps of black or unreadable
frames (``frame_rate.md`` / ``.json``). The code lives in benchmarks/benchmark_frame_rate.py
(``--help`` for the options)."""
from benchmarks.benchmark_frame_rate import main

if __name__ == "__main__":
    main()
