"""The config schema's vocabulary and its checker: what a section's values may be, and the
one-line messages (dotted key, value, what is allowed, the fix) that a bad value raises.

`Check` checks and normalises the fields of one section in its `__post_init__` (an int becomes a
float where a number is expected, an array a tuple); `suggest` adds a "did you mean" to a
misspelt name; `TableSection` is what every section provides to `torchfric.app.config`.
Within `recording_checks`, `Check` also notes each key it checks and its bounds (`Checked`):
the config reference (`torchfric.app.config.reference`) is generated from those notes.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import difflib
import math
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, ClassVar, NoReturn

from ...data.rig import EXPERIMENTS
from ...errors import TorchfricError, shorten
from .toml_io import toml_value

__all__ = [
    "INIT_KEYWORDS",
    "RIG_PREFIX",
    "RIG_VALIDATION",
    "VELOCITY_SOURCES",
    "Check",
    "Checked",
    "TableSection",
    "is_number",
    "recording_checks",
    "show",
    "suggest",
    "unknown_section_key",
]

RIG_PREFIX = "rig:"
"""A data path ``"rig:NAME"`` names the synthetic rig's experiment NAME instead of a file."""
RIG_VALIDATION: tuple[str, ...] = (RIG_PREFIX + "validation",)
"""``data.validation``'s default for rig data (a user's data has none by default)."""
INIT_KEYWORDS: tuple[str, ...] = ("prefit", "config")
VELOCITY_SOURCES: tuple[str, ...] = ("highpass", "zero_phase", "measured")


# --------------------------------------------------------------------------------------------
# Formatting and checking helpers
# --------------------------------------------------------------------------------------------


def _type_name(value: Any) -> str:
    if value is None:
        return "none"
    names = {bool: "boolean", int: "integer", float: "float", str: "string"}
    if type(value) in names:
        return names[type(value)]
    if isinstance(value, list | tuple):
        return "array"
    if isinstance(value, Mapping):
        return "table"
    return type(value).__name__


def _field_default(f: dataclasses.Field[Any]) -> Any:
    return f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]


def _a(noun: str) -> str:
    return ("an " if noun[:1] in "aeiou" else "a ") + noun


def show(value: Any) -> str:
    """`value` as it would be written in TOML (else its repr), shortened for a message."""
    try:
        text = toml_value(value)
    except (TorchfricError, RecursionError):
        text = repr(value)
    return shorten(text)


def suggest(word: str, allowed: Sequence[str]) -> str:
    """``' (did you mean "X"?)'`` for the closest of `allowed` to `word`, else ""."""
    close = difflib.get_close_matches(word, list(allowed), n=1, cutoff=0.6)
    return f' (did you mean "{close[0]}"?)' if close else ""


def is_number(value: Any) -> bool:
    """An int or a float, not a bool."""
    return isinstance(value, int | float) and not isinstance(value, bool)


@dataclasses.dataclass(frozen=True)
class Checked:
    """One key as a `Check` checked it: dotted `key`, the check's `kind` (the `Check` method:
    "number", "integer", "auto_or_integer", "boolean", "string", "numbers" or "paths") and the
    bounds it was given (``gt``, ``ge``, ``optional``, ``choices``, ``length``, ...)."""

    key: str
    kind: str
    bounds: Mapping[str, Any]


_RECORDING: contextvars.ContextVar[list[Checked] | None] = contextvars.ContextVar(
    "torchfric_recording_checks", default=None
)


@contextlib.contextmanager
def recording_checks() -> Iterator[list[Checked]]:
    """Within the block, each key a `Check` checks is appended to the list yielded, in the order
    checked (a key checked twice, e.g. "auto" or an integer, is noted twice: first the outer
    check)."""
    notes: list[Checked] = []
    token = _RECORDING.set(notes)
    try:
        yield notes
    finally:
        _RECORDING.reset(token)


class Check:
    """Checks and normalises the fields of one (frozen) section in its `__post_init__`."""

    def __init__(self, obj: Any, section: str, defaults: Mapping[str, Any] | None = None) -> None:
        """Check `obj`'s attributes as keys of `section` ("" = top level); `defaults` (key →
        default, for the messages) defaults to `obj`'s dataclass field defaults."""
        self.obj = obj
        self.section = section
        if defaults is None:
            defaults = {f.name: _field_default(f) for f in dataclasses.fields(obj)}
        self.defaults = defaults

    def key(self, name: str) -> str:
        return f"{self.section}.{name}" if self.section else name

    def _note(self, name: str, kind: str, **bounds: Any) -> None:
        notes = _RECORDING.get()
        if notes is not None:
            notes.append(Checked(self.key(name), kind, bounds))

    def _hint(self, name: str, example: Any) -> str:
        if example is None:
            example = self.defaults[name]
        return f"; write e.g. {self.key(name)} = {show(example)}" if example is not None else ""

    def type_error(self, name: str, value: Any, expected: str, example: Any = None) -> NoReturn:
        raise TorchfricError(
            f"{self.key(name)} = {show(value)} is {_a(_type_name(value))}, expected {expected}"
            + self._hint(name, example)
        )

    def range_error(self, name: str, value: Any, allowed: str) -> NoReturn:
        default = self.defaults[name]
        tail = f" (the default is {show(default)})" if default is not None else ""
        raise TorchfricError(
            f"{self.key(name)} = {show(value)} is out of range; allowed: {allowed}{tail}"
        )

    def set(self, name: str, value: Any) -> None:
        object.__setattr__(self.obj, name, value)

    def number(
        self,
        name: str,
        *,
        gt: float | None = None,
        ge: float | None = None,
        optional: bool = False,
        example: Any = None,
    ) -> None:
        self._note(name, "number", gt=gt, ge=ge, optional=optional)
        value = getattr(self.obj, name)
        if value is None and optional:
            return
        if not is_number(value):
            self.type_error(name, value, "a number", example)
        value = float(value)
        if not math.isfinite(value):
            self.range_error(name, value, "a finite number")
        if gt is not None and not value > gt:
            self.range_error(name, value, f"a number > {gt:g}")
        if ge is not None and not value >= ge:
            self.range_error(name, value, f"a number >= {ge:g}")
        self.set(name, value)

    def integer(
        self, name: str, *, ge: int | None = None, optional: bool = False, example: Any = None
    ) -> None:
        self._note(name, "integer", ge=ge, optional=optional)
        value = getattr(self.obj, name)
        if value is None and optional:
            return
        if isinstance(value, bool) or not isinstance(value, int):
            self.type_error(name, value, "an integer", example)
        if ge is not None and value < ge:
            self.range_error(name, value, f"an integer >= {ge}")
        if not -(2**63) <= value < 2**63:
            self.range_error(name, value, "a 64-bit integer")
        self.set(name, int(value))

    def auto_or_integer(self, name: str, *, ge: int, example: int) -> None:
        """``"auto"``, or an integer >= `ge` (`integer`'s checks)."""
        self._note(name, "auto_or_integer", ge=ge)
        value = getattr(self.obj, name)
        if value == "auto":
            return
        if isinstance(value, bool) or not isinstance(value, int):
            self.type_error(name, value, f'"auto" or an integer >= {ge}', example)
        self.integer(name, ge=ge)

    def auto_or_number(self, name: str, *, ge: float, example: float) -> None:
        """``"auto"``, or a finite number >= `ge` (`number`'s checks)."""
        self._note(name, "auto_or_number", ge=ge)
        value = getattr(self.obj, name)
        if value == "auto":
            return
        if not is_number(value):
            self.type_error(name, value, f'"auto" or a number >= {ge:g}', example)
        self.number(name, ge=ge)  # its note comes second: the first one is kept

    def boolean(self, name: str) -> None:
        self._note(name, "boolean")
        value = getattr(self.obj, name)
        if not isinstance(value, bool):
            self.type_error(name, value, "true or false")

    def string(self, name: str, *, choices: Sequence[str] | None = None) -> str:
        self._note(name, "string", choices=None if choices is None else tuple(choices))
        value = getattr(self.obj, name)
        listed = ", ".join(f'"{c}"' for c in choices or ())
        if not isinstance(value, str):
            self.type_error(name, value, "a string" if choices is None else f"one of {listed}")
        if choices is not None and value not in choices:
            raise TorchfricError(
                f"{self.key(name)} = {show(value)} is not allowed; choose one of {listed}"
                + suggest(value, choices)
            )
        if not value:
            self.range_error(name, value, "a non-empty string")
        return value

    def numbers(
        self, name: str, *, length: int | None = None, ge: float | None = None, scalar: bool = False
    ) -> None:
        """An array of finite numbers (or, with `scalar`, also one number) → tuple/float."""
        self._note(name, "numbers", length=length, ge=ge, scalar=scalar)
        value = getattr(self.obj, name)
        if scalar and is_number(value):
            self.number(name, ge=ge)
            return
        expected = "a number or an array of numbers" if scalar else "an array of numbers"
        if not isinstance(value, list | tuple) or not all(is_number(v) for v in value):
            self.type_error(name, value, expected)
        out = tuple(float(v) for v in value)
        if length is not None and len(out) != length:
            self.range_error(name, value, f"exactly {length} numbers")
        if not out:
            self.range_error(name, value, "at least one number")
        if not all(math.isfinite(v) and (ge is None or v >= ge) for v in out):
            what = "finite numbers" + (f" >= {ge:g}" if ge is not None else "")
            self.range_error(name, value, what)
        self.set(name, out)

    def paths(self, name: str, *, nonempty: bool) -> None:
        """A path string or an array of them → tuple of strings; ``rig:`` names validated."""
        self._note(name, "paths", nonempty=nonempty)
        value = getattr(self.obj, name)
        if isinstance(value, str):
            value = (value,)
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            self.type_error(name, value, "a path string or an array of path strings")
        value = tuple(value)
        if nonempty and not value:
            self.range_error(name, list(value), "at least one path")
        rigs = [RIG_PREFIX + e for e in EXPERIMENTS]
        for i, p in enumerate(value):
            if not p:
                self.range_error(name, list(value), "non-empty path strings")
            if p.startswith(RIG_PREFIX) and p not in rigs:
                raise TorchfricError(
                    f"{self.key(name)}[{i}] = {show(p)} is not a rig experiment"
                    f"{suggest(p, rigs)}; choose one of {', '.join(rigs)}, or give a file path"
                )
        self.set(name, value)


class TableSection:
    """What a config section provides to `torchfric.app.config`: its TOML keys, building it from
    its table and writing it back. This base serves the sections whose keys are their own
    dataclass fields; `EstimatorConfig` routes its flat keys into the estimators' settings.
    """

    PATH_KEYS: ClassVar[tuple[str, ...]] = ()
    """Keys holding paths, made absolute against the config file's folder (or the cwd)."""

    @classmethod
    def toml_keys(cls) -> dict[str, str]:
        """The section's keys in TOML order → their annotation as written (e.g. ``"str"``)."""
        return {f.name: str(f.type) for f in dataclasses.fields(cls)}  # type: ignore[arg-type]

    @classmethod
    def from_table(cls, table: Mapping[str, Any]) -> Any:
        """The section built (and validated) from its table of known keys."""
        return cls(**table)

    def to_table(self) -> dict[str, Any]:
        """The section's keys → values, in `toml_keys` order."""
        return {name: getattr(self, name) for name in self.toml_keys()}


def unknown_section_key(dotted: str, section: str, allowed: Sequence[str]) -> TorchfricError:
    """The error for an unknown key `dotted` of `section`, whose keys are `allowed`."""
    dotted_allowed = [f"{section}.{k}" for k in allowed]
    return TorchfricError(
        f'unknown key "{dotted}"{suggest(dotted, dotted_allowed)}; allowed keys '
        f"in [{section}]: {', '.join(allowed)}"
    )
