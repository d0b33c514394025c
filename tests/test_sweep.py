"""`torchfric sweep`: a sweep runs, resumes, prunes, records failures and writes a best.toml
that trains; bad spaces are refused before anything is written; the Ray backend runs."""

from __future__ import annotations

import csv
import importlib.util
import json
import pathlib

import pytest
from rig_configs import rig_config

from torchfric.app.artifacts.checkpoint import read_checkpoint
from torchfric.app.cli import main
from torchfric.app.config import Config
from torchfric.errors import TorchfricError

optuna = pytest.importorskip("optuna", reason='Optuna is not installed: pip install -e ".[sweep]"')

from torchfric.app.sweep.driver import run_sweep, shares  # noqa: E402
from torchfric.app.sweep.space import read_space  # noqa: E402

# Short trials: 2 passes of one filter over the first 2000 samples.
FAST = ["estimator.passes=2", "estimator.ensemble=0", "data.stop=2000"]


def _space(folder: pathlib.Path, text: str, name: str = "space.toml") -> pathlib.Path:
    path = folder / name
    path.write_text("[space]\n" + text, encoding="utf-8")
    return path


def _rows(out: pathlib.Path) -> list[dict[str, str]]:
    with open(out / "trials.csv", newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_sweep_writes_trials_best_and_figure_then_resumes(tmp_path, capsys):
    cfg = rig_config(tmp_path)
    space = _space(
        tmp_path,
        '"estimator.p0_theta" = { low = 0.1, high = 10.0, log = true }\n'
        '"model.size" = { choices = [2, 3] }\n',
    )
    out = tmp_path / "sweep"
    sets = sum((["--set", s] for s in FAST), [])
    argv = ["sweep", str(cfg), "--space", str(space), "--trials", "2", "--out", str(out), *sets]
    assert main(argv) == 0
    printed = capsys.readouterr()
    assert "2 done, 0 pruned, 0 failed" in printed.out
    assert "objective   validation FIT" in printed.out
    assert "trial 0:" in printed.err  # progress on stderr

    rows = _rows(out)
    assert [r["number"] for r in rows] == ["0", "1"]
    assert {r["state"] for r in rows} == {"COMPLETE"}
    for r in rows:
        assert 0.1 <= float(r["estimator.p0_theta"]) <= 10.0
        assert r["model.size"] in ("2", "3")
        # the score is the trial's run's own validation FIT, as in its metrics.json
        metrics = json.loads(
            (out / "trials" / f"{int(r['number']):04d}" / "metrics.json").read_text()
        )
        fits = list(metrics["validation"].values())
        expect = sum(0.5 * (f["fit_q"] + f["fit_qdot"]) for f in fits) / len(fits)
        assert float(r["score"]) == pytest.approx(expect, rel=1e-12)
        assert metrics["passes"] == 2
    assert (out / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    best = max(rows, key=lambda r: float(r["score"]))
    best_cfg = Config.load(out / "best.toml")
    assert best_cfg.estimator.p0_theta == pytest.approx(float(best["estimator.p0_theta"]))
    assert best_cfg.model.size == int(best["model.size"])
    assert (best_cfg.estimator.passes, best_cfg.data.stop) == (2, 2000)

    # best.toml trains as it is, from another working directory
    runs = tmp_path / "again"
    assert main(["train", str(out / "best.toml"), "--out", str(runs), "--quiet"]) == 0
    again = json.loads((runs / "metrics.json").read_text())
    first = json.loads((out / "trials" / f"{int(best['number']):04d}" / "metrics.json").read_text())
    for name, fit in first["validation"].items():
        assert again["validation"][name] == pytest.approx(fit, rel=1e-9)

    # the same command again continues the study to 3 trials in all, without repeating one
    capsys.readouterr()
    assert main([*argv[:5], "3", *argv[6:]]) == 0
    rows = _rows(out)
    assert [r["number"] for r in rows] == ["0", "1", "2"]
    values = {(r["estimator.p0_theta"], r["model.size"]) for r in rows}
    assert len(values) == 3
    assert "this run finished 1" in capsys.readouterr().out
    study = optuna.load_study(study_name="short", storage=f"sqlite:///{out / 'study.db'}")
    assert len(study.trials) == 3


def test_pruned_trials_stop_early_and_are_recorded(tmp_path):
    cfg = rig_config(tmp_path)
    space = _space(tmp_path, '"estimator.p0_theta" = { low = 0.5, high = 2.0 }\n')
    out = tmp_path / "sweep"
    # a validation FIT never reaches 200 %: the threshold pruner stops every trial at its first
    # report, after pass 1 of 3
    result = run_sweep(
        cfg, space, 2, out=out, sets=["estimator.passes=3", *FAST[1:]],
        pruner=optuna.pruners.ThresholdPruner(lower=200.0), say=lambda msg: None,
    )  # fmt: skip
    assert [r["state"] for r in result.rows] == ["PRUNED", "PRUNED"]
    assert result.best is None and not (out / "best.toml").exists()
    for r in _rows(out):
        assert (r["state"], r["pruned_at"]) == ("PRUNED", "1")
        metrics = json.loads((pathlib.Path(r["run_dir"]) / "metrics.json").read_text())
        assert metrics["passes"] == 1  # the run stopped after the pruned pass
        # a pruned trial's score is what it reported: the validation score of its pass 1
        ckpt = read_checkpoint(pathlib.Path(r["run_dir"]) / "short.pt")
        (record,) = ckpt["estimator"]["state"]["history"]
        assert float(r["score"]) == pytest.approx(record["val_score"], rel=1e-12)
        # ... which is the run's final validation FIT unless the prediction-error polish moved
        # the kept θ (then the final model's own FIT is reported)
        if "polished" not in metrics:
            fits = list(metrics["validation"].values())
            assert float(r["score"]) == pytest.approx(
                sum(0.5 * (f["fit_q"] + f["fit_qdot"]) for f in fits) / len(fits), rel=1e-12
            )
        else:  # the reported score is that of the filter's θ, kept beside the polished one
            assert ckpt["estimator"]["state"]["filter_theta"].tolist() == record["theta"]


def test_a_failing_trial_is_recorded_and_the_sweep_goes_on(tmp_path):
    cfg = rig_config(tmp_path)
    # data.start beyond data.stop makes an invalid config for one of the choices
    space = _space(tmp_path, '"data.start" = { choices = [0, 1500] }\n')
    out = tmp_path / "sweep"
    sets = ["estimator.passes=1", "estimator.ensemble=0", "data.stop=1000"]
    with pytest.raises(TorchfricError, match=r"data\.start.*1500.*not a valid value"):
        run_sweep(cfg, space, 2, out=out, sets=sets, say=lambda msg: None)
    assert not out.exists()  # refused before anything was written
    # a config valid alone whose run fails: a filter that diverges at once
    space = _space(tmp_path, '"estimator.theta_bound" = { choices = [1e-9, 1e6] }\n')
    result = run_sweep(cfg, space, 4, out=out, sets=sets, say=lambda msg: None)
    states = {r["values"]["estimator.theta_bound"]: r["state"] for r in result.rows}
    assert states == {1e-9: "FAIL", 1e6: "COMPLETE"}
    failed = [r for r in _rows(out) if r["state"] == "FAIL"]
    assert failed and all(r["error"] and not r["score"] for r in failed)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            '"estimator.pases" = { low = 1, high = 3, int = true }\n',
            'did you mean "estimator.passes"',
        ),
        ('"estimator.passes" = { low = 1, high = 3 }\n', "takes an integer; add int = true"),
        ('"estimator.p0_theta" = { low = 1, high = 3, int = true }\n', "takes a float"),
        ('"model.friction" = { low = 1, high = 3 }\n', "not a number.*choices"),
        ('"estimator.p0_theta" = { low = 3.0, high = 1.0 }\n', "must be below high"),
        ('"estimator.p0_theta" = { low = 0.0, high = 1.0, log = true }\n', "needs low > 0"),
        ('"estimator.p0_theta" = { low = "a", high = 1.0 }\n', "must be a finite number"),
        ('"estimator.p0_theta" = { low = -1.0, high = 1.0 }\n', "not a valid value"),
        ('"estimator.passes" = { low = 1, high = 100000, int = true }\n', "not a valid value"),
        ('"model.size" = { choices = [] }\n', "non-empty list"),
        ('"model.size" = { choices = [2, 2] }\n', "repeats a value"),
        ('"model.size" = { choices = [2], low = 1 }\n', "either choices or a range"),
        ('"estimator.p0_theta" = { low = 0.1, high = 1.0, lg = true }\n', 'unknown field "lg"'),
        ('"name" = { choices = ["a", "b"] }\n', "name cannot be swept"),
        ('"estimator.p0_theta" = 3.0\n', "must be a table"),
    ],
)
def test_bad_spaces_are_refused_in_one_line(tmp_path, text, message):
    cfg = Config.load(rig_config(tmp_path))
    with pytest.raises(TorchfricError, match=message) as err:
        read_space(_space(tmp_path, text), cfg)
    assert "\n" not in str(err.value)


def test_bad_space_files_and_folders_write_nothing(tmp_path, capsys):
    cfg = rig_config(tmp_path)
    out = tmp_path / "sweep"
    empty = tmp_path / "empty.toml"
    empty.write_text('x = 1\n[space]\n"model.size" = { choices = [2] }\n', encoding="utf-8")
    for space, message in ((tmp_path / "nope.toml", "no such file"), (empty, "beside it")):
        argv = ["sweep", str(cfg), "--space", str(space), "--trials", "2", "--out", str(out)]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 2  # a blank line, then one error line
    assert not out.exists()
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    space = _space(tmp_path, '"model.size" = { choices = [2] }\n')
    with pytest.raises(TorchfricError, match="not a torchfric sweep"):
        run_sweep(cfg, space, 1, out=foreign, say=lambda msg: None)
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]


def test_shares_split_the_trials_over_the_workers():
    assert shares(5, 2) == [3, 2]
    assert shares(1, 4) == [1]
    assert sum(shares(17, 3)) == 17


@pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason='Ray is not installed: pip install -e ".[ray]" (the test extra includes it)',
)
def test_ray_backend_runs_two_trials_on_a_local_ray(tmp_path):
    cfg = rig_config(tmp_path)
    space = _space(tmp_path, '"estimator.p0_theta" = { low = 0.1, high = 10.0, log = true }\n')
    out = tmp_path / "sweep"
    result = run_sweep(
        cfg, space, 2, out=out, jobs=2, backend="ray", sets=FAST, say=lambda msg: None
    )
    assert [r["state"] for r in result.rows] == ["COMPLETE", "COMPLETE"]
    for r in _rows(out):
        metrics = json.loads((pathlib.Path(r["run_dir"]) / "metrics.json").read_text())
        fits = list(metrics["validation"].values())
        assert float(r["score"]) == pytest.approx(
            sum(0.5 * (f["fit_q"] + f["fit_qdot"]) for f in fits) / len(fits), rel=1e-12
        )
    assert Config.load(out / "best.toml").estimator.passes == 2
