"""A tanh neuron that takes part of the viscous term (issue 31): `viscous_share` on hand-set
parameters, the run's identifiability report that carries it (`run_identifiability`), and a
run whose metrics.json, warnings and report.html name it.

The hand-set parameters are those of a user's rotary axis (b = 0.002, v95 = 6.73 rad/s,
median 2.56): one fit kept a neuron at its bound ``3 / v95`` (W1 = 0.464, W2 = −0.009) and reported
b = 0.00295 ± 2e-5, 47 σ off; a fit that separates them has every neuron saturated over the
upper speeds.
"""

from __future__ import annotations

import json
import math
import pathlib

import numpy as np
import pytest
import torch

import torchfric
from torchfric.app.run import confidence
from torchfric.app.run.confidence import run_identifiability
from torchfric.data import Experiment
from torchfric.data.axis import STRIBECK_AXIS, axis_record
from torchfric.estimators import sandwich, uncertainty
from torchfric.estimators.sandwich import (
    Identifiability,
    PEMCovariance,
    viscous_share,
)
from torchfric.models.arm import ArmModel
from torchfric.models.friction import OddTanhFriction, PolytopicFriction

V50, V95 = 2.56, 6.73
PINNED = {"W1[1]": 10.7, "W1[2]": 0.464, "W1[3]": 312.0,
          "W2[1]": 0.0055, "W2[2]": -0.009, "W2[3]": 0.0461, "viscous": 0.00295}  # fmt: skip
SATURATED = {"W1[1]": 10.7, "W1[2]": 4.8, "W1[3]": 312.0,
             "W2[1]": 0.0055, "W2[2]": -0.0216, "W2[3]": 0.0461, "viscous": 0.002}  # fmt: skip


def _speeds() -> torch.Tensor:
    """1001 speeds, both directions, whose |·| has the 50th and 95th percentiles V50, V95
    exactly (torch.quantile interpolates linearly: entries 500 and 950 of the sorted |v|)."""
    v = torch.cat([
        torch.linspace(0.0, V50, 501), torch.linspace(V50, V95, 451)[1:],
        torch.linspace(V95, 7.0, 51)[1:],
    ])  # fmt: skip
    return v * torch.where(torch.arange(v.numel()) % 2 == 0, 1.0, -1.0)


def _slope(w1: float, w2: float) -> float:
    # s_j = W2_j (tanh(W1_j v95) − tanh(W1_j v95/2)) / (v95/2)
    return w2 * (math.tanh(w1 * V95) - math.tanh(w1 * V95 / 2)) / (V95 / 2)


def test_a_neuron_pinned_at_its_bound_is_named_with_its_share_of_b() -> None:
    (share,) = viscous_share(PINNED, _speeds(), viscous_std=2.0e-5)
    assert share.names == ("viscous", "W1[2]", "W2[2]")
    assert (share.v_half, share.v95) == pytest.approx((V95 / 2, V95), rel=1e-6)
    assert share.slope == pytest.approx(_slope(0.464, -0.009), rel=1e-12)
    assert share.share == pytest.approx(-0.0730, abs=5e-4)  # the user's record: −6.6 %
    assert share.sigmas == pytest.approx(-10.76, abs=0.05)  # the user's record: 9.6 σ_b
    assert share.message == (
        "viscous and neuron 2 (W1[2], W2[2]) are not separately identifiable over this data's "
        "speeds: the neuron's tanh still rises between v95/2 = 3.37 and v95 = 6.73 (its slope "
        "there is -7 % of b, 11 σ_b), so b = 0.00295 is not the viscous term alone; raise "
        "model.saturation (to twice its value, 6 for the default 3) so that every neuron "
        "saturates below half the data's top speed"
    )
    d = share.to_dict()
    assert d["parameters"] == ["viscous", "W1[2]", "W2[2]"]
    assert d["share"] == share.share and (d["v_half"], d["v95"]) == (share.v_half, share.v95)


def test_a_saturated_fit_is_not_flagged() -> None:
    assert viscous_share(SATURATED, _speeds(), viscous_std=1.7e-5) == []
    # the largest share there is far below the limit, not just under it
    top = max(abs(_slope(SATURATED[f"W1[{j}]"], SATURATED[f"W2[{j}]"])) for j in (1, 2, 3))
    assert top < 1e-3 * 0.002


def test_both_limits_must_be_passed() -> None:
    # 12 % of b but only 1.8 σ_b: within what the data say about b
    assert viscous_share(PINNED, _speeds(), viscous_std=2.0e-4) == []
    # far beyond σ_b but 4 % of b: too small a share to matter
    small = {**PINNED, "W2[2]": -0.009 * 0.04 / 0.1215}
    assert viscous_share(small, _speeds(), viscous_std=1e-7) == []
    # b without a σ (not determined: the report names it already) reports nothing
    assert viscous_share(PINNED, _speeds(), viscous_std=None) == []
    assert viscous_share(PINNED, _speeds(), viscous_std=0.0) == []


def test_models_without_a_viscous_term_or_tanh_neurons_are_never_flagged() -> None:
    no_b = {k: v for k, v in PINNED.items() if k != "viscous"}
    assert viscous_share(no_b, _speeds(), viscous_std=2.0e-5) == []
    polytopic = ArmModel(PolytopicFriction(3), viscous=None).physical_parameters()
    assert viscous_share(polytopic, _speeds(), viscous_std=2.0e-5) == []
    # its slopes a1, a2 beside a (hypothetical) b are not tanh neurons either
    assert viscous_share({**polytopic, "viscous": 0.002}, _speeds(), viscous_std=1e-9) == []
    # speeds that do not spread (v50 = v95) leave no slope to measure
    assert viscous_share(PINNED, torch.full((100,), 3.0), viscous_std=2.0e-5) == []


def test_lugre_reads_its_sliding_curve_above_the_stick_velocity() -> None:
    slow = viscous_share({**PINNED, "lugre_vstick": 0.05}, _speeds(), viscous_std=2.0e-5)
    assert [s.names for s in slow] == [("viscous", "W1[2]", "W2[2]")]
    # a curve held flat up to beyond v95 has no slope between v95/2 and v95
    assert viscous_share({**PINNED, "lugre_vstick": 8.0}, _speeds(), viscous_std=2.0e-5) == []


def _pinned_model(*, dynamic: str = "none") -> ArmModel:
    """The user's model: tanh(3) with W1 bounded below by 3 / v95, at the pinned fit."""
    friction = OddTanhFriction(3, min_slope=3.0 / V95, w1=[10.7, 0.5, 312.0])
    model = ArmModel(friction, inertia=0.012, viscous=0.002, c_m=0.8, dynamic=dynamic)
    values = torch.tensor([model.physical_parameters()[n] for n in model.theta_names])
    for name, value in PINNED.items():
        values[model.theta_names.index(name)] = value
    return model.set_theta(model.from_physical(values))


def _covariance(model: ArmModel, viscous_std: float) -> PEMCovariance:
    """A stand-in for the run's sandwich: θ the model's, σ_b = `viscous_std` in physical
    units (b is stored as its log: σ of log b = σ_b / b), the rest 1 % of each entry."""
    theta = model.get_theta()
    k = model.num_parameters
    var = (0.01 * theta.abs().clamp_min(1e-3)) ** 2
    i = model.theta_names.index("viscous")
    var[i] = (viscous_std / PINNED["viscous"]) ** 2
    z = torch.zeros(k)
    return PEMCovariance(theta, torch.diag(var), torch.diag(1.0 / var), torch.eye(k), z, z, 0.0,
                         1001, 1, 1, model.theta_names, Identifiability())  # fmt: skip


@pytest.mark.parametrize("dynamic", ["none", "lugre"])
def test_the_runs_report_names_the_neuron_as_a_warning(dynamic: str) -> None:
    """`run_identifiability` (the confidence stage's report, both estimators) joins the share to
    the covariance's groups; `_messages` keeps it a warning (b is a white-box parameter)."""
    model = _pinned_model(dynamic=dynamic)
    v = _speeds()
    t = torch.arange(v.numel(), dtype=torch.float64) * 1e-3
    train = [Experiment(t, torch.zeros_like(t), torch.cumsum(v, 0) * 1e-3, v)]
    ident = run_identifiability(model, _covariance(model, 2.0e-5), train)
    assert not ident.ok
    assert ident.groups == [
        (["viscous", "W1[2]", "W2[2]"], "slope -7 % of b between v95/2 and v95")
    ]
    (line,) = confidence._messages(ident)
    assert line.startswith("viscous and neuron 2 (W1[2], W2[2]) are not separately")
    d = ident.to_dict()  # the existing keys and shape stay; the share comes beside them
    kept = {"ok", "correlation_limit", "condition_limit", "pairs", "directions", "messages"}
    assert kept <= set(d)
    assert d["pairs"] == [] and d["directions"] == [] and d["messages"] == [line]
    (entry,) = d["viscous_shares"]
    assert entry["parameters"] == ["viscous", "W1[2]", "W2[2]"]
    assert entry["v_half"] == pytest.approx(V95 / 2) and entry["v95"] == pytest.approx(V95)
    assert entry["viscous_std"] == pytest.approx(2.0e-5, rel=1e-9)
    # the same data with a σ_b ten times wider: nothing to say
    assert run_identifiability(model, _covariance(model, 2.0e-4), train).ok


def test_a_run_carries_the_check_to_metrics_warnings_and_report(
    tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The plumbing of a real (short) run. Its fit is sound, so both limits are set below 0
    here: every neuron is then flagged, and each must reach metrics.json's identifiability and
    warnings, the summary's warnings and report.html, over the run's own speeds."""
    for module in (sandwich, uncertainty):  # the check's (uncertainty) and the report's limits
        monkeypatch.setattr(module, "VISCOUS_SHARE_LIMIT", -1.0)
        monkeypatch.setattr(module, "VISCOUS_SHARE_SIGMA", -1.0)
    for kind in ("identification", "validation"):
        r = axis_record(STRIBECK_AXIS, seed=5, duration=4.0, kind=kind)
        np.savetxt(tmp_path / f"{kind}.csv", np.column_stack([r["t"], r["u"], r["q"]]),
                   delimiter=",", header="t,u,q", comments="", fmt=["%.6f", "%.10g", "%.12g"])  # fmt: skip
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        'name = "axis"\n[data]\ntrain = ["identification.csv"]\nvalidation = ["validation.csv"]\n'
        f"[model]\nc_m = {STRIBECK_AXIS.c_m!r}\n[estimator]\npasses = 2\n"
    )
    result = torchfric.fit(str(cfg), out=str(tmp_path / "run"), quiet=True)
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["parameters"]["viscous"]["std"]  # b has a σ: the check ran
    (share,) = saved["identifiability"]["viscous_shares"]  # one report: the neurons' net slope
    assert share["parameters"][0] == "viscous" and len(share["parameters"]) >= 3
    shares = [share]
    # v95 is the speed the bound W1 > saturation / v95 was made from
    v95 = shares[0]["v95"]
    assert result.model.friction.min_slope * v95 == pytest.approx(3.0, rel=1e-9)
    assert shares[0]["v_half"] == pytest.approx(v95 / 2)
    report = (tmp_path / "run" / "report.html").read_text()
    named = ", ".join(share["parameters"][1:])
    head = "viscous and neuron"
    (line,) = [m for m in saved["identifiability"]["messages"] if m.startswith(head)]
    assert f"({named})" in line
    assert line in saved["warnings"]
    assert line.split(" over this")[0] in report
    assert saved["warnings"] == result.metrics["warnings"]
    assert saved["identifiability"]["ok"] is False


def test_slow_neurons_whose_slopes_cancel_leave_b_alone() -> None:
    """The net slope decides: two slow neurons at +23 % and −24 % of b (measured on a seed of
    the coverage study's axis, b within 1.5 σ) are not a shared viscous term; one of them alone
    is, and a pair that adds up is named together, largest first."""
    base = {"viscous": 0.002, "W1[1]": 300.0, "W2[1]": 0.04}
    w1 = 0.5
    unit = _slope(w1, 1.0)
    pair = {**base, "W1[2]": w1, "W2[2]": 0.23 * 0.002 / unit, "W1[3]": w1,
            "W2[3]": -0.24 * 0.002 / unit}  # fmt: skip
    assert viscous_share(pair, _speeds(), viscous_std=2e-5) == []
    alone = {**base, "W1[2]": w1, "W2[2]": -0.24 * 0.002 / unit}
    (one,) = viscous_share(alone, _speeds(), viscous_std=2e-5)
    assert one.names == ("viscous", "W1[2]", "W2[2]")
    both = {**pair, "W2[2]": -0.04 * 0.002 / unit}
    (two,) = viscous_share(both, _speeds(), viscous_std=2e-5)
    assert two.names == ("viscous", "W1[3]", "W2[3]", "W1[2]", "W2[2]")
    assert two.share == pytest.approx(-0.28, rel=1e-9)
    assert two.message.startswith("viscous and neurons 3 and 2 (W1[3], W2[3], W1[2], W2[2])")


def test_a_stribeck_neuron_on_a_stick_slip_record_is_not_a_shared_slope() -> None:
    """A linear axis that rests half the time (median |q̇| 4e-5 m/s, v95 0.227 m/s): the neuron
    that draws its Stribeck dip (W1 = 51.5 s/m, saturated by 0.06 m/s) has a large mean slope
    between the median and v95, but none over the upper half of the speed range, where b is
    the friction's slope. A fit whose neuron pair does carry slope there is still named."""
    rest = torch.full((600,), 4e-5)
    moving = torch.linspace(0.0, 0.24, 400)
    speeds = torch.cat([rest, moving])
    fit = {"W1[1]": 1294.0, "W1[2]": 51.54, "W1[3]": 13.22, "W2[1]": 6.667,
           "W2[2]": -2.657, "W2[3]": 0.0102, "viscous": 7.75}  # fmt: skip
    assert viscous_share(fit, speeds, viscous_std=5.3e-5) == []
    pair = {"W1[1]": 17.22, "W1[2]": 19.17, "W1[3]": 2212.0, "W2[1]": 27.69,
            "W2[2]": -28.68, "W2[3]": 6.19, "viscous": 1.23}  # fmt: skip
    (share,) = viscous_share(pair, speeds, viscous_std=7.8e-6)
    assert share.names[:3] == ("viscous", "W1[1]", "W2[1]") and share.share > 1.0
