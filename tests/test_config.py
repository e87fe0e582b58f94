from __future__ import annotations

import pytest
import yaml

from rgbdslam.config import Config, preset_files, load_config, save_config
from rgbdslam.errors import ConfigError


# One non-default value per section, of every kind of type the config uses (Literal, float,
# int, bool, optional str set, optional float set, optional float cleared to None).
NON_DEFAULT = {
    "dataset.associations": "assoc.txt",  # None -> str
    "dataset.max_difference": 0.035,
    "features.n_features": 1500,
    "matching.ratio": 0.8,  # None -> float
    "registration.mp": 6,
    "registration.guided_gate": None,  # float -> None
    "registration.fusion": "thesis",
    "depth_filter.enabled": True,
    "keyframes.min_rotation_deg": 7.5,
    "loop.min_votes": 7,
    "backend.init": "odometry",
    "landmarks.sampling": "uniform",
    "mapping.gravity": "camera",
    "mapping.mesh": False,
    "output.rerun_save": "rec.rrd",
}


def test_non_default_roundtrip(tmp_path):
    overrides = [f"{k}=" + ("" if v is None else str(v)) for k, v in NON_DEFAULT.items()]
    cfg = load_config("tum_fr2", overrides)
    defaults = Config()
    sections = {k.split(".")[0] for k in NON_DEFAULT}
    assert sections == set(defaults.to_dict())  # every section has a changed value
    for key, value in NON_DEFAULT.items():
        section, name = key.split(".")
        assert getattr(getattr(cfg, section), name) == value, key
        assert getattr(getattr(defaults, section), name) != value, key  # really non-default
    assert cfg.dataset.camera == "fr2" and cfg.dataset.kind == "tum"  # from the preset
    save_config(cfg, tmp_path / "c.yaml")
    # the file alone (no preset, no overrides) gives back the whole config
    again = load_config(tmp_path / "c.yaml")
    assert again.to_dict() == cfg.to_dict()
    assert again.to_dict() != defaults.to_dict()
    # and the file holds every key of every section, not only the changed ones
    written = yaml.safe_load((tmp_path / "c.yaml").read_text())
    assert written == cfg.to_dict()


def _presets():
    return sorted(preset_files())


@pytest.mark.parametrize("preset", _presets())
def test_every_preset_loads(preset):
    data = yaml.safe_load(preset_files()[preset].read_text(encoding="utf-8"))
    assert isinstance(data, dict) and data, f"{preset}.yaml sets no keys"
    cfg = load_config(preset)
    # expected: the dataclass defaults with exactly the preset's keys replaced
    expected = Config().to_dict()
    n_keys = 0
    for section, values in data.items():
        for key, value in values.items():
            assert getattr(getattr(cfg, section), key) == value, f"{preset}: {section}.{key}"
            expected[section][key] = value
            n_keys += 1
    assert n_keys > 0
    assert cfg.to_dict() == expected


def test_required_presets_exist():
    names = set(preset_files())
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


@pytest.mark.parametrize("override, message", [
    ("features.n_levels=0", "'features.n_levels' must be between 1 and 16; got 0"),
    ("features.scale_factor=0.5", "'features.scale_factor' must be between 1 and 4; got 0.5"),
    ("registration.max_iterations=0", "'registration.max_iterations' must be at least 1; got 0"),
    ("registration.mp=-1", "'registration.mp' must be at least 1; got -1"),
    ("mapping.tsdf_voxel=0", "'mapping.tsdf_voxel' must be at least 0.001; got 0.0"),
    ("mapping.cloud_pixel_stride=0", "'mapping.cloud_pixel_stride' must be at least 1; got 0"),
    ("matching.ratio=2", "'matching.ratio' must be between 0 and 1; got 2.0"),
    ("keyframes.max_gap=-1", "'keyframes.max_gap' must be at least 1; got -1"),
    ("loop.query_gap=-3", "'loop.query_gap' must not be negative; got -3"),
    ("dataset.depth_scale=.nan", "'dataset.depth_scale' must be a finite number; got nan"),
    ("mapping.depth_min=5", "'mapping.depth_min' (5.0) must be smaller than 'mapping.depth_max' (3.0)"),
])
def test_out_of_range_values_are_one_clear_error(override, message):
    with pytest.raises(ConfigError) as e:
        load_config(None, [override])
    assert message in str(e.value)


def test_range_edges_and_yaml_quirks_are_accepted():
    """0 where 0 means 'off', the lowest legal values, a signed key, and YAML 1.1's '1e-8' string."""
    cfg = load_config(None, ["loop.query_gap=0", "registration.max_lost=0", "depth_filter.window=0",
                             "features.n_levels=1", "registration.beta=-2", "backend.relative_error_tol=1e-8",
                             "matching.ratio=1"])
    assert cfg.loop.query_gap == 0 and cfg.features.n_levels == 1 and cfg.registration.beta == -2.0
    assert cfg.backend.relative_error_tol == 1e-8 and isinstance(cfg.backend.relative_error_tol, float)


def test_a_key_given_twice_in_a_config_file_is_an_error(tmp_path):
    """PyYAML keeps the last of two equal keys silently: a second registration: section would
    quietly replace the first."""
    p = tmp_path / "dup.yaml"
    p.write_text("registration:\n  mp: 3\nloop:\n  min_votes: 9\nregistration:\n  mp: 6\n")
    with pytest.raises(ConfigError, match=r"dup.yaml:5: 'registration' is given twice in one section; keep one"):
        load_config(p)
    p.write_text("loop:\n  min_votes: 9\n  min_votes: 10\n")
    with pytest.raises(ConfigError, match=r"dup.yaml:3: 'min_votes' is given twice"):
        load_config(p)


def test_yaml_merge_keys_work_and_odd_keys_are_one_line(tmp_path):
    p = tmp_path / "merge.yaml"
    p.write_text("loop: {<<: {min_votes: 7, max_candidates: 2}, min_votes: 8}\n")
    cfg = load_config(p)  # the explicit key overrides the merged one: not a duplicate
    assert cfg.loop.min_votes == 8 and cfg.loop.max_candidates == 2
    p.write_text("loop:\n  [a, b]: 1\n")
    with pytest.raises(ConfigError, match=r"merge.yaml:2: 'list' is not a plain key name"):
        load_config(p)
