"""Rewrite configs/default.yaml from the configuration dataclasses (tests check they agree).

    .venv/bin/python tools/write_default_config.py
"""
from pathlib import Path

import yaml

from slam.config import SlamConfig, to_dict

HEADER = """# The built-in defaults, in full (tests/test_config.py checks this file equals them;
# regenerate with `.venv/bin/python tools/write_default_config.py`).
# Every key is documented in the dataclass that holds it:
#   data -> slam/io/datasets/config.py, correspondence/depth/solver/weights -> vo/config.py,
#   tracking/logging -> slam/config.py, map -> mapping/config.py.
# Copy a section into your own config to change it; unknown or mistyped keys are an error.
"""

if __name__ == "__main__":
    path = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"
    path.write_text(HEADER + yaml.safe_dump(to_dict(SlamConfig()), sort_keys=False))
    print(f"wrote {path}")
