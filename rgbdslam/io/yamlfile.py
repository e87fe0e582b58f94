"""Reading a user's YAML (config files, ``--set`` values, camera files, ``stereo.yaml``, EuRoC
``sensor.yaml``) strictly, with one short error line for anything surprising.

PyYAML's ``safe_load`` is safe from code execution but not from surprises:

- an alias (``*a``) repeats a subtree: nine nested aliases make a billion-item list (an "alias
  bomb") that takes seconds to build and whose echo fills megabytes: **aliases are refused**;
- YAML 1.1 reads ``010`` as 8, ``0x6`` as 6, ``1_0`` as 10, ``1:00`` as 60 and ``1e3`` as the
  text "1e3": **numbers are read as YAML 1.2 writes them** (decimal integers, decimal floats with
  an optional exponent, ``.inf``, ``.nan``); any other spelling stays text, which a number
  check then refuses with its own line;
- a key given twice keeps the last silently: **a repeated key is refused**, naming its line;
- 10,000 nested brackets exhaust Python's recursion: **nesting deeper than** :data:`MAX_DEPTH`
  **is refused**; so is a number longer than :data:`MAX_DIGITS` characters (Python refuses to
  convert 120,000 digits).
"""

from __future__ import annotations

import re

import yaml
from yaml.composer import Composer
from yaml.events import AliasEvent

from rgbdslam.errors import InputError, shorten

MAX_DEPTH = 64  # nested mappings/lists in one user file
MAX_DIGITS = 64  # characters in one number

_INT = re.compile(r"^[-+]?[0-9]+$")
_FLOAT = re.compile(r"^[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?$")
_SPECIAL = re.compile(r"^(?:[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$")
_BOOL = re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$")
_NULL = re.compile(r"^(?:~|null|Null|NULL|)$")


class Refused(yaml.YAMLError):
    """What :class:`StrictLoader` refuses: the line and the problem."""

    def __init__(self, line: int, problem: str):
        super().__init__(problem)
        self.line, self.problem = line, problem


class StrictLoader(yaml.SafeLoader):
    """A SafeLoader without aliases, repeated keys, deep nesting or YAML 1.1 number spellings."""

    yaml_implicit_resolvers: dict = {}  # set below: the YAML 1.2 core schema, not 1.1's

    def __init__(self, stream):
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent, index):
        if self.check_event(AliasEvent):
            event = self.peek_event()
            raise Refused(event.start_mark.line + 1, f"uses the alias *{event.anchor[:20]}; write the "
                                                    f"value out (aliases are not read)")
        self._depth += 1
        if self._depth > MAX_DEPTH:
            raise Refused(self.peek_event().start_mark.line + 1, f"nests deeper than {MAX_DEPTH} levels")
        try:
            return Composer.compose_node(self, parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # "<<: {...}": merged keys may be overridden
                continue
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, (str, int, float, bool)) and key is not None:
                raise Refused(key_node.start_mark.line + 1, f"'{type(key).__name__}' is not a plain key name; keys "
                                                            f"are names like fx or min_votes")
            if key in seen:
                raise Refused(key_node.start_mark.line + 1, f"{shorten(key, 40)} is given twice in one section; "
                                                            f"keep one (YAML would silently use the last)")
            seen.add(key)
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node):
        text = self._digits(node)
        if not _INT.match(text):  # an explicit !!int on another spelling
            raise Refused(node.start_mark.line + 1, f"{shorten(text)} is not a decimal whole number")
        return int(text)

    def construct_yaml_float(self, node):
        text = self._digits(node)
        low = text.lower()
        if _SPECIAL.match(text):
            return float("nan") if "nan" in low else float("-inf") if low.startswith("-") else float("inf")
        if not (_FLOAT.match(text) or _INT.match(text)):
            raise Refused(node.start_mark.line + 1, f"{shorten(text)} is not a decimal number")
        return float(text)

    def _digits(self, node) -> str:
        text = self.construct_scalar(node)
        if len(text) > MAX_DIGITS:
            raise Refused(node.start_mark.line + 1, f"has a number of {len(text):,} characters (at most {MAX_DIGITS})")
        return text


StrictLoader.add_implicit_resolver("tag:yaml.org,2002:bool", _BOOL, list("tTfF"))
StrictLoader.add_implicit_resolver("tag:yaml.org,2002:int", _INT, list("-+0123456789"))
StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list("-+0123456789."))
StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _SPECIAL, list("-+."))
StrictLoader.add_implicit_resolver("tag:yaml.org,2002:null", _NULL, ["~", "n", "N", ""])
StrictLoader.add_implicit_resolver("tag:yaml.org,2002:merge", re.compile(r"^(?:<<)$"), ["<"])
StrictLoader.add_constructor("tag:yaml.org,2002:int", StrictLoader.construct_yaml_int)
StrictLoader.add_constructor("tag:yaml.org,2002:float", StrictLoader.construct_yaml_float)


def load_yaml(text: str, where: str, error: type[Exception] = InputError, what: str = "YAML"):
    """The value of the YAML ``text`` read by :class:`StrictLoader`; ``error`` (one line naming
    ``where`` and the line) for invalid YAML or what the loader refuses."""
    try:
        return yaml.load(text, Loader=StrictLoader)  # noqa: S506 - a SafeLoader
    except Refused as e:
        raise error(f"{where}:{e.line}: {e.problem}") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        at = f"{where}:{mark.line + 1}" if mark is not None else where
        raise error(f"{at}: not valid {what} ({shorten(getattr(e, 'problem', None) or type(e).__name__, 80)}); "
                    f"fix its syntax") from None
    except RecursionError:
        raise error(f"{where}: nests too deeply (at most {MAX_DEPTH} levels)") from None
