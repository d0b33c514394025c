"""Run configuration: TOML → nested frozen dataclasses, dotted ``--set`` overrides, TOML out.

Each section is a frozen dataclass that checks its own values on construction
(`__post_init__`), so a `Config` that exists is valid::

    name = "arm_tanh_ekf"          # top level: name, seed, out_dir
    [data]                         # DataConfig
    train = ["rig:identification"]
    [model]                        # ModelConfig
    friction = "tanh"
    [estimator]                    # EstimatorConfig: EKFTuning, OETuning, EnsembleSpec
    passes = 10
    [simulation]                   # SimulationConfig
    [log]                          # LogConfig
    [track]                        # TrackConfig (torchfric track)

Rules the loader applies (`Config.load`):

- Unknown keys or sections, wrong types and out-of-range values raise `TorchfricError` naming
  the dotted key, the value, what is allowed and the fix. An int is accepted where a float is
  expected, a bool never where a number is; a single string is accepted for a list of paths.
- Data paths (``data.train``, ``data.validation``, ``data.test``) and a checkpoint path in
  ``model.init`` are relative to the config file's folder, or to the working directory when
  given with ``--set``; they are stored absolute. ``"rig:NAME"`` names a synthetic-rig
  experiment (`torchfric.rig.EXPERIMENTS`) and is not a file. ``out_dir`` stays as written
  (relative to the working directory of the run).
- The built-in rig's constants are defaults for rig data only: with rig data (every
  ``data.train`` entry a ``"rig:NAME"``) ``model.c_m`` defaults to the rig's 16 and
  ``data.validation`` to ``["rig:validation"]``; with a user's files ``model.c_m`` is required and
  ``data.validation`` defaults to none, and naming rig data beside them is an error.
- ``--set KEY=VALUE`` parses VALUE as a TOML value when it parses (``20``, ``1e-3``,
  ``[0.001, 0.01]``, ``true``, ``"x"``) and as a bare string otherwise (``tanh``,
  ``data/a.csv``); the same checks apply.

`Config.to_toml` writes the resolved config (``None`` values are omitted) and
``Config.loads(config.to_toml()) == config``.

Modules: `torchfric.app.config.schema` (vocabulary, `Check`, did-you-mean), `torchfric.app.config.sections`
(``[data]``, ``[model]``, ``[simulation]``, ``[log]``), `torchfric.app.config.estimator` (``[estimator]``,
which holds the estimators' own settings dataclasses and their defaults),
`torchfric.app.config.toml_io` (the TOML writer, ``--set`` values); this module: `Config`, loading,
``--set`` overrides and `SCHEMA`. Every name is importable from here.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NoReturn

from ...data.readers import FILE_TYPES
from ...data.rig import RigParameters
from ...data.units import COLUMN_NAMES
from ...errors import TorchfricError, shorten
from .estimator import (
    EstimatorConfig,
)
from .schema import (
    INIT_KEYWORDS,
    RIG_PREFIX,
    Check,
    TableSection,
    show,
    suggest,
    unknown_section_key,
)
from .sections import DataConfig, LogConfig, ModelConfig, SimulationConfig, TrackConfig
from .toml_io import parse_value, to_toml

__all__ = [
    "Config",
    "MAX_CONFIG_BYTES",
    "MAX_NAME",
    "SCHEMA",
    "SECTIONS",
    "TOP_KEYS",
    "TOP_TYPES",
    "apply_overrides",
]

MAX_CONFIG_BYTES = 1_000_000
MAX_NAME = 100
"""Longest run name: it becomes a folder and a file name."""
_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")

SECTIONS: dict[str, type[TableSection]] = {
    "data": DataConfig,
    "model": ModelConfig,
    "estimator": EstimatorConfig,
    "simulation": SimulationConfig,
    "log": LogConfig,
    "track": TrackConfig,
}


# --------------------------------------------------------------------------------------------
# The whole config
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Config:
    """A whole run.

    Attributes:
        name: run name: run directory ``out_dir/name`` (or ``name-2``, … when that exists;
            ``--out`` chooses another) and the final checkpoint ``<run directory>/name.pt``.
            Letters, digits, ``._+-``, at most `MAX_NAME` characters.
        seed: seeds torch/numpy (and the rig's noise for ``rig:`` data).
        out_dir: the folder that holds the run directories, relative to the working directory.

    Nothing a run writes goes outside its run directory: the final checkpoint is copied elsewhere
    only by the explicit ``torchfric train --checkpoint PATH``.
    """

    name: str = "run"
    seed: int = 0
    out_dir: str = "runs"
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    simulation: SimulationConfig = field(default_factory=SimulationConfig)
    log: LogConfig = field(default_factory=LogConfig)
    track: TrackConfig = field(default_factory=TrackConfig)

    def __post_init__(self) -> None:
        c = Check(self, "")
        c.string("name")
        if len(self.name) > MAX_NAME:
            raise TorchfricError(
                f"name = {show(self.name)} is {len(self.name)} characters long; a run name "
                f"becomes a folder and a file name: use at most {MAX_NAME}"
            )
        if not _NAME_RE.fullmatch(self.name):
            raise TorchfricError(
                f"name = {show(self.name)} is not a usable run name; use letters, digits and "
                '"._+-" (not starting with "." or "-"), e.g. name = "arm_tanh_ekf"'
            )
        c.integer("seed", ge=0)
        c.string("out_dir")
        for section, cls in SECTIONS.items():
            if not isinstance(getattr(self, section), cls):
                raise TorchfricError(
                    f"Config.{section} must be a {cls.__name__}, got "
                    f"{type(getattr(self, section)).__name__}; use Config.from_dict for tables"
                )
        if self.model.c_m is None:
            if not self.data.rig_only:
                raise TorchfricError(
                    "model.c_m is required with your own data (the built-in rig's c_m = 16 "
                    "applies to rig data only): add the line `c_m = VALUE` (your motor constant: "
                    "torque or force per unit of input) to the [model] section, or pass "
                    "--set model.c_m=VALUE"
                )
            c.set("model", dataclasses.replace(self.model, c_m=RigParameters.c_m))

    # -- building -------------------------------------------------------------------------------
    @classmethod
    def from_dict(
        cls,
        d: Mapping[str, Any],
        *,
        base_dir: str | os.PathLike[str] | None = None,
        check_files: bool = True,
    ) -> Config:
        """Build and validate from nested tables (a parsed TOML file or `to_dict` output).

        Relative data paths and a ``model.init`` checkpoint path are resolved against
        `base_dir` (default: the working directory). With `check_files`, those files must exist.
        """
        if not isinstance(d, Mapping):
            raise TorchfricError(f"a config must be a table of keys, got {type(d).__name__}")
        base = pathlib.Path(os.getcwd() if base_dir is None else base_dir).absolute()
        top: dict[str, Any] = {}
        sections: dict[str, Any] = {}
        for key, value in d.items():
            if key in SECTIONS:
                if not isinstance(value, Mapping):
                    raise TorchfricError(
                        f"{key} = {show(value)} must be a table: write it as a [{key}] section"
                    )
                _check_keys(key, value)
                sections[key] = SECTIONS[key].from_table(_resolve_paths(key, value, base))
            elif key in TOP_KEYS:
                top[key] = value
            else:
                _unknown_key(str(key), "", value)
        config = cls(**top, **sections)
        if check_files:
            config.check_files()
        return config

    @classmethod
    def loads(
        cls,
        text: str,
        overrides: Sequence[str] = (),
        *,
        base_dir: str | os.PathLike[str] | None = None,
        check_files: bool = True,
        source: str = "<config>",
    ) -> Config:
        """Parse TOML `text`; paths in it are relative to `base_dir`, `--set` ones to the cwd."""
        try:
            raw = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise TorchfricError(
                f"{source}: invalid TOML: {shorten(str(exc))}; fix the syntax there"
            ) from None
        except RecursionError:
            raise TorchfricError(
                f"{source}: the TOML is nested too deeply to read; a config needs tables one "
                "level deep ([data], [model], ...)"
            ) from None
        raw = apply_overrides(raw, overrides)
        return cls.from_dict(raw, base_dir=base_dir, check_files=check_files)

    @classmethod
    def load(
        cls,
        path: str | os.PathLike[str],
        overrides: Sequence[str] = (),
        *,
        check_files: bool = True,
    ) -> Config:
        """Read a TOML config file and apply ``--set`` overrides ("dotted.key=value")."""
        p = pathlib.Path(path)
        if not p.is_file():
            what = (
                "is a directory"
                if p.is_dir()
                else "is not a regular file"
                if p.exists()
                else "not found"
            )
            raise TorchfricError(
                f"config file {shorten(repr(str(p)))} {what} (working directory {os.getcwd()}); "
                "give the path of a .toml file"
            )
        if p.suffix.lower() in FILE_TYPES:
            raise TorchfricError(
                f"{shorten(str(p))} is a data file, not a config; give a .toml config (write "
                f"one for this file with: torchfric init {shorten(str(p))} --c-m VALUE)"
            )
        if p.stat().st_size > MAX_CONFIG_BYTES:
            raise TorchfricError(
                f"config file {shorten(str(p))} is {p.stat().st_size:,} bytes; a config is a few "
                f"hundred bytes (at most {MAX_CONFIG_BYTES:,}): give the .toml config, not a data "
                "file"
            )
        try:
            text = p.read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise TorchfricError(
                f"{p}: not a UTF-8 text file ({exc.reason}); save it as UTF-8"
            ) from None
        return cls.loads(
            text, overrides, base_dir=p.parent.absolute(), check_files=check_files, source=str(p)
        )

    def with_overrides(self, overrides: Sequence[str], *, check_files: bool = True) -> Config:
        """This config with ``--set`` overrides applied (their paths relative to the cwd)."""
        raw = apply_overrides(self.to_dict(), overrides)
        return Config.from_dict(raw, check_files=check_files)

    def check_files(self) -> None:
        """Raise if a data file or the ``model.init`` checkpoint does not exist."""
        for key in DataConfig.PATH_KEYS:
            for i, p in enumerate(getattr(self.data, key)):
                if not p.startswith(RIG_PREFIX) and os.path.exists(p) and not os.path.isfile(p):
                    raise TorchfricError(
                        f"data.{key}[{i}] = {show(p)} is not a regular file (a directory, FIFO "
                        "or device); give the path of a CSV, NPZ or MAT data file"
                    )
                if not p.startswith(RIG_PREFIX) and not os.path.isfile(p):
                    raise TorchfricError(
                        f"data.{key}[{i}] = {show(p)}: no such file; fix the path (relative to "
                        "the config file's folder, or to the working directory with --set) or "
                        'use a rig experiment such as "rig:identification"'
                    )
        init = self.model.init
        if init not in INIT_KEYWORDS and not os.path.isfile(init):
            raise TorchfricError(
                f'model.init = {show(init)}: no such checkpoint file; give "prefit", '
                '"config" or the path of an existing checkpoint (relative to the config file\'s '
                "folder, or to the working directory with --set)"
            )

    # -- writing --------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Nested plain dict (lists, not tuples; ``None`` kept) — checkpoint-safe."""
        return _plain(self)

    def to_toml(self) -> str:
        """The config as TOML text (``None`` values omitted); `loads` gives it back."""
        return to_toml(self.to_dict())


TOP_TYPES: dict[str, str] = {
    f.name: str(f.type) for f in dataclasses.fields(Config) if f.name not in SECTIONS
}
TOP_KEYS: tuple[str, ...] = tuple(TOP_TYPES)
SCHEMA: dict[str, tuple[str, ...]] = {
    "": TOP_KEYS,
    **{name: tuple(cls.toml_keys()) for name, cls in SECTIONS.items()},
}
"""The keys a config may hold: top-level ones under "", each section's under its name."""


def _unknown_key(dotted: str, section: str, value: Any = None) -> NoReturn:
    """Raise for an unknown `dotted` key (in `section`, "" = top level)."""
    if section:
        raise unknown_section_key(dotted, section, SCHEMA[section])
    sections = ", ".join(f"[{s}]" for s in SECTIONS)
    if dotted == "checkpoint_dir":
        raise TorchfricError(
            "checkpoint_dir was removed: a run writes its checkpoint inside its run directory "
            "only; delete the key, and copy the final checkpoint elsewhere with "
            "`torchfric train CONFIG --checkpoint PATH`"
        )
    if isinstance(value, Mapping):
        raise TorchfricError(
            f"unknown section [{dotted}]{suggest(dotted, list(SECTIONS))}; allowed sections: "
            f"{sections}; top-level keys: {', '.join(TOP_KEYS)}"
        )
    raise TorchfricError(
        f'unknown key "{dotted}"{suggest(dotted, list(TOP_KEYS) + list(SECTIONS))}; allowed '
        f"top-level keys: {', '.join(TOP_KEYS)}; sections: {sections}"
    )


def _check_keys(section: str, table: Mapping[str, Any]) -> None:
    allowed = SCHEMA[section]
    for key in table:
        if key not in allowed:
            _unknown_key(f"{section}.{key}", section)


def _resolve(path: str, base: pathlib.Path) -> str:
    p = pathlib.Path(path).expanduser()
    return os.path.normpath(p if p.is_absolute() else base / p)


def _resolve_paths(section: str, table: Mapping[str, Any], base: pathlib.Path) -> dict[str, Any]:
    """Copy of `table` with its path keys made absolute against `base` (bad types left alone)."""
    out = dict(table)
    for key in SECTIONS[section].PATH_KEYS:
        value = out.get(key)
        if key == "init":
            if isinstance(value, str) and value and value not in INIT_KEYWORDS:
                out[key] = _resolve(value, base)
            continue
        single = isinstance(value, str)
        items = [value] if single else value
        if isinstance(items, list | tuple) and all(isinstance(v, str) for v in items):
            items = [v if v.startswith(RIG_PREFIX) or not v else _resolve(v, base) for v in items]
            out[key] = items[0] if single else items
    return out


def _plain(value: Any) -> Any:
    """`value` as plain TOML-able data: sections as their flat tables, tuples as lists."""
    if isinstance(value, TableSection):
        return _plain(value.to_table())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    return value


# --------------------------------------------------------------------------------------------
# --set overrides
# --------------------------------------------------------------------------------------------


def apply_overrides(raw: Mapping[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Apply ``--set`` strings ("dotted.key=value") to nested tables `raw`; returns a copy.

    Keys are checked here (unknown → error naming the key); values by `Config.from_dict`.
    Path values are made absolute against the working directory.
    """
    if isinstance(overrides, str):
        overrides = [overrides]
    out: dict[str, Any] = {k: dict(v) if isinstance(v, Mapping) else v for k, v in raw.items()}
    cwd = pathlib.Path.cwd()
    for item in overrides:
        if not isinstance(item, str) or "=" not in item:
            raise TorchfricError(
                f"--set {item!r}: expected KEY=VALUE with a dotted key, e.g. "
                "--set estimator.passes=20 or --set model.friction=polytopic"
            )
        key, _, text = item.partition("=")
        key, text = key.strip(), text.strip()
        parts = key.split(".")
        if len(parts) == 1:
            if parts[0] in SECTIONS:
                first = SCHEMA[parts[0]][0]
                raise TorchfricError(
                    f"--set {item!r}: [{parts[0]}] is a section; set one of its keys, e.g. "
                    f"--set {parts[0]}.{first}=..."
                )
            if parts[0] not in TOP_KEYS:
                _unknown_key(key, "")
            out[key] = parse_value(text, TOP_TYPES[key] == "str")
            continue
        section, name = parts[0], parts[1]
        if section not in SECTIONS:
            _unknown_key(section, "", {})
        types = SECTIONS[section].toml_keys()
        if name not in types or (len(parts) > 2 and name != "columns") or len(parts) > 3:
            _unknown_key(key, section)
        table = out.get(section)
        if not isinstance(table, dict):
            table = out[section] = {}
        if len(parts) == 3:  # data.columns.q=qm
            if parts[2] not in COLUMN_NAMES:
                raise TorchfricError(
                    f'unknown key "{key}"{suggest(parts[2], COLUMN_NAMES)}; allowed keys in '
                    f"[data.columns]: {', '.join(COLUMN_NAMES)}"
                )
            columns = table.get("columns")
            columns = dict(columns) if isinstance(columns, Mapping) else {}
            columns[parts[2]] = parse_value(text, True)
            table["columns"] = columns
            continue
        string_field = types[name] in ("str", "tuple[str, ...]")
        value = parse_value(text, string_field)
        if name in SECTIONS[section].PATH_KEYS:
            value = _resolve_paths(section, {name: value}, cwd)[name]
        table[name] = value
    return out
