from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import pytest
import yaml

from rgbdslam.config import Config, preset_files, load_config, save_config
from rgbdslam.configspec import AtMost, Key
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
    "stereo.depth": "sgbm",
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
    ("mapping.tsdf_voxel=0", "'mapping.tsdf_voxel' must be between 0.001 and 10; got 0.0"),
    ("mapping.cloud_pixel_stride=0", "'mapping.cloud_pixel_stride' must be at least 1; got 0"),
    ("matching.ratio=2", "'matching.ratio' must be between 0 and 1; got 2.0"),
    ("keyframes.max_gap=-1", "'keyframes.max_gap' must be at least 1; got -1"),
    ("loop.query_gap=-3", "'loop.query_gap' must not be negative; got -3"),
    ("dataset.depth_scale=.nan", "'dataset.depth_scale' must be a finite number; got nan"),
    ("mapping.depth_min=5", "'mapping.depth_min' (5.0) must be smaller than 'mapping.depth_max' (3.0)"),
    ("stereo.row_ratio=0", "'stereo.row_ratio' must be positive; got 0.0"),
    ("stereo.row_ratio=1.5", "'stereo.row_ratio' must be at most 1; got 1.5"),
    ("dataset.reader_threads=0", "'dataset.reader_threads' must be at least 1; got 0"),
    ("stereo.min_disparity=128", "'stereo.min_disparity' (128.0) must be smaller than 'stereo.max_disparity' (128)"),
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


# ------------------------------------------------------------------ every numeric key is bounded


def numeric_keys() -> list[tuple[str, type]]:
    """Every int/float key of the config (optional ones too), read from Config itself, so a key
    added later is walked without touching this test."""
    import dataclasses
    import types
    import typing

    out = []
    cfg = Config()
    for section in dataclasses.fields(cfg):
        obj = getattr(cfg, section.name)
        hints = typing.get_type_hints(type(obj))
        for f in dataclasses.fields(obj):
            hint = hints[f.name]
            args = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
            kinds = [a for a in args if a in (int, float)]
            if kinds:
                out.append((f"{section.name}.{f.name}", kinds[0]))
    return out


NUMERIC_KEYS = numeric_keys()


def test_every_numeric_key_has_its_own_finite_range():
    """A new key must come with an upper bound its consumer accepts, declared on its field
    (``Range``, ``AtMost`` or ``Positive``): a number with a bare ``Key`` or no marker is named here."""
    from rgbdslam.config import SECTIONS, value_range
    from rgbdslam.configspec import numeric_without_range

    assert len(NUMERIC_KEYS) > 80
    missing = [f"{s}.{k}" for s, cls in SECTIONS.items() for k in numeric_without_range(cls)]
    assert not missing, f"declare a range on these config keys' fields (Range, AtMost or Positive): {missing}"
    for key, kind in NUMERIC_KEYS:
        lo, lo_open, hi = value_range(key, kind)
        assert math.isfinite(lo), key
        assert lo < hi < 2**31, key  # C int range; 2**31 and 1e12 are refused for every key


@dataclass
class OddSection:  # a section declared wrongly (module level: its annotations are resolved here)
    good: Annotated[int, AtMost(10, "a count")] = 1
    no_range: Annotated[float, Key("a number without a range")] = 0.5
    bare: int = 3
    range_on_text: Annotated[str, AtMost(1, "text")] = "a"
    flag: Annotated[bool, Key("a flag")] = True
    maybe: Annotated[float | None, AtMost(1.0, "optional")] = None


def test_a_key_without_its_range_or_description_is_named():
    """The check the test above relies on finds a number declared without a range, a range on a
    key that is no number and a field without a marker; validation refuses such a number too."""
    from rgbdslam.configspec import check, field_specs, numeric_without_range

    assert numeric_without_range(OddSection) == ["no_range", "bare", "range_on_text"]
    assert field_specs(OddSection)["good"] == AtMost(10, "a count") and field_specs(OddSection)["bare"] is None
    with pytest.raises(ConfigError, match="'s.no_range' holds a number but declares no range"):
        check("s.no_range", field_specs(OddSection)["no_range"], 0.5)
    with pytest.raises(ConfigError, match=r"^config key 's.good' must be at most 10; got 11$"):
        check("s.good", field_specs(OddSection)["good"], 11)


@pytest.mark.parametrize("key, kind", NUMERIC_KEYS, ids=[k for k, _ in NUMERIC_KEYS])
def test_every_numeric_key_refuses_boundary_values_before_any_work(key, kind, tmp_path):
    """min-1, max+1, 2^31, 1e12, 1e300 and NaN for every key: exit 2 with one 'error:' line naming
    the key, before the sequence is opened or the run folder made. The range's own ends pass."""
    from click.testing import CliRunner

    from rgbdslam.cli import main
    from rgbdslam.config import check_range, value_range

    lo, lo_open, hi = value_range(key, kind)
    values = [lo - 1, hi + 1, 2**31, "1e12", "1e300", ".nan", "NaN"]
    if lo_open:
        values.append(lo)
    out = tmp_path / "run"
    for v in values:
        shown = repr(v) if not isinstance(v, str) else v
        res = CliRunner().invoke(main, ["run", str(tmp_path / "no-such-sequence"), "--out", str(out), "-q",
                                        "--set", f"{key}={shown if not isinstance(v, float) else repr(v)}"])
        assert isinstance(res.exception, SystemExit) and res.exit_code == 2, (key, v, res.output)
        lines = res.output.splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: config key '{key}'"), (key, v, res.output)
        assert not out.exists()
    for v in (lo, hi) if not lo_open else (hi,):
        check_range(key, kind(v))  # the ends of the range are accepted


@pytest.mark.data
def test_upper_ends_are_accepted_by_their_consumers(desk9, tmp_path):
    """The maxima of the keys handed to C code (seeds, iteration counts, LSH sizes, TSDF blocks,
    OpenCV's RANSAC) are accepted by OpenCV, GTSAM and Open3D in a real run."""
    from click.testing import CliRunner

    from rgbdslam.cli import main
    from rgbdslam.config import value_range

    keys = ["registration.seed", "loop.seed", "mapping.seed", "matching.prefilter_iterations", "loop.lsh_tables",
            "loop.lsh_bits", "mapping.floor_ransac_iterations", "mapping.tsdf_initial_blocks",
            "backend.max_iterations", "backend.isam2_extra_updates", "dataset.prefetch"]
    sets = [f"{k}={value_range(k, int)[2]}" for k in keys]
    assert value_range("registration.seed", int)[2] == 2**31 - 1
    res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(tmp_path / "r"), "-q", "--set", "dataset.max_frames=4",
                                    "--set", "matching.prefilter=homography", "--set", "matching.prefilter_threshold=3",
                                    "--set", "backend.enabled=true", *sum((["--set", s] for s in sets), [])])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "r" / "map" / "mesh.ply").is_file() and (tmp_path / "r" / "posegraph.g2o").is_file()


# ------------------------------------------------------------------ config --explain


def test_every_key_is_explained_next_to_its_field():
    from rgbdslam.config_doc import explain_rows

    rows = explain_rows()
    assert len(rows) == sum(len(v) for v in Config().to_dict().values())
    missing = [r["key"] for r in rows if len(r["description"]) < 8]
    assert not missing, f"give these fields a description in their Key/Range marker: {missing}"
    # group headers above a block of fields are not descriptions of its first field
    assert not any(r["description"].lower().startswith(("islam (", "isvd (", "ransac baseline", "candidate search",
                                                         "verification")) for r in rows)


def test_explained_ranges_are_the_ones_enforced():
    """The range text comes from the rules validate_section applies: a value just outside fails."""
    from rgbdslam.config_doc import explain_rows

    rows = {r["key"]: r for r in explain_rows()}
    assert rows["registration.mp"]["range"] == "1 to 64" and rows["registration.mp"]["type"] == "int"
    assert rows["registration.beta"]["range"] == "-100 to 100"
    assert rows["registration.alpha"]["range"] == "> 0 and <= 100"
    assert rows["matching.ratio"]["range"] == "0 to 1, or null"
    assert rows["mapping.depth_min"]["range"] == "0 to 1000, < mapping.depth_max"
    assert rows["loop.index"]["range"] == "one of lsh, brute"
    for key, bad in (("registration.mp", 0), ("registration.mp", 65), ("matching.ratio", 1.5),
                     ("registration.alpha", 0.0), ("registration.alpha", 101.0), ("features.n_levels", 17),
                     ("mapping.voxel_size", 1e-4), ("mapping.depth_min", 1001.0)):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            load_config(None, [f"{key}={bad}"])


def test_config_explain_command_prints_every_key(tmp_path):
    from tests.conftest import cli

    res = cli(["config", "--explain", "--set", "registration.mp=6"])
    assert res.exit_code == 0, res.output
    out = res.stdout
    for section, values in Config().to_dict().items():
        for name in values:
            assert f"\n{section}.{name}: " in "\n" + out, f"{section}.{name}"
    assert "registration.mp: int, 1 to 64; default 4 (here 6)\n" in out
    assert max(len(ln) for ln in out.splitlines() if ln.startswith("    ")) <= 80


def test_landmark_keys_checked_against_each_other():
    """``landmarks.n_features`` between 1 and ``features.n_features`` would be ignored: refused with
    one line naming the keys."""
    from rgbdslam.config import ConfigError, load_config

    with pytest.raises(ConfigError, match="landmarks.n_features.*features.n_features"):
        load_config(None, ["landmarks.n_features=500"])
    load_config(None, ["landmarks.n_features=1500"])
    with pytest.raises(ConfigError, match="landmarks.n_features.*grid"):
        load_config(None, ["landmarks.n_features=1500", "features.grid_rows=2"])


# ------------------------------------------------------------------ user YAML: bounded, literal, no aliases

ALIAS_BOMB = ("{a: &a [x, x, x, x, x, x, x, x, x], b: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a], "
              "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b], d: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c], "
              "e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d], f: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e], "
              "g: &g [*f, *f, *f, *f, *f, *f, *f, *f, *f], h: [*g, *g, *g, *g, *g, *g, *g, *g, *g]}")


def test_an_alias_bomb_fails_fast_with_a_short_line(tmp_path):
    """Nine levels of aliases expand to 387 M items: PyYAML built them for seconds and the error
    echoed them (157 MB). Aliases are refused where they are read."""
    import time

    start = time.process_time()
    with pytest.raises(ConfigError) as e:
        load_config(None, [f"features.n_features={ALIAS_BOMB}"])
    assert time.process_time() - start < 1.0
    assert "uses the alias *a; write the value out" in str(e.value) and len(str(e.value)) < 300
    p = tmp_path / "bomb.yaml"
    p.write_text(f"features: {{n_features: {ALIAS_BOMB}}}\n")
    with pytest.raises(ConfigError, match=r"bomb.yaml:1: uses the alias \*a"):
        load_config(p)


@pytest.mark.parametrize("raw, expect", [("010", 10), ("+12", 12), ("1e3", 1000.0)])
def test_numbers_are_read_as_written(raw, expect):
    """YAML 1.1 read 010 as 8 (octal) and 1e3 as the text '1e3'."""
    cfg = load_config(None, [f"features.n_features={raw}" if isinstance(expect, int) else f"dataset.depth_scale={raw}"])
    assert (cfg.features.n_features if isinstance(expect, int) else cfg.dataset.depth_scale) == expect


@pytest.mark.parametrize("raw", ["0x6", "1_0", "1:00", "0o10", "0b11"])
def test_yaml_1_1_number_spellings_are_text_and_refused(raw):
    with pytest.raises(ConfigError, match=rf"features.n_features' expects int; got '{raw}'"):
        load_config(None, [f"features.n_features={raw}"])


def test_deep_nesting_and_huge_numbers_are_one_short_line(tmp_path):
    for value, words in (("[" * 10000 + "]" * 10000, "nests deeper than 64 levels"),
                         ("9" * 120000, "has a number of 120,000 characters")):
        with pytest.raises(ConfigError) as e:
            load_config(None, [f"features.n_features={value}"])
        assert words in str(e.value) and len(str(e.value)) < 300, str(e.value)[:500]
    p = tmp_path / "deep.yaml"
    p.write_text("features:\n" + "".join("  " * (i + 1) + f"k{i}:\n" for i in range(10000)))
    with pytest.raises(ConfigError, match="deep.yaml:64: nests deeper than 64 levels"):
        load_config(p)


@pytest.mark.parametrize("value", ["'" + "x" * 100000 + "'", str(list(range(100000))),
                                   "{" + ", ".join(f"k{i}: 1" for i in range(20000)) + "}"])
def test_an_echoed_value_is_shortened(value):
    with pytest.raises(ConfigError) as e:
        load_config(None, [f"features.n_features={value}"])
    assert len(str(e.value)) < 400, len(str(e.value))


def test_every_error_line_is_bounded():
    from rgbdslam.errors import MAX_MESSAGE, InputError

    text = str(InputError("x" * 10 ** 6 + " the end"))
    assert len(text) <= MAX_MESSAGE and text.endswith(" the end") and "characters left out" in text


def test_bounds_are_printed_as_written():
    """A C int's bound read "at most 2.14748e+09" (rounded by %g): not the number to type."""
    with pytest.raises(ConfigError, match=r"'registration.seed' must be at most 2147483647; got 99999999999$"):
        load_config(None, ["registration.seed=99999999999"])


def test_an_earlier_runs_config_with_retired_keys_still_loads(tmp_path):
    """A run folder's config.yaml names every key of the version that wrote it; keys removed since
    (RETIRED) are skipped, so `fuse`, `export`, `view` and `--map` still read earlier runs."""
    import yaml

    from rgbdslam.config import RETIRED, Config, load_config

    sections: dict = {}
    for key in sorted(RETIRED):
        section, name = key.split(".")
        sections.setdefault(section, {})[name] = 1
    p = tmp_path / "config.yaml"
    p.write_text(yaml.safe_dump(sections))
    assert load_config(p) == Config()
    assert {"matching.depth_edge_use", "landmarks.global_ba", "landmarks.ba_worker", "mapping.live_early",
            "mapping.live_cloud_ahead"} <= RETIRED.keys()


def test_a_retired_key_given_with_set_is_one_line_naming_it_and_where_it_is_documented():
    """--set (and a sweep's --grid, which sets its values the same way) naming a removed key would run
    and change nothing: it is refused, saying why the key went and where that is written down."""
    from rgbdslam.config import RETIRED, load_config
    from tests.conftest import cli

    for key, why in RETIRED.items():
        with pytest.raises(ConfigError) as e:
            load_config(None, [f"{key}=1"])
        assert str(e.value) == f"config key '{key}' (--set {key}=1) was removed: {why}"
    assert RETIRED["registration.pregate"] == 'it measured no gain (docs/frontend.md "Options that measured no gain")'
    assert RETIRED["registration.far_baselines"] == 'it measured no gain (docs/stereo.md "Near and far points")'
    assert RETIRED["landmarks.global_ba"] == 'it measured no gain (docs/landmarks.md "Removed options")'
    assert RETIRED["mapping.live_early"] == 'it measured no gain (docs/mapping.md "Removed options")'
    root = Path(__file__).resolve().parent.parent
    for where in {why.split("(", 1)[1] for why in RETIRED.values() if "docs/" in why}:  # the cited headings exist
        page, heading = where.split(" ", 1)
        text = (root / page).read_text(encoding="utf-8")
        assert heading.strip('")') in text, where
    res = cli(["config", "--set", "registration.far_baselines=40"])
    assert res.exit_code == 2 and res.stderr.count("\n") == 1 and "'registration.far_baselines'" in res.stderr
