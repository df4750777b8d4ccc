"""Batches of runs: ``slam evaluate`` (many sequences x modes x swept values, one table) and
``slam synth`` / ``slam train`` rendering many sequences, as tasks on Ray or local worker
processes (docs/evaluation.md).

``tasks`` (what a task is, when it is done), ``worker`` (what a worker does with one),
``executors`` (where tasks run), ``runner`` (options, progress, Ctrl-C), ``protocols`` (which
sequences), ``evaluate`` (the command), ``tables`` and ``reports`` (the paper's tables),
``map_accuracy`` (SCARED's map against its depth), ``synth`` (many synthetic sequences).
"""
