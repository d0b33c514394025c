"""``model.dynamic = "auto"``: static or LuGre friction chosen from the identification data alone
(`torchfric.estimators.sizing.compare_dynamics`, `torchfric.app.run.autosize`).

Two seeded 10-s records of machines whose class is known:

- static: a tanh(2) arm (the static class itself: M 0.0292, b 0.01, c_m 16) simulated by
  `torchfric.models.simulate` under the rig's identification excitation, positions quantised to
  the rig's encoder; measured (single filters): static's held-out windows 6.5e-4 rad RMS,
  LuGre's 1.5e-3, t = −3.4 → static;
- LuGre: the first 10 s of the synthetic rig's identification record (`torchfric.data.rig`: LuGre
  bristles around a Stribeck curve); static 5.2e-3 rad, LuGre 1.3e-3, t = +5.3 → LuGre.

Both models start from the pre-fit of the first 70 % and run one filter each (the run's default
ensemble gives the same choices: t = −4.1 and +5.2). The same rig read through an encoder 8×
coarser than its own: the windows still prefer LuGre (t = +4.3), but its bristles travel less
than a count through a reversal, so the static model is kept.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib

import pytest
import torch

from torchfric.app.commands.check import check_run
from torchfric.app.commands.init import write_starter
from torchfric.app.config import Config
from torchfric.app.run import train
from torchfric.app.run.autosize import choose_dynamic, dynamic_lines
from torchfric.app.run.outcome import summary_lines
from torchfric.data.experiment import Experiment, make_experiment
from torchfric.data.readers import save_csv
from torchfric.data.rig import RigParameters, excitation, rig_experiment
from torchfric.errors import TorchfricError
from torchfric.estimators.ekf import EKFState, FilterFailure, make_propagator, make_step, run_pass
from torchfric.estimators.passes import initial_belief, measurements, prepared
from torchfric.estimators.prefit import prefit
from torchfric.estimators.selection import filtered_states, window_errors
from torchfric.estimators.settings import EKFTuning
from torchfric.estimators.sizing import HOLDOUT, compare_dynamics, held_out_heads
from torchfric.models.arm import ArmModel
from torchfric.models.friction import OddTanhFriction
from torchfric.models.simulate import simulate

N_SAMPLES = 10_000


def _true_static() -> ArmModel:
    return ArmModel(
        OddTanhFriction(2, w1=[0.5, 5.0], w2=[0.1, 0.15]), inertia=0.0292, viscous=0.01, c_m=16.0
    )


def _static_record(quantised: bool = True) -> Experiment:
    rig = RigParameters()
    u = torch.as_tensor(excitation("identification", duration=30.0, seed=2)[:N_SAMPLES])
    t = torch.arange(N_SAMPLES, dtype=torch.float64) * rig.dt
    with torch.no_grad():
        x = simulate(_true_static(), t, u, torch.zeros(2), engine="compiled")
    if not quantised:  # exact q and q̇
        return make_experiment(t, u, x[:, 0], x[:, 1], name="exact")
    q = torch.round(x[:, 0] / rig.quantum) * rig.quantum
    return make_experiment(t, u, q, name="static").with_velocity()


@pytest.fixture(scope="module")
def static_record() -> Experiment:
    return _static_record()


@pytest.fixture(scope="module")
def lugre_record() -> Experiment:
    a = rig_experiment("identification", seed=0)
    n = N_SAMPLES
    return make_experiment(a["t"][:n], a["u"][:n], a["q"][:n], name="rig").with_velocity()


def _starts(exp: Experiment) -> tuple[ArmModel, ArmModel]:
    """The static and the LuGre start, both from the pre-fit of the head alone."""
    heads = held_out_heads([exp])
    v = float(torch.quantile(heads[0].qdot.abs(), 0.95))

    def friction() -> OddTanhFriction:
        return OddTanhFriction(3, velocity_scale=v, torque_scale=0.1)

    static = prefit(ArmModel(friction(), inertia=0.03, viscous=0.01, c_m=16.0), heads).model
    lugre = ArmModel(friction(), inertia=0.03, viscous=0.01, c_m=16.0, dynamic="lugre",
                     sigma0=1000.0, sigma1=2 * math.sqrt(30.0), stick_velocity=0.01 * v)  # fmt: skip
    return static, lugre.with_static(static)


def test_auto_keeps_the_static_model_on_static_data(static_record: Experiment) -> None:
    static, lugre = _starts(static_record)
    r = compare_dynamics(static, lugre, [static_record], EKFTuning())
    assert r.chosen == "none"
    assert r.rmse["none"] < r.rmse["lugre"] and r.t < -2.0
    assert r.windows == 59  # 3000 held-out samples, windows of 50 samples
    assert set(r.thetas) == {"none", "lugre"}


def test_auto_keeps_lugre_on_lugre_data(lugre_record: Experiment) -> None:
    static, lugre = _starts(lugre_record)
    r = compare_dynamics(static, lugre, [lugre_record], EKFTuning())
    assert r.chosen == "lugre"
    assert r.rmse["lugre"] < 0.5 * r.rmse["none"] and r.t > 2.0
    d = r.to_dict()
    assert d["criterion"] == "windowed_prediction" and d["t_min"] == 2.0
    assert [row["dynamic"] for row in d["table"]] == ["none", "lugre"]
    assert [row["chosen"] for row in d["table"]] == [False, True]
    # the rig's bristles travel 2 Fs/σ0 = 2 counts through a reversal: seen by its encoder
    assert d["position_step"] == pytest.approx(RigParameters().quantum, rel=1e-9)
    assert 1.0 < d["bristle_travel"] / d["position_step"] < 3.0
    # and the rig stuck on them settles over about three samples (0.31 of the sample rate)
    assert d["sample_time"] == RigParameters().dt
    assert 0.1 < d["stick_rate"] * d["sample_time"] < d["stick_rate_limit"] == 1.0


def test_bristles_over_within_a_sample_leave_the_static_model(
    lugre_record: Experiment, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The rule in time, wired into the choice: with the limit below the rig's own rate (as if
    it were sampled 4× slower than its bristles need) the same comparison keeps static, and
    the summary says what LuGre's better windows may mean."""
    import torchfric.models.lugre as lugre_module

    monkeypatch.setattr(lugre_module, "STICK_RATE_LIMIT", 0.1)
    static, lugre = _starts(lugre_record)
    d = compare_dynamics(static, lugre, [lugre_record], EKFTuning()).to_dict()
    assert d["t"] > 2.0 and 1.0 < d["bristle_travel"] / d["position_step"]  # seen in space
    assert d["chosen"] == "none"
    summary = " ".join(dynamic_lines(d))
    assert "over within a sample, σ0 → ∞ in time (static)" in summary
    assert "settle within a sample: if the machine may be dynamic, record it faster" in summary


def test_the_stick_rate_is_the_fast_root_of_the_stuck_axis() -> None:
    """`stick_rate` against numpy's roots of ``M s² + (σ1 + b) s + σ0`` (under- and
    overdamped), and `bristles_timed` at its limit."""
    import numpy as np

    from torchfric.models.lugre import STICK_RATE_LIMIT, bristles_timed, stick_rate

    for m, s0, s1, b in [(0.03, 1343.0, 12.0, 0.01), (18.0, 7.5e7, 8.3e4, 120.0),
                         (6.0, 2.4e5, 1920.0, 40.0), (1.0, 100.0, 20.0, 0.0)]:  # fmt: skip
        arm = {k: torch.tensor(v, dtype=torch.float64) for k, v in
               [("inertia", m), ("lugre_sigma0", s0), ("lugre_sigma1", s1), ("viscous", b)]}  # fmt: skip
        fastest = max(abs(r) for r in np.roots([m, s1 + b, s0]))
        assert stick_rate(arm) == pytest.approx(fastest, rel=1e-9)
    no_b = {"inertia": torch.tensor(1.0), "lugre_sigma0": torch.tensor(4.0),
            "lugre_sigma1": torch.tensor(1.0)}  # fmt: skip
    assert stick_rate(no_b) == pytest.approx(2.0, rel=1e-12)  # complex roots: √(σ0/M)
    assert bristles_timed(STICK_RATE_LIMIT / 1e-3, 1e-3)
    assert not bristles_timed(1.01 * STICK_RATE_LIMIT / 1e-3, 1e-3)
    assert not bristles_timed(math.nan, 1e-3)


def test_bristles_finer_than_the_encoder_leave_the_static_model(lugre_record: Experiment) -> None:
    """The same LuGre rig read by an encoder 8× coarser (1.6e-3 rad a count): its bristles
    travel 0.25 of a count through a reversal, so the record cannot tell σ0 from σ0 → ∞ and the
    static model is kept, whatever the windows say."""
    coarse_q = torch.round(lugre_record.q / 1.6e-3) * 1.6e-3
    coarse = make_experiment(lugre_record.t, lugre_record.u, coarse_q, name="coarse")
    coarse = coarse.with_velocity()
    static, lugre = _starts(coarse)
    d = compare_dynamics(static, lugre, [coarse], EKFTuning()).to_dict()
    assert d["position_step"] == pytest.approx(1.6e-3, rel=1e-9)
    assert d["bristle_travel"] < d["position_step"]
    assert d["chosen"] == "none"
    summary = " ".join(dynamic_lines(d))
    assert "position steps" in summary and "cannot tell σ0 from ∞ (static)" in summary


def test_a_close_call_with_visible_bristles_suggests_trying_lugre() -> None:
    """The summary's hint where the windows prefer LuGre by less than 2 σ and its bristles
    travel more than a step (the LuGre spindle of results.md: t +0.9, 3 steps); none where the
    bristles are finer than a step or LuGre's windows are worse."""
    row = {"dynamic": "none", "parameters": 8, "rmse_q": 1e-3, "bic": -1.0, "chosen": True}
    base = {"chosen": "none", "windows": 179, "window_seconds": 0.05, "holdout": 0.3,
            "seconds": 1.0, "t_min": 2.0, "table": [row], "position_step": 1e-3}  # fmt: skip

    def hint(**kw: float) -> bool:
        return any('model.dynamic = "lugre"' in line for line in dynamic_lines(base | kw))

    assert hint(t=0.9, gain=0.033, bristle_travel=3e-3)
    assert not hint(t=0.9, gain=0.033, bristle_travel=0.5e-3)  # finer than the encoder
    assert not hint(t=-2.7, gain=-1.07, bristle_travel=4.7e-3)  # LuGre predicted worse


def test_bristles_are_seen_between_one_step_and_the_records_span() -> None:
    """Both limits the record cannot tell from another model: a travel below one position step
    is σ0 → ∞ (static, sticking), one beyond the records' span is σ0 → 0 (bristles that never
    slide: a spring). The summary names the second (a belt-driven stage of a user walk: a fit
    with 2 g(0)/σ0 = 320 m on a 0.22-m stroke had won the windows by 5 standard errors)."""
    from torchfric.models.lugre import bristles_seen

    assert bristles_seen(2e-5, 5e-6, 0.2) and bristles_seen(2e-5, 5e-6)
    assert not bristles_seen(2e-6, 5e-6, 0.2)  # finer than the encoder
    assert not bristles_seen(320.0, 5e-6, 0.217) and not bristles_seen(0.2, 5e-6, 0.2)
    assert bristles_seen(1e-3, math.nan, 0.2) and not bristles_seen(1.0, math.nan, 0.2)
    row = {"dynamic": "none", "parameters": 8, "rmse_q": 2.7e-3, "bic": -1.0, "chosen": True}
    d = {"chosen": "none", "windows": 167, "window_seconds": 0.05, "holdout": 0.3,
         "seconds": 6.5, "t_min": 2.0, "table": [row], "t": 5.0, "gain": 0.893,
         "bristle_travel": 320.0, "position_step": 5e-6, "position_span": 0.217}  # fmt: skip
    summary = " ".join(dynamic_lines(d))
    assert "never slide within the records (σ0 → 0: a spring, not friction)" in summary
    assert "span of 0.217" in summary and 'model.dynamic = "lugre"' not in summary
    seen = " ".join(dynamic_lines(d | {"bristle_travel": 2e-5}))
    assert "never slide" not in seen and "cannot tell" not in seen


def test_the_bristle_travel_is_the_swing_of_the_steady_deflection() -> None:
    """`bristle_travel` = z(+) − z(−) of ``ż = v − σ0 |v| z / g(v)`` integrated to rest at a
    held speed below the stick velocity, one way and the other (here 2 g(0)/σ0 = 3e-4)."""
    from torchfric.models.lugre import bristle_field, bristle_travel, sliding_level

    model = ArmModel(OddTanhFriction(2, w1=[0.5, 5.0], w2=[0.1, 0.15]), inertia=0.03,
                     viscous=0.01, c_m=16.0, dynamic="lugre", sigma0=1000.0, sigma1=10.0,
                     stick_velocity=0.02)  # fmt: skip
    fric, arm = model.split(model.get_theta())
    ends = []
    for v in (0.01, -0.01):
        x = torch.tensor([0.0, v, 0.0], dtype=torch.float64)
        g = sliding_level(model.friction, x[1:2], fric, arm["lugre_vstick"])[0]
        h = 0.5 * g / (arm["lugre_sigma0"] * abs(v))  # explicit Euler on z alone, h·rate = ½
        for _ in range(200):  # the error halves each step
            zdot = bristle_field(x, torch.tensor(0.0), g, arm["lugre_sigma0"],
                                 arm["lugre_sigma1"], arm["inertia"])[2]  # fmt: skip
            x = torch.stack([x[0], x[1], x[2] + h * zdot])
        ends.append(float(x[2]))
    travel = bristle_travel(model.friction, fric, arm)
    assert ends[0] - ends[1] == pytest.approx(travel, rel=1e-9)
    assert travel == pytest.approx(2 * float(model.black_box(torch.tensor([0.02]), fric, arm)[0])
                                   / 1000.0, rel=1e-12)  # fmt: skip


def test_the_held_out_end_never_reaches_the_identification(static_record: Experiment) -> None:
    """The identified θ depend on the heads only: a different end of the record changes the
    windows' scores, never θ."""
    static, lugre = _starts(static_record)
    tuning = EKFTuning(passes=2)
    one = compare_dynamics(static, lugre, [static_record], tuning)
    cut = static_record.n - round(HOLDOUT * static_record.n)
    q = static_record.q.clone()
    q[cut:] += 0.01 * torch.sin(torch.arange(static_record.n - cut) * 0.01)
    changed = make_experiment(static_record.t, static_record.u, q, name="static")
    changed = changed.with_velocity()
    changed = make_experiment(static_record.t, static_record.u, q,
                              torch.cat([static_record.qdot[:cut], changed.qdot[cut:]]))  # fmt: skip
    two = compare_dynamics(static, lugre, [changed], tuning)
    for key in ("none", "lugre"):
        assert torch.equal(one.thetas[key], two.thetas[key])
        assert one.rmse[key] != two.rmse[key]


def test_window_errors_of_the_true_model_on_exact_data_vanish() -> None:
    """Noise-free data of the static class, q and q̇ measured: the true θ's windows predict the
    record to the filter's own small error, a wrong inertia's do not."""
    exp = _static_record(quantised=False)
    true = _true_static()
    tuning = prepared([exp], EKFTuning(r=[1e-12, 1e-8], q_state=[0.0, 1e-12]), 6, "test")[1]
    theta = true.get_theta()
    start = exp.n - 3000
    right = window_errors(true, theta, exp, tuning, start, 50)
    wrong_theta = theta.clone()
    wrong_theta[true.theta_names.index("inertia")] += math.log(1.2)
    wrong = window_errors(true, wrong_theta, exp, tuning, start, 50)
    assert right.shape == (59,)
    assert float(right.max().sqrt()) < 1e-12  # rad, against q of order 1 (measured 1.3e-14)
    assert float(wrong.mean().sqrt()) > 100 * float(right.mean().sqrt())


def _augmented_states(model: ArmModel, theta: torch.Tensor, exp: Experiment,
                      tuning: EKFTuning, firsts: list[int]) -> torch.Tensor:  # fmt: skip
    """The filtered states at `firsts` by the augmented filter with ``P_θθ = 0`` and no process
    noise on θ, stretch by stretch through `run_pass` (how `window_errors` found them before)."""
    k, s = model.num_parameters, model.state_size
    Q, P0_xx, H, R = tuning.matrices(k, s)
    Q = Q * 0.1
    Q[s:, s:] = 0.0
    R = R * 10.0
    step = make_step(make_propagator(model, tuning.substeps), compile=tuning.compile)
    u, y = exp.u.to(torch.float64), measurements(exp, tuning.measure)
    dt = torch.tensor(exp.dt, dtype=torch.float64)
    x, P = initial_belief(exp, theta[None], torch.zeros(1, k, k, dtype=torch.float64), P0_xx)
    state, out, last = EKFState(x[0], P[0]), [], 0
    for a in firsts:
        state, _ = run_pass(state, u[last : a + 1], y[last : a + 1], dt, Q, H, R, step,
                            continuing=last > 0)  # fmt: skip
        out.append(state.x[:s])
        last = a
    return torch.stack(out)


@pytest.mark.parametrize("measure", ["both", "position"])
def test_filtered_states_are_the_augmented_filters_bit_for_bit(
    static_record: Experiment, lugre_record: Experiment, measure: str
) -> None:
    """`filtered_states` (the states-only fixed-θ step, one pass, per-sample outputs) against
    the augmented filter run stretch by stretch, for a static and a LuGre model on both
    records: equal to the last bit."""
    given = (
        EKFTuning(measure=measure) if measure == "both" else EKFTuning(measure=measure, r=[1e-8])
    )
    for exp in (static_record, lugre_record):
        for model in _starts(exp):
            tuning = prepared([exp], given, model.num_parameters, "test")[1]
            firsts = list(range(exp.n - 3000, exp.n - 50, 50))
            got = filtered_states(model, model.get_theta(), exp, tuning, q_scale=0.1,
                                  r_scale=10.0, samples=firsts[-1] + 1)  # fmt: skip
            assert got.shape == (firsts[-1] + 1, model.state_size)
            want = _augmented_states(model, model.get_theta(), exp, tuning, firsts)
            assert torch.equal(got[firsts], want)


def test_filtered_states_name_the_sample_where_the_filter_fails(
    static_record: Experiment,
) -> None:
    """An inertia 1e-9 of the start's makes the explicit step unstable: the generated step and
    the eager one stop at the same sample, the first whose belief is not finite."""
    model = _starts(static_record)[0]
    tuning = prepared([static_record], EKFTuning(), model.num_parameters, "test")[1]
    theta = model.get_theta().clone()
    theta[model.theta_names.index("inertia")] += math.log(1e-9)
    with pytest.raises(FilterFailure) as failed:
        filtered_states(model, theta, static_record, tuning)
    with pytest.raises(FilterFailure) as eager:
        filtered_states(model, theta, static_record, dataclasses.replace(tuning, compile=False))
    assert 0 < failed.value.sample == eager.value.sample < 100


def test_a_record_too_short_to_hold_a_window_out_is_a_one_line_error(
    static_record: Experiment,
) -> None:
    short = static_record.slice(0, 120)
    static, lugre = _starts(static_record)
    with pytest.raises(TorchfricError, match='model.dynamic = "auto" holds out the last 30%'):
        compare_dynamics(static, lugre, [short], EKFTuning())


def _config(tmp_path: pathlib.Path, **model: object) -> Config:
    return Config.from_dict(
        {
            "name": "classed",
            "out_dir": str(tmp_path / "runs"),
            "data": {"train": [str(tmp_path / "rig.csv")], "validation": []},
            "model": {"c_m": 16.0, **model},
            "estimator": {"ensemble": 0, "passes": 3},
        }
    )


def test_a_run_with_dynamic_auto_trains_the_chosen_class(
    lugre_record: Experiment, tmp_path: pathlib.Path
) -> None:
    save_csv(tmp_path / "rig.csv", lugre_record, include_qdot=False)
    cfg = _config(tmp_path, dynamic="auto")
    assert "friction class auto" in check_run(cfg)  # checks the LuGre model; runs no filter
    lines: list[str] = []
    result = train(cfg, say=lines.append)
    assert result.model.dynamic == "lugre"
    dyn = result.metrics["dynamics"]
    assert dyn["chosen"] == "lugre" and dyn["windows"] == 59
    saved = json.loads((result.run_dir / "metrics.json").read_text())
    assert saved["dynamics"]["table"] == dyn["table"]
    assert 'dynamic = "auto"' in (result.run_dir / "config.toml").read_text()
    report = (result.run_dir / "report.html").read_text()
    assert "<h2>Friction class</h2>" in report and "% lower, " in report
    summary = summary_lines(result.metrics, {"run": str(result.run_dir)})
    assert any(line.startswith("friction class LuGre chosen") for line in summary)
    assert any(line.endswith("← chosen") and line.split()[0] == "LuGre" for line in summary)
    assert any('model.dynamic = "auto"' in line for line in lines)
    # the chosen class trains as a run of that class alone: the same model, bit for bit
    fixed = train(_config(tmp_path, dynamic="lugre"), say=lambda _: None)
    assert torch.equal(fixed.model.get_theta(), result.model.get_theta())
    assert "dynamics" not in fixed.metrics
    # a fixed class runs no comparison and records none
    plain, table = choose_dynamic(_config(tmp_path, dynamic="none"), [lugre_record])
    assert table is None and plain.model.dynamic == "none"


def test_auto_compares_the_classes_on_the_identification_records_alone(
    lugre_record: Experiment, static_record: Experiment, tmp_path: pathlib.Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    """The class comparison gets the identification records and nothing else: with a
    validation and a test record listed (each of them another record, and then swapped), the
    records it is given are the identification record, unchanged."""
    import torchfric.app.run.autosize as autosize

    save_csv(tmp_path / "rig.csv", lugre_record, include_qdot=False)
    save_csv(tmp_path / "a.csv", static_record, include_qdot=False)
    cut = static_record.n // 2
    other = make_experiment(static_record.t[:cut], static_record.u[:cut], static_record.q[:cut])
    save_csv(tmp_path / "b.csv", other, include_qdot=False)
    seen: list[list[Experiment]] = []

    class Stop(Exception):
        pass

    def compared(static, lugre, train, *args, **kwargs):  # type: ignore[no-untyped-def]
        seen.append(list(train))
        raise Stop

    monkeypatch.setattr(autosize, "compare_dynamics", compared)
    for held in (["a.csv", "b.csv"], ["b.csv", "a.csv"]):
        cfg = Config.from_dict(
            {
                "name": "classed",
                "out_dir": str(tmp_path / "runs"),
                "data": {"train": [str(tmp_path / "rig.csv")],
                         "validation": [str(tmp_path / held[0])],
                         "test": [str(tmp_path / held[1])]},
                "model": {"c_m": 16.0, "dynamic": "auto"},
                "estimator": {"ensemble": 0, "passes": 3},
            }
        )  # fmt: skip
        with pytest.raises(Stop):
            train(cfg, say=lambda _: None)
    assert [len(s) for s in seen] == [1, 1]
    for s in seen:
        torch.testing.assert_close(s[0].q, lugre_record.q, rtol=0, atol=1e-12)
        torch.testing.assert_close(s[0].u, lugre_record.u, rtol=0, atol=1e-12)
    assert not (tmp_path / "runs").exists()  # stopped before a run directory was claimed


def test_init_proposes_auto_and_a_bad_value_names_it(
    static_record: Experiment, tmp_path: pathlib.Path
) -> None:
    save_csv(tmp_path / "rig.csv", static_record, include_qdot=False)
    write_starter(tmp_path / "rig.csv", c_m=16.0, out=tmp_path / "cfg.toml")
    cfg = Config.load(tmp_path / "cfg.toml")
    assert cfg.model.dynamic == "auto"
    with pytest.raises(TorchfricError, match=r"model.dynamic = \"lagre\".*\"auto\""):
        _config(tmp_path, dynamic="lagre")


def test_the_bristles_start_from_the_data_in_its_own_units(
    lugre_record: Experiment, tmp_path: pathlib.Path
) -> None:
    """Unset σ0 starts at one position step of pre-sliding under the start's static friction at
    the stick velocity (the rig's own design: Fs/σ0 is one 2e-4-rad count), σ1 critically
    damped with the pre-fit's inertia; in millirad the step is 1000× and σ0 follows it."""
    from torchfric.app.run.inputs import config_model, initial_model, position_step

    assert position_step([lugre_record]) == pytest.approx(RigParameters().quantum, rel=1e-9)
    save_csv(tmp_path / "rig.csv", lugre_record, include_qdot=False)
    milli = make_experiment(lugre_record.t, lugre_record.u, 1000 * lugre_record.q, name="mrad")
    milli = milli.with_velocity()
    assert position_step([milli]) == pytest.approx(1000 * RigParameters().quantum, rel=1e-9)
    cfg = _config(tmp_path, dynamic="lugre")
    for exp in (lugre_record, milli):
        start = initial_model(cfg, [exp], config_model(cfg, [exp]))[0]
        p = start.physical_parameters()
        v_stick = torch.tensor([p["lugre_vstick"]], dtype=torch.float64)
        with torch.no_grad():
            level = float(start.static_twin().friction_torque(v_stick).abs()[0])
        assert p["lugre_sigma0"] == pytest.approx(level / position_step([exp]), rel=1e-12)
        assert p["lugre_sigma1"] == pytest.approx(2 * math.sqrt(p["lugre_sigma0"] * p["inertia"]))
    # a given value is kept as given
    given = initial_model(_config(tmp_path, dynamic="lugre", sigma0=700.0), [lugre_record])[0]
    assert given.physical_parameters()["lugre_sigma0"] == pytest.approx(700.0)


def test_a_dynamic_model_whose_filters_all_diverge_leaves_the_static_one(
    static_record: Experiment, monkeypatch: pytest.MonkeyPatch
) -> None:
    """LuGre's filters all diverging (`compare_sizes` raises) is no error: the static model is
    kept, LuGre's row says it diverged."""
    from torchfric.estimators import sizing

    real = sizing.compare_sizes

    def diverging(starts, *args, **kwargs):  # type: ignore[no-untyped-def]
        if next(iter(starts.values())).dynamic == "lugre":
            raise TorchfricError("every filter of every size (1) diverged")
        return real(starts, *args, **kwargs)

    monkeypatch.setattr(sizing, "compare_sizes", diverging)
    static, lugre = _starts(static_record)
    r = compare_dynamics(static, lugre, [static_record], EKFTuning(passes=2))
    assert r.chosen == "none" and r.t == -math.inf and r.rmse["lugre"] == math.inf
    row = r.to_dict()["table"][1]
    assert row["dynamic"] == "lugre" and row["bic"] == math.inf and not row["chosen"]


def test_a_long_record_is_identified_on_excerpts_and_scored_on_all_its_held_out_end() -> None:
    """Up to `COMPARE_SAMPLES` in all, `compare_dynamics` identifies the classes on the first
    70 % of the records itself (None: nothing changes for records up to 100 s at 1 kHz);
    beyond, on four excerpts of each record's first 70 %, from its start to its end, each
    record its share of 70 % of the budget, a short record's whole; the summary says so."""
    from torchfric.app.run.autosize import COMPARE_PIECES, comparison_heads

    def record(n: int, name: str) -> Experiment:
        t = torch.arange(n, dtype=torch.float64) * 1e-3
        return make_experiment(t, torch.zeros(n), torch.sin(t), name=name)

    assert comparison_heads([record(30_000, "a"), record(40_000, "b")], 100_000) is None
    long, tiny = record(600_000, "long"), record(3_000, "tiny")
    pieces = comparison_heads([long, tiny], 100_000)
    head = long.n - round(HOLDOUT * long.n)
    assert len(pieces) == COMPARE_PIECES + 1 and pieces[-1].n == tiny.n - round(HOLDOUT * tiny.n)
    length = int((1 - HOLDOUT) * 100_000 * head / (head + pieces[-1].n)) // COMPARE_PIECES
    starts = [round(float(p.t[0]) / 1e-3) for p in pieces[:-1]]
    assert [p.n for p in pieces[:-1]] == [length] * COMPARE_PIECES
    assert starts[0] == 0 and starts[-1] + length == head  # within the identification part
    assert (
        max(abs(b - a - (head - length) / 3) for a, b in zip(starts[:-1], starts[1:], strict=True))
        <= 1
    )
    assert sum(p.n for p in pieces[:-1]) <= (1 - HOLDOUT) * 100_000
    row = {"dynamic": "none", "parameters": 8, "rmse_q": 1e-3, "bic": -1.0, "chosen": True}
    result = {"chosen": "none", "windows": 9, "window_seconds": 0.05, "holdout": 0.3,
              "seconds": 1.0, "t_min": 2.0, "table": [row], "t": 0.0, "gain": 0.0,
              "excerpts": {"records": 5, "samples": 70_000, "of": 422_100}}  # fmt: skip
    assert dynamic_lines(result)[1] == (
        "  both identified on the first 70% of each record (5 excerpts: 70,000 of its 422,100 "
        "samples)"
    )
