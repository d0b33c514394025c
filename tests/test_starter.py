"""``torchfric init`` and ``torchfric check`` as a user runs them, on records written here.

The records come from a small simulation of the grey-box model itself (M q̈ = c_m u − b q̇ −
F_c tanh(q̇/v_s), M = 0.03, c_m = 16), so the pre-fit that ``check`` runs has a known answer.
"""

from __future__ import annotations

import math
import pathlib
import re

import numpy as np
import pytest

from torchfric.app.artifacts.rundir import next_run_dir
from torchfric.app.cli import main
from torchfric.app.config import Config

M, B, FC, C_M = 0.03, 0.02, 0.3, 16.0


def _simulate(n: int, dt: float) -> dict[str, np.ndarray]:
    """t, u, q, qdot of the model driven by two sines (q with 1e-4 rad of noise)."""
    rng = np.random.default_rng(0)
    t = np.arange(n) * dt
    u = 0.06 * np.sin(2 * np.pi * 0.7 * t) + 0.04 * np.sin(2 * np.pi * 2.3 * t + 1.0)
    q, qdot = np.zeros(n), np.zeros(n)
    x = v = 0.0
    sub = 20
    h = dt / sub
    for k in range(1, n):
        for _ in range(sub):
            a = (C_M * u[k - 1] - B * v - FC * math.tanh(v / 0.02)) / M
            v += h * a
            x += h * v
        q[k], qdot[k] = x, v
    return {"t": t, "u": u, "q": q + rng.normal(0.0, 1e-4, n), "qdot": qdot}


@pytest.fixture(scope="module")
def record() -> dict[str, np.ndarray]:
    return _simulate(4000, 1e-3)


def _write(path: pathlib.Path, header: list[str], columns: list[np.ndarray]) -> pathlib.Path:
    table = np.column_stack(columns)
    np.savetxt(path, table, delimiter=",", header=",".join(header), comments="", fmt="%.17g")
    return path


def _csv(path: pathlib.Path, rec: dict[str, np.ndarray], header=("t", "u", "q")) -> pathlib.Path:  # type: ignore[no-untyped-def]
    keys = ["t", "u", "q", "qdot"][: len(header)]
    return _write(path, list(header), [rec[k] for k in keys])


def _files(folder: pathlib.Path) -> set[pathlib.Path]:
    return {p for p in folder.rglob("*") if "cache" not in p.parts}


def _fails(capsys: pytest.CaptureFixture[str], argv: list[str], *expected: str) -> str:
    """Run `argv`: exit status 2 and one line ``error: ...`` holding every `expected`."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err, err
    for text in expected:
        assert text in err, err
    return err


@pytest.fixture
def user(tmp_path: pathlib.Path, worker_cache: pathlib.Path, monkeypatch: pytest.MonkeyPatch):  # type: ignore[no-untyped-def]
    """A user's folder as the working directory (the compiled-code cache of the worker's own,
    outside the folder and the user's home)."""
    folder = tmp_path / "work"
    folder.mkdir()
    monkeypatch.chdir(folder)
    return folder


def test_init_then_check_as_a_user_would(user, record, capsys) -> None:  # type: ignore[no-untyped-def]
    _csv(user / "rec.csv", record, ("time", "current", "position"))
    assert main(["init", "rec.csv", "--c-m", "16"]) == 0
    out = capsys.readouterr().out
    assert "4000 samples, 3.999 s, dt 0.001 s (1000 Hz" in out
    assert "wrote       " + str(user / "rec.toml") in out
    cfg = Config.load(user / "rec.toml")
    assert cfg.name == "rec" and cfg.model.c_m == C_M
    # a static model's neurons saturated by v95/2 (6), LuGre's by v95 (3): saturation_floor
    assert cfg.model.saturation == "auto" and cfg.model.dynamic == "auto"
    # init names the selection rule: the default, validation with identification
    assert cfg.estimator.select == "validation"
    assert 'select = "validation"' in (user / "rec.toml").read_text()
    assert cfg.data.train == (str(user / "rec.csv"),) and cfg.data.validation == ()
    assert cfg.data.columns == {"t": "time", "u": "current", "q": "position"}
    assert cfg.data.position_unit == "rad" and cfg.data.velocity_cutoff_hz is None
    text = (user / "rec.toml").read_text()
    assert 'train = ["rec.csv"]' in text  # relative to the config's folder
    assert "docs/config.md" in text and "# validation = " in text

    before = _files(user)
    assert main(["check", "rec.toml"]) == 0
    out = capsys.readouterr().out
    assert _files(user) == before and not (user / "runs").exists()  # nothing written
    assert f"rec → {pathlib.Path('runs') / 'rec'}" in out
    assert "rec.csv: 4000 samples, dt 0.001 s (1000 Hz), 3.999 s" in out
    assert re.search(r"^validation  none$", out, re.M)
    assert "highpass (causal high-pass differentiator, cut-off 200 Hz)" in out
    # model.dynamic = "auto": the larger (LuGre) of the two models it compares is checked
    assert "tanh friction, size 3, friction class auto (static and LuGre identified" in out
    assert "11 parameters, c_m 16 (known, fixed)" in out
    assert "ekf: up to 30 passes (tolerance 0.5), ensemble of 9 filters" in out
    assert re.search(r"^kept        the likeliest pass \(no validation records\)$", out, re.M)
    assert "4000 samples × 30 passes × 9 filter(s) = 1,080,000 filter steps" in out
    inertia = float(re.search(r"pre-fit on the identification data: inertia (\S+),", out)[1])
    assert inertia == pytest.approx(M, rel=0.02)  # the simulated arm's

    (user / "runs" / "rec").mkdir(parents=True)  # an earlier run: the next one is rec-2
    assert main(["check", "rec.toml", "--set", "estimator.passes=3", "--set", "estimator.ensemble=0"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert f"rec → {pathlib.Path('runs') / 'rec-2'}" in out
    assert "ekf: up to 3 passes (tolerance 0.5), one filter" in out
    assert "4000 samples × 3 passes × 1 filter(s) = 12,000 filter steps" in out
    assert "torchfric train rec.toml --set estimator.passes=3 --set estimator.ensemble=0" in out
    assert not (user / "runs" / "rec-2").exists()


def test_init_gives_the_filter_its_sub_steps_from_the_model(user, record, capsys) -> None:  # type: ignore[no-untyped-def]
    # the paper's one RK4 step a sample is the library's default; a user's config asks for
    # the count the model's friction needs (estimator.substeps = "auto", tests/test_substeps.py)
    _csv(user / "rec.csv", record, ("time", "current", "position"))
    assert main(["init", "rec.csv", "--c-m", "16"]) == 0
    assert Config.load(user / "rec.toml").estimator.substeps == "auto"
    assert 'substeps = "auto"' in (user / "rec.toml").read_text()


def test_config_in_another_folder_names_the_data_relative_to_itself(user, record, capsys) -> None:  # type: ignore[no-untyped-def]
    _csv(user / "rec.csv", record)
    (user / "configs").mkdir()
    assert main(["init", "rec.csv", "--c-m", "2.5", "--out", "configs/my.toml"]) == 0
    assert 'train = ["../rec.csv"]' in (user / "configs" / "my.toml").read_text()
    cfg = Config.load(user / "configs" / "my.toml")
    assert cfg.data.train == (str(user / "rec.csv"),) and cfg.model.c_m == 2.5
    assert cfg.data.columns == {"t": "t", "u": "u", "q": "q"}


@pytest.mark.parametrize(
    ("header", "columns", "unit"),
    [
        (("Time [s]", "Input", "Theta"), {"t": "Time [s]", "u": "Input", "q": "Theta"}, "rad"),
        (("time_s", "CURRENT", "pos_deg"), {"t": "time_s", "u": "CURRENT", "q": "pos_deg"}, "deg"),
        (
            ("sec", "torque", "angle (rad)", "Velocity"),
            {"t": "sec", "u": "torque", "q": "angle (rad)", "qdot": "Velocity"},
            "rad",
        ),
        (("t", "u", "q", "dq"), {"t": "t", "u": "u", "q": "q", "qdot": "dq"}, "rad"),
        # an alternative as one word of the name (as engineers export them)
        (
            ("Time [s]", "motor_current", "angle_deg"),
            {"t": "Time [s]", "u": "motor_current", "q": "angle_deg"},
            "deg",
        ),  # fmt: skip
        (
            ("time_s", "force_cmd_N", "pos_mm"),
            {"t": "time_s", "u": "force_cmd_N", "q": "pos_mm"},
            "mm",
        ),  # fmt: skip
    ],
)
def test_alternative_column_names_map(user, record, capsys, header, columns, unit) -> None:  # type: ignore[no-untyped-def]
    rec = dict(record)
    if unit == "deg":
        rec["q"] = np.degrees(rec["q"])
    _csv(user / "rec.csv", rec, header)
    assert main(["init", "rec.csv", "--c-m", "16"]) == 0
    cfg = Config.load(user / "rec.toml")
    assert cfg.data.columns == columns and cfg.data.position_unit == unit
    if unit == "deg":  # read in degrees, converted: the same arm as in rad
        assert main(["check", "rec.toml"]) == 0
        out = capsys.readouterr().out
        inertia = float(re.search(r"inertia (\S+),", out)[1])
        assert inertia == pytest.approx(M, rel=0.02)


def test_column_flag_and_time_step_for_a_file_without_names_or_time(user, record, capsys) -> None:  # type: ignore[no-untyped-def]
    _write(user / "rec.csv", ["a", "b"], [record["u"], record["q"]])
    err = _fails(capsys, ["init", "rec.csv", "--c-m", "16"], "cannot tell which column is t")
    assert "--time-step SECONDS" in err and "the header is: a, b" in err
    err = _fails(capsys, ["init", "rec.csv", "--c-m", "16", "--time-step", "0.001"], "is u")
    assert "--time-step" not in err and 'columns = { u = "NAME", q = "NAME" }' in err
    argv = ["init", "rec.csv", "--c-m", "16", "--time-step", "0.001", "--column", "u=a"]
    assert main([*argv, "--column", "q=b"]) == 0
    cfg = Config.load(user / "rec.toml")
    assert cfg.data.columns == {"u": "a", "q": "b"} and cfg.data.time_step == 0.001
    assert main(["check", "rec.toml"]) == 0


@pytest.mark.parametrize(
    ("header", "expected"),
    [
        (("a", "b", "c"), ["cannot tell which column is t (time in s): none does; u (input): none "
                           "does; q (position): none does", "the header is: a, b, c",
                           "--column t=NAME --column u=NAME --column q=NAME (or --time-step",
                           'columns = { t = "NAME", u = "NAME", q = "NAME" }']),
        (("t", "pos", "position"), ["column is u (input): none does; q (position): pos and "
                                    'position all look like it', 'columns = { t = "t", u = '
                                    '"NAME", q = "NAME" }']),
    ],
)  # fmt: skip
def test_init_refuses_a_header_it_cannot_map(user, record, capsys, header, expected) -> None:  # type: ignore[no-untyped-def]
    _csv(user / "rec.csv", record, header)
    before = _files(user)
    err = _fails(capsys, ["init", "rec.csv", "--c-m", "16"], *expected)
    assert "--column" in err or "ms" in err
    assert _files(user) == before


def test_init_refuses_bad_data_and_arguments_and_writes_nothing(user, record, capsys) -> None:  # type: ignore[no-untyped-def]
    rec = dict(record)
    t = rec["t"].copy()
    t[2000:] += 0.0002  # a step of 1.2 samples: no gap (those cut: test_lab_records), no record
    _csv(user / "gap.csv", {**rec, "t": t})
    q = rec["q"].copy()
    q[100:] = np.nan  # nothing but NaN after a run too short (line 2 is the first sample)
    _csv(user / "nan.csv", {**rec, "q": q})
    _csv(user / "rec.csv", rec)
    (user / "taken.toml").write_text("# mine\n")
    before = _files(user)
    _fails(capsys, ["init", "gap.csv", "--c-m", "16"], "sampling is not uniform at line 2002")
    _fails(
        capsys,
        ["init", "nan.csv", "--c-m", "16"],
        "empty or NaN at lines 102–4001",
        "no run of 200",
    )
    _fails(capsys, ["init", "rec.csv"], "--c-m is required", "not estimate it")
    _fails(capsys, ["init", "rec.csv", "--c-m", "abc"], "--c-m abc: expected a positive number")
    _fails(capsys, ["init", "rec.csv", "--c-m", "8,0"], "with a decimal point: --c-m 8.0")
    _fails(capsys, ["init", "rec.csv", "--c-m", "16", "--out", "taken.toml"], "exists", "--force")
    _fails(capsys, ["init", "rec.csv", "--c-m", "16", "--out", "rec.csv"], "names a data file")
    _fails(capsys, ["init", "missing.csv", "--c-m", "16"], "no such file")
    _fails(capsys, ["init", "rec.csv", "--c-m", "16", "--column", "x=u"], "'x' is not one of")
    assert _files(user) == before and (user / "taken.toml").read_text() == "# mine\n"
    assert main(["init", "rec.csv", "--c-m", "16", "--out", "taken.toml", "--force"]) == 0
    assert Config.load(user / "taken.toml").model.c_m == C_M


def test_split_writes_two_records_only_when_asked(user, record, capsys) -> None:  # type: ignore[no-untyped-def]
    _csv(user / "rec.csv", record, ("time", "u", "q", "qdot"))
    assert main(["init", "rec.csv", "--c-m", "16", "--split", "0.75"]) == 0
    ident, valid = user / "rec_identification.csv", user / "rec_validation.csv"
    a = np.loadtxt(ident, delimiter=",", skiprows=1)
    b = np.loadtxt(valid, delimiter=",", skiprows=1)
    assert a.shape == (3000, 4) and b.shape == (1000, 4)
    whole = np.column_stack([record[k] for k in ("t", "u", "q", "qdot")])
    np.testing.assert_array_equal(np.vstack([a, b]), whole)  # the file's samples, unchanged
    cfg = Config.load(user / "rec.toml")
    assert cfg.data.train == (str(ident),) and cfg.data.validation == (str(valid),)
    assert main(["check", "rec.toml"]) == 0
    out = capsys.readouterr().out
    assert "rec_validation.csv: 1000 samples" in out and "rec_identification.csv: 3000" in out
    # a second split into the same folder would replace them: refused, nothing written
    ident.write_text("mine\n")
    valid.unlink()
    before = _files(user)
    _fails(capsys, ["init", "rec.csv", "--c-m", "16", "--split", "0.5", "--out", "b.toml"],
           "rec_identification.csv, which exists", "never replaces a data file")  # fmt: skip
    assert _files(user) == before and ident.read_text() == "mine\n"
    _fails(capsys, ["init", "rec.csv", "--c-m", "16", "--split", "1.5", "--out", "b.toml"],
           "--split 1.5: expected the identification part's fraction")  # fmt: skip


def test_a_validation_record_beside_the_data_is_proposed_by_its_name(user, record, capsys) -> None:  # type: ignore[no-untyped-def]
    other = _simulate(1500, 1e-3)
    _csv(user / "run1_train.csv", record)
    _csv(user / "run1_val.csv", other)
    _csv(user / "run2_val.csv", other)  # another run's
    _csv(user / "slow_val.csv", _simulate(300, 1e-2))  # other sample time: never proposed
    assert main(["init", "run1_train.csv", "--c-m", "16"]) == 0
    assert "validation  run1_val.csv" in capsys.readouterr().out
    cfg = Config.load(user / "run1_train.toml")
    assert cfg.data.validation == (str(user / "run1_val.csv"),)
    _csv(user / "solo.csv", record)
    assert main(["init", "solo.csv", "--c-m", "16"]) == 0
    text = (user / "solo.toml").read_text()
    assert Config.load(user / "solo.toml").data.validation == ()
    assert '# validation = ["run1_val.csv", "run2_val.csv"]' in text and "slow_val" not in text


def test_units_and_slow_sampling_are_checked(user, record, capsys) -> None:  # type: ignore[no-untyped-def]
    counts = dict(record, q=np.round(record["q"] * 4096 / (2 * np.pi)))
    _csv(user / "counts.csv", counts)
    _fails(capsys, ["init", "counts.csv", "--c-m", "16"], "q holds whole numbers only",
           "encoder counts; rerun with --counts-per-rev N")  # fmt: skip
    assert main(["init", "counts.csv", "--c-m", "16", "--counts-per-rev", "4096"]) == 0
    capsys.readouterr()
    data = Config.load(user / "counts.toml").data
    assert (data.position_unit, data.counts_per_rev) == ("counts", 4096.0)
    deg = dict(record, q=np.degrees(record["q"]))
    _csv(user / "deg.csv", deg)
    assert main(["init", "deg.csv", "--c-m", "16"]) == 0
    out = capsys.readouterr().out
    assert (  # the terminal names the line to change, and the line to write instead
        'if q is in degrees, change the line position_unit = "rad" under [data] in deg.toml to '
        'position_unit = "deg"' in out
    )
    text = (user / "deg.toml").read_text()
    comment = re.search(r"((?:^#.*\n)+)position_unit = ", text, re.M)[1]  # the lines above it
    assert 'if q is in degrees, write position_unit = "deg" below' in comment.replace("\n# ", " ")
    assert Config.load(user / "deg.toml").data.position_unit == "rad"  # a note, not a change
    assert main(["check", "deg.toml", "--set", 'data.position_unit="deg"']) == 0  # the fix works
    inertia = float(re.search(r"inertia (\S+),", capsys.readouterr().out)[1])
    assert inertia == pytest.approx(M, rel=0.02)
    _csv(user / "rad.csv", record)
    assert main(["init", "rad.csv", "--c-m", "16"]) == 0
    assert "note" not in capsys.readouterr().out  # 8.7 rad/s at most: nothing to say
    _csv(user / "slow.csv", _simulate(1000, 1e-2))  # 100 Hz: the 200 Hz filter cannot run
    assert main(["init", "slow.csv", "--c-m", "16"]) == 0
    cfg = Config.load(user / "slow.toml")
    assert cfg.data.velocity_cutoff_hz == 20.0  # 0.4 × the 50 Hz Nyquist frequency
    assert main(["check", "slow.toml"]) == 0
    assert "cut-off 20 Hz" in capsys.readouterr().out


def test_check_refuses_a_wrong_key_and_writes_nothing(user, record, capsys) -> None:  # type: ignore[no-untyped-def]
    _csv(user / "rec.csv", record)
    cfg = user / "c.toml"
    cfg.write_text('[data]\ntrain = "rec.csv"\n[model]\nc_m = 16.0\nfricton = "tanh"\n')
    _fails(
        capsys, ["check", "c.toml"], 'unknown key "model.fricton"', 'did you mean "model.friction"'
    )
    cfg.write_text('[data]\ntrain = "rec.csv"\n[model]\nc_m = 16.0\n')
    _fails(
        capsys, ["check", "c.toml", "--set", "estimator.pases=3"], 'did you mean "estimator.passes"'
    )
    _fails(capsys, ["check", "c.toml", "--set", "data.train=nope.csv"], "no such file")
    (user / "runs").write_text("a file where run directories would go")
    _fails(capsys, ["check", "c.toml"], "is a file, not a folder")
    (user / "runs").unlink()
    assert main(["check", "c.toml"]) == 0
    assert not (user / "runs").exists()


def test_next_run_dir_is_the_one_claim_would_take_and_creates_nothing(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from torchfric.app.artifacts.rundir import claim_run_dir

    default = tmp_path / "runs" / "x"
    assert next_run_dir(default) == default and not (tmp_path / "runs").exists()
    default.mkdir(parents=True)
    (tmp_path / "runs" / "x-2").write_text("a file takes the name too")
    assert next_run_dir(default) == tmp_path / "runs" / "x-3"
    assert not (tmp_path / "runs" / "x-3").exists()
    assert claim_run_dir(default).path == tmp_path / "runs" / "x-3"  # the claim agrees


def test_a_config_that_fails_its_check_is_not_written_nor_its_split_files(user, capsys) -> None:  # type: ignore[no-untyped-def]
    n = 1000
    still = {"t": np.arange(n) * 1e-3, "u": np.zeros(n), "q": np.zeros(n)}
    _csv(user / "still.csv", still)  # reads fine, but nothing moves: the pre-fit refuses it
    before = _files(user)
    _fails(capsys, ["init", "still.csv", "--c-m", "1", "--split", "0.5"], "never move")
    assert _files(user) == before


_TERMS = (
    ("offset", 0.0, "try it when the simulation drifts one way"),
    ("gravity", 0.1, "g_c·sin q of an unbalanced rotating arm"),
    ("asymmetric", 0.0, "viscous slope b + a forwards and b − a backwards"),
)


def test_white_box_terms_are_offered_commented_out_and_work(user, record, capsys) -> None:  # type: ignore[no-untyped-def]
    """Each term is written off, in [model], below the line that says when to turn it on;
    turned on (all three in one config: one init and one check), the model builds with each and
    the pre-fit runs."""
    _csv(user / "rec.csv", record)
    assert main(["init", "rec.csv", "--c-m", "16"]) == 0
    capsys.readouterr()
    text = on = (user / "rec.toml").read_text()
    model = text.split("\n[model]\n")[1].split("\n[estimator]\n")[0]
    written = Config.load(user / "rec.toml").model
    for key, value, when in _TERMS:
        line = f"# {key} = {value}"
        assert model.count(f"\n{line}\n") == 1  # off, in [model]
        above = re.search(rf"((?:^# .*\n)+){re.escape(line)}$", model, re.M)[1]
        assert when in above.replace("\n# ", " ")
        assert getattr(written, key) is None  # off as written
        on = on.replace(f"\n{line}\n", f"\n{key} = {value}\n")
    (user / "on.toml").write_text(on)
    turned = Config.load(user / "on.toml").model
    assert [getattr(turned, key) for key, _, _ in _TERMS] == [v for _, v, _ in _TERMS]
    assert main(["check", "on.toml"]) == 0  # the model builds and the pre-fit runs with them
    out = capsys.readouterr().out
    # auto: LuGre checked (11) + the three terms
    assert "14 parameters, c_m 16 (known, fixed); terms: offset, gravity, asymmetric viscous" in out


def test_the_friction_class_is_auto_as_written_and_lugre_works(user, record, capsys) -> None:  # type: ignore[no-untyped-def]
    _csv(user / "rec.csv", record)
    assert main(["init", "rec.csv", "--c-m", "16"]) == 0
    capsys.readouterr()
    text = (user / "rec.toml").read_text()
    line = 'dynamic = "auto"'
    model = text.split("\n[model]\n")[1].split("\n[estimator]\n")[0]
    assert model.count(f"\n{line}\n") == 1
    above = re.search(rf"((?:^# .*\n)+){re.escape(line)}$", model, re.M)[1]
    assert "LuGre is kept only if it predicts the held-out" in above.replace("\n# ", " ")
    assert Config.load(user / "rec.toml").model.dynamic == "auto"
    (user / "on.toml").write_text(text.replace(f"\n{line}\n", '\ndynamic = "lugre"\n'))
    assert Config.load(user / "on.toml").model.dynamic == "lugre"
    assert main(["check", "on.toml"]) == 0
    out = capsys.readouterr().out
    # σ0 unset starts from the data (one position step of pre-sliding), not a fixed number
    sigma0 = float(re.search(r"with LuGre bristles \(sigma0 (\S+), sigma1", out)[1])
    assert "11 parameters" in out and "friction class auto" not in out and sigma0 != 1000.0


@pytest.mark.parametrize(
    ("n", "dt", "header", "noise", "why"),
    [
        (2000, 1e-3, ("t", "u", "q"), True, "a step of 0.5 s or more"),  # 1 kHz in ms: 1.0
        (5000, 1e-4, ("t", "u", "q", "qdot"), True, "the measured qdot is"),  # 10 kHz: 0.1
        (5000, 1e-4, ("t", "u", "q"), False, "q moves as if sampled much faster"),
    ],
)
def test_time_in_milliseconds_is_refused_not_filtered_around(  # type: ignore[no-untyped-def]
    user, capsys, n, dt, header, noise, why
) -> None:
    rec = _simulate(n, dt)
    if not noise:  # the simulation's noise taken out: q smooth on the scale of a sample
        rec["q"] -= np.random.default_rng(0).normal(0.0, 1e-4, n)
    _csv(user / "rec.csv", {**rec, "t": rec["t"] * 1000.0}, header)
    _write(user / "bare.csv", list(header[1:]), [rec[k] for k in header[1:]])  # no t
    before = _files(user)
    step = f"{dt * 1000:g} s ({1 / (dt * 1000):g} Hz)"
    _fails(capsys, ["init", "rec.csv", "--c-m", "16"],
           f"the time column 't' steps by {step}, which looks like milliseconds (", why,
           'name the unit in the header ("t [ms]")')  # fmt: skip
    _fails(capsys, ["init", "bare.csv", "--c-m", "16", "--time-step", f"{dt * 1000:g}"],
           f"--time-step {dt * 1000:g}: a sample time of {step} looks like milliseconds",
           "e.g. --time-step 0.001 for 1 ms samples")  # fmt: skip
    assert _files(user) == before  # nothing written
    assert main(["init", "bare.csv", "--c-m", "16", "--time-step", f"{dt:g}"]) == 0  # in s: fine


def test_slow_but_plausible_sampling_keeps_a_lowered_cutoff(user, capsys) -> None:  # type: ignore[no-untyped-def]
    _csv(user / "disc.csv", _simulate(1000, 0.025))  # 40 Hz, as the unbalanced disc
    assert main(["init", "disc.csv", "--c-m", "16"]) == 0
    assert "warning" not in capsys.readouterr().out  # the data check finds nothing either
    assert Config.load(user / "disc.toml").data.velocity_cutoff_hz == 8.0  # 0.4 × 20 Hz


@pytest.mark.parametrize(
    ("data", "siblings", "validation", "test"),
    [
        ("run1_train", ["run1_test", "run2_test"], ["run1_test"], []),
        ("train", ["test"], ["test"], []),
        ("Training-Data", ["Testing-Data"], ["Testing-Data"], []),
        ("rec", ["rec_test", "rec_val"], ["rec_val"], ["rec_test"]),
        ("step_test", ["step_test_val"], ["step_test_val"], []),  # "test" in the data's name
    ],
)
def test_a_test_record_beside_the_data_pairs_too(  # type: ignore[no-untyped-def]
    user, record, capsys, data, siblings, validation, test
) -> None:
    other = _simulate(1500, 1e-3)
    _csv(user / f"{data}.csv", record)
    for name in siblings:
        _csv(user / f"{name}.csv", other)
    assert main(["init", f"{data}.csv", "--c-m", "16"]) == 0
    out = capsys.readouterr().out
    assert f"validation  {', '.join(f'{v}.csv' for v in validation)}" in out
    assert ("test        " in out) == bool(test)
    cfg = Config.load(user / f"{data}.toml")
    assert cfg.data.validation == tuple(str(user / f"{v}.csv") for v in validation)
    assert cfg.data.test == tuple(str(user / f"{v}.csv") for v in test)
    assert main(["check", f"{data}.toml"]) == 0


def test_a_coarse_encoder_gets_a_quieter_velocity_in_any_unit(user, capsys) -> None:  # type: ignore[no-untyped-def]
    """A heavy axis with a 4096-count encoder: the 200-Hz velocity carries noise of about 3 % of
    its v95 (a run at 200 Hz did not converge in 100 passes, and did in 3 at 50 Hz), so init
    writes a lower ``velocity_cutoff_hz`` and says why. The share is a ratio of speeds, so the
    same record in counts or in rad gets the same cut-off; the quieter records of this file
    keep the default (`test_init_then_check_as_a_user_would`), and so does a slow record whose
    motion, not noise, fills its second differences (`test_slow_but_plausible_sampling…`)."""
    from torchfric.data.axis import AxisParameters, axis_record, write_csv

    heavy = AxisParameters(inertia=0.5, c_m=3.0, viscous=0.3, coulomb=1.2, static=1.8,
                           stribeck_velocity=0.8, quantum=2 * math.pi / 4096, max_speed=15.0,
                           max_input=3.0)  # fmt: skip
    rec = axis_record(heavy, seed=1, duration=10.0)
    write_csv(user / "counts.csv", rec, position_unit="counts", counts_per_rev=4096)
    write_csv(user / "rad.csv", rec)
    cutoffs = []
    for name, extra in (("counts", ["--counts-per-rev", "4096"]), ("rad", [])):
        assert main(["init", f"{name}.csv", "--c-m", "3", *extra]) == 0
        out = capsys.readouterr().out
        assert re.search(r"at 200 Hz carries noise of 2\.\d% of its 95th-percentile speed", out)
        cutoffs.append(Config.load(user / f"{name}.toml").data.velocity_cutoff_hz)
    assert cutoffs[0] == cutoffs[1] and 30.0 < cutoffs[0] < 120.0


def test_a_vertical_axis_gets_its_offset_and_a_config_without_it_a_warning(user, capsys) -> None:  # type: ignore[no-untyped-def]
    """Gravity on a vertical axis (12 kg, 117.7 N) is a constant force the odd friction curve
    cannot hold: without the offset term such a run reached an inertia of 7e42. init turns
    ``model.offset`` on and says why; ``check`` of a config without it warns, naming the key;
    the records of this file (no constant force) keep it off."""
    from torchfric.data.axis import AxisParameters, axis_record, write_csv

    z = AxisParameters(inertia=12.0, c_m=60.0, viscous=150.0, coulomb=15.0, static=22.0,
                       stribeck_velocity=0.002, smoothing=0.05, offset=117.7, quantum=1e-6,
                       max_speed=0.4, max_input=5.0)  # fmt: skip
    write_csv(user / "z.csv", axis_record(z, seed=0, duration=8.0), position_unit="mm",
              unit_header=True)  # fmt: skip
    assert main(["init", "z.csv", "--c-m", "60"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"constant force or torque of 11\d\.\d .*: model\.offset is on", out)
    assert Config.load(user / "z.toml").model.offset == 0.0
    text = (user / "z.toml").read_text().replace("\noffset = 0.0", "\n# offset = 0.0")
    (user / "without.toml").write_text(text)
    assert main(["check", "without.toml"]) == 0
    out = capsys.readouterr().out
    assert "leave a constant 11" in out and "set model.offset = 0.0" in out


def _pendulum(
    n: int, dt: float, zero_deg: float, delay: int = 0, constant: float = 0.0, bias: float = 0.0
) -> dict[str, np.ndarray]:
    """An unbalanced arm, M q̈ = u − b q̇ − Fc tanh(q̇/0.01) − g sin q − `constant` (M 0.05, b
    0.01, Fc 0.05, g 0.5), swung by two sines (plus `bias`) to about ±100°; q in degrees from a
    zero `zero_deg` past the lowest point, as an encoder mounted anywhere reads it; the logged
    u acts `delay` samples late."""
    t = np.arange(n) * dt
    u = 0.45 * np.sin(2 * np.pi * 0.6 * t) + 0.2 * np.sin(2 * np.pi * 1.7 * t + 1.0) + bias
    q = np.zeros(n)
    x = v = 0.0
    h = dt / 10
    for k in range(1, n):
        for _ in range(10):
            drive = u[k - 1 - delay] if k - 1 - delay >= 0 else 0.0
            a = (drive - 0.01 * v - 0.05 * math.tanh(v / 0.01) - 0.5 * math.sin(x) - constant) / 0.05
            v += h * a
            x += h * v
        q[k] = x
    return {"t": t, "u": u, "q": np.degrees(q) + zero_deg}


def test_an_arms_constant_torque_is_fitted_beside_its_gravity_not_before_it(user, capsys) -> None:  # type: ignore[no-untyped-def]
    """A constant torque beside an arm's g sin q (a cable, friction that differs by direction)
    takes little of the inverse dynamics' residual, yet left out it biased a robot joint's M
    by 16 % (user walk): with gravity init turns the offset on too, its note naming the
    constant fitted beside g sin q (a constant alone is the mean of g sin q over the record,
    wherever the arm swung); a config with gravity and without the offset is warned."""
    for constant in (0.02, 0.0):
        rec = _pendulum(6000, 2e-3, 0.0, constant=constant, bias=0.2)  # mostly at q > 0
        _write(user / "arm.csv", ["t", "u", "q [deg]"], [rec["t"], rec["u"], rec["q"]])
        assert main(["init", "arm.csv", "--c-m", "1", "--force"]) == 0
        out = capsys.readouterr().out
        assert "model.gravity is on" in out and "model.offset is on" in out, out
        found = float(re.search(r"leave a constant torque of ([-0-9.e]+)", out).group(1))
        assert found == pytest.approx(constant, abs=0.004), out
    text = re.sub(r"\noffset = [0-9.e-]+\n", "\n", (user / "arm.toml").read_text())
    (user / "no_offset.toml").write_text(text)
    assert Config.load(user / "no_offset.toml").model.offset is None
    assert main(["check", "no_offset.toml"]) == 0
    assert "beside which a constant goes" in capsys.readouterr().out


def test_an_unbalanced_arm_gets_its_gravity_term_when_q_is_zero_at_the_bottom(user, capsys) -> None:  # type: ignore[no-untyped-def]
    """An arm that swings back (g sin q): init turns ``model.gravity`` on, with the amplitude
    its inverse dynamics give as the start; an encoder zeroed 90° away gets a note to re-zero q
    and the term stays off; ``check`` of a config without it names ``model.gravity``. An input
    that acts two samples late gets ``data.input_delay = 2``."""
    rec = _pendulum(6000, 2e-3, 0.0)
    _write(user / "arm.csv", ["t", "u", "q [deg]"], [rec["t"], rec["u"], rec["q"]])
    assert main(["init", "arm.csv", "--c-m", "1"]) == 0
    assert "model.gravity is on" in capsys.readouterr().out
    assert Config.load(user / "arm.toml").model.gravity == pytest.approx(0.5, rel=0.05)
    text = re.sub(r"\ngravity = [0-9.e-]+\n", "\n", (user / "arm.toml").read_text())
    (user / "without.toml").write_text(text)
    assert main(["check", "without.toml"]) == 0
    assert "the model has no gravity term: set model.gravity = 0.5" in capsys.readouterr().out
    off = _pendulum(6000, 2e-3, 90.0)
    _write(user / "off.csv", ["t", "u", "q [deg]"], [off["t"], off["u"], off["q"]])
    assert main(["init", "off.csv", "--c-m", "1"]) == 0
    out = capsys.readouterr().out
    assert "lowest point at q0 = 90°" in out and "re-zero q" in out
    assert Config.load(user / "off.toml").model.gravity is None
    assert "input_delay" not in out  # u acts at once here
    late = _pendulum(6000, 2e-3, 0.0, delay=2)
    _write(user / "late.csv", ["t", "u", "q [deg]"], [late["t"], late["u"], late["q"]])
    assert main(["init", "late.csv", "--c-m", "1"]) == 0
    assert "fit best with u acting 2 sample(s) late" in capsys.readouterr().out
    assert Config.load(user / "late.toml").data.input_delay == 2
