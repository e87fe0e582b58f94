from __future__ import annotations

import pytest
import yaml

from rgbdslam.config import PRESET_DIR, Config, load_config, save_config
from rgbdslam.errors import ConfigError


def test_defaults_roundtrip(tmp_path):
    cfg = load_config()
    save_config(cfg, tmp_path / "c.yaml")
    again = load_config(tmp_path / "c.yaml")
    assert again.to_dict() == cfg.to_dict()


@pytest.mark.parametrize("preset", sorted(p.stem for p in PRESET_DIR.glob("*.yaml")))
def test_every_preset_loads(preset):
    cfg = load_config(preset)
    assert isinstance(cfg, Config)


def test_required_presets_exist():
    names = {p.stem for p in PRESET_DIR.glob("*.yaml")}
    assert {"default", "tum_fr1", "tum_fr2", "tum_fr3", "put_kinect1"} <= names


def test_override_changes_value_and_type():
    cfg = load_config(None, ["dataset.max_difference=0.05", "dataset.camera=fr2"])
    assert cfg.dataset.max_difference == 0.05
    assert cfg.dataset.camera == "fr2"
    # an int given for a float key is accepted as float
    cfg = load_config(None, ["dataset.max_difference=1"])
    assert isinstance(cfg.dataset.max_difference, float)


def test_unknown_key_named(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump({"dataset": {"no_such_key": 1}}))
    with pytest.raises(ConfigError, match=r"dataset\.no_such_key"):
        load_config(p)
    with pytest.raises(ConfigError, match="nosection"):
        load_config(None, ["nosection.key=1"])


def test_ill_typed_value_named():
    with pytest.raises(ConfigError, match=r"dataset\.max_difference"):
        load_config(None, ["dataset.max_difference=abc"])
    with pytest.raises(ConfigError, match=r"dataset\.camera"):
        load_config(None, ["dataset.camera=fr9"])
    with pytest.raises(ConfigError, match="section.key=value"):
        load_config(None, ["justakey"])


def test_missing_config_file_message():
    with pytest.raises(ConfigError, match="not found"):
        load_config("definitely_not_a_preset")


def test_invalid_yaml(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("dataset: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(p)
