"""Typed configuration: the sections composed, loaded, overridden and cross-checked.

Each stage declares its own section, one dataclass beside its code (``rgbdslam/<stage>/config.py``),
every key once on its field with its type, range and description (:mod:`rgbdslam.configspec`).
This module composes them into :class:`Config`, and holds what spans keys: the cross-checks
(:data:`ORDERED`, :func:`validate`), the retired keys (:data:`RETIRED`) and the presets. Presets are
YAML files inside the package (``rgbdslam/presets/``, read with ``importlib.resources`` so an
installed wheel has them) that override the defaults; ``--set section.key=value`` overrides a
preset. Unknown keys and values of the wrong type or outside their range are rejected with a
message naming the key.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args, get_origin, get_type_hints

import yaml

from rgbdslam.backend.config import BackendConfig
from rgbdslam.configspec import check, field_specs
from rgbdslam.datasets.config import DatasetConfig
from rgbdslam.errors import ConfigError, cut, shorten
from rgbdslam.frontend.config import (DepthFilterConfig, FeaturesConfig, KeyframeConfig, MatchingConfig,
                                      RegistrationConfig)
from rgbdslam.landmarks.config import LandmarksConfig
from rgbdslam.loop.config import LoopConfig
from rgbdslam.mapping.config import MappingConfig
from rgbdslam.io.text import read_text
from rgbdslam.io.yamlfile import Refused, StrictLoader, load_yaml
from rgbdslam.stereo.config import StereoConfig
from rgbdslam.viz.config import OutputConfig


def preset_files() -> dict[str, Any]:
    """Name -> resource of every preset shipped inside the package (``rgbdslam/presets/*.yaml``)."""
    root = importlib.resources.files("rgbdslam") / "presets"
    return {e.name[:-5]: e for e in root.iterdir() if e.name.endswith(".yaml") and e.is_file()}


@dataclass
class Config:
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    features: FeaturesConfig = field(default_factory=FeaturesConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    depth_filter: DepthFilterConfig = field(default_factory=DepthFilterConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    landmarks: LandmarksConfig = field(default_factory=LandmarksConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def dump(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


SECTIONS = {f.name: f.default_factory for f in dataclasses.fields(Config)}  # section name -> its dataclass

# --------------------------------------------------------------------------- validation


def _check_value(key: str, value: Any, hint: Any) -> Any:
    """Return ``value`` converted to ``hint`` or raise ConfigError naming ``key``."""
    origin = get_origin(hint)
    if origin is Literal:
        allowed = get_args(hint)
        if value not in allowed:
            raise ConfigError(
                f"config key '{key}' must be one of {', '.join(map(str, allowed))}; got {shorten(value)}"
            )
        return value
    if origin in (typing.Union, types.UnionType):
        args = get_args(hint)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _check_value(key, value, a)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if errors else f"config key '{key}' has an invalid value {shorten(value)}")
    if hint is bool:
        if isinstance(value, bool):
            return value
    elif hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif hint is float:
        if isinstance(value, str):  # YAML 1.1 reads "1e-8" (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):
                raise ConfigError(f"config key '{key}' must be a finite number; got {shorten(value)}")
            return float(value)
    elif hint is str:
        if isinstance(value, str):
            return value
    else:  # pragma: no cover - only the types above are used
        return value
    raise ConfigError(
        f"config key '{key}' expects {getattr(hint, '__name__', hint)}; got {shorten(value)}"
    )


# Cross-checks between keys of one section: pairs (a, b) that need a < b.
ORDERED = [("matching.min_depth", "matching.max_depth"), ("depth_filter.min_depth", "depth_filter.max_depth"),
           ("mapping.depth_min", "mapping.depth_max"), ("mapping.obstacle_min_height", "mapping.obstacle_max_height"),
           ("stereo.min_disparity", "stereo.max_disparity")]


def key_spec(key: str) -> Any:
    """The declaration (:mod:`rgbdslam.configspec` marker) of ``section.name``."""
    section, name = key.split(".", 1)
    return field_specs(SECTIONS[section])[name]


def value_range(key: str, kind: type) -> tuple[float, bool, float]:
    """``(lo, lo_open, hi)``: the values ``key`` (of type ``kind``, int or float) accepts are
    ``lo < v`` (``lo_open``) or ``lo <= v``, and ``v <= hi`` (declared on the key's field)."""
    return key_spec(key).bounds(kind)


def check_range(key: str, v: int | float) -> None:
    """ConfigError naming ``key`` when ``v`` is outside the range declared on its field."""
    check(key, key_spec(key), v)



def validate_section(section: str, obj: Any) -> Any:
    """Check one section's values: types (as for YAML input, so a section built in Python is
    held to the same rules) and ranges (:func:`check_range`, ORDERED); ConfigError names the key."""
    hints = get_type_hints(type(obj))
    specs = field_specs(type(obj))
    for f in dataclasses.fields(obj):
        key = f"{section}.{f.name}"
        v = _check_value(key, getattr(obj, f.name), hints[f.name])
        setattr(obj, f.name, v)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        check(key, specs[f.name], v)
    for a, b in ORDERED:
        if a.split(".")[0] == section:
            va, vb = getattr(obj, a.split(".")[1]), getattr(obj, b.split(".")[1])
            if not va < vb:
                raise ConfigError(f"config key '{a}' ({shorten(va)}) must be smaller than '{b}' ({shorten(vb)})")
    if section == "mapping":
        most = (2 * obj.outlier_radius + 1) ** 3 - 1
        if obj.outlier_min_neighbors > most:
            raise ConfigError(
                f"config key 'mapping.outlier_min_neighbors' ({obj.outlier_min_neighbors}) must be at most the "
                f"{most} voxels around a point at mapping.outlier_radius={obj.outlier_radius}")
    return obj


def validate(cfg: Config) -> Config:
    """Check every section (:func:`validate_section`)."""
    for section in dataclasses.fields(cfg):
        validate_section(section.name, getattr(cfg, section.name))
    lm = cfg.landmarks
    if 0 < lm.n_features < cfg.features.n_features:
        raise ConfigError(
            f"config key 'landmarks.n_features' ({lm.n_features}) must be 0 (off) or at least "
            f"'features.n_features' ({cfg.features.n_features})")
    if lm.n_features > cfg.features.n_features and cfg.features.grid_rows * cfg.features.grid_cols > 1:
        raise ConfigError(
            f"config key 'landmarks.n_features' ({lm.n_features}) cannot be used with a key-point grid "
            f"(features.grid_rows x grid_cols = {cfg.features.grid_rows} x {cfg.features.grid_cols}): the "
            f"registration's strongest subset would not follow the grid; set one of them off")
    return cfg


# keys that earlier versions had, and why they went: a saved configuration (an earlier run folder's
# config.yaml, a YAML file) that names one still loads, the key skipped; --set or a sweep's --grid
# naming one is an error (it would run and change nothing)
def _no_gain(where: str) -> str:
    return f"it measured no gain ({where})"


RETIRED = {
    "loop.sigma_floor": "loop edges carry their registration's information (one noise floor, in the front end)",
    # options that measured no gain, removed with their code
    **{f"landmarks.{k}": _no_gain('docs/landmarks.md "Removed options"') for k in (
        "anchor_age", "anchor_edges", "anchor_info_scale", "anchor_min_landmarks", "ba_every", "ba_handover",
        "ba_noise_scale", "ba_worker", "consistency_floor", "drift_sigma", "global_ba",
        "global_ba_frames", "global_ba_iterations", "global_ba_odometry", "graph_information", "loop_correct",
        "match_old_bonus", "observe", "ransac_confidence", "revisit_min_inliers",
        "revisit_radius", "sigma_px_scale")},
    # the fusion's consistency scale: without it the fused pose is better where the registration is the one off
    **{f"landmarks.{k}": ('the fusion takes both estimates\' information as it is; the consistency scale that blamed '
                          'the map pose for every disagreement was removed (docs/landmarks.md "Far points")')
       for k in ("consistency_window", "loop_refine_scaled")},
    "loop.query": _no_gain('docs/speed.md "Work that decides nothing"'),
    # the 3-D stereo refit of the whole pose: its translations ~1-2 % short on exact depth (wrong matches at the
    # kitti preset's disparity noise); the rotation comes from the reprojection refit, the translation from inliers
    **{f"registration.{k}": ('stereo poses are refit by registration.stereo_reprojection: rotation from the far '
                             'points, translation from the near inliers (docs/stereo.md "Far points turn, near '
                             'points move")')
       for k in ("noise_refit", "noise_refit_all")},
    # the windowed local BA at keyframes: worse than none on the fast synthetic motions (docs/landmarks.md)
    **{f"landmarks.{k}": _no_gain('docs/landmarks.md "Local BA, removed"') for k in (
        "local_ba", "ba_window", "ba_iterations", "ba_solver", "ba_max_landmarks", "ba_baseline", "ba_huber",
        "ba_landmark_prior", "ba_prior_floor", "ba_min_observations", "ba_max_move",
        "ba_max_move_deg", "ba_frames")},
    "mapping.live_cloud_ahead": _no_gain('docs/mapping.md "Removed options"'),
    "mapping.live_early": _no_gain('docs/mapping.md "Removed options"'),
    "matching.depth_edge_use": _no_gain('docs/frontend.md "Scale bias"'),
    "registration.far_baselines": _no_gain('docs/stereo.md "Near and far points"'),
    **{f"registration.{k}": _no_gain('docs/frontend.md "Options that measured no gain"')
       for k in ("depth_weighting", "joint_gate", "joint_refit", "pregate")},
}


def _apply(section_obj: Any, section: str, values: dict[str, Any], source: str, saved: bool) -> None:
    hints = get_type_hints(type(section_obj))
    for k, v in values.items():
        if f"{section}.{k}" in RETIRED:
            if saved:
                continue
            raise ConfigError(f"config key '{section}.{k}' ({source}) was removed: {RETIRED[f'{section}.{k}']}")
        if k not in hints:
            known = ", ".join(hints)
            raise ConfigError(f"unknown config key '{cut(section)}.{cut(k)}' in {source}; known keys: {known}")
        setattr(section_obj, k, _check_value(f"{section}.{k}", v, hints[k]))


def merge(cfg: Config, data: dict[str, Any] | None, source: str = "config", saved: bool = True) -> Config:
    """Apply a nested mapping (as read from YAML) onto ``cfg`` in place and return it. ``saved``: the
    mapping is a saved configuration, whose retired keys (:data:`RETIRED`) are skipped; otherwise
    (a ``--set``) naming one is an error."""
    if not data:
        return cfg
    if not isinstance(data, dict):
        raise ConfigError(f"{source} must be a mapping of sections (dataset:, features:, ...)")
    sections = {f.name for f in dataclasses.fields(Config)}
    for section, values in data.items():
        if section not in sections:
            raise ConfigError(
                f"unknown config section '{cut(section)}' in {source}; known sections: {', '.join(sorted(sections))}"
            )
        if values is None:
            continue
        if not isinstance(values, dict):
            raise ConfigError(f"config section '{section}' in {source} must be a mapping")
        _apply(getattr(cfg, section), section, values, source, saved)
    return cfg


def resolve_preset(name_or_path: str | Path):
    """A path to a YAML file, or the name of a preset shipped in the package (``tum_fr1``);
    returns the file (a Path or an ``importlib.resources`` Traversable)."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    presets = preset_files()
    if str(name_or_path) in presets:
        return presets[str(name_or_path)]
    names = ", ".join(sorted(presets)) or "(none: the package's presets are missing; reinstall rgbdslam)"
    raise ConfigError(f"config file {name_or_path} not found; give a YAML path or one of the presets: {names}")


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Defaults, then the YAML file (if any), then ``section.key=value`` overrides."""
    cfg = Config()
    if path is not None:
        p = resolve_preset(path)
        data = load_yaml(read_text(p, "config file"), str(p), ConfigError)
        merge(cfg, data, str(p))
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ConfigError(f"override '{cut(item)}' must look like section.key=value")
        key, raw = item.split("=", 1)
        section, name = key.split(".", 1)
        try:
            value = yaml.load(raw, Loader=StrictLoader) if raw != "" else None  # noqa: S506 - a SafeLoader
        except Refused as e:
            raise ConfigError(f"--set {shorten(item)}: the value {e.problem}") from None
        except yaml.YAMLError:
            value = raw
        merge(cfg, {section: {name: value}}, f"--set {cut(item)}", saved=False)
    return validate(cfg)


# where one run writes its outputs: given on the command line (--rerun-save, --rerun), not part of a
# configuration that is given back to --config to repeat a run (it would overwrite the earlier recording)
RUN_OUTPUT_KEYS = {"output.rerun": False, "output.rerun_save": None}


def save_config(cfg: Config, path: str | Path, outputs: bool = True) -> None:
    """Write ``cfg`` as YAML atomically; ``outputs=False`` leaves the one-run output keys
    (:data:`RUN_OUTPUT_KEYS`) at their defaults, as a run folder's config.yaml does."""
    import copy

    from rgbdslam.io.atomic import atomic_write_text

    if not outputs:
        cfg = copy.deepcopy(cfg)
        for key, default in RUN_OUTPUT_KEYS.items():
            section, name = key.split(".")
            setattr(getattr(cfg, section), name, default)
    atomic_write_text(path, cfg.dump())
