"""Prediction-error covariance (torchfric.estimators.covariance) against exact references.

- The fixed-θ filter against an independent one written here. With ``P_θθ = 0`` and no process
  noise on θ, the augmented filter's cross-covariances ``P_xθ`` and the θ rows of its gain stay
  exactly 0, so it *is* the 2-state EKF on ``[q, q̇]`` at that θ: `_reference` writes that filter
  from scratch in scalars (RK4 3/8 mean with zero-order-hold u, the RK4 map's exact Jacobian
  ``Φ = [[1, α], [0, β]]`` by the variational recursion, ``P⁻ = Φ P Φᵀ + ½ (Φ Q Φᵀ + Q) dt``,
  the textbook update of q measured alone) for a tanh(n) `ArmModel` with viscous b, and returns
  the innovations ``e_t`` and their variances ``S_t`` as differentiable functions of θ.
  `torch.func.jacrev` through it gives the exact sensitivities ``∂e_t/∂θ``, from which the
  quantities `pem_covariance` documents — the criterion ``−½ Σ e²/S``, its score
  ``−e ∂e / S`` with the weights 1/S held, the Gauss–Newton information ``Σ ∂eᵀ∂e / S``, the
  Newton step, the block scores' Bartlett covariance and the sandwich — are computed exactly and
  compared with the module's central differences. Autograd's Hessian of the criterion checks
  that the Gauss–Newton information is the curvature the Newton step needs.
- `identifiability`: a model with c_m estimated (c_m, M, b and the friction scaled by one factor
  give the same q) is flagged by name; a well-posed model on rich data is not; hand-made
  matrices give exactly the expected pairs, groups and null directions.
- `long_run_covariance` (and its one-experiment form `_bartlett`) on synthetic score series:
  its formula, Andrews' bandwidth, i.i.d. blocks and an AR(1) series.
- Coverage: the ±2σ of the sandwich around Newton-refined estimates cover the true inertia over
  20 independent records, where ``I⁻¹`` alone is 15–30× too wide (the filter's Q is a tuning).

Two former defects (σ = 0 from one block, a singular sandwich from few) are checked at the end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
import scipy.signal
import torch

from torchfric.data.experiment import Experiment, make_experiment
from torchfric.errors import TorchfricError
from torchfric.estimators.covariance import (
    BLOCKS,
    CONDITION_LIMIT,
    CORRELATION_LIMIT,
    PEMCovariance,
    fixed_theta_loglik,
    identifiability,
    innovations,
    long_run_covariance,
    pem_covariance,
)
from torchfric.estimators.sandwich import _bartlett
from torchfric.estimators.settings import EKFTuning
from torchfric.models.arm import ArmModel
from torchfric.models.friction import CoulombFriction, OddTanhFriction
from torchfric.models.simulate import simulate

DT = 1e-3
C_M = 1.0
SIGMA_Q = 1e-5  # measurement noise of q [rad]
LOG_2PI = math.log(2.0 * math.pi)


# =============================================================================================
# Helpers
# =============================================================================================
def _tuning() -> EKFTuning:
    """Absolute tuning, q measured alone (the app's form): R = the true noise variance, Q_q̇ the
    paper's 1e-3 — a tuning, not the truth (the simulated machine has no process noise)."""
    return EKFTuning(units="absolute", measure="position", r=(SIGMA_Q**2,), q_state=(0.0, 1e-3))


def _tanh_arm(w1: tuple[float, ...], w2: tuple[float, ...]) -> ArmModel:
    return ArmModel(
        OddTanhFriction(len(w1), w1=list(w1), w2=list(w2)), inertia=0.03, viscous=0.01, c_m=C_M
    )


def _short_record(model: ArmModel, n: int, seed: int) -> Experiment:
    """`n` samples at 1 kHz from rest: two sines (4 and 11 Hz) plus white input noise, |q̇| up
    to ≈ 2.6 rad/s, Gaussian noise on q (no velocity: the filter starts at q̇ = 0, as here)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n, dtype=torch.float64) * DT
    u = torch.sin(2 * math.pi * 4.0 * t) + 0.6 * torch.sin(2 * math.pi * 11.0 * t + 1.0)
    u = u + 0.2 * torch.randn(n, generator=g)
    with torch.no_grad():
        x = simulate(model, t, u, torch.zeros(2), substeps=4, engine="compiled")
    return make_experiment(t, u, x[:, 0] + SIGMA_Q * torch.randn(n, generator=g), name="short")


def _reference(
    theta: torch.Tensor, exp: Experiment, tuning: EKFTuning
) -> tuple[torch.Tensor, torch.Tensor]:
    """Innovations ``e`` `(n,)` and variances ``S`` `(n,)` of the 2-state EKF measuring q, for
    the tanh(m) arm with viscous b, θ = [W1, W2, log b, log M] (m = (k − 2) / 2): differentiable
    in θ (module docstring)."""
    m = (theta.shape[0] - 2) // 2
    w1, w2 = theta[:m], theta[m : 2 * m]
    b, inv_mass = theta[2 * m].exp(), (-theta[2 * m + 1]).exp()
    w12 = w1 * w2
    cu = C_M * exp.u
    q1, q2 = tuning.q_state
    (r,) = tuning.r
    h = exp.dt

    def field(v: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """q̈ = (c_m u − b q̇ − Σ W2 tanh(W1 q̇)) / M and its slope ∂q̈/∂q̇."""
        s = torch.tanh(w1 * v)
        acc = (u - b * v - (w2 * s).sum()) * inv_mass
        slope = -(b + (w12 * (1.0 - s * s)).sum()) * inv_mass
        return acc, slope

    es, ss = [], []

    def update(xq, xv, p11, p12, p22, y):  # type: ignore[no-untyped-def]
        # S = p11 + r, e = y − q⁻, K = P Hᵀ / S, x += K e, P −= K S Kᵀ
        s = p11 + r
        e = y - xq
        es.append(e)
        ss.append(s)
        k1, k2 = p11 / s, p12 / s
        return xq + k1 * e, xv + k2 * e, p11 - k1 * p11, p12 - k1 * p12, p22 - k2 * p12

    zero = theta.new_zeros(())
    q = exp.q
    # Sample 0: update only, from x = [q_0, 0] and P = P0_xx = 0 (the paper's known start).
    xq, xv, p11, p12, p22 = update(q[0], zero, zero, zero, zero, q[0])
    for j in range(1, exp.n):
        u = cu[j - 1]
        k1, a1 = field(xv, u)
        v2 = xv + h * k1 / 3.0
        k2, a2 = field(v2, u)
        v3 = xv + h * (k2 - k1 / 3.0)
        k3, a3 = field(v3, u)
        v4 = xv + h * (k1 - k2 + k3)
        k4, a4 = field(v4, u)
        # Variational recursion of the 3/8 rule for Φ's second column (α, β); q enters no stage.
        d2 = 1.0 + h * a1 / 3.0
        d3 = 1.0 + h * (a2 * d2 - a1 / 3.0)
        d4 = 1.0 + h * (a1 - a2 * d2 + a3 * d3)
        al = h * (1.0 + 3.0 * d2 + 3.0 * d3 + d4) / 8.0
        be = 1.0 + h * (a1 + 3.0 * a2 * d2 + 3.0 * a3 * d3 + a4 * d4) / 8.0
        xq = xq + h * (xv + 3.0 * v2 + 3.0 * v3 + v4) / 8.0
        xv = xv + h * (k1 + 3.0 * k2 + 3.0 * k3 + k4) / 8.0
        # P⁻ = Φ P Φᵀ + ½ (Φ Q Φᵀ + Q) dt with Φ = [[1, α], [0, β]], Q = diag(q1, q2)
        t11 = p11 + 2.0 * al * p12 + al * al * p22 + 0.5 * h * (2.0 * q1 + al * al * q2)
        t12 = be * (p12 + al * p22) + 0.5 * h * al * be * q2
        t22 = be * be * p22 + 0.5 * h * (be * be + 1.0) * q2
        xq, xv, p11, p12, p22 = update(xq, xv, t11, t12, t22, q[j])
    return torch.stack(es), torch.stack(ss)


def _gaussian_loglik(e: torch.Tensor, S: torch.Tensor) -> torch.Tensor:
    return -0.5 * (e * e / S + S.log() + LOG_2PI).sum()


def _pseudo_inverse(information: torch.Tensor) -> torch.Tensor:
    """I⁻¹ on unit-diagonal scaling (all eigenvalues are kept in the cases here)."""
    d = torch.diagonal(information).sqrt()
    return torch.linalg.inv(information / (d[:, None] * d[None, :])) / (d[:, None] * d[None, :])


@dataclass(repr=False)  # a failure report prints the fixture: keep the model's repr out of it
class Exact:
    model: ArmModel
    exp: Experiment
    tuning: EKFTuning
    theta: torch.Tensor
    e: torch.Tensor  # innovations of the reference filter
    S: torch.Tensor  # their variances
    De: torch.Tensor  # (n, k) ∂e_t/∂θ by autograd
    scores: torch.Tensor  # (n, k) per-sample score −e ∂e / S
    information: torch.Tensor  # Σ ∂eᵀ∂e / S
    pem: PEMCovariance  # pem_covariance at θ


# A tanh(2) arm whose neurons bend at ≈ 1.4 and 0.25 rad/s, inside the record's velocity range.
TANH2 = ((0.7, 4.0), (0.05, 0.05))


@pytest.fixture(scope="module")
def tanh2() -> Exact:
    model = _tanh_arm(*TANH2)
    exp = _short_record(model, 400, seed=2)
    tuning = _tuning()
    theta = model.get_theta()
    e, S = _reference(theta, exp, tuning)
    De = torch.func.jacrev(lambda th: _reference(th, exp, tuning)[0])(theta)
    scores = -(e / S)[:, None] * De
    information = (De / S[:, None]).T @ De
    pem = pem_covariance(model, [exp], tuning, theta)
    return Exact(model, exp, tuning, theta, e, S, De, scores, information, pem)


# =============================================================================================
# The fixed-θ filter, and the derivatives of its criterion against autograd
# =============================================================================================
def test_innovations_and_loglik_equal_the_independent_filter(tanh2: Exact) -> None:
    c = tanh2
    ((e, S),) = innovations(c.model, [c.exp], c.tuning, c.theta)
    # Same arithmetic up to summation order and Joseph vs. textbook update: rounding only. e is
    # the difference of q ≈ 1 rad and its prediction, so its rounding is ~1e-16 rad absolute.
    torch.testing.assert_close(e, c.e, rtol=0.0, atol=1e-9 * float(c.e.abs().max()))
    torch.testing.assert_close(S, c.S, rtol=1e-12, atol=0.0)
    lik = fixed_theta_loglik(c.model, [c.exp], c.tuning, c.theta[None])
    torch.testing.assert_close(lik.total[0], _gaussian_loglik(c.e, c.S), rtol=1e-9, atol=0.0)
    torch.testing.assert_close(lik.blocks.sum(1), lik.total, rtol=1e-12, atol=0.0)
    assert lik.samples == c.exp.n and bool(lik.ok.all())
    # Several θ in one batch: each row is its own filter (a second θ ≈ 1 σ away in W1, b).
    other = c.theta + torch.tensor([0.05, -0.3, 0.002, -0.001, 0.1, 0.002])
    both = fixed_theta_loglik(c.model, [c.exp], c.tuning, torch.stack([c.theta, other]))
    expected = torch.stack([_gaussian_loglik(c.e, c.S), _gaussian_loglik(*_reference(other, c.exp, c.tuning))])  # fmt: skip
    torch.testing.assert_close(both.total, expected, rtol=1e-9, atol=0.0)
    # pem_covariance's criterion: −½ Σ e²/S.
    assert c.pem.loglik == pytest.approx(float(-0.5 * (c.e**2 / c.S).sum()), rel=1e-9)
    assert c.pem.samples == c.exp.n


def test_a_trial_steps_filter_is_the_covariance_base_bit_for_bit(tanh2: Exact) -> None:
    """`pem_refine` takes a trial step's innovations, filtered in a batch of trials, as the
    base of the covariance at that step (it does not filter them again): they are the numbers
    of that θ's own filter, so the covariance is the same to the last bit."""
    from torchfric.estimators.covariance import _loglik

    c = tanh2
    trials = c.theta + torch.tensor([[0.01, -0.02, 0.0, 0.001, 0.0, 0.0], [0.0] * 6,
                                     [0.02, 0.0, 0.001, 0.0, -0.01, 0.0]])  # fmt: skip
    ll, none = _loglik(c.model, [c.exp], c.tuning, trials, 1.0, 1.0, None)  # above = inf
    assert none is None and float(ll[1]) > float(ll[0])  # the middle row (θ̂) is the likeliest
    _, first = _loglik(c.model, [c.exp], c.tuning, trials, 1.0, 1.0, None, above=float(ll[0]))
    assert first is not None and torch.equal(first[0][0], innovations(c.model, [c.exp], c.tuning, trials[1])[0][0])  # fmt: skip
    again = pem_covariance(c.model, [c.exp], c.tuning, trials[1])
    reused = pem_covariance(c.model, [c.exp], c.tuning, trials[1], base=first)
    for name in ("information", "gradient", "cov", "score_cov"):
        assert torch.equal(getattr(again, name), getattr(reused, name)), name
    assert again.loglik == reused.loglik


def test_information_is_the_gauss_newton_matrix_of_the_exact_sensitivities(tanh2: Exact) -> None:
    c = tanh2
    exact, fd = c.information, c.pem.information
    d = torch.diagonal(exact).sqrt()
    # Central first differences with h = 1e-4 max(|θ|, 1) err by (h²/6) ∂³e ≈ 1e-8 relative
    # (measured: 1.7e-8 in norm, 7e-8 on the unit-diagonal scaled matrix): 1e-6 and 1e-5.
    assert float(torch.linalg.matrix_norm(fd - exact) / torch.linalg.matrix_norm(exact)) < 1e-6
    assert float(((fd - exact) / (d[:, None] * d[None, :])).abs().max()) < 1e-5
    torch.testing.assert_close(fd, fd.T, rtol=1e-14, atol=0.0)
    assert float(torch.linalg.eigvalsh(fd).min()) > 0.0  # Gauss–Newton: PSD by construction
    torch.testing.assert_close(c.pem.steps, 1e-4 * c.theta.abs().clamp_min(1.0))


def test_gauss_newton_information_approximates_the_observed_curvature(tanh2: Exact) -> None:
    """The Newton step uses ``Σ ∂eᵀ∂e / S`` for ``−∇²(−½ Σ e²/S)``; they differ by
    ``Σ e ∂²e / S`` and the θ-dependence of S, terms of mean ≈ 0 at the truth."""
    c = tanh2
    hess = torch.autograd.functional.hessian(
        lambda th: (lambda e, S: -0.5 * (e * e / S).sum())(*_reference(th, c.exp, c.tuning)),
        c.theta,
        vectorize=True,
    )
    observed, gn = -hess, c.pem.information
    d = torch.diagonal(observed).sqrt()
    # Measured: 1e-4 relative on the well-determined entries (W2, log M), which dominate the
    # norm, and up to 10 % (scaled) on the second neuron's W1, a short record's weakest
    # direction, where the residual terms are a sampling fluctuation of ~1/sqrt(its information).
    assert (
        float(torch.linalg.matrix_norm(gn - observed) / torch.linalg.matrix_norm(observed)) < 1e-2
    )
    assert float(((gn - observed) / (d[:, None] * d[None, :])).abs().max()) < 0.25


def test_gradient_matches_autograd(tanh2: Exact) -> None:
    c = tanh2
    # autograd's gradient of −½ Σ e(θ)²/S with the weights 1/S held at θ's (pem's score)
    theta = c.theta.clone().requires_grad_(True)
    e, _ = _reference(theta, c.exp, c.tuning)
    (grad,) = torch.autograd.grad(-0.5 * (e * e / c.S).sum(), theta)
    torch.testing.assert_close(grad, c.scores.sum(0), rtol=1e-10, atol=0.0)
    # Truncation ≈ 1e-8 relative (measured 2e-8 in norm): 1e-6.
    assert float((c.pem.gradient - grad).norm() / grad.norm()) < 1e-6


def test_samples_left_out_of_the_criterion_are_not_in_its_sums(tanh2: Exact) -> None:
    """`moving`: the masked samples' innovations are 0 and the rest unchanged bit for bit, so
    ℓ, the information and the gradient are the exact ones summed over the kept samples; an
    all-True mask is no mask."""
    c = tanh2
    keep = torch.ones(c.exp.n, dtype=torch.bool)
    keep[100:180] = False
    keep[300:] = False
    ((e_all, _),) = innovations(c.model, [c.exp], c.tuning, c.theta)
    ((e, S),) = innovations(c.model, [c.exp], c.tuning, c.theta, moving=[keep])
    assert bool((e[~keep] == 0).all()) and torch.equal(e[keep], e_all[keep])
    (e1, _), (e2, _) = innovations(c.model, [c.exp, c.exp], c.tuning, c.theta, moving=[keep, ~keep])
    assert torch.equal(e1, e) and torch.equal(e2, torch.where(keep, 0.0, e_all))  # each its own
    pem = pem_covariance(c.model, [c.exp], c.tuning, c.theta, moving=[keep])
    w = keep.to(torch.float64)
    assert pem.loglik == pytest.approx(float(-0.5 * (w * c.e**2 / c.S).sum()), rel=1e-9)
    info = (c.De * (w / c.S)[:, None]).T @ c.De
    assert (
        float(torch.linalg.matrix_norm(pem.information - info) / torch.linalg.matrix_norm(info))
        < 1e-6
    )
    grad = (c.scores * w[:, None]).sum(0)
    assert float((pem.gradient - grad).norm() / grad.norm()) < 1e-6
    assert not torch.allclose(pem.cov, c.pem.cov, rtol=1e-3)  # the left-out samples mattered
    whole = pem_covariance(c.model, [c.exp], c.tuning, c.theta, moving=[torch.ones_like(keep)])
    assert torch.equal(whole.cov, c.pem.cov) and whole.loglik == c.pem.loglik


def test_newton_step_matches_the_exact_one(tanh2: Exact) -> None:
    c = tanh2
    # The scaled information's smallest eigenvalue is 2e-4 here (the steep neuron's W1 against
    # b): a 1e-8 error of I moves the step by ~1e-6 relative (measured 1.1e-6): 1e-4.
    exact = _pseudo_inverse(c.information) @ c.scores.sum(0)
    assert float((c.pem.newton - exact).norm() / exact.norm()) < 1e-4
    sigma = torch.diagonal(_pseudo_inverse(c.information)).sqrt()
    assert float(((c.pem.newton - exact) / sigma).abs().max()) < 1e-4
    # I is well inside CONDITION_LIMIT: the step is the plain solve.
    torch.testing.assert_close(
        c.pem.newton, torch.linalg.solve(c.pem.information, c.pem.gradient), rtol=1e-6, atol=0.0
    )


def test_score_covariance_and_sandwich_match_exact_block_scores(tanh2: Exact) -> None:
    c = tanh2
    # Default blocks: about BLOCKS of them over all samples (here 400 // 256 = 1 sample each).
    size = max(1, c.exp.n // BLOCKS)
    blocks = torch.stack([part.sum(0) for part in torch.split(c.scores, size)])
    J, bandwidth = long_run_covariance(blocks)
    assert (c.pem.blocks, c.pem.bandwidth) == (blocks.shape[0], bandwidth)
    torch.testing.assert_close(c.pem.score_cov, J, rtol=0.0, atol=1e-6 * float(J.abs().max()))
    inv = _pseudo_inverse(c.information)
    cov = inv @ J @ inv
    # I⁻¹ multiplies the 1e-8 errors by the condition number (measured 1e-7 in norm): 1e-4.
    error = torch.linalg.matrix_norm(c.pem.cov - cov) / torch.linalg.matrix_norm(cov)
    assert float(error) < 1e-4
    torch.testing.assert_close(c.pem.cov, c.pem.cov.T, rtol=0.0, atol=0.0)
    torch.testing.assert_close(c.pem.std, torch.diagonal(cov).sqrt(), rtol=1e-3, atol=0.0)
    torch.testing.assert_close(c.pem.newton_sigma, c.pem.newton / c.pem.std)
    # An explicit block length: 20 blocks of 20 samples (more than 2k = 12), the same gradient.
    pem = pem_covariance(c.model, [c.exp], c.tuning, c.theta, block=20)
    blocks = torch.stack([c.scores[i : i + 20].sum(0) for i in range(0, c.exp.n, 20)])
    J, bandwidth = long_run_covariance(blocks)
    assert (pem.blocks, pem.bandwidth) == (20, bandwidth)
    torch.testing.assert_close(pem.score_cov, J, rtol=0.0, atol=1e-6 * float(J.abs().max()))
    torch.testing.assert_close(pem.gradient, c.pem.gradient, rtol=1e-12, atol=0.0)


# =============================================================================================
# Identifiability
# =============================================================================================
def _coulomb_arm(estimate_c_m: bool = False) -> ArmModel:
    return ArmModel(
        CoulombFriction(fc=0.1, eps=0.05),
        inertia=0.03,
        viscous=0.02,
        c_m=C_M,
        estimate_c_m=estimate_c_m,
    )


def _rich_records(model: ArmModel, n: int, records: int, seed: int = 0) -> list[Experiment]:
    """`records` records of `n` samples from rest: two sines under a slow envelope (|q̇| from
    ≈ 0.1 to 7 rad/s, so Coulomb and viscous friction separate), input and measurement noise
    independent per record."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n, dtype=torch.float64) * DT
    env = 0.25 + 0.75 * (0.5 + 0.5 * torch.sin(2 * math.pi * 0.35 * t)) ** 3
    sines = torch.sin(2 * math.pi * 1.3 * t) + 0.6 * torch.sin(2 * math.pi * 4.7 * t + 1)
    u = (1.5 * env * sines)[:, None] + 0.15 * torch.randn(n, records, generator=g)
    with torch.no_grad():
        x = simulate(model, t, u, torch.zeros(records, 2), substeps=2, engine="compiled")
    return [
        make_experiment(t, u[:, s], x[:, s, 0] + SIGMA_Q * torch.randn(n, generator=g))
        for s in range(records)
    ]


def test_unidentifiable_motor_constant_is_named() -> None:
    model = _coulomb_arm(estimate_c_m=True)
    assert model.theta_names == ["Fc", "viscous", "inertia", "c_m"]
    (exp,) = _rich_records(model, 20_000, 1, seed=5)
    pem = pem_covariance(model, [exp], _tuning(), model.get_theta())
    ident = pem.identifiability
    assert not ident.ok
    # Scaling c_m, M, b and Fc by one factor leaves q unchanged: in log coordinates the exact
    # null direction is (1, 1, 1, 1), whose scaled components are largest for c_m and M.
    assert any({"c_m", "inertia"} <= set(names) for names, _ in ident.groups)
    assert any("c_m" in m and "inertia" in m for m in ident.messages)
    null = torch.full((4,), 0.5)  # the unit vector (1, 1, 1, 1)/2 in θ
    # Along it, ∂e/∂θ · null = 0 up to the differences' truncation (1e-8): I's curvature there
    # is ~1e-16 of its largest (measured 2e-17).
    curvature = float(null @ pem.information @ null)
    assert abs(curvature) < 1e-10 * float(torch.linalg.eigvalsh(pem.information).max())
    assert ident.to_dict()["ok"] is False and ident.to_dict()["messages"] == ident.messages


def test_well_posed_model_on_rich_data_is_not_flagged() -> None:
    model = _coulomb_arm()
    (exp,) = _rich_records(model, 20_000, 1, seed=5)
    pem = pem_covariance(model, [exp], _tuning(), model.get_theta())
    assert not any("inertia" in names for names, _ in pem.identifiability.groups)
    assert pem.identifiability.ok, pem.identifiability.messages  # measured |ρ| ≤ 0.88
    assert pem.blocks == math.ceil(20_000 / (20_000 // BLOCKS)) and pem.bandwidth >= 1
    assert bool((pem.std > 0).all())


def _covariance(std: list[float], corr: list[list[float]]) -> torch.Tensor:
    s = torch.tensor(std, dtype=torch.float64)
    return torch.tensor(corr, dtype=torch.float64) * s[:, None] * s[None, :]


def test_identifiability_of_a_correlated_pair() -> None:
    # Very different scales, so that only the scaled matrices can be right.
    cov = _covariance([1e-3, 5.0, 2e2], [[1.0, 0.995, 0.0], [0.995, 1.0, 0.0], [0.0, 0.0, 1.0]])
    ident = identifiability(torch.linalg.inv(cov), cov, ["a", "b", "c"])
    assert len(ident.pairs) == 1
    a, b, rho = ident.pairs[0]
    assert (a, b) == ("a", "b") and rho == pytest.approx(0.995, abs=1e-12)
    # The scaled information's eigenvalues are 1/(1 ± ρ) and 1: condition 400, no null direction.
    assert ident.directions == []
    assert [names for names, _ in ident.groups] == [["a", "b"]]
    assert len(ident.messages) == 1 and ident.messages[0].startswith("a and b are not")
    # Just below the limit nothing is reported.
    cov2 = _covariance([1.0, 1.0], [[1.0, 0.98], [0.98, 1.0]])
    assert identifiability(torch.linalg.inv(cov2), cov2, ["a", "b"]).ok
    assert CORRELATION_LIMIT == 0.99


def test_identifiability_joins_pairs_into_groups() -> None:
    # Two independent collinear pairs → two groups; a chain a–b–c → one group of three.
    cov = _covariance([1.0, 2.0, 3.0, 4.0], [[1.0, 0.995, 0.0, 0.0], [0.995, 1.0, 0.0, 0.0],
                                               [0.0, 0.0, 1.0, -0.999], [0.0, 0.0, -0.999, 1.0]])  # fmt: skip
    ident = identifiability(torch.linalg.inv(cov), cov, ["a", "b", "c", "d"])
    assert sorted(sorted(n) for n, _ in ident.groups) == [["a", "b"], ["c", "d"]]
    chain = _covariance([1.0, 1.0, 1.0], [[1.0, 0.995, 0.991], [0.995, 1.0, 0.995], [0.991, 0.995, 1.0]])  # fmt: skip
    assert float(torch.linalg.eigvalsh(chain).min()) > 0
    groups = identifiability(torch.linalg.inv(chain), chain, ["a", "b", "c"]).groups
    assert len(groups) == 1 and sorted(groups[0][0]) == ["a", "b", "c"]
    assert "0.9950" in groups[0][1]


def test_identifiability_names_a_null_direction_of_the_information() -> None:
    # I = D (1 − v vᵀ) D: exactly singular along D⁻¹ v. In the unit-diagonal scaling the null
    # vector's components are v_i sqrt(1 − v_i²): a, b and c large, d negligible (< 0.2 × max).
    v = torch.tensor([1.0, -1.0, 0.8, 0.01])
    v = v / v.norm()
    D = torch.diag(torch.tensor([1e-3, 1.0, 30.0, 1e6]))
    information = D @ (torch.eye(4) - torch.outer(v, v)) @ D
    names = ["a", "b", "c", "d"]
    ident = identifiability(information, torch.eye(4), names)
    assert ident.pairs == []
    assert len(ident.directions) == 1
    picked, relative = ident.directions[0]
    assert set(picked) == {"a", "b", "c"} and picked[-1] == "c"  # largest components first
    assert abs(relative) < CONDITION_LIMIT
    assert [set(n) for n, _ in ident.groups] == [{"a", "b", "c"}]
    assert "relative information" in ident.groups[0][1]
    # A well-conditioned information has no null direction.
    assert identifiability(D @ D, torch.eye(4), names).ok


def test_an_offset_keeps_only_what_the_information_determines() -> None:
    # Two estimates of one run (the filter's kept pass, the polish's end) can differ along a
    # direction the data do not determine by anything at all: there the likelihood is flat and
    # the polish walks freely (log b moved by 4e138 on a ball-screw table, its σ then ±5e140).
    # `determined` keeps the offset's part that the information sees: I⁺ I offset, the
    # identity on the determined directions, zero along a null one and on a held entry.
    from torchfric.estimators.sandwich import Identifiability

    v = torch.tensor([1.0, -1.0, 0.8, 0.01], dtype=torch.float64)
    v = v / v.norm()
    d = torch.tensor([1e-3, 1.0, 30.0, 1e6, 2.0], dtype=torch.float64)
    information = torch.zeros(5, 5, dtype=torch.float64)
    scale = torch.diag(d[:4])
    information[:4, :4] = scale @ (torch.eye(4, dtype=torch.float64) - torch.outer(v, v)) @ scale
    information[4, 4] = 3.0 * d[4] ** 2
    information[0, 4] = information[4, 0] = 0.1 * d[0] * d[4]  # the held entry is coupled
    zero = torch.zeros(5, dtype=torch.float64)
    pem = PEMCovariance(theta=zero, cov=torch.eye(5, dtype=torch.float64), information=information,
                        score_cov=information, gradient=zero, newton=zero, loglik=0.0, samples=1,
                        blocks=1, bandwidth=1, names=["a", "b", "c", "d", "e"],
                        identifiability=Identifiability(held=["e"]))  # fmt: skip
    null = torch.cat([v / d[:4], torch.zeros(1, dtype=torch.float64)])  # null among the free
    assert float((information[:4, :4] @ null[:4]).abs().max()) < 1e-12
    seen = torch.cat([torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64) / d[:4],
                      torch.zeros(1, dtype=torch.float64)])  # ⟂ v once scaled  # fmt: skip
    torch.testing.assert_close(pem.determined(seen), seen, rtol=1e-12, atol=1e-15)
    assert float(pem.determined(1e138 * null).abs().max()) < 1e138 * 1e-12
    held = torch.tensor([0.0, 0.0, 0.0, 0.0, 7.0], dtype=torch.float64)
    assert pem.determined(held).tolist() == [0.0] * 5
    mixed = pem.determined(seen + 5.0 * null + held)
    torch.testing.assert_close(mixed, seen, rtol=1e-9, atol=1e-12)


def test_a_slope_pinned_at_its_floor_is_held_and_the_rest_keep_finite_sigma() -> None:
    # A neuron whose input weight sits on its floor (W1 = min_slope: the data would take it
    # lower) no longer moves with its stored r (slope sigmoid(r/lo) = 0). Inverted with the
    # rest, its variance in θ was 1e283 on a 20-minute record and the curve's band ±5e53 N m.
    # Held: its row and column are zero, and the others' covariance is the sandwich of the
    # sub-problem without it (information and score covariance restricted to the free entries).
    lo = 0.5
    model = ArmModel(
        OddTanhFriction(2, w1=[1.0, 20.0], w2=[0.05, 0.1], min_slope=lo),
        inertia=0.03, viscous=0.01, c_m=C_M,
    )  # fmt: skip
    theta = model.get_theta()
    theta[0] = -100.0 * lo  # r/lo = -100: W1[1] = lo (1 + 4e-44)
    model.set_theta(theta)
    assert model.friction.flat_bounded().tolist() == [True, True, False, False]
    exp = _short_record(model, 20_000, seed=3)
    pem = pem_covariance(model, [exp], _tuning(), model.get_theta())
    assert pem.identifiability.held == ["W1[1]"] and not pem.identifiability.ok
    assert any(m.startswith("W1[1] sits at its lower bound") for m in pem.identifiability.messages)
    assert pem.identifiability.to_dict()["held_at_bound"] == ["W1[1]"]
    assert not any("W1[1]" in names for names, _ in pem.identifiability.directions)
    assert bool((pem.cov[0] == 0).all()) and bool((pem.cov[:, 0] == 0).all())
    free = torch.tensor([False, True, True, True, True, True])
    inv = torch.linalg.inv(pem.information[free][:, free])
    expected = inv @ pem.score_cov[free][:, free] @ inv
    torch.testing.assert_close(pem.cov[free][:, free], expected, rtol=1e-6, atol=0.0)
    assert float(pem.newton[0]) == 0.0  # the polish's Newton step does not move it either
    # The curve's band stays on the scale of the friction (≤ 0.15 N m here), not 1e50.
    from torchfric.estimators.uncertainty import friction_band

    _, std = friction_band(model, pem.cov, torch.linspace(-2.5, 2.5, 11))
    assert bool(torch.isfinite(std).all()) and float(std.max()) < 0.01


def test_a_neuron_that_is_a_step_at_every_moving_speed_is_held() -> None:
    # W1[2] = 400 rad⁻¹ s: its tanh has risen to 0.99991 by 12.5 mrad/s. Above a stick speed of
    # 0.02 rad/s every sample the criterion keeps sees a step; how steep it is shows only in
    # rounding-sized, sample-by-sample changes of ℓ (the polish walked such a weight to 2·10⁵
    # and its σ moved 3.7× with a 1e-12 change of θ). Held: no σ, no Newton step, named.
    from torchfric.estimators.sandwich import STEEP_LIMIT, held_entries

    model = ArmModel(
        OddTanhFriction(2, w1=[1.0, 400.0], w2=[0.05, 0.1], min_slope=0.5),
        inertia=0.03, viscous=0.01, c_m=C_M,
    )  # fmt: skip
    theta = model.get_theta()
    speed = 0.02
    floor, steep = held_entries(model, theta, speed)
    assert not floor.any() and steep.tolist() == [False, True, False, False, False, False]
    assert not held_entries(model, theta)[1].any()  # without a stick speed: none
    edge = STEEP_LIMIT / float(model.to_physical(theta)[1])  # the speed at which it turns
    assert not held_entries(model, theta, 0.999 * edge)[1].any()
    assert held_entries(model, theta, 1.001 * edge)[1][1]
    exp = _short_record(model, 20_000, seed=4)
    pem = pem_covariance(model, [exp], _tuning(), theta, stick_speed=speed)
    ident = pem.identifiability
    assert ident.steep == ["W1[2]"] and ident.held == [] and not ident.ok
    assert ident.to_dict()["held_steep"] == ["W1[2]"]
    assert any(m.startswith("W1[2] makes its neuron a step") for m in ident.messages)
    assert bool((pem.cov[1] == 0).all()) and float(pem.newton[1]) == 0.0
    free = torch.tensor([True, False, True, True, True, True])
    inv = torch.linalg.inv(pem.information[free][:, free])
    torch.testing.assert_close(pem.cov[free][:, free], inv @ pem.score_cov[free][:, free] @ inv,
                               rtol=1e-6, atol=0.0)  # fmt: skip
    free_run = pem_covariance(model, [exp], _tuning(), theta)
    assert free_run.identifiability.steep == [] and float(free_run.cov[1, 1]) > 0


# =============================================================================================
# Long-run score covariance
# =============================================================================================
def _bartlett_direct(scores: torch.Tensor, L: int, segment: torch.Tensor) -> torch.Tensor:
    """``B/(B−1) Σ_{s,t} w(|s−t|) c_s c_tᵀ`` with ``w(l) = max(0, 1 − l/(L+1))`` over block
    pairs of the same experiment, ``c`` the blocks centred on their overall mean."""
    B = scores.shape[0]
    c = scores - scores.mean(0)
    lag = (torch.arange(B)[:, None] - torch.arange(B)[None, :]).abs()
    w = (1.0 - lag / (L + 1.0)).clamp_min(0.0) * (segment[:, None] == segment[None, :])
    return c.T @ w @ c * (B / (B - 1))


def _andrews_lags(scores: torch.Tensor) -> int:
    """Andrews (1991) AR(1) plug-in for the Bartlett kernel, one experiment: per column
    ρ̂ = Σ c_{t+1} c_t / Σ c_t², α̂ = mean of 4ρ̂² / ((1 − ρ̂)² (1 + ρ̂)²), lags ⌊1.1447 (α̂ B)^⅓⌋."""
    B = scores.shape[0]
    c = scores - scores.mean(0)
    rho = (c[1:] * c[:-1]).sum(0) / (c * c).sum(0)
    alpha = float((4 * rho**2 / ((1 - rho) ** 2 * (1 + rho) ** 2)).mean())
    return math.floor(1.1447 * (alpha * B) ** (1.0 / 3.0))


def _ar1_rows(e: torch.Tensor, phi: float):  # type: ignore[no-untyped-def]
    x = torch.zeros_like(e[0])
    for row in e:
        x = phi * x + row
        yield x


def test_long_run_covariance_equals_its_formula() -> None:
    g = torch.Generator().manual_seed(3)
    for B in (2, 3, 7, 150, 1000):
        # an AR(1) series (φ = 0.6), so that the bandwidth rule has lags to choose
        e = torch.randn(B, 3, generator=g)
        scores = torch.stack(list(_ar1_rows(e, 0.6)))
        J, L = long_run_covariance(scores)
        assert 1 <= L <= max(1, B // 4)
        if B >= 150:
            assert L == min(B // 4, max(1, _andrews_lags(scores)))
        torch.testing.assert_close(J, _bartlett_direct(scores, L, torch.zeros(B)))
        J1, L1 = _bartlett(scores)  # the one-experiment form
        torch.testing.assert_close(J1, J, rtol=0.0, atol=0.0)
        assert L1 == L
        # The Bartlett kernel keeps J positive semi-definite.
        assert float(torch.linalg.eigvalsh(J).min()) > -1e-12 * float(J.abs().max())
    # Two experiments: no products across their boundary.
    scores = torch.randn(200, 2, generator=g)
    segment = torch.cat([torch.zeros(120), torch.ones(80)]).long()
    J, L = long_run_covariance(scores, segment)
    torch.testing.assert_close(J, _bartlett_direct(scores, L, segment))


def test_long_run_covariance_of_iid_blocks_is_the_sum_of_their_variances() -> None:
    g = torch.Generator().manual_seed(0)
    A = torch.tensor([[1.0, 0.0, 0.0], [0.5, 2.0, 0.0], [-0.3, 0.4, 0.7]])
    sigma = A @ A.T
    B = 20_000
    J, L = long_run_covariance(torch.randn(B, 3, generator=g) @ A.T)
    # White blocks: ρ̂ ~ 1/sqrt(B), so α̂ B = O(1) and the plug-in keeps a lag or two.
    assert 1 <= L <= 3
    # Each entry of J/B has a standard error ≈ sqrt(Σ_ii Σ_jj (1 + 2 Σ_l w_l²) / B) ≈ 0.01 of
    # sqrt(Σ_ii Σ_jj); 0.05 is 5 standard errors.
    s = torch.diagonal(sigma).sqrt()
    assert float(((J / B - sigma) / (s[:, None] * s[None, :])).abs().max()) < 0.05


def test_long_run_covariance_of_an_ar1_series_approaches_the_long_run_variance() -> None:
    rng = np.random.default_rng(0)
    phi, B = 0.5, 100_000
    x = scipy.signal.lfilter([1.0], [1.0, -phi], rng.standard_normal(B))
    J, L = long_run_covariance(torch.as_tensor(x)[:, None])
    # Andrews' rule for φ = 0.5: α = 4φ²/((1−φ)²(1+φ)²) = 16/9, 1.1447 (α B)^⅓ = 64.3.
    assert abs(L - 64) <= 3
    long_run = 1.0 / (1.0 - phi) ** 2  # σ² / (1 − φ)², σ² = 1
    # What the kernel estimates at this bandwidth: γ_0 + 2 Σ_{l ≤ L} (1 − l/(L+1)) γ_l with
    # γ_l = φ^l / (1 − φ²) — 2 % below the long-run variance (Bartlett's bias at L ≈ 64).
    gamma = [phi**lag / (1.0 - phi**2) for lag in range(L + 1)]
    kernel = gamma[0] + 2.0 * sum((1.0 - lag / (L + 1.0)) * gamma[lag] for lag in range(1, L + 1))
    # Sampling error of J/B ≈ LRV · sqrt(4L/(3B)) ≈ 3 %: 10 % is 3 standard errors.
    assert float(J[0, 0]) / B == pytest.approx(kernel, rel=0.1)
    assert float(J[0, 0]) / B == pytest.approx(long_run, rel=0.15)


# =============================================================================================
# Coverage
# =============================================================================================
def test_sandwich_two_sigma_covers_the_true_inertia() -> None:
    """20 independent records (20 000 samples each) of a Coulomb + viscous arm; θ̂ by 3 Newton
    steps (θ ← θ + newton) from the truth perturbed by 0.05 in log Fc, log b and 0.02 in log M
    (hundreds of σ); is the true inertia within ±2σ̂?

    Measured with the default blocks (≈ 256 of 78 samples, 7–9 Bartlett lags): 20/20 inside for
    every parameter; RMS of (θ̂ − θ)/σ̂ is 0.82 (Fc), 0.74 (b) and 0.51 (M) with the sandwich,
    but 0.03–0.07 with ``sqrt((I⁻¹)_ii)`` alone (the filter's Q_q̇ = 1e-3 tells it the data are
    far less informative than they are). If σ̂ were right the count would be about
    Binomial(20, 0.95): P(≤ 13) < 1e-3. The RMS band [0.3, 2] rejects a σ̂ as far too wide as
    I⁻¹ alone is here, and one too narrow; it does not pin the sandwich's own conservatism here
    (σ̂ of M ≈ 1.9× the spread of θ̂ over 40 records at the default blocks, 1.07× with
    ``block=1000``).
    """
    model = _coulomb_arm()
    truth = model.get_theta()
    tuning = _tuning()
    inertia = model.theta_names.index("inertia")
    z, inside = [], 0
    for exp in _rich_records(model, 20_000, 20, seed=0):
        theta = truth + torch.tensor([0.05, -0.05, 0.02])
        pem = pem_covariance(model, [exp], tuning, theta)
        trace = [pem.loglik]
        for _ in range(3):
            theta = theta + pem.newton
            pem = pem_covariance(model, [exp], tuning, theta)
            trace.append(pem.loglik)
        # The steps reached the criterion's maximum: each raised it, the last moves < 0.01 σ.
        assert all(b >= a - 1e-6 for a, b in zip(trace, trace[1:], strict=False)), trace
        assert float(pem.newton_sigma.abs().max()) < 1e-2
        zi = float((theta[inertia] - truth[inertia]) / pem.std[inertia])
        z.append(zi)
        inside += abs(zi) <= 2.0
    rms = math.sqrt(sum(x * x for x in z) / len(z))
    assert inside >= 14, (inside, z)
    assert 0.3 < rms < 2.0, (rms, z)


# =============================================================================================
# Former defects: too few blocks are refused
# =============================================================================================
def test_one_block_does_not_report_zero_sigma(tanh2: Exact) -> None:
    """One block (an explicit `block` ≥ the record) would give J = 0 and σ = 0: refused."""
    with pytest.raises(TorchfricError, match="too few to measure"):
        pem_covariance(tanh2.model, [tanh2.exp], tanh2.tuning, tanh2.theta, block=1000)


def test_few_blocks_give_a_nonsingular_sandwich() -> None:
    model = _coulomb_arm()
    (exp,) = _rich_records(model, 3_000, 1, seed=5)
    """B ≤ 2k blocks leave J singular (rank ≤ B − 1): refused rather than a singular sandwich;
    the default blocks give a well-conditioned one on the same record."""
    with pytest.raises(TorchfricError, match="too few to measure"):
        pem_covariance(model, [exp], _tuning(), model.get_theta(), block=1000)
    pem = pem_covariance(model, [exp], _tuning(), model.get_theta())
    assert float(torch.linalg.eigvalsh(pem.correlation).min()) > 1e-3, pem.correlation


def test_damped_steps_ascend_and_shorten_towards_the_gradient() -> None:
    """`pem_refine`'s fallback when no fraction of the Gauss–Newton step raises ℓ: each
    Levenberg–Marquardt step is an ascent direction, shorter as λ grows and further from the
    Gauss–Newton step (the lightest, λ = 0.01, within 10 % of it here: 6.5 %)."""
    from types import SimpleNamespace

    from torchfric.estimators.covariance import _damped_steps

    gen = torch.Generator().manual_seed(3)
    A = torch.randn(5, 5, generator=gen, dtype=torch.float64)
    info = A @ A.T + 0.5 * torch.eye(5, dtype=torch.float64)
    info = info * torch.tensor([1e6, 1.0, 1e-3, 10.0, 1e2], dtype=torch.float64).sqrt().outer(
        torch.tensor([1e6, 1.0, 1e-3, 10.0, 1e2], dtype=torch.float64).sqrt()
    )  # parameters in very different units, as θ's are
    grad = torch.randn(5, generator=gen, dtype=torch.float64)
    names = [f"p{i}" for i in range(5)]
    cov = SimpleNamespace(information=info, gradient=grad, names=names,
                          identifiability=SimpleNamespace(held=[], steep=[]))  # fmt: skip
    steps = _damped_steps(cov)
    assert all(float(grad @ s) > 0 for s in steps)
    scale = torch.diagonal(info).sqrt()  # lengths in the parameters' own units
    lengths = [float((s * scale).norm()) for s in steps]
    assert lengths == sorted(lengths, reverse=True)
    newton = torch.linalg.solve(info, grad)
    away = [float((s - newton).norm() / newton.norm()) for s in steps]
    assert away == sorted(away) and away[0] < 0.1
    # An entry held at its bound stays; the others take the steps of the problem without it.
    cov.identifiability.held = ["p2"]
    free = torch.tensor([True, True, False, True, True])
    sub = info[free][:, free]
    for lam, step in zip((1e-2, 1e-1, 1.0, 10.0, 100.0), _damped_steps(cov), strict=True):
        assert float(step[2]) == 0.0
        expected = torch.linalg.solve(sub + lam * torch.diag(torch.diagonal(sub)), grad[free])
        torch.testing.assert_close(step[free], expected)


def test_the_polish_never_steps_to_the_search_bound(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """`pem_refine` on a quadratic ℓ whose optimum lies beyond half the θ box (where a run
    flags a parameter "at a bound"): every step it takes stays inside and still raises ℓ; with
    a box that holds the optimum, the same steps reach it."""
    from types import SimpleNamespace

    from torchfric.estimators import covariance

    info = torch.tensor([[4.0, 1.0], [1.0, 2.0]], dtype=torch.float64)
    best = torch.tensor([0.5, 30.0], dtype=torch.float64)

    def loglik(theta):  # type: ignore[no-untyped-def]
        d = theta - best
        return float(-0.5 * d @ info @ d)

    def at(theta):  # type: ignore[no-untyped-def]
        grad = -info @ (theta - best)
        newton = torch.linalg.solve(info, grad)
        return SimpleNamespace(theta=theta, loglik=loglik(theta), gradient=grad, newton=newton,
                               information=info, cov=torch.linalg.inv(info), names=["a", "b"],
                               identifiability=SimpleNamespace(held=[], steep=[]))  # fmt: skip

    monkeypatch.setattr(covariance, "pem_covariance", lambda m, e, t, theta, **kw: at(theta))
    monkeypatch.setattr(covariance, "_loglik",
                        lambda m, e, t, thetas, q, r, moving, above: (torch.tensor([loglik(x) for x in thetas]), None))  # fmt: skip
    start = torch.tensor([0.0, 1.0], dtype=torch.float64)
    for bound, reaches in ((1e6, True), (20.0, False)):
        tuning = EKFTuning(theta_bound=bound)
        theta, _, trace = covariance.pem_refine(None, [], tuning, start, iterations=8)
        assert trace == sorted(trace) and len(trace) > 1  # every step taken raised ℓ
        assert bool((theta.abs() < 0.5 * bound).all())
        assert bool(torch.allclose(theta, best)) is reaches


def test_the_noise_model_keeps_the_filters_velocity_from_the_model(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """`noise_model` tries only noise models whose process noise over one sample is at most
    `NOISE_STEP_LIMIT` of the measurement's variance (``q·dt³ ≤ R/100``): a record whose
    machine is shaken by a strong white torque that the record does not hold makes the likelihood prefer a filter that follows
    the encoder sample by sample (above the limit: the assertion on the uncapped grid), and the
    capped grid returns none of those, ranked best first."""
    import torchfric.estimators.covariance as cov

    model = _tanh_arm((40.0,), (0.3,))
    n = 3000
    g = torch.Generator().manual_seed(7)
    t = torch.arange(n, dtype=torch.float64) * DT
    u = torch.sin(2 * math.pi * 4.0 * t)
    shaking = 3.0 * torch.randn(n, generator=g)  # a torque the record does not hold
    with torch.no_grad():
        x = simulate(model, t, u + shaking, torch.zeros(2), substeps=4)
    exp = make_experiment(t, u, x[:, 0] + SIGMA_Q * torch.randn(n, generator=g), name="shaken")
    tuning = _tuning()
    theta = model.theta_vector().detach()

    def step_ratio(q: float, r: float) -> float:
        return q * tuning.q_state[1] * DT**3 / (r * tuning.r[0])

    monkeypatch.setattr(cov, "NOISE_STEP_LIMIT", math.inf)
    uncapped = cov.noise_model(model, [exp], tuning, theta)
    assert step_ratio(*uncapped[0]) > 1e-2  # the likeliest: above the limit
    monkeypatch.setattr(cov, "NOISE_STEP_LIMIT", 1e-2)
    capped = cov.noise_model(model, [exp], tuning, theta)
    assert capped and all(step_ratio(q, r) <= 1e-2 * (1 + 1e-9) for q, r in capped)
    assert capped == [g for g in uncapped if step_ratio(*g) <= 1e-2 * (1 + 1e-9)]
