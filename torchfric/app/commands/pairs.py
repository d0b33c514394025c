"""Records beside a user's data that are named as its held-out ones (`torchfric init` proposes
them): ``run1_train.csv`` ↔ ``run1_val.csv`` or ``run1_test.csv``, ``identification`` ↔
``validation``, ``train`` ↔ ``test``.

- `held_out_role`: whether a file's name says validation or test, and whether it pairs with the
  data's name once the role words are dropped;
- `held_out_siblings`: those that also read with the data's columns and sample time.
"""

from __future__ import annotations

import pathlib
import re
from collections.abc import Mapping

from ...data import load_segments
from ...errors import TorchfricError

__all__ = ["held_out_role", "held_out_siblings"]

_TRAIN_WORDS = {"train", "training", "identification", "ident", "id", "idf", "estimation", "fit"}
_VALID_WORDS = {"val", "valid", "validation", "validate"}
_TEST_WORDS = {"test", "testing"}


def _words(stem: str) -> list[str]:
    return [w for w in re.split(r"[^a-z0-9]+", stem.lower()) if w]


def held_out_role(data: pathlib.Path, other: pathlib.Path) -> tuple[str, bool] | None:
    """("validation" or "test", whether it pairs with `data`) when `other` is named as a
    held-out record (a validation word wins over a test word), else None. It pairs when the
    two names agree once the role words are dropped: ``run1_train`` ↔ ``run1_val`` and
    ``run1_test``, ``train`` ↔ ``test``."""
    words = _words(other.stem)
    role = (
        "validation"
        if any(w in _VALID_WORDS for w in words)
        else "test"
        if any(w in _TEST_WORDS for w in words)
        else None
    )
    if role is None:
        return None
    roles = _TRAIN_WORDS | _VALID_WORDS | _TEST_WORDS
    rest = [w for w in words if w not in roles]
    return role, rest == [w for w in _words(data.stem) if w not in roles]


def held_out_siblings(
    data: pathlib.Path,
    mapping: Mapping[str, str],
    time_step: float | None,
    dt: float,
    units: Mapping[str, object],
) -> tuple[list[pathlib.Path], list[pathlib.Path], list[pathlib.Path]]:
    """(validation, test, other): the held-out-named records beside `data` that read with its
    columns and sample time (`_held_out`); the first two pair with `data`, the last do not.
    Test-named ones are the validation when no validation-named one pairs."""
    found: dict[tuple[str, bool], list[pathlib.Path]] = {}
    for p in sorted(data.parent.iterdir()):
        if p == data or p.suffix.lower() != data.suffix.lower() or not p.is_file():
            continue
        kind = held_out_role(data, p)
        if kind is None:
            continue
        try:
            exp = load_segments(p, columns=mapping, time_step=time_step, **units)[0][0]  # type: ignore[arg-type]
        except TorchfricError:
            continue
        if abs(exp.dt - dt) <= 1e-3 * dt:
            found.setdefault(kind, []).append(p)
    val, test = found.get(("validation", True), []), found.get(("test", True), [])
    other = sorted(found.get(("validation", False), []) + found.get(("test", False), []))
    return (val, test, other) if val else (test, [], other)
