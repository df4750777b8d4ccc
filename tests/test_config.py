"""Configuration: defaults file, validation, overrides, one-line errors."""
from pathlib import Path

import pytest
import yaml

from slam.config import SlamConfig, load_config, to_dict
from slam.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_default_yaml_equals_builtin_defaults():
    # regenerate with tools/write_default_config.py after changing a default
    assert yaml.safe_load((ROOT / "configs" / "default.yaml").read_text()) == to_dict(SlamConfig())


@pytest.mark.parametrize("name", ["default", "stereomis_frame2frame", "scared_frame2model", "synthetic"])
def test_shipped_configs_load(name):
    load_config(ROOT / "configs" / f"{name}.yaml")


def test_overrides_and_types(tmp_path):
    cfg = load_config(None, ["solver.max_iters=7", "tracking.mode=frame2model", "depth.max_depth_mm=180"])
    assert cfg.solver.max_iters == 7 and cfg.tracking.mode == "frame2model" and cfg.depth.max_depth_mm == 180.0


@pytest.mark.parametrize(
    "text, needle",
    [
        ("solver:\n  max_iter: 3\n", "unknown key 'solver.max_iter' (did you mean 'solver.max_iters'?)"),
        ("solver:\n  max_iters: many\n", "'solver.max_iters' must be an integer"),
        ("tracking:\n  mode: frame2nothing\n", "'tracking.mode' must be one of"),
        ("depth: 5\n", "'depth' must be a mapping"),
        ("solver: [\n", "not valid YAML"),
        ("depth:\n  min_depth_mm: 300\n", "min_depth_mm < max_depth_mm"),
    ],
)
def test_bad_configs_give_one_line_errors(tmp_path, text, needle):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    msg = str(err.value)
    assert needle in msg and "\n" not in msg


def test_bad_override():
    with pytest.raises(ConfigError, match="unknown key 'weights.w4d'"):
        load_config(None, ["weights.w4d=1"])
    with pytest.raises(ConfigError, match="expected key=value"):
        load_config(None, ["weights"])


def test_unquoted_yes_and_no_are_the_choices_not_booleans(tmp_path):
    """YAML reads an unquoted ``yes`` / ``no`` as a boolean: ``data.rectified`` takes them as its choices."""
    from slam.config import load_config

    assert load_config(None, ["data.rectified=yes"]).data.rectified == "yes"
    assert load_config(None, ["data.rectified=no"]).data.rectified == "no"
    path = tmp_path / "c.yaml"
    path.write_text("data:\n  rectified: no\n")
    assert load_config(path).data.rectified == "no"
