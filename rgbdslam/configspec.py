"""How a config key is declared: once, on its field, with its range and description.

Each stage owns its section's dataclass (``rgbdslam/<stage>/config.py``); every field carries one
of the markers below in ``Annotated``::

    search_radius: Annotated[float, Positive(1000.0, "pixels around a landmark's projection")] = 10.0
    mode: Annotated[Literal["seed", "fuse"], Key("how the map pose combines with ...")] = "fuse"

* :class:`Key` - a choice, flag or text: the description only;
* :class:`Range` - a number in the closed interval ``[lo, hi]``;
* :class:`AtMost` - a number in ``[0, hi]``;
* :class:`Positive` - a number in ``(0, hi]`` (an int: ``[1, hi]``).

Every numeric key needs an upper bound its consumer accepts (a C int for OpenCV/GTSAM/Open3D
arguments and seeds, a memory or time budget for sizes and iteration counts), so that an absurd value
stops before any work instead of failing in a library after the run; a numeric field with a bare
:class:`Key` fails :func:`numeric_without_range` (tests/test_config.py walks every section with it).
``rgbdslam.config`` composes the sections, checks the values (:func:`check`) and cross-checks keys of
one section against each other; ``rgbdslam config --explain`` prints the descriptions.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, get_args, get_origin, get_type_hints

from rgbdslam.errors import ConfigError, shorten

C_INT_MAX = 2**31 - 1  # seeds and counts handed to OpenCV, GTSAM and Open3D are C ints


@dataclass(frozen=True)
class Key:
    """A key that is not a number (choice, flag, text): its one-line description."""

    doc: str


@dataclass(frozen=True)
class Range:
    """A number in the closed interval ``[lo, hi]``."""

    lo: float
    hi: float
    doc: str

    def bounds(self, kind: type) -> tuple[float, bool, float]:
        return self.lo, False, self.hi

    def check(self, key: str, v: float) -> None:
        if not self.lo <= v <= self.hi:
            raise ConfigError(f"config key '{key}' must be between {bound_text(self.lo)} and {bound_text(self.hi)}; "
                              f"got {shorten(v)}")


@dataclass(frozen=True)
class AtMost:
    """A number in ``[0, hi]``."""

    hi: float
    doc: str

    def bounds(self, kind: type) -> tuple[float, bool, float]:
        return 0, False, self.hi

    def check(self, key: str, v: float) -> None:
        if not v >= 0:
            raise ConfigError(f"config key '{key}' must not be negative; got {shorten(v)}")
        _check_high(key, v, self.hi)


@dataclass(frozen=True)
class Positive:
    """A number in ``(0, hi]``; an int in ``[1, hi]``."""

    hi: float
    doc: str

    def bounds(self, kind: type) -> tuple[float, bool, float]:
        return (1, False, self.hi) if kind is int else (0.0, True, self.hi)

    def check(self, key: str, v: float) -> None:
        if isinstance(v, int):
            if not v >= 1:
                raise ConfigError(f"config key '{key}' must be at least 1; got {shorten(v)}")
        elif not v > 0:
            raise ConfigError(f"config key '{key}' must be positive; got {shorten(v)}")
        _check_high(key, v, self.hi)


NUMERIC = (Range, AtMost, Positive)


def _check_high(key: str, v: float, hi: float) -> None:
    if not v <= hi:
        raise ConfigError(f"config key '{key}' must be at most {bound_text(hi)}; got {shorten(v)}")


def bound_text(x: int | float) -> str:
    """A range bound as written: whole numbers in full (2147483647, not 2.14748e+09)."""
    if isinstance(x, int) or (math.isfinite(x) and x == int(x) and abs(x) < 1e16):
        return str(int(x)) if abs(x) < 1e7 or x != 10 ** round(math.log10(abs(x))) else f"{x:g}"
    return f"{x:g}"


def number_kind(hint: Any) -> type | None:
    """int or float when the field holds a number (optionally None), else None."""
    args = get_args(hint) if get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
    return next((a for a in args if a in (int, float)), None)


@lru_cache(maxsize=None)
def field_specs(cls: type) -> dict[str, Key | Range | AtMost | Positive | None]:
    """``{field: its marker}`` of section dataclass ``cls`` (None: the field has none)."""
    hints = get_type_hints(cls, include_extras=True)
    out = {}
    for f in dataclasses.fields(cls):
        meta = getattr(hints[f.name], "__metadata__", ())
        out[f.name] = next((m for m in meta if isinstance(m, (Key, *NUMERIC))), None)
    return out


def numeric_without_range(cls: type) -> list[str]:
    """The fields of ``cls`` that hold a number but declare no range (or no marker at all)."""
    hints = get_type_hints(cls)
    specs = field_specs(cls)
    return [n for n, s in specs.items() if (number_kind(hints[n]) is not None) != isinstance(s, NUMERIC)
            or s is None]


def check(key: str, spec: Any, v: int | float) -> None:
    """ConfigError naming ``key`` when number ``v`` is outside the range ``spec`` declares."""
    if not isinstance(spec, NUMERIC):
        raise ConfigError(f"config key '{key}' holds a number but declares no range (Range, AtMost or Positive)")
    spec.check(key, v)
