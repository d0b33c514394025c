"""A short config on the synthetic rig's records, written as a user writes one: the tests that
run `train` end to end start from it and change only what they test."""

from __future__ import annotations

import pathlib
from typing import Any

from torchfric.app.config.toml_io import to_toml


def rig_config(
    folder: pathlib.Path, name: str = "short", **sections: dict[str, Any]
) -> pathlib.Path:
    """Write ``folder/NAME.toml``: the rig's identification record with its validation record,
    a tanh(3) model with the rig's c_m, one filter (``ensemble = 0``), runs under
    ``folder/runs``. Each keyword is a section whose keys are added or replaced
    (``estimator={"passes": 2}``); None as a value removes the key."""
    tables: dict[str, dict[str, Any]] = {
        "data": {"train": ["rig:identification"], "validation": ["rig:validation"]},
        "model": {"friction": "tanh", "c_m": 16.0},
        "estimator": {"ensemble": 0},
    }
    for section, keys in sections.items():
        table = tables.setdefault(section, {})
        table.update(keys)
        for key in [k for k, v in table.items() if v is None]:
            del table[key]
    path = folder / f"{name}.toml"
    top = {"name": name, "out_dir": (folder / "runs").as_posix()}
    path.write_text(to_toml({**top, **tables}), encoding="utf-8")
    return path
