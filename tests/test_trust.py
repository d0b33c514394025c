"""A user's data, files and machine are safe (issue 19): no rig defaults on a user's data, runs
that never destroy anything, atomic outputs, locks, Ctrl-C, bounded resources, clean errors.

Runs are short slices of the synthetic rig (1500 samples, 1–2 passes of one filter)."""

from __future__ import annotations

import json
import math
import os
import pathlib
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from torchfric.app.artifacts.rundir import LOCK, MARKER
from torchfric.app.cli import main
from torchfric.app.config import Config
from torchfric.errors import TorchfricError
from torchfric.files import json_safe, write_json

SHORT = ["--set", "data.stop=1500", "--set", "estimator.passes=1", "--set", "estimator.tolerance=0"]


def _rig_config(tmp: pathlib.Path, name: str = "short", extra: str = "") -> pathlib.Path:
    cfg = tmp / f"{name}.toml"
    cfg.write_text(
        textwrap.dedent(
            f"""
            name = "{name}"
            out_dir = "{(tmp / "runs").as_posix()}"
            [data]
            train = ["rig:identification"]
            [model]
            friction = "tanh"
            [estimator]
            ensemble = 0
            """
        )
        + extra
    )
    return cfg


def _user_csv(
    path: pathlib.Path, n: int = 3000, *, clip: float | None = None, t_scale=1.0, qdot=False
) -> pathlib.Path:
    """The rig's identification record as a user's own CSV (t, u, q, and the true qdot)."""
    from torchfric.data.rig import rig_experiment

    a = rig_experiment("identification", seed=0)
    u = a["u"][:n].copy()
    if clip is not None:
        lim = clip * np.abs(u).max()
        u = np.clip(u, -lim, lim)
    columns = [a["t"][:n] * t_scale, u, a["q"][:n]] + ([a["qdot_true"][:n]] if qdot else [])
    header = "t,u,q,qdot" if qdot else "t,u,q"
    np.savetxt(
        path, np.column_stack(columns), delimiter=",", header=header, comments="", fmt="%.17g"
    )
    return path


def _user_config(
    tmp: pathlib.Path, data: pathlib.Path, model: str = "c_m = 16.0\n"
) -> pathlib.Path:
    cfg = tmp / "mine.toml"
    cfg.write_text(
        f'name = "mine"\nout_dir = "{(tmp / "runs").as_posix()}"\n[data]\ntrain = "{data.as_posix()}"\n'
        f'[model]\nfriction = "tanh"\n{model}[estimator]\nensemble = 0\npasses = 1\n'
    )
    return cfg


def _one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: "), err
    assert "\n" not in err and "Traceback" not in err
    return err


# -- 1. no silent defaults from the built-in rig ----------------------------------------------
def test_rig_defaults_apply_to_rig_data_only(tmp_path: pathlib.Path) -> None:
    rig = Config()
    assert rig.model.c_m == 16.0 and rig.data.validation == ("rig:validation",)
    data = tmp_path / "mine.csv"
    data.write_text("t,u,q\n0,0,0\n")
    with pytest.raises(TorchfricError, match=r"model\.c_m is required .*`c_m = VALUE`.*\[model\]"):
        Config.loads(f'[data]\ntrain = "{data}"\n')
    mine = Config.loads(f'[data]\ntrain = "{data}"\n[model]\nc_m = 0.5\n')
    assert mine.model.c_m == 0.5 and mine.data.validation == ()
    for key in ("validation", "test"):
        with pytest.raises(TorchfricError, match=rf"data\.{key} = .*rig:.*your own data"):
            Config.loads(
                f'[data]\ntrain = "{data}"\n{key} = ["rig:validation"]\n[model]\nc_m = 1\n'
            )
    # A rig config retargeted at a user's file with --set keeps no rig validation silently.
    with pytest.raises(TorchfricError, match="data.validation"):
        Config.load(
            pathlib.Path(__file__).parents[1] / "experiments" / "configs" / "arm_tanh_ekf.toml",
            [f"data.train={data}"],
        )


def test_a_users_csv_without_c_m_is_refused_before_anything_is_written(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = _user_config(tmp_path, _user_csv(tmp_path / "mine.csv"), model="")
    assert main(["train", str(cfg), "--quiet"]) == 2
    assert "model.c_m" in _one_line_error(capsys)
    assert not (tmp_path / "runs").exists()


def test_a_users_csv_runs_on_its_own_data_only(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = _user_config(tmp_path, _user_csv(tmp_path / "mine.csv"))
    assert main(["train", str(cfg), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    run = pathlib.Path(out["run_dir"])
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["validation"] == {} and metrics["test"] == {}
    assert isinstance(metrics["warnings"], list)
    saved = Config.load(run / "config.toml", check_files=False)
    assert saved.data.validation == () and saved.model.c_m == 16.0


def test_saturated_input_and_millisecond_time_are_warned(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    clipped = _user_config(tmp_path, _user_csv(tmp_path / "clipped.csv", clip=0.5))
    assert main(["train", str(clipped), "--json", "--quiet"]) == 0
    warnings = json.loads(capsys.readouterr().out)["warnings"]
    assert any("satur" in w or "clip" in w for w in warnings), warnings

    # Milliseconds in a seconds column: the differentiator cannot run at "1 Hz", and the error
    # says why; with a measured qdot the record loads, and the warning says it.
    ms = _user_config(tmp_path, _user_csv(tmp_path / "ms.csv", t_scale=1000.0))
    assert main(["train", str(ms), "--json", "--quiet"]) == 2
    assert "looks like milliseconds in a seconds column" in _one_line_error(capsys)
    ms = _user_config(tmp_path, _user_csv(tmp_path / "ms.csv", t_scale=1000.0, qdot=True))
    assert main(["train", str(ms), "--json", "--quiet", "--set", "data.velocity=measured"]) == 0
    warnings = json.loads(capsys.readouterr().out)["warnings"]
    assert any("looks like milliseconds" in w for w in warnings), warnings


def test_result_warnings_name_what_is_almost_certainly_wrong() -> None:
    from torchfric.app.run import result_warnings
    from torchfric.models.arm import ArmModel
    from torchfric.models.friction import OddTanhFriction

    cfg = Config()
    model = ArmModel(OddTanhFriction(3), inertia=0.03, viscous=0.01, c_m=16.0)
    fine = {"inertia": 0.03, "initial_inertia": 0.029, "converged": True, "passes": 4,
            "validation": {"v": {"fit_q": 90.0}}}  # fmt: skip
    assert result_warnings(cfg, model, fine, "prefit") == []
    bad = {"inertia": 0.03, "initial_inertia": 0.005, "converged": False, "passes": 30,
           "last_gain": 3.25, "validation": {"v": {"fit_q": -105.0}},
           "test": {"x": {"fit_q": None}}}  # fmt: skip
    text = " | ".join(result_warnings(cfg, model, bad, "prefit"))
    assert "6× the pre-fit's" in text
    assert "validation v: FIT on q is -105.0 %" in text and "test x: FIT on q is None" in text
    assert (
        "stopped at the pass limit (estimator.passes = 30) with the innovation log-likelihood "
        "still rising by 3.25 nats a pass, above estimator.tolerance 0.5 × "
        f"{model.num_parameters} parameters = {0.5 * model.num_parameters:.3g} nats: "
        "raise estimator.passes"
    ) in text


# -- 2. runs never destroy what the user has ----------------------------------------------------
def test_out_with_foreign_files_is_refused_and_untouched(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = _rig_config(tmp_path)
    mine = tmp_path / "project"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    monkeypatch.chdir(mine)
    for out in (".", str(mine)):
        for extra in ([], ["--overwrite"]):
            assert main(["train", str(cfg), "--quiet", *SHORT, "--out", out, *extra]) == 2
            assert "did not write (thesis.tex)" in _one_line_error(capsys)
    assert sorted(p.name for p in mine.iterdir()) == ["thesis.tex"]
    assert (mine / "thesis.tex").read_text() == "years of work"


def test_out_with_an_earlier_run_needs_overwrite_and_replaces_it_only_at_the_end(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = _rig_config(tmp_path)
    out = tmp_path / "run"
    assert main(["train", str(cfg), "--quiet", *SHORT, "--out", str(out)]) == 0
    assert (out / MARKER).is_file() and (out / "short.pt").is_file()
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert main(["train", str(cfg), "--quiet", *SHORT, "--out", str(out)]) == 2
    assert "--overwrite" in _one_line_error(capsys)

    # A re-run that fails half-way leaves the earlier run exactly as it was.
    import torchfric.app.run.runner as runner
    from torchfric.errors import DivergenceError

    def diverge(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise DivergenceError("the filter diverged (test)")

    monkeypatch.setattr(runner, "identify_ekf", diverge)
    assert main(["train", str(cfg), "--quiet", *SHORT, "--out", str(out), "--overwrite"]) == 2
    assert "diverged" in _one_line_error(capsys)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    monkeypatch.undo()

    assert main(["train", str(cfg), "--quiet", *SHORT, "--out", str(out), "--overwrite"]) == 0
    assert (out / "short.pt").read_bytes() != before[out / "short.pt"]
    assert not (tmp_path / "run.new").exists() and not list(tmp_path.glob("run.old-*"))
    assert not (out / LOCK).exists()


def test_checkpoints_are_copied_only_by_the_explicit_step(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = _rig_config(tmp_path)
    monkeypatch.chdir(tmp_path)
    assert main(["train", str(cfg), "--quiet", *SHORT]) == 0
    assert not (tmp_path / "checkpoints").exists()  # nothing outside the run directory
    assert (tmp_path / "runs" / "short" / "short.pt").is_file()
    target = tmp_path / "checkpoints" / "short.pt"
    assert main(["train", str(cfg), "--quiet", *SHORT, "--checkpoint", str(target)]) == 0
    from torchfric.app.artifacts.checkpoint import read_checkpoint

    assert read_checkpoint(target)["complete"]
    notes = tmp_path / "notes.pt"
    notes.write_text("not a checkpoint")
    assert main(["train", str(cfg), "--quiet", *SHORT, "--checkpoint", str(notes)]) == 2
    assert "not a torchfric checkpoint" in _one_line_error(capsys)
    assert notes.read_text() == "not a checkpoint"


def test_a_second_run_into_a_locked_directory_stops_naming_the_owner(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = _rig_config(tmp_path)
    out = tmp_path / "busy"
    out.mkdir()
    owner = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (out / LOCK).write_text(
            json.dumps({"pid": owner.pid, "host": os.uname().nodename, "since": 0})
        )
        assert main(["train", str(cfg), "--quiet", *SHORT, "--out", str(out)]) == 2
        assert f"in use by another torchfric run (pid {owner.pid})" in _one_line_error(capsys)
        assert sorted(p.name for p in out.iterdir()) == [LOCK]
    finally:
        owner.kill()
        owner.wait()
    # The owner is gone: its stale lock is taken over and the run goes through.
    assert main(["train", str(cfg), "--quiet", *SHORT, "--out", str(out)]) == 0
    assert (out / "short.pt").is_file() and not (out / LOCK).exists()


def test_ctrl_c_names_the_last_pass_and_the_resume_command(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import torchfric.app.run.snapshots as snapshots

    original = snapshots.Snapshots.on_pass_end

    def interrupt_after_pass_1(self, record, result):  # type: ignore[no-untyped-def]
        original(self, record, result)
        if record.index == 1:
            raise KeyboardInterrupt

    monkeypatch.setattr(snapshots.Snapshots, "on_pass_end", interrupt_after_pass_1)
    cfg = _rig_config(tmp_path)
    args = ["train", str(cfg), "--quiet", "--set", "data.stop=1500", "--set", "estimator.passes=2",
            "--set", "estimator.tolerance=0"]  # fmt: skip
    assert main(args) == 130
    err = capsys.readouterr().err.strip()
    run = tmp_path / "runs" / "short"
    assert "the last completed pass 1 is saved in" in err
    assert f"--resume {run}" in err and "--set data.stop=1500" in err
    assert not list(tmp_path.rglob("*.tmp")) and not (run / LOCK).exists()
    assert not (run / "metrics.json").exists()
    monkeypatch.undo()
    assert main([*args, "--resume", str(run)]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["passes"] == 2


def test_simulate_export_and_generate_never_overwrite_without_force(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # a copy of a shipped checkpoint (what it is refused to overwrite needs no training here)
    (tmp_path / "r").mkdir()
    shipped = pathlib.Path(__file__).parents[1] / "checkpoints" / "arm_tanh_ekf.pt"
    ckpt = str(tmp_path / "r" / "short.pt")
    shutil.copyfile(shipped, ckpt)
    data = _user_csv(tmp_path / "in.csv", n=300)
    original = data.read_bytes()
    keep = tmp_path / "keep.csv"
    keep.write_text("mine")
    for cmd in (
        ["simulate", ckpt, str(data), "--out", str(data)],
        ["simulate", ckpt, str(data), "--out", str(data), "--force"],
        ["simulate", ckpt, str(data), "--out", ckpt, "--force"],
        ["simulate", ckpt, str(data), "--out", str(keep)],
        ["export", ckpt, "--out", ckpt, "--force"],
        ["export", ckpt, "--out", str(keep)],
    ):
        assert main(cmd) == 2, cmd
        _one_line_error(capsys)
    assert data.read_bytes() == original and keep.read_text() == "mine"
    assert main(["simulate", ckpt, str(data), "--out", str(keep), "--force"]) == 0
    assert keep.read_text().startswith("t,u,q,qdot")
    rig = tmp_path / "rig"
    rig.mkdir()
    (rig / "truth.json").write_text("mine")
    assert main(["generate", str(rig)]) == 2
    assert "--force" in _one_line_error(capsys)
    assert sorted(p.name for p in rig.iterdir()) == ["truth.json"]


def test_a_closed_pipe_is_not_a_traceback() -> None:
    """`torchfric evaluate ... | head`: the reader may leave before the table is written (here it
    never reads: `true` exits at once, so the write always meets a closed pipe); no traceback."""
    ckpt = pathlib.Path(__file__).parents[1] / "checkpoints" / "arm_tanh_ekf.pt"
    cmd = f"{sys.executable} -m torchfric evaluate {ckpt} rig:validation | true"
    out = subprocess.run(["bash", "-c", "set -o pipefail; " + cmd], capture_output=True, text=True)
    assert "Traceback" not in out.stderr and "Error" not in out.stderr, out.stderr
    assert out.returncode == 141


def test_json_never_holds_nan() -> None:
    clean, reasons = json_safe({"a": {"fit_q": math.nan}, "b": [1.0, math.inf], "c": 2.0})
    assert clean == {"a": {"fit_q": None}, "b": [1.0, None], "c": 2.0}
    assert set(reasons) == {"a.fit_q", "b[1]"}


def test_write_json_is_atomic_and_strict(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "metrics.json"
    write_json(path, {"fit": math.nan})

    def refuse(name: str) -> None:
        raise AssertionError(f"non-standard JSON constant {name}")

    data = json.loads(path.read_text(), parse_constant=refuse)
    assert data["fit"] is None and "fit" in data["null_reasons"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]


# -- 5. bounded resources, clean errors -----------------------------------------------------
@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--set", "model.size=100000"], r"model\.size = 100000 .* needs about .* is available"),
        (["--set", "estimator.ensemble=1000000"], r"estimator\.ensemble = 1000000 .* needs about"),
        (["--set", "estimator.passes=100000000"], r"estimator\.passes .*from 1 to 1000"),
        (["--set", "name=" + "n" * 300], r"300 characters long"),
    ],
)
def test_sizes_that_cannot_fit_are_refused_up_front(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    import re

    cfg = _rig_config(tmp_path)
    assert main(["train", str(cfg), "--quiet", *SHORT, *args]) == 2
    err = _one_line_error(capsys)
    assert re.search(message, err), err
    assert len(err) < 700  # a bad value is echoed in at most ~200 characters
    assert not (tmp_path / "runs").exists()


def test_bad_files_and_environment_are_one_line_errors(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = _rig_config(tmp_path)
    deep = tmp_path / "deep.toml"
    deep.write_text("a = " + "[" * 5000 + "]" * 5000 + "\n")
    assert main(["train", str(deep)]) == 2
    assert "nested too deeply" in _one_line_error(capsys)
    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)
    for bad in (tmp_path, fifo, pathlib.Path("/dev/zero")):
        monkeypatch.setenv("TORCHFRIC_THREADS", "1")
        assert main(["train", str(cfg), "--quiet", "--set", f"data.train={bad}",
                     "--set", "model.c_m=1"]) == 2  # fmt: skip
        _one_line_error(capsys)
    assert main(["train", str(fifo)]) == 2
    assert "not a regular file" in _one_line_error(capsys)
    for name, value in (("TORCHFRIC_THREADS", "lots"), ("TORCHFRIC_NATIVE", "x" * 5000)):
        monkeypatch.setenv(name, value)
        assert main(["train", str(cfg), "--quiet", *SHORT]) == 2
        err = _one_line_error(capsys)
        assert name in err and len(err) < 400
        monkeypatch.delenv(name)
    assert not (tmp_path / "runs").exists()
