"""A newcomer's whole way, as the README tells it: a CSV of their own → ``init`` → ``check`` →
``train`` → ``evaluate``, through the command line in a temporary working directory, checked
against the rig's truth and against the files the run says it wrote."""

from __future__ import annotations

import json
import os
import pathlib
import tomllib

import numpy as np
import pytest

from torchfric.app.cli import main
from torchfric.data.rig import RigParameters, rig_experiment

NOMINAL = RigParameters()


@pytest.fixture
def user_dir(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> pathlib.Path:
    """A user's folder with two records of their machine (here: the rig's, written as plain
    CSV with the user's own column names), and the working directory set to it."""
    for name, stem in (("identification", "axis_run1_train"), ("validation", "axis_run1_val")):
        exp = rig_experiment(name)
        n = 6000 if name == "identification" else 4000
        table = np.column_stack([exp["t"][:n], exp["u"][:n], exp["q"][:n]])
        np.savetxt(tmp_path / f"{stem}.csv", table, delimiter=",", fmt="%.10g",
                   header="time [s],current,position_rad", comments="")  # fmt: skip
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_init_check_train_evaluate_on_a_users_csv(
    user_dir: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = sorted(p.name for p in user_dir.iterdir())

    # init: a starter config for the file, the validation record found beside it
    assert main(["init", "axis_run1_train.csv", "--c-m", "16", "--out", "axis.toml"]) == 0
    init_out = capsys.readouterr().out
    assert "axis.toml" in init_out
    raw = tomllib.loads((user_dir / "axis.toml").read_text())
    assert raw["model"]["c_m"] == 16.0
    assert raw["data"]["train"] == ["axis_run1_train.csv"]
    assert raw["data"]["validation"] == ["axis_run1_val.csv"]
    assert raw["data"]["columns"] == {"t": "time [s]", "u": "current", "q": "position_rad"}
    # the config is commented: a newcomer reads what each key means
    assert sum(line.lstrip().startswith("#") for line in (user_dir / "axis.toml").open()) >= 10

    # check: what would run, nothing written
    short = ["--set", "estimator.passes=3", "--set", "estimator.ensemble=0"]
    assert main(["check", "axis.toml", *short]) == 0
    check_out = capsys.readouterr().out
    assert "6000" in check_out and "axis_run1_val" in check_out
    assert not (user_dir / "runs").exists()

    # train: the summary on stdout names the files, which exist
    assert main(["train", "axis.toml", "--quiet", *short]) == 0
    summary = capsys.readouterr().out
    run = user_dir / "runs" / "axis"
    metrics = json.loads((run / "metrics.json").read_text())
    for name in ("axis.pt", "report.html", "metrics.json"):
        assert (run / name).is_file() and str(pathlib.Path("runs", "axis", name)) in summary
    assert (run / "config.toml").is_file()
    assert f"kept pass {metrics['best_pass']} of 3" in summary
    # the rig's truth: inertia within 2 % of the true 0.0292 from 6 s of data and 3 passes
    inertia = metrics["parameters"]["inertia"]
    assert inertia["value"] == pytest.approx(NOMINAL.inertia, rel=0.02)
    # σ: finite, within that 2 %, and covering the truth (the rig sticks at its reversals, and
    # its σ hold the kept pass's distance from the optimum without the stuck samples)
    assert 0 < inertia["std"] < 0.02 * inertia["value"]
    assert abs(inertia["value"] - NOMINAL.inertia) <= 2.0 * inertia["std"]
    assert set(metrics["validation"]) == {"axis_run1_val"}  # the user's record, never the rig's
    val = metrics["validation"]["axis_run1_val"]
    assert val["fit_q"] > 80 and val["fit_qdot"] > 80

    # evaluate: the same FIT on the same record, from the checkpoint alone
    assert main(["evaluate", str(run / "axis.pt"), "axis_run1_val.csv", "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["fit_q"] == pytest.approx(val["fit_q"], abs=1e-9)
    assert ev["parameters"]["inertia"] == inertia

    # nothing else in the user's folder was written or changed
    after = sorted(p.name for p in user_dir.iterdir())
    assert after == sorted([*before, "axis.toml", "runs"])
    assert os.listdir(user_dir / "runs") == ["axis"]
