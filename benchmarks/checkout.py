"""The ``slam`` command of another checkout (e.g. a ``git worktree`` of an older commit), for tools
that compare two versions of the code."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def slam_command(tree: str | Path) -> list[str]:
    """The argv prefix that runs the ``slam`` command of the checkout ``tree`` (with ``tree`` on
    PYTHONPATH). The module is chosen by the file there: older checkouts kept it in ``slam.cli``.
    Trying the import would prove nothing: the virtual environment's editable install makes
    ``slam.app`` importable from any checkout."""
    module = "slam.app.cli" if (Path(tree) / "slam" / "app" / "cli.py").is_file() else "slam.cli"
    return [sys.executable, "-c", f"import sys\nfrom {module} import main\nsys.argv[0] = 'slam'\nsys.exit(main())"]


def run_slam(tree: str | Path, *args: str, **kwargs) -> subprocess.CompletedProcess:
    """``slam ARGS`` of the checkout ``tree``, run in ``tree`` with its code first on PYTHONPATH and
    ``OMP_NUM_THREADS=1``; ``kwargs`` go to :func:`subprocess.run` (``check``, ``capture_output``, ...)."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    return subprocess.run([*slam_command(tree), *map(str, args)], cwd=tree, env=env, **kwargs)
