"""The config reference (``docs/config.md``), generated from the config schema itself.

Every key a run config accepts, with its type, default, allowed values and meaning:

- the keys: `SCHEMA` (top level and sections), the ``[data.columns]`` keys (`COLUMN_NAMES`), and
  for ``[estimator]`` the settings field each flat key sets (`ESTIMATOR_KEYS`);
- types and allowed values: what `Check` checks for each key, noted while a default config is
  built (`recording_checks`), so the choices are the registries' own (`FRICTIONS`, `SOLVERS`,
  `VELOCITY_SOURCES`, ...); `_RULES` adds the few rules the sections check in code of their own;
- defaults: a default config's values (rig data) beside those of a config for a user's file;
- meanings: the ``Attributes:`` sections of the dataclasses' docstrings (a key without an entry
  there is an error here, not a gap in the page).

``python -m torchfric.app.config.reference`` prints the page; ``--check FILE`` exits 1 when
FILE is not what it prints.

Why this size: one generated page, whose parts (each key's type, default, rule and docstring)
are written in the page's order; split, they would be read in two places to change one line.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import pathlib
import re
import sys
from collections.abc import Mapping, Sequence
from typing import Any

from ...data.readers import FILE_TYPES
from ...data.rig import EXPERIMENTS
from ...data.units import COLUMN_NAMES
from ...errors import TorchfricError
from ...estimators.ekf import MEASUREMENTS
from .config import _NAME_RE, MAX_NAME, SCHEMA, Config
from .estimator import ENSEMBLE_KEYS, ESTIMATOR_KEYS, MAX_EPOCHS, MAX_PASSES, EstimatorConfig
from .schema import INIT_KEYWORDS, RIG_PREFIX, Checked, recording_checks
from .toml_io import toml_value

__all__ = ["COMMAND", "KeyDoc", "attribute_docs", "config_keys", "config_reference", "main"]

COMMAND = "python -m torchfric.app.config.reference > docs/config.md"
"""The command that writes ``docs/config.md``, named in the page's first lines."""

_OWN_FILE = "data.csv"
"""The identification file of the config that stands for a user's data (never opened)."""

_RULES: dict[str, str] = {
    "data.validation": "no `rig:` records when `data.train` is your own data",
    "data.test": "no `rig:` records when `data.train` is your own data",
    "data.stop": "> `data.start`",
    "model.size": 'odd with `model.friction = "polytopic"`; `"auto"` only with `"tanh"` or '
    '`"polytopic"` and `model.init = "prefit"` or `"config"`',
    "model.sizes": 'integers >= 1, odd with `model.friction = "polytopic"`; only with '
    '`model.size = "auto"`',
    "model.viscous": '> 0 with `model.log_positive = true` (except `model.friction = "polytopic"`)',
    "estimator.passes": f"at most {MAX_PASSES}",
    "estimator.r": "each > 0, one per channel that `estimator.measure` measures ("
    + ", ".join(f'`"{name}"`: {len(rows)}' for name, rows in MEASUREMENTS.items())
    + ")",
    "estimator.epochs": f'at most {MAX_EPOCHS}; with `method = "output_error"`, 0 only with '
    "`estimator.lbfgs_steps` > 0",
    "estimator.lr_final": '<= `estimator.lr` (with `method = "output_error"`)',
    "estimator.window": 'not 1 (with `method = "output_error"`)',
    "estimator.schedule": "each 0 (full length) or >= 2; at most `estimator.epochs` entries "
    '(with `method = "output_error"`)',
    "estimator.learn_states": "`true` needs `estimator.window` >= 2 and an empty "
    '`estimator.schedule` (with `method = "output_error"`)',
    "estimator.ensemble_q_scales": "non-empty, each > 0",
    "estimator.ensemble_r_scales": "non-empty, each > 0",
}
"""Rules the sections check in code of their own, beside `Check`'s bounds (each is tested);
the ensemble keys' rule is `_ENSEMBLE_RULE`."""
_ENSEMBLE_RULE = 'with `method = "output_error"`: the default only'

_SECTION_TITLES = {"": "Top level", "data.columns": "[data.columns]"}


@dataclasses.dataclass(frozen=True)
class KeyDoc:
    """One key's entry in the reference (every field is Markdown-ready text)."""

    key: str
    """Dotted name, e.g. ``data.velocity`` (top-level keys have no dot)."""
    section: str
    """``""`` (top level), ``"data"``, ``"data.columns"``, ``"model"``, ..."""
    type: str
    default: str
    allowed: str
    meaning: str
    sets: str = ""
    """For ``[estimator]`` keys: the settings field(s) the key sets (``EKFTuning.passes``)."""


# --------------------------------------------------------------------------------------------
# Meanings: the docstrings' Attributes sections
# --------------------------------------------------------------------------------------------

_ENTRY = re.compile(r"^ {4}(?P<names>[\w.]+(?:, [\w.]+)*): (?P<text>.*)$")


def attribute_docs(cls: type) -> dict[str, str]:
    """Attribute name → its text in `cls`'s docstring's ``Attributes:`` section (one line).

    An entry is ``name: text`` (or ``a, b: text`` for two names sharing one text) indented by
    four spaces, continued by lines indented further; the section ends at the first line that
    is neither.
    """
    lines = (inspect.getdoc(cls) or "").splitlines()
    if "Attributes:" not in lines:
        return {}
    entries: list[tuple[list[str], list[str]]] = []
    for line in lines[lines.index("Attributes:") + 1 :]:
        match = _ENTRY.match(line)
        if match:
            entries.append((match["names"].split(", "), [match["text"].strip()]))
        elif line.startswith(" " * 8) and entries:
            entries[-1][1].append(line.strip())
        else:
            break
    return {name: " ".join(text) for names, text in entries for name in names}


def _summary(cls: type) -> str:
    """The first paragraph of `cls`'s docstring, without its leading ``[section]``: name."""
    doc = (inspect.getdoc(cls) or "").split("\n\n")[0].replace("\n", " ")
    return _sentence(re.sub(r"^``\[[\w.]+\]``: ", "", doc))


def _estimator_holders() -> dict[str, type]:
    """`EstimatorConfig`'s settings fields ("" for itself) → their dataclass."""
    default = EstimatorConfig()
    holders: dict[str, type] = {"": EstimatorConfig}
    for f in dataclasses.fields(EstimatorConfig):
        value = getattr(default, f.name)
        if dataclasses.is_dataclass(value):
            holders[f.name] = type(value)
    return holders


def _meaning(key: str, section_classes: Mapping[str, type]) -> tuple[str, str]:
    """(meaning, the settings fields it sets) of dotted `key`, from the docstrings."""
    section, _, name = key.rpartition(".")
    if section == "data.columns":
        section, name = "data", f"columns.{name}"
    if section != "estimator":
        cls = section_classes[section]
        text = attribute_docs(cls).get(name)
        if not text:
            raise TorchfricError(f"{key} has no entry in {cls.__name__}'s docstring Attributes")
        return text, ""
    holders = _estimator_holders()
    routes = [(holder, field) for holder, field in ESTIMATOR_KEYS[name] if holder]
    sets = ", ".join(f"`{holders[h].__name__}.{f}`" for h, f in routes)
    own = attribute_docs(EstimatorConfig).get(name)
    if own:
        return own, sets
    texts = {(h, f): attribute_docs(holders[h]).get(f) for h, f in routes}
    missing = [f"{holders[h].__name__}.{f}" for (h, f), text in texts.items() if not text]
    if missing or not texts:
        raise TorchfricError(
            f"{key} has no entry in the docstring Attributes of EstimatorConfig or "
            f"{', '.join(missing) or 'its settings'}"
        )
    if len(texts) == 1:
        return str(next(iter(texts.values()))), sets
    return " ".join(f'With method = "{h}": {t}' for (h, _), t in texts.items()), sets


def _sentence(text: str) -> str:
    """`text` with a capital first word when that word is a plain lower-case word."""
    word, _, rest = text.partition(" ")
    if len(word) > 1 and word.replace("-", "").isalpha() and word.islower():
        word = word.capitalize()
    return f"{word} {rest}" if rest else word


# --------------------------------------------------------------------------------------------
# Types and allowed values: what `Check` checks
# --------------------------------------------------------------------------------------------


def _notes() -> dict[str, Checked]:
    """Each key's first `Check` note while a default config is built (the outer check)."""
    with recording_checks() as notes:
        Config()
    out: dict[str, Checked] = {}
    for note in notes:
        out.setdefault(note.key, note)
    return out


def _number(x: float) -> str:
    return f"{x:g}"


def _type(key: str, note: Checked | None, annotation: str) -> str:
    if note is None:
        by_annotation = {
            "dict[str, str]": "table of strings",
            "tuple[int, ...]": "array of integers",
        }
        if key.startswith("data.columns."):
            return "string"
        if annotation not in by_annotation:
            raise TorchfricError(f"{key}: no check noted and no type for annotation {annotation}")
        return by_annotation[annotation]
    b = note.bounds
    if note.kind == "numbers":
        if b["length"] is not None:
            return f"array of {b['length']} floats"
        return "float or array of floats" if b["scalar"] else "array of floats"
    kinds = {
        "number": "float",
        "integer": "integer",
        "auto_or_integer": 'integer or "auto"',
        "auto_or_number": 'float or "auto"',
        "boolean": "boolean",
        "string": "string",
        "paths": "string or array of strings",
    }
    return kinds[note.kind]


def _allowed(key: str, note: Checked | None) -> str:
    parts: list[str] = []
    b = note.bounds if note is not None else {}
    kind = note.kind if note is not None else ""
    if key == "name":
        parts.append(f"matches `{_NAME_RE.pattern}`, at most {MAX_NAME} characters")
    elif key == "model.init":
        listed = ", ".join(f'`"{k}"`' for k in INIT_KEYWORDS)
        parts.append(f"{listed}, or the path of a checkpoint (`.pt`) written by a run")
    elif key == "data.columns":
        parts.append(f"keys {', '.join(f'`{c}`' for c in COLUMN_NAMES)} (below)")
    elif key.startswith("data.columns."):
        parts.append('a column (array) name in the file; `"A:k"` for column k of array A')
    elif kind in ("number", "integer"):
        bounds = [f"> {_number(b['gt'])}" if b.get("gt") is not None else ""]
        bounds.append(f">= {_number(b['ge'])}" if b.get("ge") is not None else "")
        bounds = [x for x in bounds if x]
        what = "any finite number" if kind == "number" else "any integer"
        parts.append(", ".join(bounds) or what)
        if b.get("optional"):
            parts.append("or unset (omit the key)")
    elif kind == "auto_or_integer":
        parts.append(f'`"auto"`, or an integer >= {b["ge"]}')
    elif kind == "auto_or_number":
        parts.append(f'`"auto"`, or a number >= {_number(b["ge"])}')
    elif kind == "boolean":
        parts.append("`true`, `false`")
    elif kind == "string":
        choices = b["choices"]
        parts.append(", ".join(f'`"{c}"`' for c in choices) if choices else "any non-empty string")
    elif kind == "numbers":
        pieces = [f"exactly {b['length']} numbers" if b["length"] is not None else ""]
        pieces.append(f"each >= {_number(b['ge'])}" if b["ge"] is not None else "")
        if b["scalar"]:
            pieces.append("one number for every θ entry, or one per entry")
        parts.append(", ".join(p for p in pieces if p) or "finite numbers")
    elif kind == "paths":
        rigs = ", ".join(f"`{RIG_PREFIX}{e}`" for e in EXPERIMENTS)
        files = ", ".join(f"`{s}`" for s in FILE_TYPES)
        many = "one path, or an array of " + (
            "at least one" if b["nonempty"] else "them (`[]`: none)"
        )
        parts.append(f"{many}: data files ({files}) or the built-in rig's records ({rigs})")
    if key in _RULES:
        parts.append(_RULES[key])
    if key.startswith("estimator.") and key.removeprefix("estimator.") in ENSEMBLE_KEYS:
        parts.append(_ENSEMBLE_RULE + (" (or 0)" if key == "estimator.ensemble" else ""))
    if not parts:
        raise TorchfricError(f"{key}: no allowed values known (no check noted, no rule)")
    return "; ".join(parts)


# --------------------------------------------------------------------------------------------
# Defaults: rig data and a user's data
# --------------------------------------------------------------------------------------------


def _flat(tables: Mapping[str, Any]) -> dict[str, Any]:
    """A config's `to_dict` → dotted key → value (``data.columns.X`` included)."""
    out: dict[str, Any] = {}
    for key, value in tables.items():
        if key in SCHEMA:
            for name, v in value.items():
                out[f"{key}.{name}"] = v
        else:
            out[key] = value
    for column in COLUMN_NAMES:
        out[f"data.columns.{column}"] = out["data.columns"].get(column, column)
    return out


def _nest(flat: Mapping[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in flat.items():
        section, _, name = key.rpartition(".")
        (out.setdefault(section, {}) if section else out)[name] = value
    return out


def _own_data_defaults(rig: Mapping[str, Any]) -> tuple[dict[str, Any], set[str]]:
    """The defaults with a user's file as ``data.train``, and the keys that then become
    required (those the config refuses to go without, given there as the rig's value)."""
    given: dict[str, Any] = {"data.train": [_OWN_FILE]}
    required: set[str] = set()
    while True:
        try:
            config = Config.from_dict(_nest(given), check_files=False)
        except TorchfricError as err:
            key = next((k for k in rig if str(err).startswith(f"{k} ") and k not in given), None)
            if key is None:
                raise
            given[key] = rig[key]
            required.add(key)
            continue
        return _flat(config.to_dict()), required


def _toml(value: Any) -> str:
    return "unset" if value is None else f"`{toml_value(value)}`"


def _defaults() -> dict[str, str]:
    rig = _flat(Config().to_dict())
    own, required = _own_data_defaults(rig)
    out = {}
    for key, value in rig.items():
        if key in required:
            out[key] = f"{_toml(value)} with rig data; required with your own data"
        elif key != "data.train" and own[key] != value:
            out[key] = f"{_toml(value)} with rig data, {_toml(own[key])} with your own data"
        else:
            out[key] = _toml(value)
    return out


# --------------------------------------------------------------------------------------------
# The reference
# --------------------------------------------------------------------------------------------


def _section_classes() -> dict[str, type]:
    out: dict[str, type] = {"": Config}
    default = Config()
    for section in SCHEMA:
        if section:
            out[section] = type(getattr(default, section))
    return out


def _annotations(section_classes: Mapping[str, type]) -> dict[str, str]:
    out = {name: str(f.type) for name, f in _fields(Config).items() if name in SCHEMA[""]}
    for section, cls in section_classes.items():
        if section:
            keys = cls.toml_keys()  # type: ignore[attr-defined]
            out.update({f"{section}.{name}": annotation for name, annotation in keys.items()})
    return out


def _fields(cls: type) -> dict[str, dataclasses.Field[Any]]:
    return {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]


def config_keys() -> list[KeyDoc]:
    """Every key a run config accepts, in the order of `config_reference`."""
    classes = _section_classes()
    notes = _notes()
    defaults = _defaults()
    annotations = _annotations(classes)
    keys: list[tuple[str, str]] = []
    for section, names in SCHEMA.items():
        keys += [(section, f"{section}.{name}" if section else name) for name in names]
        if section == "data":
            keys += [("data.columns", f"data.columns.{c}") for c in COLUMN_NAMES]
    out = []
    for section, key in keys:
        meaning, sets = _meaning(key, classes)
        note = notes.get(key)
        out.append(
            KeyDoc(
                key=key,
                section=section,
                type=_type(key, note, annotations.get(key, "")),
                default=defaults[key],
                allowed=_allowed(key, note),
                meaning=_sentence(meaning),
                sets=sets,
            )
        )
    return out


_INTRO = """\
A run config is a TOML file: the top-level keys first, then one table per section
(`[data]`, `[model]`, `[estimator]`, `[simulation]`, `[log]`). Every key may be left out
(except `model.c_m` with your own data); it then takes the default below. `--set KEY=VALUE`
overrides one key for one command, e.g. `torchfric train config.toml --set
estimator.passes=20` (the same checks apply; repeat it for more keys).

Some defaults depend on the data. With **rig data** (every `data.train` entry names a record of
the built-in synthetic rig, `rig:NAME`) the rig's own constants apply; with **your own data**
(files) `model.c_m` is required and `data.validation` is empty unless you give records.
Relative data paths are relative to the config file's folder (to the working directory when
given with `--set`). A bad key or value stops the command with a one-line message naming the
key, the value, what is allowed and a fix.

Each entry gives the key's type (as written in TOML), its default, its allowed values and its
meaning; for `[estimator]` keys also the estimator setting it sets in the Python API
(`torchfric.estimators.settings`). "Unset" (``None`` in the Python API) means the key is left
out of the file: TOML has no null."""


def config_reference() -> str:
    """The config reference as Markdown (what ``docs/config.md`` holds)."""
    classes = _section_classes()
    lines = [
        "# Config reference",
        "",
        f"*Generated from the config schema by `{COMMAND}`: do not edit by hand (the tests "
        "fail when this page is stale).*",
        "",
        _INTRO,
    ]
    section = None
    for doc in config_keys():
        if doc.section != section:
            section = doc.section
            title = _SECTION_TITLES.get(section, f"[{section}]")
            lines += ["", f"## {title}"]
            if section in classes and section:
                lines += ["", _summary(classes[section])]
        lines += ["", f"### `{doc.key}`", "", f"- Type: {doc.type}", f"- Default: {doc.default}"]
        lines.append(f"- Allowed: {doc.allowed}")
        if doc.sets:
            lines.append(f"- Sets: {doc.sets}")
        lines += ["", doc.meaning]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Print the reference, or with ``--check FILE`` exit 1 when FILE differs from it."""
    parser = argparse.ArgumentParser(
        prog="python -m torchfric.app.config.reference",
        description="Print the config reference (Markdown) generated from the config schema.",
    )
    parser.add_argument(
        "--check", metavar="FILE", help="exit 1 when FILE is not the reference as printed"
    )
    args = parser.parse_args(argv)
    text = config_reference()
    if args.check is None:
        sys.stdout.buffer.write(text.encode("utf-8"))
        sys.stdout.flush()
        return 0
    path = pathlib.Path(args.check)
    regenerate = f"python -m torchfric.app.config.reference > {path}"
    try:
        current = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        print(
            f"{path}: cannot read it ({type(exc).__name__}); write it with `{regenerate}`",
            file=sys.stderr,
        )
        return 1
    if current != text:
        print(
            f"{path} differs from the generated config reference (a config key, default or "
            f"docstring changed); regenerate it with `{regenerate}`",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
