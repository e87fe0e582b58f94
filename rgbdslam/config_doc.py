"""``rgbdslam config --explain``: every config key with its type, range, default and description.

The description of a key is the comment written next to its field in ``rgbdslam/config.py``
(the trailing ``# ...`` on the field's line, else the comment lines right above it), so the
documentation lives beside the field and its range beside the rules (``SIGNED``, ``POSITIVE``,
``BOUNDS``, ``MAXIMA``, ``ORDERED``) that :func:`rgbdslam.config.validate_section` enforces: nothing is
written twice. A test checks that every key has a description.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import textwrap
import tokenize
import types
import typing
from functools import lru_cache
from typing import Any, Literal, get_args, get_origin, get_type_hints

from rgbdslam import config as C


@lru_cache(maxsize=None)
def field_comments(cls: type) -> dict[str, str]:
    """``{field: description}`` from the comments next to the fields of dataclass ``cls``."""
    src = textwrap.dedent(inspect.getsource(cls))
    comments: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = tok.string.lstrip("#").strip()
    lines = src.splitlines()
    out: dict[str, str] = {}
    for node in ast.parse(src).body[0].body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        text = comments.get(node.end_lineno, "") if lines[node.end_lineno - 1].split("#")[0].strip() else ""
        if not text:  # the comment block right above the field
            block, k = [], node.lineno - 1
            while k >= 1 and k in comments and lines[k - 1].lstrip().startswith("#"):
                block.insert(0, comments[k])
                k -= 1
            text = " ".join(block)
        out[node.target.id] = text
    return out


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
        notes = field_comments(cls)
        for f in dataclasses.fields(cls):
            key = f"{section.name}.{f.name}"
            rows.append({"key": key, "type": _type_name(hints[f.name]), "range": key_range(key, hints[f.name]),
                         "default": _value(getattr(getattr(defaults, section.name), f.name)),
                         "value": _value(getattr(getattr(cfg, section.name), f.name)),
                         "description": notes.get(f.name, "")})
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
