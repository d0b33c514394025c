"""`torchfric evaluate` and `simulate` on a record laid out unlike the training data.

One short run on the rig (its validation record read to sample 1500, the input one sample
late), then its validation record written as a user's file would be: other column names, q in
degrees. Read back with ``--column`` and ``--position-unit``, `evaluate` scores it exactly as the
run scored its validation record (metrics.json), `simulate` writes the same simulation, and
both say the units of what they print.
"""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest
from rig_configs import rig_config

from torchfric.accel.native.lugre import lugre_integrator
from torchfric.app.cli import build_parser, main
from torchfric.data.rig import rig_experiment
from torchfric.data.units import POSITION_UNITS

STOP = 1500
RENAMED = ["--column", "t=time_s", "--column", "u=cmd", "--column", "q=pos_deg"]


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, pathlib.Path]:
    """The run (checkpoint, metrics.json) and its validation record as a CSV of other names."""
    tmp = tmp_path_factory.mktemp("evaluate")
    # input_delay: the run scores with the input one sample late; evaluate must do the same.
    data = {"stop": STOP, "test": [], "input_delay": 1}
    cfg = rig_config(tmp, data=data, estimator={"passes": 1})
    assert main(["train", str(cfg), "--quiet"]) == 0
    folder = tmp / "runs" / "short"
    rec = rig_experiment("validation", seed=0, integrate=lugre_integrator())
    table = np.column_stack([rec["t"], rec["u"], np.degrees(rec["q"])])[:STOP]
    csv = tmp / "bench_log.csv"
    np.savetxt(csv, table, delimiter=",", header="time_s,cmd,pos_deg", comments="", fmt="%.17g")
    return {"ckpt": folder / "short.pt", "metrics": folder / "metrics.json", "csv": csv}


def _validation(run: dict[str, pathlib.Path]) -> dict[str, float]:
    return json.loads(run["metrics"].read_text())["validation"]["validation"]


def test_evaluate_reads_other_names_and_units_and_scores_as_the_run_did(
    run: dict[str, pathlib.Path], capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["evaluate", str(run["ckpt"]), str(run["csv"]), *RENAMED, "--position-unit", "deg"]
    assert main([*argv, "--json"]) == 0
    out = capsys.readouterr()
    assert "warning" not in out.err  # a rotary model on a rotary record
    got, want = json.loads(out.out), _validation(run)
    assert got["samples"] == STOP - 1  # the input delay drops the first sample
    assert got["unit"] == {"q": "rad", "qdot": "rad/s"}
    for key in ("fit_q", "fit_qdot"):
        assert abs(got[key] - want[key]) < 1e-9, key
    for key in ("rms_q", "rms_qdot"):
        assert got[key] == pytest.approx(want[key], rel=1e-9, abs=0.0), key

    method = json.loads(run["metrics"].read_text())["covariance"]["method"]
    assert got["sigma"] == method == "sandwich"

    assert main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[2].split()[:3] == ["RMS", "[rad,", "rad/s]"]
    assert float(lines[2].split()[3]) == pytest.approx(want["rms_q"], rel=1e-5)
    assert lines[-1].startswith("σ: the run's sandwich covariance of its one-step prediction")


def test_evaluate_says_when_the_sigma_are_the_filters_own(
    run: dict[str, pathlib.Path], tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A checkpoint written before runs computed a covariance (the committed ones of 2026-11-25)
    # holds the filter's P_θθ only: its σ are printed with what they are.
    import torch

    raw = torch.load(run["ckpt"], weights_only=True)
    del raw["metrics"]["covariance"]
    old = tmp_path / "old.pt"
    torch.save(raw, old)
    argv = ["evaluate", str(old), str(run["csv"]), *RENAMED, "--position-unit", "deg"]
    assert main([*argv, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["sigma"] == "filter"
    assert main(argv) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    assert last.startswith("σ: the filter's own P_θθ, narrower than the real error as a rule")


def test_simulate_writes_the_runs_simulation_and_says_its_units(
    run: dict[str, pathlib.Path], tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "sim.csv"
    argv = ["simulate", str(run["ckpt"]), str(run["csv"]), *RENAMED, "--position-unit", "deg"]
    assert main([*argv, "--out", str(out)]) == 0
    said = capsys.readouterr().out.strip()
    assert said == f"wrote {out} ({STOP - 1} samples; q in rad, qdot in rad/s)"
    assert out.read_text().splitlines()[0] == "t,u,q,qdot"
    sim = np.loadtxt(out, delimiter=",", skiprows=1)
    rec = rig_experiment("validation", seed=0, integrate=lugre_integrator())
    q = rec["q"][1:STOP]  # as read: in rad again, after the one-sample input delay
    np.testing.assert_allclose(sim[:, 0], rec["t"][1:STOP], rtol=0, atol=0)
    np.testing.assert_allclose(sim[:, 1], rec["u"][: STOP - 1], rtol=0, atol=0)
    fit_q = 100.0 * (1.0 - np.linalg.norm(q - sim[:, 2]) / np.linalg.norm(q - q.mean()))
    assert abs(fit_q - _validation(run)["fit_q"]) < 1e-9


def test_a_missing_column_names_the_flag(
    run: dict[str, pathlib.Path], tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ckpt, csv = str(run["ckpt"]), str(run["csv"])
    # Without --column the checkpoint's own columns (t, u, q) are looked for.
    assert main(["evaluate", ckpt, csv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err
    assert "no column 'u' (for u)" in err and "--column u=NAME" in err
    # --column replaces the checkpoint's columns: the one not given is looked for as ours.
    out = str(tmp_path / "x.csv")
    argv = ["simulate", ckpt, csv, "--column", "u=cmd", "--column", "q=pos_deg", "--out", out]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "no time column 't'" in err and "--column t=NAME" in err and "\n" not in err
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--column", "x=time_s"], "'x' is not one of our columns"),
        (["--column", "time_s"], "--column time_s: expected OURS=NAME"),
        (["--column", "q="], "--column q=: no column name"),
    ],
)
def test_bad_column_flags_are_one_line_errors(
    run: dict[str, pathlib.Path], capsys: pytest.CaptureFixture[str], argv: list[str], says: str
) -> None:
    assert main(["evaluate", str(run["ckpt"]), str(run["csv"]), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and says in err and "\n" not in err


def test_the_rigs_records_take_no_column_or_unit(
    run: dict[str, pathlib.Path], capsys: pytest.CaptureFixture[str]
) -> None:
    for flags in (["--column", "q=pos"], ["--position-unit", "deg"]):
        assert main(["evaluate", str(run["ckpt"]), "rig:validation", *flags]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"error: {flags[0]} is for a data file") and "\n" not in err


def test_a_record_of_the_other_kind_of_axis_warns(
    run: dict[str, pathlib.Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """A rotary model on a record read in mm: a one-line warning, the scores still print, in m."""
    argv = ["evaluate", str(run["ckpt"]), str(run["csv"]), *RENAMED, "--position-unit", "mm"]
    assert main(argv) == 0
    out = capsys.readouterr()
    warning = [line for line in out.err.splitlines() if line.strip()]
    assert len(warning) == 1 and warning[0].startswith("warning: ")
    assert (
        "rotary axis" in warning[0]
        and "linear axis" in warning[0]
        and "--position-unit mm" in warning[0]
    )
    assert "RMS [m, m/s]" in out.out


def test_a_linear_models_checkpoint_on_the_rig_warns(capsys: pytest.CaptureFixture[str]) -> None:
    """The shipped EMPS checkpoint (data.position_unit = "m") on the rig's rotary arm."""
    ckpt = pathlib.Path(__file__).resolve().parents[1] / "checkpoints" / "emps_defaults.pt"
    assert main(["evaluate", str(ckpt), "rig:validation"]) == 0
    out = capsys.readouterr()
    assert out.err.strip().startswith("warning: the model was identified on a linear axis")
    assert "rig:validation is a rotary axis" in out.err and "\n" not in out.err.strip()
    assert "RMS [rad, rad/s]" in out.out


def test_position_unit_choices_are_the_schemas() -> None:
    """The parser spells the choices out (importing the schema would import torch for --help)."""
    parser = build_parser()
    (commands,) = [a for a in parser._actions if a.dest == "command"]
    for name in ("evaluate", "simulate", "init"):
        option = commands.choices[name]._option_string_actions["--position-unit"]
        assert tuple(option.choices) == tuple(POSITION_UNITS)
