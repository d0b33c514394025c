"""A sweep's search space: the ``[space]`` table of SPACE.toml, checked against the config.

    [space]
    "estimator.p0_theta" = { low = 0.1, high = 10.0, log = true }   # a float, log-uniform
    "estimator.passes"   = { low = 2, high = 8, int = true }         # an integer
    "model.size"         = { choices = [2, 3, 4] }                   # one of a list

Each key is a config key as ``--set`` names it (dotted, or ``seed`` at the top). A range has
``low`` and ``high`` (numbers, low < high) and optionally ``log = true`` (low > 0), ``int = true``
(integer ends; the key must take integers) and ``step`` (a grid: low, low + step, ...; not with
log). ``choices`` is a non-empty list of values as ``--set`` would take them; arrays (an
``estimator.r`` pair, say) are allowed and are shown as their TOML text. Both ends of a range and
every choice must make a valid config on their own (`read_space` checks them all), so a sweep
never starts with a space its first trial would refuse.
"""

from __future__ import annotations

import math
import pathlib
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ...errors import TorchfricError, shorten
from ..config import is_number, parse_value, show, suggest, toml_value

if TYPE_CHECKING:
    from ..config import Config

__all__ = ["Param", "read_space", "space_table", "MAX_SPACE_BYTES"]

MAX_SPACE_BYTES = 100_000
# Keys the sweep sets itself: the study and its trials' folders are named after them.
_OWN_KEYS = ("name", "out_dir")
_RANGE_FIELDS = ("low", "high", "log", "int", "step")


@dataclass(frozen=True)
class Param:
    """One dimension of the space: the config `key` and its range or choices."""

    key: str
    low: float | int | None = None
    high: float | int | None = None
    log: bool = False
    integer: bool = False
    step: float | int | None = None
    choices: tuple[Any, ...] | None = None

    @property
    def encoded(self) -> bool:
        """Whether the choices go to Optuna as their TOML text (arrays, tables: Optuna's
        categorical values are scalars)."""
        return self.choices is not None and not all(
            c is None or isinstance(c, bool | int | float | str) for c in self.choices
        )

    def distribution(self) -> Any:
        """The Optuna distribution of this dimension."""
        import optuna.distributions as od

        if self.choices is not None:
            values = [toml_value(c) for c in self.choices] if self.encoded else self.choices
            return od.CategoricalDistribution(list(values))
        if self.integer:
            return od.IntDistribution(
                int(self.low), int(self.high), log=self.log, step=int(self.step or 1)
            )
        return od.FloatDistribution(float(self.low), float(self.high), log=self.log, step=self.step)

    def suggest(self, trial: Any) -> Any:
        """This dimension's value for an Optuna `trial` (a config value: `value` decoded)."""
        if self.choices is not None:
            return self.value(trial.suggest_categorical(self.key, self.distribution().choices))
        if self.integer:
            return trial.suggest_int(
                self.key, int(self.low), int(self.high), step=int(self.step or 1), log=self.log
            )
        return trial.suggest_float(
            self.key, float(self.low), float(self.high), step=self.step, log=self.log
        )

    def value(self, suggested: Any) -> Any:
        """The config value of what Optuna suggested (TOML text back to an array)."""
        if self.encoded and isinstance(suggested, str):
            return parse_value(suggested, False)
        return suggested

    def describe(self) -> str:
        """The dimension as SPACE.toml writes it (for messages and the summary)."""
        if self.choices is not None:
            return f"{self.key} in {toml_value(list(self.choices))}"
        kind = "int" if self.integer else "float"
        extra = ", log" if self.log else f", step {self.step:g}" if self.step else ""
        return f"{self.key} in [{self.low:g}, {self.high:g}] ({kind}{extra})"


def space_table(params: list[Param]) -> dict[str, dict[str, Any]]:
    """The space as a plain table (stored with the study: a resumed sweep must use the same)."""
    out: dict[str, dict[str, Any]] = {}
    for p in params:
        if p.choices is not None:
            out[p.key] = {"choices": list(p.choices)}
            continue
        spec: dict[str, Any] = {"low": p.low, "high": p.high}
        spec.update({"log": True} if p.log else {})
        spec.update({"int": True} if p.integer else {})
        spec.update({"step": p.step} if p.step is not None else {})
        out[p.key] = spec
    return out


def read_space(path: str | pathlib.Path, cfg: Config) -> list[Param]:
    """Read SPACE.toml and check each dimension against `cfg`'s schema and values.

    Raises `TorchfricError` (one line naming the key and the fix) for a missing or unreadable
    file, a file without a ``[space]`` table, an unknown config key, a range that is not
    numeric or empty, a log range reaching 0, ``int = true`` on a key that takes floats (or
    a float range on an integer key), and any end or choice that the config itself refuses.
    """
    p = pathlib.Path(path)
    if not p.is_file():
        raise TorchfricError(
            f"--space {p}: {'not a regular file' if p.exists() else 'no such file'}; give a "
            'TOML file with a [space] table, e.g. "estimator.passes" = { low = 2, high = 8, '
            "int = true }"
        )
    if p.stat().st_size > MAX_SPACE_BYTES:
        raise TorchfricError(
            f"--space {p} is {p.stat().st_size:,} bytes; a space is a few lines: give the "
            "TOML file with its [space] table"
        )
    try:
        raw = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise TorchfricError(f"--space {p}: invalid TOML: {shorten(str(exc))}; fix it") from None
    extra = [k for k in raw if k != "space"]
    if extra or not isinstance(raw.get("space"), Mapping) or not raw["space"]:
        what = f"has {show(extra[0])} beside it" if extra else "has no [space] table or it is empty"
        raise TorchfricError(
            f"--space {p} {what}; a space file holds one [space] table of dotted config keys, "
            'e.g. [space] then "estimator.p0_theta" = { low = 0.1, high = 10.0, log = true }'
        )
    return [_param(p, str(key), spec, cfg) for key, spec in raw["space"].items()]


def _key_type(where: str, key: str) -> str:
    """The schema's type of config `key` (e.g. ``"int"``, ``"float | None"``)."""
    from ..config import SCHEMA, SECTIONS, TOP_TYPES

    if key in _OWN_KEYS:
        raise TorchfricError(
            f"{where}: {key} cannot be swept: the sweep names the study and its trials' folders "
            "after the config; remove it from [space]"
        )
    section, _, name = key.partition(".")
    if not name:
        if key in TOP_TYPES:
            return TOP_TYPES[key]
        allowed = [k for k in SCHEMA[""] if k not in _OWN_KEYS]
    elif section in SECTIONS and name in (types := SECTIONS[section].toml_keys()):
        return types[name]
    else:
        allowed = [f"{s}.{k}" for s, keys in SCHEMA.items() if s for k in keys] + ["seed"]
    raise TorchfricError(
        f'{where}: unknown config key "{key}"{suggest(key, allowed)}; [space] keys are config '
        'keys as --set names them, e.g. "estimator.passes" or "model.size" (see docs/config.md)'
    )


def _param(path: pathlib.Path, key: str, spec: Any, cfg: Config) -> Param:
    where = f"--space {path.name}: [space] {key}"
    kind = _key_type(f"--space {path.name}", key)
    if not isinstance(spec, Mapping):
        raise TorchfricError(
            f"{where} = {show(spec)} must be a table: {{ low = ..., high = ... }} or "
            "{ choices = [...] }"
        )
    if "choices" in spec:
        if set(spec) != {"choices"}:
            raise TorchfricError(
                f"{where}: give either choices or a range (low, high, ...), not both"
            )
        choices = spec["choices"]
        if not isinstance(choices, list) or not choices:
            raise TorchfricError(f"{where}: choices = {show(choices)} must be a non-empty list")
        if len({toml_value(c) for c in choices}) < len(choices):
            raise TorchfricError(
                f"{where}: choices = {show(choices)} repeats a value; list each once"
            )
        param = Param(key, choices=tuple(choices))
        for c in choices:
            _check_value(cfg, where, key, c, "a choice")
        return param
    unknown = [k for k in spec if k not in _RANGE_FIELDS]
    if unknown:
        raise TorchfricError(
            f'{where}: unknown field "{unknown[0]}"{suggest(str(unknown[0]), _RANGE_FIELDS)}; a '
            "range has low, high and optionally log, int, step; a list has choices"
        )
    return _range(cfg, where, key, kind, spec)


def _range(cfg: Config, where: str, key: str, kind: str, spec: Mapping[str, Any]) -> Param:
    low, high = spec.get("low"), spec.get("high")
    scalars = {part.strip() for part in kind.split("|")}
    takes_float, takes_int = "float" in scalars, "int" in scalars
    if not (takes_float or takes_int):
        raise TorchfricError(
            f"{where}: {key} is not a number (it takes {kind}); sweep it with "
            "{ choices = [...] } instead of low/high"
        )
    for name, v in (("low", low), ("high", high)):
        if not is_number(v) or not math.isfinite(v):
            raise TorchfricError(f"{where}: {name} = {show(v)} must be a finite number")
    log, integer, step = spec.get("log", False), spec.get("int", False), spec.get("step")
    for name, v in (("log", log), ("int", integer)):
        if not isinstance(v, bool):
            raise TorchfricError(f"{where}: {name} = {show(v)} must be true or false")
    if not low < high:
        raise TorchfricError(f"{where}: low = {low:g} must be below high = {high:g}")
    if log and low <= 0:
        raise TorchfricError(f"{where}: a log range needs low > 0, got low = {low:g}")
    if integer and not (isinstance(low, int) and isinstance(high, int)):
        raise TorchfricError(f"{where}: int = true needs integer ends, got {low!r} and {high!r}")
    if integer and not takes_int:
        raise TorchfricError(f"{where}: {key} takes a float; remove int = true")
    if not integer and not takes_float:
        raise TorchfricError(f"{where}: {key} takes an integer; add int = true to its range")
    if step is not None:
        if not is_number(step) or not step > 0 or (integer and not isinstance(step, int)):
            raise TorchfricError(f"{where}: step = {show(step)} must be a positive number")
        if log:
            raise TorchfricError(f"{where}: step and log = true do not go together; drop one")
    param = Param(key, low, high, log, integer, step)
    for end in (low, high):
        _check_value(cfg, where, key, end, "an end of the range")
    return param


def _check_value(cfg: Config, where: str, key: str, value: Any, what: str) -> None:
    """Raise unless `cfg` with ``key = value`` is a valid config."""
    try:
        cfg.with_overrides([f"{key}={toml_value(value)}"])
    except TorchfricError as err:
        raise TorchfricError(
            f"{where}: {show(value)} ({what}) is not a valid value: {err}"
        ) from None
