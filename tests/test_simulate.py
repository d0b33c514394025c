"""Tests of torchfric.models.simulate against closed forms (viscous spin-down, constant torque, the
smooth-Coulomb stop, a frictionless pendulum's energy), the integrators' convergence orders, the
exact zero-order hold, batching, automatic sub-steps, gradients through friction → ODE → loss,
and every bad-input message.

Simulated horizons are kept short: the eager solver costs ~0.75 ms per rk4 step."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.integrate
import torch

from torchfric.accel import native
from torchfric.accel.simulation import rk4_chunk
from torchfric.errors import TorchfricError
from torchfric.models.arm import ArmModel
from torchfric.models.friction import CoulombFriction, OddTanhFriction, PolytopicFriction
from torchfric.models.simulate import (
    ENGINES,
    SOLVERS,
    auto_substeps,
    sample_grid,
    simulate,
)


def _no_black_box(**kwargs) -> ArmModel:
    """Arm whose black-box friction is identically zero (W2 = 0): only the white-box terms act."""
    return ArmModel(OddTanhFriction(1, w1=[1.0], w2=[0.0]), **kwargs)


def _steep_arm(w1: float = 2000.0) -> ArmModel:
    # λ = max |∂q̈/∂q̇| = (b + W1 W2) / M at v = 0.
    return ArmModel(OddTanhFriction(1, w1=[w1], w2=[0.1]), inertia=0.03, viscous=0.01)


# -- closed forms ---------------------------------------------------------------------------------
def test_viscous_spin_down() -> None:
    big_m, b, q0, w0 = 0.1, 0.5, 0.3, 2.0
    arm = _no_black_box(inertia=big_m, viscous=b)
    t = torch.arange(201) * 5e-3
    with torch.no_grad():
        x = simulate(arm, t, torch.zeros(201), torch.tensor([q0, w0]), substeps=2)
    decay = torch.exp(-b * t / big_m)
    expected = torch.stack([q0 + w0 * big_m / b * (1 - decay), w0 * decay], dim=-1)
    # rk4 truncation: R(−z) − e^{−z} ≈ z⁵/120 per step with z = λh = 0.0125, so the global error
    # is ≈ w0 λt e^{−λt} z⁴/120 ≤ 1.5e-10 (at λt = 1).
    torch.testing.assert_close(x, expected, rtol=0.0, atol=3e-10)


def test_constant_torque_without_friction_is_a_parabola() -> None:
    big_m, c_m, u0, offset = 0.2, 2.5, 0.4, 0.3
    arm = _no_black_box(inertia=big_m, viscous=None, c_m=c_m, offset=offset)
    t = torch.arange(101) * 1e-2
    q0, v0 = -0.5, 0.7
    with torch.no_grad():
        x = simulate(arm, t, torch.full((101,), u0), torch.tensor([q0, v0]), substeps=1)
    acc = (c_m * u0 - offset) / big_m
    expected = torch.stack([q0 + v0 * t + 0.5 * acc * t**2, v0 + acc * t], dim=-1)
    # rk4 is exact on a parabola: only rounding is left.
    torch.testing.assert_close(x, expected, rtol=1e-13, atol=1e-13)


def test_constant_torque_with_raw_zero_viscous() -> None:
    # viscous = 0 stored raw (log_positive=False) behaves as no viscous term at all.
    arm = _no_black_box(inertia=0.5, viscous=0.0, c_m=1.0, log_positive=False)
    t = torch.arange(21) * 0.05
    with torch.no_grad():
        x = simulate(arm, t, torch.ones(21), torch.zeros(2), substeps=1)
    torch.testing.assert_close(x[:, 0], t**2, rtol=1e-13, atol=1e-13)  # ½ (1/0.5) t²


def _coulomb_velocity(t: np.ndarray, v0: float, a: float, eps: float) -> np.ndarray:
    # v̇ = −a tanh(v/ε) ⇒ sinh(v/ε) = sinh(v0/ε) e^{−a t/ε}.
    return eps * np.arcsinh(np.sinh(v0 / eps) * np.exp(-a * t / eps))


def test_coulomb_deceleration_to_rest() -> None:
    big_m, fc, eps, v0 = 0.1, 0.3, 1e-2, 1.0
    a = fc / big_m  # deceleration while sliding
    t_stop = v0 * big_m / fc
    arm = ArmModel(CoulombFriction(fc=fc, eps=eps), inertia=big_m, viscous=None)
    t = torch.arange(451) * 1e-3  # stops at 0.333 s; 35 time constants ε/a of rest afterwards
    with torch.no_grad():
        x = simulate(arm, t, torch.zeros(451), torch.tensor([0.0, v0]), substeps=2)
    q, v = x[:, 0].numpy(), x[:, 1].numpy()
    tn = t.numpy()

    # 1. The exact solution of the smoothed model. rk4 truncation peaks in the stiff stop phase
    #    (λ = a/ε = 300 /s, z = λh = 0.15): ≈ ε z⁴/120 ≈ 4e-8, measured 1.1e-8.
    v_exact = _coulomb_velocity(tn, v0, a, eps)
    torch.testing.assert_close(torch.tensor(v), torch.tensor(v_exact), rtol=0.0, atol=5e-8)

    # 2. The ideal Coulomb stop: v = max(v0 − a t, 0). The smooth sign only ever brakes less than
    #    Fc, so the smoothed v lies above the ideal line, by at most ε·asinh(½) ≈ 0.48 ε
    #    (at t_stop).
    gap = v - np.maximum(v0 - a * tn, 0.0)
    assert gap.min() >= -5e-8 and gap.max() <= 0.5 * eps

    # 3. Linear deceleration with slope −Fc/M while sliding (v ≫ ε: tanh(v/ε) = 1 − O(e^{−2v/ε})).
    sliding = tn < t_stop - 10 * eps / a
    slope = np.polyfit(tn[sliding], v[sliding], 1)[0]
    assert slope == pytest.approx(-a, rel=1e-8)

    # 4. Stopping time: v falls through ε at t_stop − ε·ln(2 sinh 1)/a, within ε M / Fc of v0 M/Fc.
    k = int(np.argmax(v < eps))
    t_cross = tn[k - 1] + (v[k - 1] - eps) / (v[k - 1] - v[k]) * (tn[k] - tn[k - 1])
    assert abs(t_cross - t_stop) <= eps / a

    # 5. Distance to rest: q(∞) = (ε²/a) ∫_0^{sinh(v0/ε)} asinh(s)/s ds = v0²/(2a) + π² ε²/(12 a)
    #    up to O(e^{−2 v0/ε}): the smoothing's extra creep, 2.7e-5 here, resolved to 1e-9.
    distance = v0**2 / (2 * a) + math.pi**2 * eps**2 / (12 * a)
    assert q[-1] == pytest.approx(distance, abs=1e-9)
    assert v[-1] == pytest.approx(0.0, abs=1e-12)


def test_frictionless_pendulum_conserves_energy() -> None:
    big_m, g = 0.05, 0.5  # small-angle period 2π √(M/g) ≈ 2 s
    arm = _no_black_box(inertia=big_m, viscous=None, gravity=g)
    t = torch.arange(201) * 1e-2
    with torch.no_grad():
        x = simulate(arm, t, torch.zeros(201), torch.tensor([2.0, 0.0]), substeps=2)
    energy = 0.5 * big_m * x[:, 1] ** 2 + g * (1 - torch.cos(x[:, 0]))
    # rk4 with ω h ≈ 0.016 drifts by ~1e-11 relative over a period.
    torch.testing.assert_close(energy, energy[:1].expand(201), rtol=1e-9, atol=0.0)
    # It swings back through −2 rad: gravity pulls towards q = 0 (the term is −g sin q).
    assert float(x[:, 0].min()) == pytest.approx(-2.0, abs=1e-3)


# -- integrator order -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("method", "order"),
    [("euler", 1), ("midpoint", 2), ("rk4", 4)],
)
def test_convergence_order(method: str, order: int) -> None:
    big_m, b = 0.1, 0.5  # λ = 5 /s; u = 0 so the input hold plays no part
    arm = _no_black_box(inertia=big_m, viscous=b)
    t = torch.arange(51) * 0.02
    x0 = torch.tensor([0.1, 1.5])
    decay = torch.exp(-b * t / big_m)
    exact = torch.stack([x0[0] + x0[1] * big_m / b * (1 - decay), x0[1] * decay], dim=-1)
    errors = []
    for steps in (1, 2, 4):  # λh = 0.1, 0.05, 0.025
        with torch.no_grad():
            x = simulate(arm, t, torch.zeros(51), x0, method=method, substeps=steps)
        errors.append(float((x - exact).abs().max()))
    # Halving h divides the global error by 2^order (measured 2.04/2.02, 4.16/4.08, 16.7/16.3);
    # the bands (±10 %, ±12 %, ±25 %) allow for the O(h) pre-asymptotic term.
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    lo, hi = {1: (1.8, 2.2), 2: (3.5, 4.5), 4: (12.0, 20.0)}[order]
    assert all(lo <= r <= hi for r in ratios), (method, errors, ratios)


# -- exact zero-order hold ------------------------------------------------------------------------
def _jittered_times(n: int, dt: float, gen: torch.Generator) -> torch.Tensor:
    # Sample times that are not multiples of a representable dt, with ±20 % jitter.
    steps = dt * (1 + 0.2 * (2 * torch.rand(n - 1, generator=gen) - 1))
    return 0.123 + torch.cat([torch.zeros(1), torch.cumsum(steps, 0)])


@pytest.mark.parametrize(("method", "steps"), [("rk4", 1), ("rk4", 3), ("midpoint", 2)])
def test_zero_order_hold_is_exact_piecewise_parabola(method: str, steps: int) -> None:
    gen = torch.Generator().manual_seed(3)
    n, big_m, c_m, offset = 150, 0.05, 1.5, 0.2
    t = _jittered_times(n, 1e-3, gen)
    u = torch.randn(n, generator=gen)  # a new level every sample
    arm = _no_black_box(inertia=big_m, viscous=None, c_m=c_m, offset=offset)
    x0 = torch.tensor([0.4, -0.3])
    with torch.no_grad():
        x = simulate(arm, t, u, x0, method=method, substeps=steps)
    # Reference: on [t_k, t_{k+1}] the acceleration is the constant (c_m u_k − offset)/M.
    ref = [x0.tolist()]
    q, v = x0.tolist()
    for k in range(n - 1):
        h = float(t[k + 1] - t[k])
        acc = (c_m * float(u[k]) - offset) / big_m
        q, v = q + v * h + 0.5 * acc * h * h, v + acc * h
        ref.append([q, v])
    # rk4 and midpoint integrate a parabola exactly; any stage that saw u_{k+1} inside interval k
    # would be off by ~h c_m Δu / (8 M) ≈ 1e-3 per sample.
    torch.testing.assert_close(x, torch.tensor(ref), rtol=0.0, atol=1e-12)


def test_zero_order_hold_nonlinear_against_solve_ivp() -> None:
    gen = torch.Generator().manual_seed(4)
    n, dt = 80, 1e-3
    arm = ArmModel(
        OddTanhFriction(2, w1=[5.0, 40.0], w2=[0.05, 0.03]),
        inertia=0.05,
        viscous=0.02,
        c_m=1.2,
        offset=-0.05,
        gravity=0.3,
    )
    t = torch.arange(n) * dt
    u = 0.3 * torch.randn(n, generator=gen)
    x0 = torch.tensor([0.5, 0.2])
    with torch.no_grad():
        x = simulate(arm, t, u, x0, substeps=2)
        theta = arm.get_theta()

    def rhs(_time: float, y: np.ndarray, uk: float) -> np.ndarray:
        with torch.no_grad():
            return arm.vector_field(torch.tensor(y), torch.tensor(uk), theta).numpy()

    # Integrate each sample interval separately with its constant u_k.
    ref = [x0.numpy()]
    for k in range(n - 1):
        sol = scipy.integrate.solve_ivp(
            rhs,
            (float(t[k]), float(t[k + 1])),
            ref[-1],
            method="DOP853",
            rtol=1e-13,
            atol=1e-14,
            args=(float(u[k]),),
        )
        ref.append(sol.y[:, -1])
    ref_t = torch.tensor(np.array(ref))
    # rk4 truncation at h = 0.5 ms is 1.8e-9 here (the steep neuron's high derivatives near v = 0);
    # DOP853 at rtol 1e-13 is far below that.
    torch.testing.assert_close(x, ref_t, rtol=0.0, atol=5e-9)
    # The error is truncation, not a leaked input: it falls as h⁴ (×16 per halving). A stage that
    # saw u_{k+1} would leave an O(h_sub) error falling only ×2.
    with torch.no_grad():
        errors = [float((simulate(arm, t, u, x0, substeps=s) - ref_t).abs().max()) for s in (1, 4)]
    assert 12.0 <= errors[0] / float((x - ref_t).abs().max()) <= 20.0
    assert 12.0 <= float((x - ref_t).abs().max()) / errors[1] <= 20.0


def test_sample_grid_contains_the_samples_exactly() -> None:
    gen = torch.Generator().manual_seed(5)
    t = _jittered_times(7, 1e-3, gen)
    grid = sample_grid(t, 3)
    assert grid.shape == (19,)
    torch.testing.assert_close(grid[::3], t, rtol=0.0, atol=0.0)
    assert bool((grid[1:] > grid[:-1]).all())
    torch.testing.assert_close(grid[1] - grid[0], (t[1] - t[0]) / 3)


# -- batching -------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("make", "n"),
    [
        (
            lambda: ArmModel(
                OddTanhFriction(3, w1=[1.0, 5.0, 20.0], w2=[0.05, 0.03, 0.02]),
                inertia=0.05,
                viscous=0.02,
                offset=0.01,
            ),
            40,
        ),
        # Short: torch.softmax on tiny (B, n) tensors is slow with several CPU threads.
        (
            lambda: ArmModel(
                PolytopicFriction(3, a=[0.1, 0.02], b=[0.05], c=[0.5], sigma=[0.1, 0.2]),
                inertia=0.05,
                viscous=None,
                gravity=0.2,
            ),
            10,
        ),
    ],
    ids=["tanh", "polytopic"],
)
def test_batched_runs_equal_separate_runs(make, n: int) -> None:
    arm = make()
    batch = 3
    t = torch.arange(n) * 2e-3
    u = torch.randn(n, batch)
    x0 = torch.randn(batch, 2)
    with torch.no_grad():
        xb = simulate(arm, t, u, x0, substeps=2)
        single = torch.stack(
            [simulate(arm, t, u[:, j], x0[j], substeps=2) for j in range(batch)], 1
        )
    assert xb.shape == (n, batch, 2)
    # Identical arithmetic per run; only vectorised reductions may round differently.
    torch.testing.assert_close(xb, single, rtol=1e-13, atol=1e-14)


# -- automatic sub-steps --------------------------------------------------------------------------
@pytest.mark.parametrize(("method", "expected"), [("euler", 7), ("midpoint", 5), ("rk4", 4)])
def test_auto_substeps_formula(method: str, expected: int) -> None:
    # λ = (0.01 + 2000 · 0.1) / 0.03 = 6667 /s, dt = 1 ms: S = ⌈λ dt / c⌉ with c = 1, 1.5, 2.
    assert auto_substeps(_steep_arm(), 1e-3, method) == expected
    assert SOLVERS[method] > 0


def test_auto_substeps_grows_with_steepness_and_is_capped() -> None:
    gentle = auto_substeps(_steep_arm(10.0), 1e-3)
    steep = auto_substeps(_steep_arm(2000.0), 1e-3)
    steeper = auto_substeps(_steep_arm(20000.0), 1e-3)
    assert gentle == 1 < steep == 4 < steeper == 34
    assert auto_substeps(_steep_arm(1e6), 1e-3) == 64  # capped at max_substeps
    assert auto_substeps(_steep_arm(1e6), 1e-3, max_substeps=200) == 200


def test_auto_substeps_keeps_steep_friction_accurate() -> None:
    arm = _steep_arm()  # λ ≈ 6667 /s: one rk4 step per 1 ms sample has λh = 6.7 (unstable)
    n = 50
    t = torch.arange(n) * 1e-3
    u = torch.full((n,), 0.05)  # settles at v ≈ 2.7e-4, right in the steep region
    x0 = torch.zeros(2)
    with torch.no_grad():
        auto = simulate(arm, t, u, x0)
        one = simulate(arm, t, u, x0, substeps=1)
        fine = simulate(arm, t, u, x0, substeps=16)
    assert bool(torch.isfinite(auto).all())
    # Bounded: |v| can never exceed c_m max|u| / b (friction only dissipates).
    assert float(auto[:, 1].abs().max()) <= 0.05 / 0.01
    # auto (S = 4, λh = 1.7) against a 4× finer run: ~1e-7, while S = 1 settles on a spurious
    # velocity 1e-3 away (twice the true one).
    torch.testing.assert_close(auto, fine, rtol=0.0, atol=1e-6)
    assert float((one - fine)[:, 1].abs().max()) > 1e-4


def test_auto_substeps_uses_the_given_theta() -> None:
    gentle, steep = _steep_arm(10.0), _steep_arm(2000.0)
    n = 30
    t = torch.arange(n) * 1e-3
    u = torch.full((n,), 0.05)
    with torch.no_grad():
        via_theta = simulate(gentle, t, u, torch.zeros(2), theta=steep.get_theta())
        direct = simulate(steep, t, u, torch.zeros(2), substeps=4)
    torch.testing.assert_close(via_theta, direct, rtol=0.0, atol=1e-15)


def test_auto_substeps_stable_on_non_uniform_grid() -> None:
    arm = _steep_arm()
    # 20 samples at 1 ms, then one 10 ms gap (a dropped-sample stretch) with the input reversed.
    t = torch.cat([torch.arange(20) * 1e-3, torch.tensor([0.029])])
    u = torch.full((21,), 0.05)
    u[-2] = -0.05
    with torch.no_grad():
        auto = simulate(arm, t, u, torch.zeros(2))
        fine = simulate(arm, t, u, torch.zeros(2), substeps=64)
    # With S sized for the 10 ms gap (34) the error is 3e-8; sized for the mean (5) v is 10× off.
    torch.testing.assert_close(auto, fine, rtol=0.0, atol=1e-6)


# -- gradients through friction → ODE → loss ------------------------------------------------------
@pytest.mark.parametrize(
    "make",
    [
        lambda: ArmModel(
            OddTanhFriction(3, w1=[1.0, 5.0, 20.0], w2=[0.05, 0.03, 0.02]),
            inertia=0.05,
            viscous=0.02,
            offset=0.01,
            gravity=0.2,
        ),
        lambda: ArmModel(
            PolytopicFriction(3, a=[0.1, 0.02], b=[0.05], c=[0.5], sigma=[0.1, 0.2]),
            inertia=0.05,
            viscous=None,
        ),
    ],
    ids=["tanh", "polytopic"],
)
def test_gradcheck_loss_through_simulation(make) -> None:
    arm = make()
    n = 12
    t = torch.arange(n) * 5e-3
    u = 0.5 * torch.sin(40 * t)
    x0 = torch.tensor([0.1, 0.3])
    target = torch.randn(n, 2) * 0.1

    def loss(theta: torch.Tensor) -> torch.Tensor:
        x = simulate(arm, t, u, x0, theta=theta, substeps=1)
        return ((x - target) ** 2).sum()

    theta = arm.get_theta().requires_grad_(True)
    assert torch.autograd.gradcheck(loss, (theta,))
    # The same gradient reaches the module's own parameters when θ is not given.
    x = simulate(arm, t, u, x0, substeps=1)
    ((x - target) ** 2).sum().backward()
    # θ order: the friction's parameters (registration order), then the arm's own raw_* ones.
    params = [*arm.friction.parameters(), *arm.parameters(recurse=False)]
    got = torch.cat([p.grad.reshape(-1) for p in params])
    (expected,) = torch.autograd.grad(loss(theta), theta)
    torch.testing.assert_close(got, expected)


def test_gradient_with_respect_to_initial_state() -> None:
    arm = _no_black_box(inertia=0.1, viscous=0.5)  # linear: x(t) = Φ(t) x0
    t = torch.arange(11) * 0.02
    x0 = torch.tensor([0.2, 1.0], requires_grad=True)
    x = simulate(arm, t, torch.zeros(11), x0, substeps=4)
    (grad,) = torch.autograd.grad(x[-1, 0], x0)
    # q(T) = q0 + v0 M/b (1 − e^{−bT/M}).
    expected = torch.tensor([1.0, 0.1 / 0.5 * (1 - math.exp(-0.5 * 0.2 / 0.1))])
    # ∂x/∂x0 obeys the same linear ODE, so it carries the same rk4 truncation (measured 2e-9 rel).
    torch.testing.assert_close(grad, expected, rtol=1e-8, atol=0.0)


# -- bad input ------------------------------------------------------------------------------------
@pytest.fixture
def small() -> tuple[ArmModel, torch.Tensor, torch.Tensor, torch.Tensor]:
    return _steep_arm(10.0), torch.arange(5) * 1e-3, torch.zeros(5), torch.zeros(2)


def test_unknown_method(small) -> None:
    arm, t, u, x0 = small
    with pytest.raises(TorchfricError, match=r"unknown solver 'dopri5'; choose one of \['euler'"):
        simulate(arm, t, u, x0, method="dopri5")


@pytest.mark.parametrize("substeps", [0, -2, "x", 1.5, True, None])
def test_bad_substeps(small, substeps) -> None:
    arm, t, u, x0 = small
    with pytest.raises(TorchfricError, match=r"substeps must be a positive integer or 'auto', got"):
        simulate(arm, t, u, x0, substeps=substeps)


def test_input_length_mismatch(small) -> None:
    arm, t, _, x0 = small
    with pytest.raises(TorchfricError, match=r"u has 4 samples but t has 5"):
        simulate(arm, t, torch.zeros(4), x0)
    with pytest.raises(TorchfricError, match=r"u has 6 samples but t has 5"):
        simulate(arm, t, torch.zeros(6, 2), torch.zeros(2, 2))


def test_bad_times_and_initial_state(small) -> None:
    arm, t, u, x0 = small
    with pytest.raises(TorchfricError, match=r"strictly increasing"):
        simulate(arm, torch.tensor([0.0, 1e-3, 1e-3, 2e-3, 3e-3]), u, x0)
    with pytest.raises(TorchfricError, match=r"strictly increasing"):
        simulate(arm, t.flip(0), u, x0)
    with pytest.raises(TorchfricError, match=r"1-D tensor of at least 2 samples, got shape \(1,\)"):
        simulate(arm, t[:1], u[:1], x0)
    with pytest.raises(
        TorchfricError, match=r"1-D tensor of at least 2 samples, got shape \(5, 1\)"
    ):
        simulate(arm, t[:, None], u, x0)
    with pytest.raises(
        TorchfricError, match=r"x0 must end in 2 entries \[q, qdot\], got shape \(3,\)"
    ):
        simulate(arm, t, u, torch.zeros(3))


def test_theta_of_wrong_length_is_rejected_with_auto_substeps() -> None:
    arm = _steep_arm(10.0)
    t = torch.arange(5) * 1e-3
    too_long = torch.cat([arm.get_theta(), torch.zeros(2)])
    with pytest.raises(TorchfricError, match=r"theta has 6 entries but this model has 4"):
        simulate(arm, t, torch.zeros(5), torch.zeros(2), theta=too_long)


def test_theta_of_wrong_length_is_rejected() -> None:
    arm = _steep_arm(10.0)
    t = torch.arange(5) * 1e-3
    too_long = torch.cat([arm.get_theta(), torch.zeros(2)])
    with pytest.raises(TorchfricError, match=r"theta has 6 entries but this model has 4"):
        simulate(arm, t, torch.zeros(5), torch.zeros(2), theta=too_long, substeps=1)


def test_returns_x0_first_and_keeps_input_unchanged(small) -> None:
    arm, t, _, _ = small
    u = torch.linspace(0.0, 1.0, 5)
    x0 = torch.tensor([0.3, -0.2])
    u_before = u.clone()
    with torch.no_grad():
        x = simulate(arm, t, u, x0, substeps=1)
    assert x.shape == (5, 2)
    torch.testing.assert_close(x[0], x0, rtol=0.0, atol=0.0)
    torch.testing.assert_close(u, u_before, rtol=0.0, atol=0.0)


def test_compiled_engine_equals_odeint_across_models_of_one_structure() -> None:
    """The compiled rk4 twin is cached per model structure with θ as an input: a second model
    of the same structure (other θ) reuses it and must still simulate *its* θ; sub-steps,
    a length that is not a multiple of the chunk and a non-uniform grid included."""
    first = ArmModel(OddTanhFriction(3, w1=[0.5, 5.0, 50.0], w2=[0.04, 0.05, 0.1]), 0.03, 0.01)
    other = ArmModel(OddTanhFriction(3, w1=[1.0, 2.0, 20.0], w2=[0.08, -0.02, 0.2]), 0.02, 0.03)
    t = torch.cumsum(torch.full((700,), 1e-3), 0) - 1e-3
    t[400:] += 2e-4  # one longer interval
    u = 0.3 * torch.sin(2 * math.pi * 1.5 * t) + 0.1 * torch.sign(torch.sin(2 * math.pi * 4 * t))
    x0 = torch.tensor([0.1, -0.4])
    with torch.no_grad():
        for model, steps in [(first, 1), (other, 3), (first, "auto")]:
            ref = simulate(model, t, u, x0, substeps=steps)
            fast = simulate(model, t, u, x0, substeps=steps, engine="compiled")
            assert fast.shape == ref.shape
            torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)
    with pytest.raises(TorchfricError, match="unknown simulation engine 'fast'"):
        simulate(first, t[:50], u[:50], x0, engine="fast")


def test_compiled_engine_keeps_only_the_sample_states_by_blocks(monkeypatch) -> None:
    """Without a gradient the compiled engine runs the record by blocks of sample intervals and
    keeps each interval's last state (all sub-steps' states cost substeps × the result: over
    1 GB in a 20-minute record's member selection); blocks of 7 intervals, 3 sub-steps, a batch
    of 2, on uneven sample intervals: the same numbers, bit for bit, as one block (each block's
    piece of the solver grid is the whole grid's), and odeint's to rounding; no block builds
    more of the grid than its own piece (the whole grid of a 20-minute record at 64 sub-steps
    is 0.6 GB)."""
    import torchfric.accel.simulation as compiled

    model = ArmModel(OddTanhFriction(3, w1=[0.5, 5.0, 50.0], w2=[0.04, 0.05, 0.1]), 0.03, 0.01)
    gen = torch.Generator().manual_seed(3)
    t = torch.cumsum(1e-3 * (1.0 + 0.2 * torch.rand(300, generator=gen, dtype=torch.float64)), 0)
    u = torch.stack([0.3 * torch.sin(2 * math.pi * 1.5 * t), 0.2 * torch.cos(2 * math.pi * t)], 1)
    x0 = torch.tensor([[0.1, -0.4], [0.0, 0.3]])
    grids: list[int] = []

    def piece(times: torch.Tensor, substeps: int) -> torch.Tensor:
        grids.append(times.numel())
        return sample_grid(times, substeps)

    with torch.no_grad():
        whole = simulate(model, t, u, x0, substeps=3, engine="compiled")
        monkeypatch.setattr(compiled, "_BLOCK", 7)
        monkeypatch.setattr(compiled, "sample_grid", piece)
        blocks = simulate(model, t, u, x0, substeps=3, engine="compiled")
        ref = simulate(model, t, u, x0, substeps=3)
    assert torch.equal(blocks, whole)
    assert len(grids) == 150 and max(grids) == 3  # 2 intervals a block: 3 sample times
    torch.testing.assert_close(blocks, ref, rtol=1e-12, atol=1e-12)
    # each block's kept states own their memory: a strided view of the block's sub-step
    # states kept them all alive until the end (a 20-minute selection grew to 1.9 GiB)
    kept: list[torch.Tensor] = []

    class Torch:  # the simulation module's `torch`, with `cat` recording what it joins
        def __getattr__(self, name: str) -> object:
            return getattr(torch, name)

        @staticmethod
        def cat(parts: list[torch.Tensor]) -> torch.Tensor:
            kept.extend(parts)
            return torch.cat(parts)

    monkeypatch.setattr(compiled, "torch", Torch())
    with torch.no_grad():
        again = simulate(model, t, u, x0, substeps=3, engine="compiled")
    assert torch.equal(again, whole) and len(kept) > 10
    assert all(p.untyped_storage().nbytes() == p.numel() * p.element_size() for p in kept[1:])


@pytest.mark.parametrize("batch", [None, 3])
def test_compiled_engine_gradient_equals_backprop_through_odeint(batch) -> None:
    """The compiled engine's gradient (a compiled reverse scan with the VJP of one rk4 step) is
    the exact gradient of the discrete map: equal to backpropagation through odeint's rk4 in θ
    and x0, over several chunks (2 sub-steps × 1299 intervals = 2598 solver steps), for one run
    and a batch of runs sharing θ, with a loss on every state."""
    model = ArmModel(OddTanhFriction(3, w1=[0.5, 5.0, 50.0], w2=[0.04, 0.05, 0.1]), 0.03, 0.01)
    t = torch.arange(1300, dtype=torch.float64) * 1e-3
    u = 0.3 * torch.sin(2 * math.pi * 1.5 * t) + 0.1 * torch.sign(torch.sin(2 * math.pi * 4 * t))
    x0 = torch.tensor([0.1, -0.4])
    if batch:
        u = torch.stack([u * (1 + 0.2 * b) for b in range(batch)], 1)
        x0 = x0 * torch.arange(1.0, batch + 1)[:, None]
    weights = torch.randn(u.shape + (2,), generator=torch.Generator().manual_seed(0))
    grads = {}
    for engine in ENGINES:
        theta = model.get_theta().clone().requires_grad_()
        x = x0.clone().requires_grad_()
        states = simulate(model, t, u, x, substeps=2, theta=theta, engine=engine)
        loss = (weights * states.sin()).sum()
        grads[engine] = (states.detach(), *torch.autograd.grad(loss, (theta, x)))
    for ref, got in zip(grads["odeint"], grads["compiled"], strict=True):
        torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-12)
    if native.compiler() is not None:  # both scans ran as generated C
        for direction in ("forward", "backward"):
            chunk = rk4_chunk(model, direction)
            assert chunk.path == "native", chunk.why_not_native


@pytest.mark.parametrize("dynamic", ["none", "lugre"])
def test_a_batch_of_runs_equals_each_run_alone_to_the_bit(dynamic: str, worker_cache) -> None:  # type: ignore[no-untyped-def]
    """A batch of simulations, each with its own input, start and θ (the auto comparison's
    windows, the ensemble's members), runs through the member program (`rk4_members_chunk`:
    traced for one run, four runs to a SIMD vector); every run's rows are the bits of that run
    simulated alone through the single-run program, and the batch ran natively."""
    from torchfric.accel.simulation import rk4_members_chunk

    kw = {"dynamic": "lugre", "sigma0": 1200.0, "sigma1": 11.0} if dynamic == "lugre" else {}
    model = ArmModel(OddTanhFriction(3, w1=[0.5, 5.0, 50.0], w2=[0.04, 0.05, 0.1]), 0.03, 0.01,
                     c_m=16.0, **kw)  # fmt: skip
    g = torch.Generator().manual_seed(3)
    B, n = 6, 80  # six runs: a full vector of four and a last one with two lanes repeated
    t = torch.arange(n) * 1e-3
    u = 0.05 * torch.randn(n, B, generator=g)
    x0 = torch.zeros(B, model.state_size)
    x0[:, :2] = 0.1 * torch.randn(B, 2, generator=g)
    theta = model.theta_vector().detach()
    thetas = theta * (1 + 0.05 * torch.randn(B, theta.numel(), generator=g))
    with torch.no_grad():
        for th in (theta, thetas):
            batch = simulate(model, t, u, x0, theta=th, substeps=4, engine="compiled")
            assert rk4_members_chunk(model, th.dim() == 2).path == "native"
            for j in range(B):
                alone = simulate(model, t, u[:, j], x0[j], theta=th if th.dim() == 1 else th[j],
                                 substeps=4, engine="compiled")  # fmt: skip
                assert torch.equal(batch[:, j], alone), j
        # one input or one θ for all runs is broadcast; a batch of another size is refused
        shared = simulate(model, t, u[:, :1], x0, theta=theta[None], substeps=4, engine="compiled")
        wide = simulate(model, t, u[:, :1].expand(-1, B), x0, theta=theta, substeps=4,
                        engine="compiled")  # fmt: skip
        assert torch.equal(shared, wide)
        with pytest.raises(TorchfricError, match=r"a batch of 6 simulations .* u with 8 runs"):
            simulate(model, t, torch.zeros(n, 8), x0, theta=theta, substeps=4, engine="compiled")
        with pytest.raises(TorchfricError, match=r"theta with 2 runs"):
            simulate(model, t, u, x0, theta=thetas[:2], substeps=4, engine="compiled")
