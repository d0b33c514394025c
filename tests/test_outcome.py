"""What a run hands the user: the kept pass, parameters ± σ, the summary, `torchfric.fit` and
the progress bars. Checked against independent computations and the run's own records."""

from __future__ import annotations

import io
import json
import math
import pathlib

import pytest
import torch
from rig_configs import rig_config

import torchfric
from torchfric.app.artifacts.checkpoint import read_checkpoint
from torchfric.app.cli import main
from torchfric.app.config import Config
from torchfric.app.run.inputs import load_data
from torchfric.app.run.launch import fit, override_strings
from torchfric.app.run.outcome import keep_best, parameter_table, summary_lines
from torchfric.errors import TorchfricError
from torchfric.estimators.metrics import score_simulation
from torchfric.estimators.passes import EKFResult, PassRecord
from torchfric.estimators.uncertainty import parameter_std
from torchfric.models.arm import ArmModel
from torchfric.models.friction import OddTanhFriction

SHORT = {"data.stop": 1500, "data.test": [], "estimator.passes": 3, "estimator.tolerance": 0}


def _model() -> ArmModel:
    torch.manual_seed(0)
    return ArmModel(friction=OddTanhFriction(2), inertia=0.03, viscous=0.01, c_m=16.0)


def _record(model: ArmModel, index: int, shift: float, **kw: object) -> PassRecord:
    theta = model.get_theta() + shift
    k = theta.numel()
    return PassRecord(
        index=index, theta=theta.tolist(), parameters={}, trace_P=0.0, trace_P_theta=0.0,
        innovation_rms=[0.0], nis=1.0, loglik=kw.pop("loglik", 0.0), rel_change=0.1, seconds=0.0,
        samples=10, P_theta=(torch.eye(k) * (index + 1) * 1e-4).tolist(), **kw,
    )  # fmt: skip


def _result(model: ArmModel, history: list[PassRecord]) -> EKFResult:
    last = history[-1]
    theta = torch.tensor(last.theta)
    fitted = type(model)(friction=OddTanhFriction(2), inertia=0.03, viscous=0.01, c_m=16.0)
    fitted.set_theta(theta)
    return EKFResult(fitted, theta, torch.tensor(last.P_theta), history, converged=False)


def test_keep_best_takes_the_best_validated_pass_with_its_own_covariance() -> None:
    model = _model()
    hist = [
        _record(model, 1, 0.01, val_score=80.0),
        _record(model, 2, 0.02, val_score=91.2),
        _record(model, 3, 0.03, val_score=85.6),
    ]
    kept, best = keep_best(_result(model, hist), validating=True)
    assert best == 2
    torch.testing.assert_close(kept.theta, torch.tensor(hist[1].theta), rtol=0, atol=0)
    torch.testing.assert_close(kept.P_theta, torch.tensor(hist[1].P_theta), rtol=0, atol=0)
    torch.testing.assert_close(kept.model.get_theta(), kept.theta, rtol=0, atol=0)
    assert kept.history is hist and kept.passes == 3  # the run's history is kept whole


def test_keep_best_skips_rolled_back_passes_and_breaks_ties_to_the_later() -> None:
    model = _model()
    hist = [
        _record(model, 1, 0.01, val_score=90.0),
        _record(model, 2, 0.02, val_score=90.0),
        _record(model, 3, 0.03, val_score=99.0, rolled_back=True),
    ]
    result = _result(model, hist[:2])
    result.history = hist
    assert keep_best(result, validating=True)[1] == 2


def test_without_validation_the_likelihood_decides() -> None:
    model = _model()
    hist = [_record(model, 1, 0.01, loglik=-5.0), _record(model, 2, 0.02, loglik=-7.0)]
    assert keep_best(_result(model, hist), validating=False)[1] == 1
    # the last pass, when it is the best, is returned as is
    result = _result(model, hist[:1])
    assert keep_best(result, validating=False) == (result, 1)


def test_parameter_std_equals_the_delta_method_through_to_physical() -> None:
    model = _model()
    k = model.num_parameters
    A = torch.randn(k, k, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    P = 1e-3 * (A @ A.T + torch.eye(k))
    theta = model.get_theta()
    J = torch.func.jacrev(model.to_physical)(theta)  # (k, k): independent of parameter_std
    expected = torch.sqrt(torch.diagonal(J @ P @ J.T))
    got = parameter_std(model, P)
    assert list(got) == model.theta_names
    torch.testing.assert_close(torch.tensor(list(got.values())), expected, rtol=1e-12, atol=0)
    table = parameter_table(model, P)
    assert table["inertia"]["value"] == pytest.approx(0.03, rel=1e-12)
    assert table["inertia"]["std"] == pytest.approx(0.03 * math.sqrt(float(P[-1, -1])), rel=1e-12)
    assert all(v["std"] is None for v in parameter_table(model, None).values())


def test_override_strings_accept_sections_dotted_keys_and_top_level_keys() -> None:
    sets = override_strings(
        {"estimator": {"passes": 3, "r": [0.001, 0.01]}, "data.stop": 100, "name": "trial"}
    )
    assert sets == [
        "estimator.passes=3",
        "estimator.r=[0.001, 0.01]",
        "data.stop=100",
        'name="trial"',
    ]


def _config(tmp: pathlib.Path) -> pathlib.Path:
    return rig_config(tmp)


def test_fit_runs_the_cli_train_and_keeps_the_best_validated_pass(tmp_path: pathlib.Path) -> None:
    before = torch.get_default_dtype()
    result = fit(_config(tmp_path), quiet=True, **SHORT)
    assert torch.get_default_dtype() == before  # the float64 default does not leak out
    assert result.run_dir == tmp_path / "runs" / "short"
    m = json.loads((result.run_dir / "metrics.json").read_text())
    assert m == json.loads(json.dumps(result.metrics))
    # every pass that was not rolled back was scored on the validation record; the kept one
    # scores highest (a rolled-back pass is undone: never scored, never kept)
    ckpt = read_checkpoint(result.checkpoint)
    state = ckpt["estimator"]["state"]
    hist = state["history"]
    assert all((h["val_score"] is None) == h["rolled_back"] for h in hist)
    scores = [h["val_score"] if not h["rolled_back"] else -math.inf for h in hist]
    assert m["best_pass"] == 1 + max(range(len(scores)), key=lambda i: (scores[i], i))
    kept = torch.tensor(hist[m["best_pass"] - 1]["theta"], dtype=torch.float64)
    fit_v = m["validation"]["validation"]
    # The final model is the kept pass's θ, polished by prediction-error steps when metrics
    # say so (the filter's θ stays as filter_theta); its validation FIT is its own.
    torch.testing.assert_close(result.model.get_theta(), ckpt["theta"], rtol=0, atol=0)
    if "polished" in m:
        torch.testing.assert_close(state["filter_theta"], kept, rtol=0, atol=0)
        assert m["polished"]["steps"] >= 1 and m["polished"]["loglik_gain"] > 0
        cfg = Config.load(result.run_dir / "config.toml")
        (val,) = load_data(cfg)[1]
        ref = score_simulation(result.model, val)
        assert fit_v["fit_q"] == pytest.approx(ref.fit_q, abs=1e-6)
        assert fit_v["fit_qdot"] == pytest.approx(ref.fit_qdot, abs=1e-6)
    else:
        torch.testing.assert_close(result.model.get_theta(), kept, rtol=0, atol=0)
        assert 0.5 * (fit_v["fit_q"] + fit_v["fit_qdot"]) == pytest.approx(max(scores), abs=1e-9)
    # tolerance 0: only a rolled-back pass ends the passes as converged
    if hist[-1]["rolled_back"]:
        assert m["converged"] is True and m["stopped"] == "rolled_back"
    else:
        assert m["converged"] is False and m["stopped"] == "budget"
    # parameters ± σ from the run's covariance at the final θ (the prediction-error sandwich);
    # the filter's own P_θθ of the kept pass stays beside it
    torch.testing.assert_close(
        state["filter_P_theta"],
        torch.tensor(hist[m["best_pass"] - 1]["P_theta"], dtype=torch.float64),
        rtol=0,
        atol=0,
    )
    assert m["covariance"]["method"] == "sandwich"
    expected = parameter_std(result.model, torch.as_tensor(state["P_theta"], dtype=torch.float64))
    for name, entry in m["parameters"].items():
        if expected[name] == 0.0:  # no information (a pseudo-inverse direction): no σ, named
            assert entry["std"] is None
            assert any(name in line for line in m["identifiability"]["messages"]), name
        else:
            assert entry["std"] == pytest.approx(expected[name], rel=1e-12) and entry["std"] > 0
    assert m["inertia"] == m["parameters"]["inertia"]["value"]
    # a second fit never overwrites the first run
    again = fit(str(_config(tmp_path)), quiet=True, estimator={"passes": 1}, data={"stop": 1500})
    assert again.run_dir == tmp_path / "runs" / "short-2"


def test_fit_refuses_what_is_not_a_config() -> None:
    with pytest.raises(TorchfricError, match="config file path or a torchfric.Config"):
        fit(42)  # type: ignore[arg-type]
    assert torchfric.fit is fit


def test_train_prints_a_summary_and_json_has_sigma_best_pass_and_files(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = _config(tmp_path)
    sets = [a for k, v in SHORT.items() for a in ("--set", f"{k}={json.dumps(v)}")]
    assert main(["train", str(cfg), "--quiet", *sets]) == 0
    out, err = capsys.readouterr()
    assert err == ""  # --quiet: no progress
    m = json.loads((tmp_path / "runs" / "short" / "metrics.json").read_text())
    assert f"kept pass {m['best_pass']} of 3 (best validation FIT)" in out
    state = read_checkpoint(tmp_path / "runs" / "short" / "short.pt")["estimator"]["state"]
    hist = state["history"]
    # tolerance 0: not converged after all 3 passes, unless the last was rolled back
    undone = hist[-1]["rolled_back"]
    if undone:
        assert (
            "converged in 3 passes: the last lowered the innovation likelihood and was undone, "
            "so the pass before is the filter's best fit of the data"
        ) in out
    else:
        gain = f"{hist[-1]['loglik'] - hist[-2]['loglik']:.2g}"
        assert (
            f"NOT converged: the last of all 3 passes still raised the innovation log-likelihood "
            f"by {gain} nats (estimator.tolerance 0 × {len(m['parameters'])} parameters = 0 "
            "nats); raise estimator.passes"
        ) in out
    inertia = m["parameters"]["inertia"]
    assert f"inertia  {inertia['value']:.6g} ± {inertia['std']:.2g}" in out
    assert "validation FIT (validation): q" in out and "report" in out
    assert main(["train", str(cfg), "--json", "--quiet", *sets]) == 0
    js = json.loads(capsys.readouterr().out)
    m2 = json.loads((tmp_path / "runs" / "short-2" / "metrics.json").read_text())
    assert js["best_pass"] == m2["best_pass"] and js["parameters"] == m2["parameters"]
    assert set(js["parameters"]["inertia"]) == {"value", "std"}
    assert js["converged"] is undone and js["run_dir"].endswith("short-2")
    assert pathlib.Path(js["files"]["metrics"]).is_file()
    # evaluate shows the same σ from the checkpoint
    assert main(["evaluate", js["checkpoint"], "rig:validation", "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["parameters"] == js["parameters"]


def test_progress_bars_show_passes_with_rate(tmp_path: pathlib.Path) -> None:
    from torchfric.app.config import Config
    from torchfric.app.run import train

    cfg = Config.load(_config(tmp_path), [f"{k}={json.dumps(v)}" for k, v in SHORT.items()])
    stream, lines = io.StringIO(), []
    train(cfg, say=lines.append, bars=stream)
    text = stream.getvalue()
    assert "passes" in text and ("pass/s" in text or "s/pass" in text)
    assert "3/3" in text  # the bar reached the last pass
    assert sum("done in" in line for line in lines) == 3 + 1  # one line per pass, one at the end


def test_summary_lines_say_why_the_run_stopped() -> None:
    base = {"name": "x", "estimator": "ekf", "seconds": 1.0, "passes": 4, "best_pass": 4,
            "parameters": {"inertia": {"value": 0.03, "std": None}}, "validation": {}}  # fmt: skip
    files = {"checkpoint": "x.pt"}
    assert any(
        line.startswith("converged")
        for line in summary_lines({**base, "stopped": "converged"}, files)
    )
    text = "\n".join(summary_lines({**base, "stopped": "budget"}, files))
    assert "NOT converged" in text and "all 4 passes" in text and "highest likelihood" in text
    assert "inertia  0.03\n" in text + "\n"  # no σ: no "±"
    # no σ at all: an EKF run whose data determined nothing says so, output error says its own
    assert "no σ: the data determined none of them" in text
    oe_text = "\n".join(summary_lines({**base, "estimator": "output_error"}, files))
    assert "no σ: output error keeps no parameter covariance" in oe_text
    oe = {**base, "epochs": 5, "stopped": "early"}
    oe.pop("passes")
    assert "kept epoch 4 of 5" in "\n".join(summary_lines(oe, files))
    # an output-error run whose epochs ran out: still improving, or best long before the end
    oe = {**oe, "stopped": "budget"}
    assert "still improving at the last of the 5 epochs" in "\n".join(
        summary_lines({**oe, "best_pass": 5}, files)
    )
    assert "none validated better than epoch 0" in "\n".join(
        summary_lines({**oe, "best_pass": 0}, files)
    )
    # an ensemble's passes are its kept member's: the others may have run to the limit
    ens = {**base, "ensemble": {"members": 9, "status": {"converged": 1, "running": 8}, "best": 3,
                                "best_q_scale": 10.0, "best_r_scale": 1.0,
                                "selected_by": "validation_and_train_fit"}}  # fmt: skip
    lines = summary_lines({**ens, "stopped": "converged"}, files)
    assert "1 converged, 8 ran every pass" in lines[1]
    assert any(line.startswith("the kept member converged in 4 passes") for line in lines)
    assert any(line.startswith("NOT converged (the kept member): the last of all 4 passes")
               for line in summary_lines({**ens, "stopped": "budget"}, files))  # fmt: skip


def test_warnings_name_what_the_data_left_at_its_prior_and_a_missing_offset(
    tmp_path: pathlib.Path,
) -> None:
    from torchfric.app.config import Config
    from torchfric.app.run.assessment import result_warnings

    cfg = Config.load(rig_config(tmp_path))
    model = _model()
    P0 = cfg.estimator.ekf_tuning().initial_P_theta(model, model.get_theta())
    metrics = {"inertia": 0.03, "initial_inertia": 0.03, "validation": {}}
    # the prior itself: every parameter uninformed; half its variance: none
    text = " ".join(result_warnings(cfg, model, metrics, "prefit", covariance=P0, start=model))
    assert "hardly informed" in text and all(n in text for n in model.theta_names)
    P = P0.clone()
    P[0, 0] *= 0.5  # σ at 71 % of the prior: informed
    text = " ".join(result_warnings(cfg, model, metrics, "prefit", covariance=P, start=model))
    assert model.theta_names[0] not in text.split("informed")[-1].split(":")[0]
    assert "hardly informed" in text  # the others still are not
    assert "so the ± shows the prior" in text  # no covariance of the run: the ± are P_θθ's
    # with the run's covariance the ± are the data's; an entry held at its bound is left out
    held = model.theta_names[1]
    ran = {**metrics, "covariance": {"method": "sandwich"},
           "identifiability": {"held_at_bound": [held]}}  # fmt: skip
    text = " ".join(result_warnings(cfg, model, ran, "prefit", covariance=P0, start=model))
    listed = text.split("hardly informed ")[1].split(":")[0].split(", ")
    assert held not in listed and set(listed) == set(model.theta_names) - {held}
    assert "the ± shown are the data's" in text and "shows the prior" not in text
    half = 0.5 * P0
    assert not any(
        "informed" in w
        for w in result_warnings(cfg, model, metrics, "prefit", covariance=half, start=model)
    )
    # a record simulated worse than a constant: the offset hint only when there is no offset
    bad = {**metrics, "validation": {"v": {"fit_q": -93.0, "fit_qdot": 10.0}}}
    assert "model.offset=0.0" in " ".join(result_warnings(cfg, model, bad, "prefit"))
    assert "the speeds (FIT on q̇ 10.0 %) too" in " ".join(result_warnings(cfg, model, bad, "prefit"))
    with_offset = Config.load(rig_config(tmp_path, "off", model={"offset": 0.0}))
    assert "model.offset" not in " ".join(result_warnings(with_offset, model, bad, "prefit"))
    # an inertia 50 % from the pre-fit's and 15 σ from it: two estimates the σ do not hold
    def apart(value: float, std: float, init: str = "prefit") -> list[str]:
        m = {**metrics, "inertia": value, "parameters": {"inertia": {"value": value, "std": std}}}
        return [w for w in result_warnings(cfg, model, m, init) if "from the pre-fit's" in w]

    (far,) = apart(0.045, 0.001)
    assert "inertia 0.045 ± 0.001 is +50% from the pre-fit's 0.03 (+15 σ)" in far
    assert apart(0.045, 0.01) == []  # within 2 σ of it
    assert apart(0.033, 1e-6) == []  # 10 %: within what a pre-fit's own bias is
    assert apart(0.02, 1e-6) != [] and apart(0.045, 0.001, "initial value") == []


def test_a_data_file_given_as_the_config_says_so(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "axis.csv"
    data.write_text("t,u,q\n0,0,0\n0.001,0,0\n")
    assert main(["train", str(data)]) == 2
    err = capsys.readouterr().err
    assert "is a data file, not a config" in err and f"torchfric init {data}" in err
    assert err.count("\n") <= 2 and "Traceback" not in err


def test_an_ensembles_summary_says_which_member_and_what_became_of_the_others() -> None:
    metrics = {"name": "x", "estimator": "ekf", "seconds": 1.0, "passes": 2, "best_pass": 1,
               "stopped": "budget", "validation": {},
               "parameters": {"inertia": {"value": 0.03, "std": 1e-5}},
               "ensemble": {"members": 9, "status": {"running": 3, "diverged": 6}, "best": 4,
                            "best_q_scale": 10.0, "best_r_scale": 0.1,
                            "selected_by": "train_fit"}}  # fmt: skip
    text = "\n".join(summary_lines(metrics, {"checkpoint": "x.pt"}))
    assert "ensemble of 9 filters (3 ran every pass, 6 diverged); kept member 4" in text
    assert "(Q ×10, R ×0.1) by train fit, after its 2 passes" in text


def test_without_validation_the_identification_records_are_scored_and_said_to_flatter(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = rig_config(tmp_path, data={"validation": [], "test": [], "stop": 1500},
                     estimator={"passes": 2, "tolerance": 0})  # fmt: skip
    assert main(["train", str(cfg), "--quiet"]) == 0
    out = capsys.readouterr().out
    m = json.loads((tmp_path / "runs" / "short" / "metrics.json").read_text())
    assert m["validation"] == {} and set(m["identification"]) == {"identification"}
    fit_q = m["identification"]["identification"]["fit_q"]
    assert f"identification FIT (identification): q {fit_q:.2f} %" in out
    assert "highest likelihood" in out and "flatters the model" in out
    page = (tmp_path / "runs" / "short" / "report.html").read_text(encoding="utf-8")
    assert "flatters the model" in page and f"{fit_q:.2f}" in page


def test_an_unconverged_run_on_a_noisy_velocity_names_a_quieter_cutoff(tmp_path: pathlib.Path) -> None:
    """`velocity_noise` is the reconstructed velocity's error from the position's own steps
    (against the simulator's true q̇, within 10 %); the not-converged warning adds a cut-off
    where that noise exceeds 2 % of v95 (a heavy axis with a 4096-count encoder: 3.1 % at 200
    Hz, which did not converge in 100 passes and did in 3 at 50 Hz), and nothing on the rig."""
    import math

    from torchfric.app.config import Config
    from torchfric.app.run.assessment import result_warnings
    from torchfric.data import make_experiment, reconstruct_velocity
    from torchfric.data.axis import AxisParameters, axis_record
    from torchfric.data.rig import rig_experiment
    from torchfric.data.velocity import velocity_noise

    heavy = AxisParameters(inertia=0.5, c_m=3.0, viscous=0.3, coulomb=1.2, static=1.8,
                           stribeck_velocity=0.8, quantum=2 * math.pi / 4096, max_speed=15.0,
                           max_input=3.0)  # fmt: skip
    rec = axis_record(heavy, seed=1, duration=20.0, kind="identification")
    q = torch.as_tensor(rec["q"])
    error = (reconstruct_velocity(q, 1e-3) - torch.as_tensor(rec["qdot_true"]))[100:]
    assert velocity_noise(q, 1e-3, "highpass") == pytest.approx(float(error.std()), rel=0.1)
    cfg = Config.load(rig_config(tmp_path))
    model = _model()
    stuck = {"inertia": 0.5, "initial_inertia": 0.5, "validation": {}, "converged": False,
             "passes": cfg.estimator.passes, "last_gain": 5.5}  # fmt: skip
    exp = make_experiment(*(torch.as_tensor(rec[k]) for k in ("t", "u", "q")), name="h")
    text = " ".join(result_warnings(cfg, model, stuck, "prefit", train=[exp.with_velocity()]))
    assert "stopped at the pass limit" in text and "data.velocity_cutoff_hz = " in text
    suggested = float(text.split("data.velocity_cutoff_hz = ")[1].split()[0])
    assert 30.0 < suggested < 120.0
    r = rig_experiment("identification")
    rig = make_experiment(*(torch.as_tensor(r[k]) for k in ("t", "u", "q")), name="r")
    text = " ".join(result_warnings(cfg, model, stuck, "prefit", train=[rig.with_velocity()]))
    assert "stopped at the pass limit" in text and "velocity_cutoff_hz" not in text
