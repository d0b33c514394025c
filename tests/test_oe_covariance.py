"""The simulation-error sandwich covariance of an output-error estimate (`simulation_covariance`).

Synthetic data as in test_output_error.py: an `ArmModel` with known θ simulated under the rig's
identification excitation (seed 2), with independent white noise added to q and to a measured
q̇, so that the residuals at the truth are white (for the LuGre model up to its bristle state at
the start, which a record cut from a longer run does not have at its steady deflection).
"""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from torchfric.data.experiment import Experiment
from torchfric.data.rig import excitation
from torchfric.errors import TorchfricError
from torchfric.estimators import oe_covariance, sandwich
from torchfric.estimators.oe_covariance import simulation_covariance
from torchfric.models.arm import ArmModel
from torchfric.models.friction import CoulombFriction, OddTanhFriction
from torchfric.models.simulate import full_state, simulate, solver_step

DT = 1e-3
U = torch.as_tensor(excitation("identification", duration=30.0, seed=2))


def _tanh_arm(**kw: object) -> ArmModel:
    friction = OddTanhFriction(3, w1=[0.5, 5.0, 50.0], w2=[0.04, 0.05, 0.1])
    return ArmModel(friction, inertia=0.0292, viscous=0.01, c_m=16.0, **kw)  # type: ignore[arg-type]


def _lugre_arm() -> ArmModel:
    friction = OddTanhFriction(2, w1=[1.0, 20.0], w2=[0.05, 0.1])
    return ArmModel(friction, inertia=0.0292, viscous=0.01, c_m=16.0, offset=0.005,
                    dynamic="lugre", sigma0=2e3, sigma1=2.0, stick_velocity=0.05)  # fmt: skip


_TRUTH: dict[str, Tensor] = {}


def _truth(model: ArmModel) -> Tensor:
    """`(N, 2)` the whole excitation's noise-free response of `model` from rest (memoised)."""
    key = repr(model.spec())
    if key not in _TRUTH:
        with torch.no_grad():
            t = torch.arange(U.numel()) * DT
            _TRUTH[key] = simulate(model, t, U, torch.zeros(2), substeps=1, engine="compiled")
    return _TRUTH[key]


def _record(
    model: ArmModel, n: int, noise: tuple[float, float], seed: int, start: int = 1000
) -> Experiment:
    """Samples `start` … `start + n − 1` of `model`'s response (the excitation begins at sample
    500), with white noise of standard deviations `noise` on q and on the measured q̇; the
    measured start is the true state (noise on x0 is not what these tests are about)."""
    x = _truth(model)[start : start + n]
    g = torch.Generator().manual_seed(seed)
    q = x[:, 0] + noise[0] * torch.randn(n, generator=g)
    v = x[:, 1] + noise[1] * torch.randn(n, generator=g)
    q[0], v[0] = x[0, 0], x[0, 1]
    t = torch.arange(n) * DT
    return Experiment(t=t, u=U[start : start + n], q=q, qdot=v, name=f"seed{seed}")


def _reversal(model: ArmModel) -> int:
    """A start 100 samples before the first reversal of q̇ after sample 1000: a stretch in which
    every friction parameter acts (at one speed the steep tanh units are saturated)."""
    v = _truth(model)[1000:, 1]
    return 1000 + int(((v[1:] * v[:-1]) < 0).nonzero()[0]) - 100


def _stepped(model: ArmModel, exp: Experiment, theta: Tensor) -> Tensor:
    """The simulated outputs `(N−1, 2)` after the start by the model's own solver step in a plain
    loop (what simulate's engines run), so that autograd sees every operation."""
    fric, arm = model.split(theta)
    x = full_state(model, torch.stack([exp.q[0], exp.qdot[0]]), theta)
    out = []
    for i in range(exp.n - 1):
        x = solver_step(model, x, exp.u[i], exp.dt, fric, arm)
        out.append(x[:2])
    return torch.stack(out)


@pytest.mark.parametrize("kind", ["tanh", "lugre"])
def test_information_is_the_gauss_newton_matrix_of_autograd(kind: str) -> None:
    model = _tanh_arm() if kind == "tanh" else _lugre_arm()
    exp = _record(model, 200, (2e-4, 2e-3), seed=1, start=_reversal(model))
    theta = model.get_theta()
    cov = simulation_covariance(model, exp, theta, substeps=1)
    # The plain loop is the simulation (to rounding), so its Jacobian is ∂ŷ/∂θ.
    with torch.no_grad():
        sim = simulate(model, exp.t, exp.u, torch.stack([exp.q[0], exp.qdot[0]]), substeps=1)
    torch.testing.assert_close(_stepped(model, exp, theta), sim[1:], rtol=0, atol=1e-12)
    D = torch.autograd.functional.jacobian(
        lambda th: _stepped(model, exp, th), theta, strategy="forward-mode", vectorize=True
    )  # (N−1, 2, k)
    r = torch.stack([exp.q, exp.qdot], -1)[1:] - sim[1:]
    W = 1.0 / (r * r).mean(0)
    info = torch.einsum("tci,c,tcj->ij", D, W, D)
    grad = torch.einsum("tci,c,tc->i", D, W, r)
    # Central differences at half a conditional σ are the secant over ±h, off the derivative by
    # (h²/6) ∂³ŷ/∂θ³: measured ≤ 1e-5 (scaled to unit diagonal) for the near-linear entries and
    # up to 8e-4 for the few whose ½σ is 1–3 % of their value on 200 samples (the steep tanh
    # unit; LuGre's σ0 and v_s). 3e-3 keeps that margin; a wrong W, sign or step is off by O(1).
    scale = torch.diagonal(info).sqrt()
    torch.testing.assert_close(
        cov.information / (scale[:, None] * scale[None, :]),
        info / (scale[:, None] * scale[None, :]),
        rtol=0,
        atol=3e-3,
    )
    torch.testing.assert_close(cov.gradient / scale, grad / scale, rtol=0, atol=3e-3)
    assert cov.method == "sandwich_simulation"
    assert cov.samples == exp.n - 1
    torch.testing.assert_close(cov.newton, sandwich._inverse(cov.information) @ cov.gradient)


def test_unidentifiable_scale_is_named() -> None:
    """With c_m free, (c_m, M, b, W2) scale together without changing the simulation."""
    model = _tanh_arm(estimate_c_m=True)
    exp = _record(model, 300, (2e-4, 2e-3), seed=2)
    cov = simulation_covariance(model, exp, model.get_theta(), substeps=1)
    groups = [set(names) for names, _ in cov.identifiability.groups]
    assert any({"c_m", "inertia"} <= g for g in groups), cov.identifiability.messages
    assert not cov.identifiability.ok
    assert torch.isfinite(cov.cov).all()


def _white_box(inertia: float = 0.03, viscous: float = 0.02, fc: float = 0.1) -> ArmModel:
    return ArmModel(CoulombFriction(fc=fc, eps=0.05), inertia=inertia, viscous=viscous, c_m=16.0)


def test_two_sigma_covers_the_truth_over_seeds() -> None:
    """Coverage on 20 records (disjoint 1.4 s stretches, independent noise): Gauss–Newton from a
    perturbed start with the function's own `newton`, then the truth within ±2σ. Nominal 95 %
    (19 of 20); measured over 100 such fits 96–98 %, and z = error/σ with a standard deviation
    of 1.0–1.08. The bands (≥ 15 of 20; mean z² in [0.4, 2], a χ²₂₀/20's 99.9 % range) catch a
    σ that is off by √2 either way, as the earlier 33-block J was (z std 1.25–1.37)."""
    true = _white_box()
    names = true.theta_names
    z: dict[str, list[float]] = {"inertia": [], "viscous": []}
    for seed in range(20):
        exp = _record(true, 1400, (5e-4, 5e-3), seed=100 + seed, start=600 + 1400 * seed)
        theta = _white_box(inertia=0.033, viscous=0.018, fc=0.11).get_theta()
        for _ in range(4):
            theta = theta + simulation_covariance(true, exp, theta, substeps=1).newton
        cov = simulation_covariance(true, exp, theta, substeps=1)
        assert float(cov.newton_sigma.abs().max()) < 0.05  # converged: the step is a small σ
        err = true.to_physical(theta) - true.to_physical(true.get_theta())
        sigma = cov.std * true.physical_slope(theta)
        for name, zs in z.items():
            i = names.index(name)
            zs.append(float(err[i] / sigma[i]))
    for name, zs in z.items():
        hits = sum(abs(v) <= 2.0 for v in zs)
        mean_square = sum(v * v for v in zs) / len(zs)
        assert hits >= 15, (name, zs)
        assert 0.4 <= mean_square <= 2.0, (name, zs)


# -- errors -----------------------------------------------------------------------------------
def test_simulation_that_is_not_finite_is_refused() -> None:
    model = _tanh_arm()
    exp = _record(model, 100, (2e-4, 2e-3), seed=3)
    theta = model.get_theta()
    stiff = theta.clone()
    stiff[model.theta_names.index("viscous")] = 20.0  # b/M ≈ 2e10 /s: RK4 at 1 ms blows up
    with pytest.raises(TorchfricError, match=r"simulation at θ is not finite"):
        simulation_covariance(model, exp, stiff, substeps=1)


def test_exact_fit_is_refused() -> None:
    model = _tanh_arm()
    exp = _record(model, 100, (0.0, 0.0), seed=3)
    with pytest.raises(TorchfricError, match=r"reproduces the measured q exactly"):
        simulation_covariance(model, exp, model.get_theta(), substeps=1)


def test_perturbed_simulation_that_is_not_finite_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    model = _tanh_arm()
    exp = _record(model, 100, (2e-4, 2e-3), seed=3)
    k = model.num_parameters
    real = oe_covariance.simulate

    def broken(*args: object, **kw: object) -> Tensor:
        out = real(*args, **kw)  # type: ignore[arg-type]
        out[5:, k + 1 + k - 1] = math.nan  # θ − h e_inertia blows up
        return out

    monkeypatch.setattr(oe_covariance, "simulate", broken)
    with pytest.raises(TorchfricError, match=r"not finite when inertia moves"):
        simulation_covariance(model, exp, model.get_theta(), substeps=1)


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"weights": (0.0, 0.0)}, r"not both 0"),
        ({"weights": (1.0, -1.0)}, r">= 0"),
        ({"substeps": 0}, r"substeps must be"),
        ({"block": 0}, r"block must be"),
    ],
)
def test_bad_arguments(kw: dict, match: str) -> None:
    model = _tanh_arm()
    exp = _record(model, 100, (2e-4, 2e-3), seed=4)
    with pytest.raises(TorchfricError, match=match):
        simulation_covariance(model, exp, model.get_theta(), **kw)


def test_wrong_theta_and_missing_velocity() -> None:
    model = _tanh_arm()
    exp = _record(model, 100, (2e-4, 2e-3), seed=4)
    with pytest.raises(TorchfricError, match=r"theta has 3 entries but this model has 8"):
        simulation_covariance(model, exp, torch.zeros(3))
    bare = Experiment(t=exp.t, u=exp.u, q=exp.q, qdot=None, name="bare")
    with pytest.raises(TorchfricError, match=r"has no velocity"):
        simulation_covariance(model, bare, model.get_theta())
