"""Parameters a user can trust (issue 31): identifiable by construction, the same physical model
in any units, relative tuning, a convergence rule that ordinary data reaches, and the
identifiability report of a run.

The records come from `torchfric.data.axis`, an independent simulator of a user-style axis
(M 0.012, c_m 0.8, b 0.004, Stribeck friction), not from the built-in rig.
"""

from __future__ import annotations

import json
import math
import pathlib

import numpy as np
import pytest
import torch

import torchfric
from torchfric.data.axis import STRIBECK_AXIS, AxisParameters, axis_record
from torchfric.estimators.passes import CONVERGED, ROLLED_BACK, PassLedger, PassSums
from torchfric.estimators.sandwich import CONDITION_LIMIT
from torchfric.estimators.settings import REFERENCE_VELOCITY, EKFTuning, velocity_scale
from torchfric.models.friction import OddTanhFriction

AXIS = STRIBECK_AXIS


@pytest.fixture(scope="module")
def records() -> dict[str, dict[str, np.ndarray]]:
    return {
        k: axis_record(AXIS, seed=5, duration=8.0, kind=k) for k in ("identification", "validation")
    }


def _write(
    folder: pathlib.Path, records, q_scale: float, c_m: float, counts: bool, extra: str = ""
) -> pathlib.Path:
    folder.mkdir()
    for kind, r in records.items():
        q = r["q"] * q_scale
        q = np.round(q) if counts else q
        rows = np.column_stack([r["t"], r["u"], q])
        np.savetxt(folder / f"{kind}.csv", rows, delimiter=",", header="t,u,q", comments="",
                   fmt=["%.6f", "%.10g", "%.12g"])  # fmt: skip
    cfg = folder / "cfg.toml"
    cfg.write_text(
        'name = "axis"\n[data]\ntrain = ["identification.csv"]\nvalidation = ["validation.csv"]\n'
        f"[model]\nc_m = {c_m!r}\n[estimator]\n{extra}"
    )
    return cfg


@pytest.fixture(scope="module")
def variants(records, tmp_path_factory) -> dict[str, tuple[dict, float, float]]:
    """The same record in rad, in degrees, in encoder counts, and with c_m ×10, each trained as
    a user would: (metrics, position factor, torque factor) per variant."""
    root = tmp_path_factory.mktemp("units")
    out = {}
    for name, q_scale, torque, counts in (
        ("rad", 1.0, 1.0, False),
        ("deg", 180.0 / math.pi, 1.0, False),
        ("counts", 1.0 / AXIS.quantum, 1.0, True),
        ("c_m x10", 1.0, 10.0, False),
    ):
        cfg = _write(root / name.replace(" ", "_"), records, q_scale, AXIS.c_m * torque, counts)
        result = torchfric.fit(str(cfg), out=str(cfg.parent / "run"), quiet=True)
        out[name] = (result.metrics, q_scale, torque)
    return out


def _physical(metrics: dict, q_scale: float, torque: float) -> dict[str, float]:
    """M, b, W1 and W2 brought back to rad and the true c_m (M, b: torque·s^k per unit of q)."""
    p = {k: v["value"] for k, v in metrics["parameters"].items()}
    back = {"inertia": q_scale / torque, "viscous": q_scale / torque}
    out = {k: p[k] * back[k] for k in back}
    out |= {k: v * q_scale for k, v in p.items() if k.startswith("W1")}
    out |= {k: v / torque for k, v in p.items() if k.startswith("W2")}
    return out


def test_units_and_c_m_scale_the_physical_parameters_exactly(variants) -> None:
    """Data in other units, or with c_m ×10, give the same physical model scaled by the units,
    and the same FIT. Every step is equivariant in exact arithmetic (relative tuning, the
    data-scaled neuron bound, relative floors); what is left is rounding (a CSV in degrees
    holds 12 digits), which the passes can amplify into a neighbouring optimum of the tanh
    curve: measured, M agrees to ~1e-4 and b to ~0.5 %, inside the runs' own σ. So the check is
    in σ units (each variant's σ, brought back to rad), not to a fixed fraction.

    The FIT: a run keeps its prediction-error polish unless it scores worse than the filter's θ
    by more than 0.1 point of (FIT q + FIT q̇)/2, and where the two lie about 0.1 apart the
    decision goes either way with rounding (measured on one machine: the record in rad rejected
    its polish by 0.0004 point, the same record in degrees kept its by 0.0012; the filter's own
    θ scored 99.763 and 99.720 in the two). Variants that decided alike agree in that score
    to the rule's own 0.1 point, the difference the run itself treats as none; across decisions
    by at most that 0.1 plus the filters' own spread (0.05 allowed, 0.043 measured). FIT q
    alone is no finer: near 99.8 % it moves 0.1 point when the simulation's error norm moves
    by half, as it does within σ (on an AVX-512 machine the rad and degree runs, both
    polished, scored FIT q 99.78 / 99.90 % and q̇ 99.54 / 99.59 %: 0.083 point apart)."""
    ref_metrics, *_ = variants["rad"]
    ref = _physical(*variants["rad"])
    for name, (metrics, q_scale, torque) in variants.items():
        got = _physical(metrics, q_scale, torque)
        for key in ("inertia", "viscous"):
            sigma = metrics["parameters"][key]["std"] * q_scale / torque
            sigma_ref = ref_metrics["parameters"][key]["std"]
            assert abs(got[key] - ref[key]) < 3.0 * math.hypot(sigma, sigma_ref), (name, key)
            assert got[key] == pytest.approx(ref[key], rel=0.02), (name, key)
    fits = {n: next(iter(m["validation"].values())) for n, (m, *_) in variants.items()}
    kept = {n: "polished" in m for n, (m, *_) in variants.items()}
    for a in variants:
        for b in variants:
            fa, fb = fits[a], fits[b]
            score = 0.5 * (fa["fit_q"] + fa["fit_qdot"] - fb["fit_q"] - fb["fit_qdot"])
            assert abs(score) < (0.1 if kept[a] == kept[b] else 0.1 + 0.05), (a, b)
        assert metrics["converged"] is True, name


def test_the_viscous_term_is_the_slope_at_high_speed(variants) -> None:
    """No neuron stays linear over the data: every W1 is at least 3 / v95 of the data, so b is
    the total friction's slope where the data run fast, and it lands near the truth."""
    metrics, *_ = variants["rad"]
    p = {k: v["value"] for k, v in metrics["parameters"].items()}
    v95 = float(
        np.quantile(np.abs(np.gradient(axis_record(AXIS, seed=5, duration=8.0)["q"], 1e-3)), 0.95)
    )
    for k, v in p.items():
        if k.startswith("W1"):
            assert v * v95 > 2.0, (k, v, v95)  # the bound is 3 / v95 of the reconstructed q̇
    assert p["viscous"] == pytest.approx(AXIS.viscous, rel=0.05)
    assert p["inertia"] == pytest.approx(AXIS.inertia, rel=0.01)


def test_bounded_tanh_slope_round_trips_and_stays_odd() -> None:
    fr = OddTanhFriction(3, w1=[0.6, 2.0, 50.0], w2=[0.1, -0.2, 0.3], min_slope=0.5)
    raw = fr.raw_vector().detach()
    phys = fr.flat_to_physical(raw)
    torch.testing.assert_close(phys[:3], torch.tensor([0.6, 2.0, 50.0], dtype=torch.float64))
    torch.testing.assert_close(fr.flat_from_physical(phys), raw)
    for r in (-1e3, -30.0, 0.0, 7.0, 1e4):  # any stored value keeps W1 above the bound
        w1 = fr.split(torch.tensor([r] * 3 + [0.1] * 3, dtype=torch.float64))["W1"]
        assert bool((w1 >= 0.5).all())
    v = torch.linspace(-30, 30, 301, dtype=torch.float64)
    torch.testing.assert_close(fr(-v), -fr(v))
    assert float(fr(torch.zeros(1, dtype=torch.float64)).detach()) == 0.0
    with pytest.raises(torchfric.TorchfricError, match="above min_slope"):
        OddTanhFriction(2, w1=[0.4, 1.0], min_slope=0.5)


def test_relative_tuning_is_the_papers_at_the_rig_scale(records) -> None:
    exp = torchfric.Experiment(
        torch.tensor(records["identification"]["t"]),
        torch.tensor(records["identification"]["u"]),
        torch.tensor(records["identification"]["q"]),
    ).with_velocity()
    tuning = EKFTuning(units="relative")
    got = tuning.resolved([exp])
    scale = (velocity_scale([exp]) / REFERENCE_VELOCITY) ** 2
    assert got.units == "absolute" and got.p0_relative
    assert got.r == pytest.approx(tuple(x * scale for x in tuning.r))
    assert got.q_state == pytest.approx(tuple(x * scale for x in tuning.q_state))
    assert got.resolved([exp]) is got  # idempotent
    absolute = EKFTuning(units="absolute")
    assert absolute.resolved([exp]) is absolute
    with pytest.raises(torchfric.TorchfricError, match="units"):
        EKFTuning(units="inches").check(3)


def _sums(theta: torch.Tensor, loglik: float) -> PassSums:
    k = theta.shape[1]
    return PassSums(theta, torch.eye(k)[None].double(), torch.eye(k + 2)[None].double(),
                    torch.ones(1, 2).double(), torch.ones(1).double(),
                    torch.tensor([loglik], dtype=torch.float64), 100, [""])  # fmt: skip


def test_passes_converge_once_the_likelihood_stops_rising() -> None:
    """The rule is the gain of innovation log-likelihood, not θ's relative change: θ may keep
    creeping while the likelihood has stopped rising."""
    model = torchfric.ArmModel(OddTanhFriction(1), inertia=0.01, viscous=0.01)
    k = model.num_parameters
    ledger = PassLedger(
        model, EKFTuning(tolerance=1.0), torch.zeros(1, k).double(), torch.eye(k)[None].double()
    )
    for p, (ll, shift) in enumerate([(100.0, 0.5), (150.0, 0.2), (150.5, 0.1)], start=1):
        ledger.judge(p, _sums(torch.full((1, k), shift, dtype=torch.float64), ll), 0.0)
    assert ledger.status == [CONVERGED]  # +0.5 nats < 1, while θ still moved by 0.1
    ledger = PassLedger(
        model, EKFTuning(tolerance=1.0), torch.zeros(1, k).double(), torch.eye(k)[None].double()
    )
    for p, ll in enumerate([100.0, 99.0], start=1):
        ledger.judge(p, _sums(torch.zeros(1, k, dtype=torch.float64), ll), 0.0)
    assert ledger.status == [ROLLED_BACK] and ledger.result(0).converged


def test_quick_start_converges_and_reports_a_covariance(tmp_path) -> None:
    result = torchfric.fit(
        "experiments/configs/arm_tanh_ekf.toml", out=str(tmp_path / "run"), quiet=True
    )
    m = result.metrics
    assert m["converged"] is True and m["passes"] < 10
    assert m["covariance"]["method"] == "sandwich"
    assert all(v["std"] and v["std"] > 0 for v in m["parameters"].values())
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert "identifiability" in saved and "messages" in saved["identifiability"]


def test_an_unidentifiable_model_is_named_in_metrics_and_summary(records, tmp_path) -> None:
    """With c_m estimated too, c_m, M, b and the curve scale trade off exactly (from u and q
    alone only their ratios are determined): the run says so, by name."""
    cfg = _write(tmp_path / "cm", records, 1.0, AXIS.c_m, False, extra="passes = 3\n")
    text = cfg.read_text().replace("[estimator]", "estimate_c_m = true\n[estimator]")
    cfg.write_text(text)
    result = torchfric.fit(str(cfg), out=str(tmp_path / "run"), quiet=True)
    ident = result.metrics["identifiability"]
    assert not ident["ok"]
    named = [m for m in ident["messages"] if "c_m" in m and "inertia" in m]
    assert named and not named[0].startswith("(within")
    assert any("c_m" in w and "inertia" in w for w in result.metrics["warnings"])
    report = (tmp_path / "run" / "report.html").read_text()
    assert "<h2>Identifiability</h2>" in report and named[0].split(" are ")[0] in report


@pytest.mark.parametrize("kept", ["filter", "polish"])
def test_sigma_include_the_distance_between_the_runs_two_estimates(
    kept, records, tmp_path, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    """A run has two estimates, the filter's kept pass and the prediction-error optimum; its
    covariance is the sandwich's at the reported one plus the outer product of their offset,
    ``cov + o oᵀ``. A rejected polish (forced: the polished θ scored 0) keeps the filter's θ
    and reports ``offset_to_optimum``; a kept polish (forced: scored 100) reports
    ``offset_to_filter``, the filter's θ minus the polished one, each along the directions the
    information determines. The correlation is the sandwich's alone, and every σ² is at least
    its parameter's offset²."""
    import torchfric.app.run.confidence as confidence

    scores = iter([0.0, 100.0] if kept == "filter" else [100.0, 0.0])  # polished θ first
    monkeypatch.setattr(confidence, "_score", lambda *args: next(scores))
    cfg = _write(tmp_path / kept, records, 1.0, AXIS.c_m, False)
    result = torchfric.fit(str(cfg), out=str(tmp_path / "run"), quiet=True)
    m = result.metrics
    assert 0 < m["covariance"]["noise_model"]["step_ratio"] <= 1e-2 * (1 + 1e-9)
    state = torchfric.read_checkpoint(result.checkpoint)["estimator"]["state"]
    theta = torch.as_tensor(state["theta"], dtype=torch.float64)
    if kept == "filter":
        assert "polish_rejected" in m and "polished" not in m
        assert "offset_to_filter" not in m["covariance"]
        offset = torch.tensor(m["covariance"]["offset_to_optimum"], dtype=torch.float64)
    else:
        assert "polished" in m and "polish_rejected" not in m
        assert "offset_to_optimum" not in m["covariance"]
        offset = torch.tensor(m["covariance"]["offset_to_filter"], dtype=torch.float64)
        filter_theta = torch.as_tensor(state["filter_theta"], dtype=torch.float64)
        model = torchfric.load_checkpoint(result.checkpoint)  # the physical distance, in θ's
        physical = model.to_physical(filter_theta) - model.to_physical(theta)  # scale at θ
        distance = physical / model.physical_slope(theta)
    ident = m["identifiability"]
    held = set(ident["held_at_bound"]) | set(ident["held_steep"])
    names = list(m["parameters"])
    free = torch.tensor([n not in held for n in names])
    # only the part the information determines (`PEMCovariance.determined`): none on a held
    # entry, and all of it where no direction is near null
    assert bool((offset[~free] == 0).all())
    if kept == "polish" and not ident["directions"]:
        # I⁺ I d rounds to within κ·eps of d, κ ≤ 1 / CONDITION_LIMIT on the directions kept
        bound = torch.finfo(torch.float64).eps / CONDITION_LIMIT  # 2.2e-8; 6.5e-9 measured
        torch.testing.assert_close(offset[free], distance[free], rtol=bound,
                                   atol=bound * float(distance[free].abs().max()))  # fmt: skip
    assert offset.abs().max() > 0
    P = torch.as_tensor(state["P_theta"], dtype=torch.float64)
    torch.testing.assert_close(P, P.T)
    assert bool((torch.diagonal(P) >= offset**2).all())
    sandwich = P - torch.outer(offset, offset)
    d = torch.sqrt(torch.diagonal(sandwich).clamp_min(0.0))
    # entries held (a neuron at its floor or a step) have no σ of their own: only those
    assert bool((d[~free] < 1e-12 * d.max()).all()) and bool((d[free] > 0).all())
    torch.testing.assert_close(
        (sandwich / torch.outer(d, d))[free][:, free],
        torch.tensor(m["covariance"]["correlation"], dtype=torch.float64)[free][:, free],
        rtol=1e-8,
        atol=1e-10,
    )


def test_the_offset_is_the_physical_distance_between_the_two_estimates() -> None:
    """`physical_offset`: in θ's coordinates by the delta method's scale at θ, so σ_b² reported
    (slope² × (σ_θ² + offset²)) is the sandwich's plus (b_other − b)². A polish that drove log b
    to −4e138 (b = 0, on a ball-screw table) is all of b away, not 4e138."""
    from torchfric.app.run.confidence import physical_offset
    from torchfric.models.arm import ArmModel

    model = ArmModel(OddTanhFriction(2, w1=[1.0, 20.0], w2=[0.05, 0.1]), inertia=18.0,
                     viscous=120.0, c_m=40.0)  # fmt: skip
    names = model.theta_names
    theta = model.get_theta()
    other = theta.clone()
    other[names.index("viscous")] = -4e138
    other[names.index("inertia")] += math.log(1.5)
    other[names.index("W2[1]")] += 0.25
    off = physical_offset(model, theta, other)
    slope = model.physical_slope(theta)
    assert float(off[names.index("viscous")] * slope[names.index("viscous")]) == pytest.approx(-120.0)
    assert float(off[names.index("viscous")]) == pytest.approx(-1.0)
    assert float(off[names.index("inertia")] * slope[names.index("inertia")]) == pytest.approx(9.0)
    assert float(off[names.index("W2[1]")]) == pytest.approx(0.25, rel=1e-12)
    assert float(off[names.index("W1[1]")]) == 0.0


# A light linear axis that sticks at its reversals (3.5 kg, 1 µm encoder, Coulomb 2.5 N, which
# one tanh neuron draws, and a 12-Hz load disturbance): the user walk of docs/results.md.
LIGHT = AxisParameters(inertia=3.5, c_m=8.0, viscous=15.0, coulomb=2.5, static=2.5,
                       stribeck_velocity=0.02, quantum=1e-6, max_speed=0.3, max_input=2.5,
                       disturbance_std=0.05, disturbance_bandwidth=12.0)  # fmt: skip


def test_a_sticking_axis_leaves_its_stuck_samples_out_of_the_criterion(tmp_path) -> None:
    """A static curve cannot hold a stuck axis, and with the stuck samples in the prediction-error
    criterion its optimum put M +0.9 % off at 60 σ on this machine. Left out (`moving_samples`),
    M and b come back inside ±2σ of the truth, M within 0.3 %."""
    recs = {k: axis_record(LIGHT, seed=s, duration=DURATION_LIGHT, kind=k)
            for k, s in (("identification", 300), ("validation", 400))}  # fmt: skip
    cfg = _write(tmp_path / "light", recs, 1.0, LIGHT.c_m, False)
    m = torchfric.fit(str(cfg), out=str(tmp_path / "run"), quiet=True).metrics
    assert 0.1 < m["covariance"]["stuck_left_out"] < 0.5
    for name, truth in (("inertia", LIGHT.inertia), ("viscous", LIGHT.viscous)):
        p = m["parameters"][name]
        assert abs(p["value"] - truth) <= 2.0 * p["std"], (name, p, truth)
    assert abs(m["parameters"]["inertia"]["value"] / LIGHT.inertia - 1.0) < 3e-3


DURATION_LIGHT = 10.0


def test_a_curve_that_pushes_the_axis_near_rest_is_named() -> None:
    """Friction is passive (F q̇ >= 0). The belt stage's static fit drew its stick as a negative
    lobe below 2.4 mm/s (−8.8 tanh(1760 q̇) under +12 tanh(77 q̇)): named with the speeds and the
    depth; a Stribeck curve (a positive sum of tanh) and the shipped rig model are not."""
    from torchfric.app.run.assessment import _active_friction, _v95
    from torchfric.data import make_experiment
    from torchfric.models.arm import ArmModel

    t = torch.arange(1000, dtype=torch.float64) * 1e-3
    v = 0.2 * torch.sin(2 * math.pi * t)  # v95 of |q̇|: 0.1975
    exp = make_experiment(t, torch.zeros(1000), torch.zeros(1000), v)

    def model(w1: list[float], w2: list[float]) -> ArmModel:
        return ArmModel(OddTanhFriction(2, w1=w1, w2=w2), inertia=1.8, viscous=15.0, c_m=6.0)

    (line,) = _active_friction(model([1760.0, 77.0], [-8.8, 12.0]), _v95([exp]))
    assert line.startswith("the friction curve pushes the axis instead of braking it at ")
    low, high = (float(x) for x in line.split(" at ")[1].split(" (")[0].split(" <= |q̇| <= "))

    # the odd part b v − 8.8 tanh(1760 v) + 12 tanh(77 v) is negative from the grid's first
    # speed (1e-5 v95) to its zero (by bisection), within one step of the log grid (2.3 %)
    def odd(x: float) -> float:
        return 15.0 * x - 8.8 * math.tanh(1760.0 * x) + 12.0 * math.tanh(77.0 * x)

    a, b = 1e-4, 0.1
    for _ in range(200):
        a, b = (a, 0.5 * (a + b)) if odd(0.5 * (a + b)) > 0 else (0.5 * (a + b), b)
    assert low == pytest.approx(1e-5 * float(torch.quantile(v.abs(), 0.95)), rel=1e-2)
    assert high < a <= high * 1.03 and 'model.dynamic = "lugre"' in line
    # after auto compared both classes and kept the static one, LuGre is not the advice
    (kept,) = _active_friction(model([1760.0, 77.0], [-8.8, 12.0]), _v95([exp]), compared=True)
    assert kept.split(": ")[:2] == line.split(": ")[:2] and "lugre" not in kept
    assert kept.endswith("compared LuGre on these records and kept the static model, so below "
                         "that speed the curve is the stick drawn, not friction: a simulation "
                         "that starts from rest is pushed there")  # fmt: skip
    assert _active_friction(model([200.0, 20.0], [2.0, 4.0]), _v95([exp])) == []
    root = pathlib.Path(__file__).resolve().parents[1]
    rig = torchfric.load_checkpoint(root / "checkpoints" / "arm_tanh_ekf.pt")
    assert _active_friction(rig, _v95([exp])) == [] and _active_friction(rig, _v95([])) == []
