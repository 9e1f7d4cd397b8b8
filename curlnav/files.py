"""Reading the files a user (or anyone who hands them one) gives curlnav, at a bounded cost:
world, curriculum and config YAML, ``metadata.json``, rankings, pull listings.

- a size cap per file, checked before parsing (a 100 MB YAML took 98 s and 1.17 GB);
- YAML without aliases (a 388-byte alias bomb expands to 9**8 strings) and at most
  ``MAX_DEPTH`` levels of nesting (deeper ones overflowed PyYAML's recursion);
- JSON without NaN, Infinity or numbers that overflow to them (``1e400``), and a one-line
  refusal where nesting overflows the decoder's recursion;
- no key given twice in one mapping, YAML or JSON (a duplicate silently took the last value);
- numbers in ASCII decimal only, in files and on the command line (``decimal_int``,
  ``decimal_float``): YAML 1.1's ``0_1``, ``0x1f``, ``0o17``, ``1:30`` and a leading zero, and
  Python's ``int``/``float`` spellings with ``_`` or non-ASCII digits, are not numbers here (in a
  file they stay text, which the field's own check refuses);
- ``shown(value)``: a user value for an error message, cut to a few dozen characters.

Every refusal is a ``FileRefused`` (a ``ValueError``) with one line naming the file.
"""

from __future__ import annotations

import json
import math
import os
import re
import reprlib
from pathlib import Path
from typing import Any

import yaml

MAX_YAML_BYTES = 1 << 20  # world, curriculum and config files are a few KB
MAX_JSON_BYTES = 4 << 20  # metadata.json, rankings, pull listings
MAX_DEPTH = 64  # nesting levels of YAML or JSON

_PLAIN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}")

#: a whole number in ASCII decimal: an optional sign, then 0 or digits without a leading zero
DECIMAL_INT = re.compile(r"[-+]?(?:0|[1-9][0-9]*)")
#: a number in ASCII decimal: a whole number, a decimal fraction, or either with an exponent
DECIMAL_FLOAT = re.compile(r"[-+]?(?:(?:0|[1-9][0-9]*)(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")

__all__ = ["DECIMAL_FLOAT", "DECIMAL_INT", "FileRefused", "MAX_DEPTH", "MAX_JSON_BYTES", "MAX_YAML_BYTES",
           "decimal_float", "decimal_int", "is_plain_file_name", "loads_json", "loads_yaml", "read_capped",
           "read_json", "read_yaml", "shown"]


class FileRefused(ValueError):
    """A file (or text) curlnav will not parse: too large, too deep, aliased, or not finite."""


def shown(value: Any, limit: int = 60) -> str:
    """``repr(value)`` for an error message, at most about ``limit`` characters, whatever its size."""
    short = reprlib.Repr()
    short.maxstring = short.maxother = limit
    short.maxlist = short.maxtuple = short.maxdict = short.maxset = 6
    short.maxlevel = 3
    text = short.repr(value)
    return text if len(text) <= limit + 10 else text[:limit] + "..."


def decimal_int(text: str) -> int:
    """``text`` (surrounding blanks dropped) as a whole number in ASCII decimal (``DECIMAL_INT``);
    ``ValueError`` (one line) for anything else: ``0_1``, ``0x1f``, ``1e3``, non-ASCII digits."""
    stripped = text.strip() if isinstance(text, str) else text
    if not isinstance(stripped, str) or len(stripped) > 40 or not DECIMAL_INT.fullmatch(stripped):
        raise ValueError(f"not a whole number in decimal digits: {shown(text, 40)}")
    return int(stripped)


def decimal_float(text: str) -> float:
    """``text`` (surrounding blanks dropped) as a finite number in ASCII decimal (``DECIMAL_FLOAT``);
    ``ValueError`` (one line) for anything else: ``0_1``, ``nan``, ``inf``, ``1e400``, non-ASCII digits."""
    stripped = text.strip() if isinstance(text, str) else text
    if not isinstance(stripped, str) or len(stripped) > 60 or not DECIMAL_FLOAT.fullmatch(stripped):
        raise ValueError(f"not a number in decimal digits: {shown(text, 40)}")
    value = float(stripped)
    if not math.isfinite(value):
        raise ValueError(f"not a finite number: {shown(text, 40)}")
    return value


def is_plain_file_name(name: Any) -> bool:
    """A file name alone: no separator, no ``..``, not hidden, no absolute path, 1-128 characters."""
    return isinstance(name, str) and _PLAIN_NAME.fullmatch(name) is not None and ".." not in name


def read_capped(path: str | os.PathLike, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of ``path``, refused beyond ``max_bytes`` (read no further: /dev/zero ends too).
    Raises ``OSError`` when it cannot be read."""
    with open(path, "rb") as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise FileRefused(f"{path}: a {what} above {max_bytes // 1024} KiB; refused")
    return data


def _decode(data: bytes, source: str) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FileRefused(f"{source}: not UTF-8 text (byte {exc.start})") from None


# -- YAML ----------------------------------------------------------------------------------------
_INT_TAG, _FLOAT_TAG = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"
_YAML_FLOAT = re.compile(rf"{DECIMAL_FLOAT.pattern}|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)")


class _BoundedLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses aliases, more than ``MAX_DEPTH`` levels of nesting and a key
    given twice, and reads numbers in ASCII decimal only (``DECIMAL_INT``, ``DECIMAL_FLOAT``; ``.inf``
    and ``.nan`` too, which the fields' own checks refuse)."""

    # YAML 1.1's number forms (``0_1`` is octal 1, ``1:30`` is 90) replaced by decimal ones
    yaml_implicit_resolvers = {
        first: [(tag, rx) for tag, rx in resolvers if tag not in (_INT_TAG, _FLOAT_TAG)]
        for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}

    def __init__(self, stream) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(None, None, "aliases (*name) are not allowed in curlnav files",
                                              event.start_mark)
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise yaml.composer.ComposerError(None, None, f"nested too deep (more than {MAX_DEPTH} levels)",
                                                  self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            self.flatten_mapping(node)
            seen: set = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    duplicate = key in seen
                    seen.add(key)
                except TypeError:  # an unhashable key: the base class names it
                    continue
                if duplicate:
                    raise yaml.constructor.ConstructorError(None, None, f"the key {shown(key, 40)} is given twice",
                                                            key_node.start_mark)
        return super().construct_mapping(node, deep)

    def construct_yaml_int(self, node):
        text = self.construct_scalar(node)
        if not DECIMAL_INT.fullmatch(text):
            raise yaml.constructor.ConstructorError(None, None, f"{shown(text, 40)} is not a whole number in "
                                                    "decimal digits", node.start_mark)
        return int(text)

    def construct_yaml_float(self, node):
        text = self.construct_scalar(node)
        if not _YAML_FLOAT.fullmatch(text):
            raise yaml.constructor.ConstructorError(None, None, f"{shown(text, 40)} is not a number in decimal "
                                                    "digits", node.start_mark)
        return super().construct_yaml_float(node)

    # flow collections ([ ... ], { ... }) recurse in the parser, before the composer sees them
    def fetch_flow_collection_start(self, token_class):
        if self.flow_level >= MAX_DEPTH:
            raise yaml.scanner.ScannerError(None, None, f"nested too deep (more than {MAX_DEPTH} levels)",
                                            self.get_mark())
        super().fetch_flow_collection_start(token_class)


_BoundedLoader.add_implicit_resolver(_INT_TAG, re.compile(rf"^{DECIMAL_INT.pattern}$"), list("-+0123456789"))
_BoundedLoader.add_implicit_resolver(_FLOAT_TAG, re.compile(rf"^(?:{_YAML_FLOAT.pattern})$"), list("-+0123456789."))
_BoundedLoader.add_constructor(_INT_TAG, _BoundedLoader.construct_yaml_int)
_BoundedLoader.add_constructor(_FLOAT_TAG, _BoundedLoader.construct_yaml_float)


def loads_yaml(text: str, source: str = "<text>") -> Any:
    """Parse YAML text without aliases and deep nesting; ``FileRefused`` names ``source`` and the spot."""
    try:
        return yaml.load(text, Loader=_BoundedLoader)  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise FileRefused(f"{source}: not valid YAML{where}: {shown(problem, 160)[1:-1]}") from None
    except RecursionError:
        raise FileRefused(f"{source}: nested too deep") from None


def read_yaml(path: str | os.PathLike, max_bytes: int = MAX_YAML_BYTES, what: str = "YAML file") -> Any:
    """Read and parse a YAML file with the caps above. Raises ``OSError`` when unreadable."""
    return loads_yaml(_decode(read_capped(path, max_bytes, what), str(path)), str(path))


# -- JSON ----------------------------------------------------------------------------------------
def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise FileRefused(f"the number {shown(text, 30)} is not finite")
    return value


def _no_constant(name: str):
    raise FileRefused(f"{name} is not a number curlnav accepts")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict:
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise FileRefused(f"the key {shown(key, 40)} is given twice")
        out[key] = value
    return out


def loads_json(text: str | bytes, source: str = "<text>") -> Any:
    """Parse JSON refusing NaN, Infinity, numbers beyond float range and deep nesting;
    ``FileRefused`` names ``source``."""
    if isinstance(text, bytes):
        text = _decode(text, source)
    try:
        return json.loads(text, parse_float=_finite, parse_constant=_no_constant, object_pairs_hook=_unique_keys)
    except FileRefused as exc:
        raise FileRefused(f"{source}: {exc}") from None
    except RecursionError:
        raise FileRefused(f"{source}: nested too deep") from None
    except ValueError as exc:  # JSONDecodeError, or an integer of more than 4300 digits
        raise FileRefused(f"{source}: not valid JSON: {shown(str(exc), 120)[1:-1]}") from None


def read_json(path: str | os.PathLike, max_bytes: int = MAX_JSON_BYTES, what: str = "JSON file") -> Any:
    """Read and parse a JSON file with the caps above. Raises ``OSError`` when unreadable."""
    return loads_json(read_capped(Path(path), max_bytes, what), str(path))
