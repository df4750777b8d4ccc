"""Rewrite configs/default.yaml from the configuration dataclasses (tests check they agree).

    .venv/bin/python tools/write_default_config.py
"""
from pathlib import Path

import yaml

from slam.config import default_tree

HEADER = """# Every key a person may set, at its built-in default (tests/test_config.py checks this file
# equals them; regenerate with `.venv/bin/python tools/write_default_config.py`).
# Each key is documented once, in the dataclass that holds it:
#   data -> slam/io/datasets/config.py, correspondence/depth/solver/weights -> vo/config.py,
#   tracking/health/graph/logging -> slam/config.py, map -> mapping/config.py.
# Copy a section into your own config to change it; an unknown, mistyped or removed key is a
# one-line error (a removed one names what replaces it).
"""

if __name__ == "__main__":
    path = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"
    path.write_text(HEADER + yaml.safe_dump(default_tree(), sort_keys=False))
    print(f"wrote {path}")
