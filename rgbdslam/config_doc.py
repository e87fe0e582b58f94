"""``rgbdslam config --explain``: every config key with its type, range, default and description.

The range and the description of a key are what its field declares (``Annotated[..., Range(lo, hi,
"description")]``, :mod:`rgbdslam.configspec`) in its stage's ``config.py``: the text printed is the
rule :func:`rgbdslam.config.validate_section` enforces, and nothing is written twice. A test checks
that every key has a description.
"""

from __future__ import annotations

import dataclasses
import textwrap
import types
import typing
from typing import Any, Literal, get_args, get_origin, get_type_hints

from rgbdslam import config as C
from rgbdslam.configspec import field_specs


def _type_name(hint: Any) -> str:
    origin = get_origin(hint)
    if origin is Literal:
        return "choice"
    if origin in (typing.Union, types.UnionType):
        args = [a for a in get_args(hint) if a is not type(None)]
        return " | ".join(_type_name(a) for a in args) + " | null"
    return getattr(hint, "__name__", str(hint))


def _base(hint: Any) -> Any:
    if get_origin(hint) in (typing.Union, types.UnionType):
        return next(a for a in get_args(hint) if a is not type(None))
    return hint


def key_range(key: str, hint: Any) -> str:
    """The values ``validate_section`` accepts for ``key``, in words."""
    base = _base(hint)
    if get_origin(base) is Literal:
        rng = "one of " + ", ".join(map(str, get_args(base)))
    elif base is bool:
        rng = "true or false"
    elif base in (int, float):
        lo, lo_open, hi = C.value_range(key, base)  # what check_range enforces, upper bound included
        rng = f"> {lo:.7g} and <= {hi:.7g}" if lo_open else f"{lo:.7g} to {hi:.7g}"
        for a, b in C.ORDERED:
            if key == a:
                rng += f", < {b}"
            elif key == b:
                rng += f", > {a}"
    else:
        rng = "text"
    if get_origin(hint) in (typing.Union, types.UnionType) and type(None) in get_args(hint):
        rng += ", or null"
    return rng


def _value(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    return str(v)


def explain_rows(cfg: C.Config | None = None) -> list[dict[str, str]]:
    """One row per key: key, type, range, default, value (of ``cfg``), description."""
    defaults = C.Config()
    cfg = cfg or defaults
    rows = []
    for section in dataclasses.fields(C.Config):
        cls = type(getattr(defaults, section.name))
        hints = get_type_hints(cls)
        specs = field_specs(cls)
        for f in dataclasses.fields(cls):
            key = f"{section.name}.{f.name}"
            rows.append({"key": key, "type": _type_name(hints[f.name]), "range": key_range(key, hints[f.name]),
                         "default": _value(getattr(getattr(defaults, section.name), f.name)),
                         "value": _value(getattr(getattr(cfg, section.name), f.name)),
                         "description": specs[f.name].doc if specs[f.name] else ""})
    return rows


def explain(cfg: C.Config | None = None, width: int = 80) -> str:
    """Text for ``rgbdslam config --explain``: per key a line ``key: type, range; default D``
    (and the effective value when the preset or --set changed it), then the description
    wrapped to ``width`` columns."""
    out = []
    section = None
    for r in explain_rows(cfg):
        s = r["key"].split(".")[0]
        if s != section:
            section = s
            out.append(f"\n[{s}]" if out else f"[{s}]")
        head = f"{r['key']}: {r['type']}, {r['range']}; default {r['default']}"
        if r["value"] != r["default"]:
            head += f" (here {r['value']})"
        out.append(head)
        out.extend(textwrap.wrap(r["description"] or "(no description)", width=width, initial_indent="    ",
                                 subsequent_indent="    ", break_on_hyphens=False))
    return "\n".join(out) + "\n"


def preset_list() -> str:
    """``rgbdslam config --list-presets``: every preset shipped in the package, the first line of
    its own comment, and the layouts ``run`` chooses it for without --config."""
    from rgbdslam.datasets.preset_choice import AUTOMATIC

    lines = []
    for name, res in sorted(C.preset_files().items()):
        text = res.read_text(encoding="utf-8").splitlines()
        about = next((ln.lstrip("# ").strip() for ln in text if ln.startswith("#")), "")
        lines.append(f"{name:<12} {about}")
        if name in AUTOMATIC:
            lines.append(f"{'':<12} chosen without --config for: {AUTOMATIC[name]}")
    return "\n".join(lines) + "\n"
