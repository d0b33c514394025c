"""Change detection on a machine other than the rig (issue 33): a user-style rotary axis
(`torchfric.data.axis.STRIBECK_AXIS`, another scale and friction law than the rig), identified
as a user would, then ``torchfric track`` with every default: a 40 % rise of its dry friction is
flagged within 2 s, and unchanged data raise no alarm. Seeded; about 20 s on one core."""

from __future__ import annotations

import dataclasses
import json
import pathlib

import numpy as np
import pytest

import torchfric
from torchfric.app.cli import main
from torchfric.data.axis import STRIBECK_AXIS, axis_record

AXIS = dataclasses.replace(STRIBECK_AXIS, disturbance_std=0.02 * STRIBECK_AXIS.coulomb,
                           disturbance_bandwidth=10.0)  # fmt: skip
AFTER = dataclasses.replace(AXIS, coulomb=1.4 * AXIS.coulomb, static=1.4 * AXIS.static)


def _csv(path: pathlib.Path, rec: dict) -> pathlib.Path:
    np.savetxt(path, np.column_stack([rec["t"], rec["u"], rec["q"]]), delimiter=",",
               header="t,u,q", comments="", fmt="%.17g")  # fmt: skip
    return path


@pytest.fixture(scope="module")
def axis_model(tmp_path_factory) -> pathlib.Path:  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("axis")
    _csv(d / "ident.csv", axis_record(AXIS, seed=100, duration=15.0, kind="identification"))
    (d / "cfg.toml").write_text(f'name = "axis"\n[data]\ntrain = ["{d / "ident.csv"}"]\n'
                                f"[model]\nc_m = {AXIS.c_m!r}\n")  # fmt: skip
    result = torchfric.fit(str(d / "cfg.toml"), out=str(d / "run"), quiet=True,
                           **{"estimator.passes": 4})  # fmt: skip
    return pathlib.Path(result.checkpoint)


def _track(checkpoint: pathlib.Path, csv: pathlib.Path) -> list[float]:
    out = csv.with_suffix("")
    assert main(["track", str(checkpoint), str(csv), "--out", str(out), "--quiet"]) == 0
    return json.loads((out / "events.json").read_text())["changes"]


def test_a_coulomb_change_on_a_user_axis_is_found(axis_model, tmp_path) -> None:  # type: ignore[no-untyped-def]
    rec = axis_record(AXIS, seed=1, duration=32.0, kind="validation", change=(25.0, AFTER))
    changes = _track(axis_model, _csv(tmp_path / "change.csv", rec))
    assert len(changes) == 1 and 0.0 < changes[0] - float(rec["change"]) < 2.0, changes


def test_unchanged_user_axis_raises_no_alarm(axis_model, tmp_path) -> None:  # type: ignore[no-untyped-def]
    rec = axis_record(AXIS, seed=7, duration=60.0, kind="validation")
    assert _track(axis_model, _csv(tmp_path / "quiet.csv", rec)) == []
