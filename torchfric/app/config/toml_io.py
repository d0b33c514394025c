"""TOML in and out for run configs: a small writer and the ``--set`` value parser.

The standard library reads TOML (`tomllib`) but does not write it; `to_toml` writes what a
config holds (str, int, float, bool, arrays, nested tables; ``None`` omitted), so that a resolved
config stored in a run directory or a checkpoint reads back to the same `Config`.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Mapping
from typing import Any

from ...errors import TorchfricError

__all__ = ["parse_value", "to_toml", "toml_value"]

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
_ESCAPES = {'"': '\\"', "\\": "\\\\", "\n": "\\n", "\t": "\\t", "\r": "\\r", "\b": "\\b"}


def _toml_string(s: str) -> str:
    out = []
    for ch in s:
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _toml_key(key: Any) -> str:
    if not isinstance(key, str):
        raise TorchfricError(f"TOML keys must be strings, got {key!r}")
    return key if _BARE_KEY.fullmatch(key) else _toml_string(key)


def toml_value(value: Any) -> str:
    """`value` as a TOML value (tables inline); raises `TorchfricError` for other types."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return _toml_string(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value if v is not None) + "]"
    if isinstance(value, Mapping):
        items = [f"{_toml_key(k)} = {toml_value(v)}" for k, v in value.items() if v is not None]
        return "{ " + ", ".join(items) + " }" if items else "{}"
    raise TorchfricError(f"cannot write {value!r} ({type(value).__name__}) as a TOML value")


def to_toml(data: Mapping[str, Any]) -> str:
    """Nested tables → TOML text: top-level keys, then one ``[section]`` per top-level table;
    tables inside sections are written inline (``columns = { q = "qm" }``)."""
    lines = [f"{_toml_key(k)} = {toml_value(v)}" for k, v in data.items() if _scalar(v)]
    for k, v in data.items():
        if isinstance(v, Mapping):
            lines += ["", f"[{_toml_key(k)}]"] if lines else [f"[{_toml_key(k)}]"]
            lines += [
                f"{_toml_key(kk)} = {toml_value(vv)}" for kk, vv in v.items() if vv is not None
            ]
    return "\n".join(lines) + "\n"


def _scalar(value: Any) -> bool:
    return value is not None and not isinstance(value, Mapping)


def parse_value(text: str, string_field: bool) -> Any:
    """A ``--set`` VALUE: a TOML value when `text` parses as one, else the bare string.

    For a string key (`string_field`) a value that parses as a number or a boolean stays the
    text as written: ``name=2024`` or a path like ``12`` is a string.
    """
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text
    if string_field and not isinstance(value, str | list | dict):
        return text  # name=2024 or a path like 12 stays a string
    return value
