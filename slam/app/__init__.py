"""The application: the ``slam`` command (``cli``), one run end to end (``runner``, ``pipeline``:
read, track, write rows, log, finish), ``compare`` and ``inspect``, and what a run writes (the
run folder, ``tracking.csv``, plots, the rerun recording, progress, signals)."""
