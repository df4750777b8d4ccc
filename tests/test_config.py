"""Configuration: defaults file, validation, overrides, one-line errors."""
from pathlib import Path

import pytest
import yaml

from slam.config import REMOVED, default_tree, load_config, save_config
from slam.errors import ConfigError
from slam.schema import count_keys

ROOT = Path(__file__).resolve().parents[1]


def test_default_yaml_equals_builtin_defaults():
    # regenerate with tools/write_default_config.py after changing a default
    assert yaml.safe_load((ROOT / "configs" / "default.yaml").read_text()) == default_tree()


def test_at_most_45_keys_a_person_may_set():
    assert count_keys(default_tree()) <= 45
    assert "analysis" not in default_tree()


@pytest.mark.parametrize("key", sorted(REMOVED))
def test_a_removed_key_names_its_replacement(key):
    with pytest.raises(ConfigError) as err:
        load_config(None, [f"{key}=1"])
    msg = str(err.value)
    assert f"'{key}' {REMOVED[key]}" in msg and "\n" not in msg


def test_a_fixed_constant_is_not_a_setting():
    with pytest.raises(ConfigError, match="'solver.max_pixels' is gone"):
        load_config(None, ["solver.max_pixels=10"])


def test_analysis_switches_land_on_their_constants():
    cfg = load_config(None, ["analysis.inpaint_px=0", "analysis.solver_kernel=torch", "analysis.map_kernels=torch",
                             "analysis.covariance_scale_frame=1", "analysis.depth_source=groundtruth"])
    assert cfg.correspondence.inpaint_px == 0.0 and cfg.solver.kernel == "torch" and cfg.map.kernels == "torch"
    assert cfg.health.covariance_scale_frame == 1.0 and cfg.analysis.depth_source == "groundtruth"
    assert load_config(None, []).correspondence.inpaint_px == 3.0


def test_saved_config_reads_back(tmp_path):
    cfg = load_config(ROOT / "configs" / "paper.yaml", ["analysis.fb_check_px=1", "tracking.refine_passes=1"])
    save_config(cfg, tmp_path / "config.yaml")
    again = load_config(tmp_path / "config.yaml")
    assert again == cfg
    assert yaml.safe_load((tmp_path / "config.yaml").read_text())["analysis"] == {"fb_check_px": 1.0}


@pytest.mark.parametrize("name", ["default", "paper", "stereomis_frame2frame", "scared_frame2model", "synthetic"])
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
