"""Correctness of the augmented-state continuous–discrete EKF (torchfric.estimators.ekf, torchfric.estimators.identify).

- A linear system (black box switched off by zero variance) against an independent linear
  continuous–discrete Kalman filter in numpy (matrix exponentials, Van Loan), step by step, for
  every measurement variant; and the augmented filter with uncertain b and M against an
  independent numpy EKF with the analytic Jacobian.
- The RK4 propagator: its Φ against `torch.func.jacrev` through the RK4 map for every friction
  model, its convergence order against the exact flow.
- `predict` against a fine-step integration of ``ẋ = f``, ``Ṗ = F P + P Fᵀ + Q``.
- `update` against the textbook form, NIS by hand and scipy's log-density.
- `identify_ekf`: resets between passes and experiments, resume, early stop, callbacks, and
  divergence / bad tuning by message.

Filter runs are kept short (one eager EKF step costs ~1 ms). Comparisons between algebraically
equal implementations stay within ≤ 200 samples of a 2-state filter or ≤ 50 samples of the
augmented one: cond(P) of the augmented filter lets equal algebra drift apart later.
The slow parameter-recovery runs live in tests/test_identify.py.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import scipy.linalg
import scipy.stats
import torch
from ekf_reference import make_reference_flow
from torch.func import jacrev

from torchfric.accel import make_chunk
from torchfric.data.experiment import Experiment, make_experiment
from torchfric.errors import DivergenceError, TorchfricError
from torchfric.estimators.ekf import (
    EKFState,
    FilterFailure,
    make_propagator,
    make_step,
    measurement_matrix,
    predict,
    run_pass,
    stage_jacobians,
    step,
    update,
)
from torchfric.estimators.identify import (
    EKFCallback,
    EKFResult,
    EKFTuning,
    PassRecord,
    identify_ekf,
)
from torchfric.models.arm import ArmModel
from torchfric.models.friction import (
    CoulombFriction,
    OddTanhFriction,
    PolytopicFriction,
    StribeckFriction,
)
from torchfric.models.simulate import simulate

DT = 1e-3


# =============================================================================================
# Helpers
# =============================================================================================
def _t(x: float | np.ndarray) -> torch.Tensor:
    return torch.as_tensor(x, dtype=torch.float64)


def _linear_arm(inertia: float = 0.03, viscous: float = 0.01, c_m: float = 2.0) -> ArmModel:
    """θ = [W1, W2, log b, log M] with W2 = 0: C ≡ 0 as long as W2 has zero variance."""
    return ArmModel(
        OddTanhFriction(1, w1=[1.0], w2=[0.0]), inertia=inertia, viscous=viscous, c_m=c_m
    )


def _linear_matrices(model: ArmModel) -> tuple[np.ndarray, np.ndarray]:
    """A, B of ``ẋ = A x + B u`` for `_linear_arm`: A = [[0, 1], [0, −b/M]], B = [0, c_m/M]."""
    big_m, b, c_m = (float(p.detach()) for p in (model.inertia, model.viscous, model.c_m))
    return np.array([[0.0, 1.0], [0.0, -b / big_m]]), np.array([0.0, c_m / big_m])


def _zoh(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretisation with held input: expm([[A, B], [0, 0]] dt) = [[Φ, Γ], [0, 1]]."""
    n = A.shape[0]
    big = np.zeros((n + 1, n + 1))
    big[:n, :n], big[:n, n] = A, B
    E = scipy.linalg.expm(big * dt)
    return E[:n, :n], E[:n, n]


def _van_loan(A: np.ndarray, Qc: np.ndarray, dt: float) -> np.ndarray:
    """Exact ``Q_d = ∫₀^dt e^{As} Qc e^{Aᵀs} ds``: expm([[−A, Qc], [0, Aᵀ]] dt) = [[·, Φ⁻¹Q_d],
    [0, Φᵀ]] (Van Loan 1978)."""
    n = A.shape[0]
    big = np.zeros((2 * n, 2 * n))
    big[:n, :n], big[:n, n:], big[n:, n:] = -A, Qc, A.T
    E = scipy.linalg.expm(big * dt)
    Phi = E[n:, n:].T
    return Phi @ E[:n, n:]


def _trapezoid_qd(A: np.ndarray, Qc: np.ndarray, dt: float) -> np.ndarray:
    Phi = scipy.linalg.expm(A * dt)
    return 0.5 * (Phi @ Qc @ Phi.T + Qc) * dt


def _reference_kf(
    A: np.ndarray,
    B: np.ndarray,
    Qd: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    x0: np.ndarray,
    P0: np.ndarray,
    u: np.ndarray,
    y: np.ndarray,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Textbook linear discrete KF on the exact discretisation; per sample (x⁻, P⁻, x⁺, P⁺).
    Sample 0 is an update only (the prior is the initial belief), as in `run_pass`."""
    Phi, Gam = _zoh(A, B, DT)
    x, P = x0.copy(), P0.copy()
    out = []
    for k in range(y.shape[0]):
        if k > 0:
            x = Phi @ x + Gam * u[k - 1]
            P = Phi @ P @ Phi.T + Qd
        xp, Pp = x.copy(), P.copy()
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        x = x + K @ (y[k] - H @ x)
        P = P - K @ S @ K.T
        P = 0.5 * (P + P.T)
        out.append((xp, Pp, x.copy(), P.copy()))
    return out


def _ekf_trace(
    state: EKFState,
    u: torch.Tensor,
    y: torch.Tensor,
    Q: torch.Tensor,
    H: torch.Tensor,
    R: torch.Tensor,
    flow,
) -> list[tuple[EKFState, EKFState]]:
    """The EKF's (prior, posterior) per sample, with `run_pass`'s schedule."""
    out = []
    dt = _t(DT)
    for k in range(y.shape[0]):
        prior = predict(state, u[k - 1], dt, Q, flow) if k > 0 else state
        state, _ = update(prior, y[k], H, R)
        out.append((prior, state))
    return out


def _linear_data(model: ArmModel, n: int, measure: str, seed: int = 3) -> tuple[np.ndarray, ...]:
    """Inputs and noisy measurements of the exact linear system (the filter need not know)."""
    rng = np.random.default_rng(seed)
    A, B = _linear_matrices(model)
    Phi, Gam = _zoh(A, B, DT)
    u = 0.02 * np.sin(2 * np.pi * 3.0 * DT * np.arange(n)) + 0.01 * rng.standard_normal(n)
    x = np.array([0.1, -0.5])
    xs = []
    for k in range(n):
        xs.append(x)
        x = Phi @ x + Gam * u[k]
    xs = np.array(xs)
    y = xs + rng.standard_normal((n, 2)) * np.array([2e-3, 5e-2])
    idx = {"both": [0, 1], "position": [0], "velocity": [1]}[measure]
    return u, y[:, idx]


# =============================================================================================
# Linear system vs an independent linear continuous–discrete Kalman filter
# =============================================================================================
@pytest.mark.parametrize("measure", ["both", "position", "velocity"])
@pytest.mark.parametrize("noise", ["none", "trapezoid"])
def test_linear_system_equals_linear_kalman_filter(measure: str, noise: str) -> None:
    model = _linear_arm()
    k = model.num_parameters
    n = 2 + k
    A, B = _linear_matrices(model)
    N = 200
    u, y = _linear_data(model, N, measure)
    idx = {"both": [0, 1], "position": [0], "velocity": [1]}[measure]
    H_np = np.eye(2)[idx]
    R_np = np.diag([1e-3, 1e-2])[np.ix_(idx, idx)]
    Qc = np.diag([0.0, 0.0]) if noise == "none" else np.diag([1e-2, 1.0])
    x0 = np.array([0.12, -0.4])
    P0 = np.array([[1e-2, 2e-3], [2e-3, 1e-1]])

    # The augmented filter with zero variance on every parameter: a linear KF on [q, q̇].
    P0_aug = torch.zeros(n, n)
    P0_aug[:2, :2] = _t(P0)
    Q_aug = torch.zeros(n, n)
    Q_aug[:2, :2] = _t(Qc)
    theta0 = model.get_theta()
    state = EKFState(torch.cat([_t(x0), theta0]), P0_aug)
    H = measurement_matrix(measure, n)
    assert H.shape == (len(H_np), n)
    torch.testing.assert_close(H[:, :2], _t(H_np), rtol=0, atol=0)
    assert bool((H[:, 2:] == 0).all())
    trace = _ekf_trace(state, _t(u), _t(y), Q_aug, H, _t(R_np), make_propagator(model, 1))

    # Reference: exact Φ, Γ; Q_d by the same trapezoid rule (agreement to rounding).
    ref = _reference_kf(A, B, _trapezoid_qd(A, Qc, DT), H_np, R_np, x0, P0, u, y)
    for (prior, post), (xp, Pp, xr, Pr) in zip(trace, ref, strict=True):
        # RK4 vs expm: the RK4 map is the 4th-order Taylor polynomial of e^{A dt}, so its local
        # error is (A dt)⁵/120 ≈ |b/M|⁴ dt⁵/120 ≈ 1e-19 relative (b/M = 1/3 s⁻¹, dt = 1e-3 s).
        torch.testing.assert_close(prior.x[:2], _t(xp), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(prior.P[:2, :2], _t(Pp), rtol=1e-10, atol=1e-14)
        torch.testing.assert_close(post.x[:2], _t(xr), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(post.P[:2, :2], _t(Pr), rtol=1e-10, atol=1e-14)
        # Zero-variance parameters never move; the cross terms stay exactly zero.
        assert torch.equal(post.x[2:], theta0)
        assert bool((post.P[2:, :] == 0).all()) and bool((post.P[:, 2:] == 0).all())

    # run_pass is the same loop.
    final, stats = run_pass(
        state, _t(u), _t(y), _t(DT), Q_aug, H, _t(R_np), make_step(make_propagator(model, 1))
    )
    torch.testing.assert_close(final.x, trace[-1][1].x, rtol=1e-14, atol=1e-15)
    torch.testing.assert_close(final.P, trace[-1][1].P, rtol=1e-14, atol=1e-18)
    assert stats.samples == N

    if noise == "none":
        return
    # Against the exact (Van Loan) Q_d, per step from the same posterior: the EKF's trapezoid
    # Q_d ≈ ½(ΦQΦᵀ + Q)dt errs by dt³/12·g''(ξ) with g(s) = e^{As}Qe^{Aᵀs},
    # ‖g''‖ ≤ e^{2‖A‖dt}‖A²Q + 2AQAᵀ + QAᵀ²‖: bound 2.1e-10, measured 1.7e-10 (Q_d ≈ 1e-3).
    Qd_exact = _van_loan(A, Qc, DT)
    G = A @ A @ Qc + 2 * A @ Qc @ A.T + Qc @ A.T @ A.T
    a_norm = np.linalg.norm(A, 2)
    bound = DT**3 / 12 * math.exp(2 * a_norm * DT) * np.linalg.norm(G, 2)
    Phi, Gam = _zoh(A, B, DT)
    worst = 0.0
    for k in range(1, N):
        post = trace[k - 1][1]
        P_exact = Phi @ post.P[:2, :2].numpy() @ Phi.T + Qd_exact
        worst = max(worst, float(np.abs(trace[k][0].P[:2, :2].numpy() - P_exact).max()))
    assert worst <= 1.01 * bound + 1e-15, (worst, bound)
    # ... and the bound is meaningful: a rectangle rule (Q dt) would miss it by far.
    assert np.abs(Qc * DT - Qd_exact).max() > 100 * bound


def _analytic_f(z: np.ndarray, u: float, c_m: float) -> np.ndarray:
    """Linear arm in the reduced augmented state z = [q, q̇, β = log b, μ = log M]."""
    b, big_m = math.exp(z[2]), math.exp(z[3])
    return np.array([z[1], (c_m * u - b * z[1]) / big_m, 0.0, 0.0])


def _analytic_F(z: np.ndarray, u: float, c_m: float) -> np.ndarray:
    """∂f/∂z by hand: ∂q̈/∂q̇ = −b/M, ∂q̈/∂log b = −b q̇/M, ∂q̈/∂log M = −q̈ (log space)."""
    b, big_m = math.exp(z[2]), math.exp(z[3])
    acc = (c_m * u - b * z[1]) / big_m
    F = np.zeros((4, 4))
    F[0, 1] = 1.0
    F[1, 1], F[1, 2], F[1, 3] = -b / big_m, -b * z[1] / big_m, -acc
    return F


def _analytic_ekf_step(
    z: np.ndarray, P: np.ndarray, u: float, c_m: float, Qc: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Classical RK4 for the mean and the variational equation Φ̇ = F Φ (F analytic), then
    P⁻ = Φ P Φᵀ + ½(Φ Q Φᵀ + Q) dt. (The EKF's 3/8-rule RK4 differs by O(dt⁵) ≈ 1e-16 here.)"""
    h = DT
    f, F = _analytic_f, _analytic_F
    k1, F1 = f(z, u, c_m), F(z, u, c_m)
    z2 = z + 0.5 * h * k1
    k2, F2 = f(z2, u, c_m), F(z2, u, c_m)
    z3 = z + 0.5 * h * k2
    k3, F3 = f(z3, u, c_m), F(z3, u, c_m)
    z4 = z + h * k3
    k4, F4 = f(z4, u, c_m), F(z4, u, c_m)
    eye = np.eye(4)
    K1 = F1
    K2 = F2 @ (eye + 0.5 * h * K1)
    K3 = F3 @ (eye + 0.5 * h * K2)
    K4 = F4 @ (eye + h * K3)
    Phi = eye + h / 6 * (K1 + 2 * K2 + 2 * K3 + K4)
    z_next = z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return z_next, Phi @ P @ Phi.T + 0.5 * (Phi @ Qc @ Phi.T + Qc) * h


def test_augmented_linear_arm_equals_analytic_jacobian_ekf() -> None:
    """b and M uncertain: the augmented EKF against a numpy EKF with the analytic Jacobian."""
    true = _linear_arm(inertia=0.03, viscous=0.02)
    model = _linear_arm(inertia=0.036, viscous=0.012)  # the filter starts off
    c_m = float(model.c_m)
    N = 50  # ≤ 50 samples: cond(P) of the augmented filter lets equal algebra drift later
    u, y = _linear_data(true, N, "both", seed=5)
    u = 10 * u  # larger accelerations: the data move θ within 50 samples
    A, B = _linear_matrices(true)
    Phi_true, Gam_true = _zoh(A, B, DT)
    x = np.array([0.1, -0.5])
    rng = np.random.default_rng(11)
    for k in range(N):
        y[k] = x + rng.standard_normal(2) * np.array([2e-3, 5e-2])
        x = Phi_true @ x + Gam_true * u[k]

    theta0 = model.get_theta()  # [W1, W2, log b, log M]
    # W1, W2 fixed (zero variance); log b and log M uncertain.
    p0 = torch.diag(_t([1e-4, 1e-2, 0.0, 0.0, 0.3, 0.2]))
    p0[0, 1] = p0[1, 0] = 1e-4
    Qc4 = np.diag([1e-6, 1e-2, 1e-5, 1e-5])
    Q = torch.zeros(6, 6)
    Q[np.ix_([0, 1, 4, 5], [0, 1, 4, 5])] = _t(Qc4)
    R = torch.diag(_t([1e-3, 1e-2]))
    H = measurement_matrix("both", 6)
    state = EKFState(torch.cat([_t([0.1, -0.5]), theta0]), p0)
    trace = _ekf_trace(state, _t(u), _t(y), Q, H, R, make_propagator(model, 1))

    keep = [0, 1, 4, 5]
    z = state.x[keep].numpy()
    P = p0[np.ix_(keep, keep)].numpy()
    H4, R4 = np.eye(2, 4), R.numpy()
    for k in range(N):
        if k > 0:
            z, P = _analytic_ekf_step(z, P, float(u[k - 1]), c_m, Qc4)
        prior = trace[k][0]
        torch.testing.assert_close(prior.x[keep], _t(z), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(
            prior.P[np.ix_(keep, keep)], _t(P), rtol=1e-10, atol=1e-10 * np.abs(P).max()
        )
        # Textbook update (the EKF's is Joseph form).
        S = H4 @ P @ H4.T + R4
        K = np.linalg.solve(S, H4 @ P).T
        z = z + K @ (y[k] - H4 @ z)
        P = (np.eye(4) - K @ H4) @ P
        P = 0.5 * (P + P.T)
        post = trace[k][1]
        torch.testing.assert_close(post.x[keep], _t(z), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(
            post.P[np.ix_(keep, keep)], _t(P), rtol=1e-10, atol=1e-10 * np.abs(P).max()
        )
        # The fixed black-box weights never move.
        assert torch.equal(post.x[2:4], theta0[:2])
        assert bool((post.P[2:4] == 0).all())
    # The filter did learn something: b and M moved towards the truth.
    moved = trace[-1][1].x[4:] - theta0[2:]
    assert float(moved.abs().min()) > 1e-3


# =============================================================================================
# The propagator: Φ by the RK4 variational recursion == jacrev through the RK4 map
# =============================================================================================
def _propagator_models() -> dict[str, ArmModel]:
    kw = {"c_m": 1.6, "offset": 0.03, "gravity": 0.2}
    return {
        "tanh": ArmModel(
            OddTanhFriction(3, w1=[0.8, 4.0, 25.0], w2=[0.05, -0.02, 0.03]),
            inertia=0.05,
            viscous=0.02,
            **kw,
        ),
        "polytopic": ArmModel(
            PolytopicFriction(3, a=[0.5, 0.02], b=[0.1], c=[1.0], sigma=[0.1, 0.8]),
            inertia=0.05,
            viscous=None,
            **kw,
        ),
        "coulomb": ArmModel(CoulombFriction(fc=0.1, eps=0.05), inertia=0.05, viscous=0.02, **kw),
        "stribeck": ArmModel(
            StribeckFriction(fc=0.1, fs=0.15, vs=0.3, eps=0.05),
            inertia=0.05,
            viscous=0.02,
            estimate_c_m=True,
            **kw,
        ),
    }


@pytest.mark.parametrize("substeps", [1, 3])
@pytest.mark.parametrize("kind", ["tanh", "polytopic", "coulomb", "stribeck"])
def test_propagator_matches_jacrev_of_rk4_map(kind: str, substeps: int) -> None:
    model = _propagator_models()[kind]
    theta0 = model.get_theta()
    prop = make_propagator(model, substeps)
    ref = make_reference_flow(model, substeps)
    gen = torch.Generator().manual_seed(7)
    for dt in (1e-3, 1e-2):
        for _ in range(3):
            x = torch.randn(2, generator=gen) * _t([1.0, 2.0])
            theta = theta0 + 0.1 * torch.randn(theta0.shape, generator=gen)
            z = torch.cat([x, theta])
            u = 0.1 * torch.randn((), generator=gen)
            x_next, Phi = prop(z, u, _t(dt))
            x_ref, Phi_ref = ref(z, u, _t(dt))
            assert Phi.shape == (2, z.numel())
            torch.testing.assert_close(x_next, x_ref, rtol=1e-12, atol=1e-14)
            torch.testing.assert_close(Phi, Phi_ref, rtol=1e-12, atol=1e-12 * Phi_ref.abs().max())
            # Φ is the Jacobian of a step, not the identity: it must see the dynamics.
            assert float((Phi[:, :2] - torch.eye(2)).abs().max()) > 1e-6
            assert float(Phi[1, 2:].abs().max()) > 1e-8


@pytest.mark.parametrize("kind", ["tanh", "polytopic", "coulomb", "stribeck"])
def test_stage_jacobians_match_jacrev_of_the_vector_field(kind: str) -> None:
    model = _propagator_models()[kind]
    theta = model.get_theta()
    gen = torch.Generator().manual_seed(3)
    X = torch.randn(4, 2, generator=gen)
    u = _t(0.07)
    F = stage_jacobians(model, X, u, theta)
    assert F.shape == (4, 2, 2 + theta.numel())
    for i in range(4):
        z = torch.cat([X[i], theta])
        expected = jacrev(lambda zz: model.vector_field(zz[:2], u, zz[2:]))(z)
        torch.testing.assert_close(F[i], expected, rtol=1e-13, atol=1e-13)


def test_propagator_has_fourth_order_and_substeps_refine() -> None:
    """Against the exact flow of a stiff-ish linear arm (b/M = 50 1/s): the one-step error of
    RK4 is (A h)⁵/120, so halving dt divides it by 2⁵ and S substeps divide it by S⁴."""
    model = _linear_arm(inertia=0.02, viscous=1.0, c_m=2.0)
    A, B = _linear_matrices(model)
    z = torch.cat([_t([0.2, 1.5]), model.get_theta()])
    u = _t(0.3)

    def errors(dt: float, substeps: int) -> tuple[float, float]:
        x_next, Phi = make_propagator(model, substeps)(z, u, _t(dt))
        Phi_e, Gam_e = _zoh(A, B, dt)
        x_exact = Phi_e @ z[:2].numpy() + Gam_e * 0.3
        return (
            float(np.abs(x_next.numpy() - x_exact).max()),
            float(np.abs(Phi[:, :2].numpy() - Phi_e).max()),
        )

    # |b/M|·dt = 0.25 and 0.125: close enough to the asymptotic regime for the ratios.
    e1 = errors(0.005, 1)
    e2 = errors(0.0025, 1)
    for a, b in zip(e1, e2, strict=True):
        order = math.log2(a / b)
        assert 4.8 < order < 5.2, order  # local order 5 (global 4); measured 4.99
    e_sub = errors(0.0025, 2)
    for a, b in zip(e2, e_sub, strict=True):
        ratio = a / b
        assert 15.0 < ratio < 18.0, ratio  # measured 16.9  # 2 substeps: 2·(h/2)⁵ = h⁵/16


# =============================================================================================
# Covariance propagation against a fine-step reference of ẋ = f, Ṗ = F P + P Fᵀ + Q
# =============================================================================================
_C_M = 2.0


def _fine_model() -> ArmModel:
    # tanh(3) with viscous, offset and gravity: F has a q column and every kind of θ column.
    return ArmModel(
        OddTanhFriction(3, w1=[0.8, 6.0, 40.0], w2=[0.03, 0.04, 0.08]),
        inertia=0.03,
        viscous=0.01,
        c_m=_C_M,
        offset=0.02,
        gravity=0.3,
    )


def _tanh_field(z: np.ndarray, u: float) -> tuple[np.ndarray, np.ndarray]:
    """f* and F = ∂f*/∂x* by hand for `_fine_model`; θ = [W1(3), W2(3), log b, log M, offset,
    log g]."""
    q, v = z[0], z[1]
    w1, w2 = z[2:5], z[5:8]
    b, big_m, off, g = math.exp(z[8]), math.exp(z[9]), z[10], math.exp(z[11])
    th = np.tanh(w1 * v)
    sech2 = 1.0 - th**2
    acc = (_C_M * u - b * v - w2 @ th - off - g * math.sin(q)) / big_m
    n = z.size
    f = np.zeros(n)
    f[0], f[1] = v, acc
    F = np.zeros((n, n))
    F[0, 1] = 1.0
    F[1, 0] = -g * math.cos(q) / big_m
    F[1, 1] = (-b - w2 @ (w1 * sech2)) / big_m
    F[1, 2:5] = -w2 * v * sech2 / big_m
    F[1, 5:8] = -th / big_m
    F[1, 8] = -b * v / big_m
    F[1, 9] = -acc
    F[1, 10] = -1.0 / big_m
    F[1, 11] = -g * math.sin(q) / big_m
    return f, F


def _fine_reference(
    z0: np.ndarray, P0: np.ndarray, u: float, Qc: np.ndarray, steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """Classical RK4 on (x*, P) jointly with `steps` sub-steps over one interval DT."""
    h = DT / steps

    def rhs(z: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f, F = _tanh_field(z, u)
        return f, F @ P + P @ F.T + Qc

    z, P = z0.copy(), P0.copy()
    for _ in range(steps):
        a1, b1 = rhs(z, P)
        a2, b2 = rhs(z + 0.5 * h * a1, P + 0.5 * h * b1)
        a3, b3 = rhs(z + 0.5 * h * a2, P + 0.5 * h * b2)
        a4, b4 = rhs(z + h * a3, P + h * b3)
        z = z + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
        P = P + h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
    return z, P


def test_analytic_jacobian_of_the_fine_reference_matches_autograd() -> None:
    model = _fine_model()
    theta = model.get_theta()
    gen = torch.Generator().manual_seed(5)
    X = torch.randn(4, 2, generator=gen)
    F_auto = stage_jacobians(model, X, _t(0.1), theta)
    for i in range(4):
        z = torch.cat([X[i], theta]).numpy()
        f, F = _tanh_field(z, 0.1)
        torch.testing.assert_close(_t(F[:2]), F_auto[i], rtol=1e-13, atol=1e-13)
        torch.testing.assert_close(
            _t(f[:2]), model.vector_field(X[i], _t(0.1), theta), rtol=1e-14, atol=1e-14
        )


@pytest.mark.parametrize("v0", [0.05, 1.0, -2.0])
def test_predict_matches_fine_step_covariance_integration(v0: float) -> None:
    model = _fine_model()
    theta = model.get_theta().numpy()
    k = theta.size
    n = 2 + k
    u = 0.1
    z0 = np.concatenate([[0.4, v0], theta])
    P0 = np.diag(np.r_[1e-4, 1e-2, [0.05] * k])
    P0[0, 1] = P0[1, 0] = 2e-4
    P0[1, 2:] = P0[2:, 1] = 1e-3  # correlated velocity and parameters
    Qc = np.diag(np.r_[1e-2, 1.0, [1e-2] * k])
    # 1000 RK4 sub-steps (h = 1 µs, ‖F‖h ≈ 5e-5): the reference's own error is ~(‖F‖h)⁴‖F‖dt‖P‖,
    # far below anything compared here.
    z_ref, P_ref = _fine_reference(z0, P0, u, Qc, 1000)
    prior = predict(EKFState(_t(z0), _t(P0)), _t(u), _t(DT), _t(Qc), make_propagator(model, 1))
    # Mean: one RK4 step, local error ~(‖F_x‖dt)⁵ |ẋ| dt ≪ 1e-10.
    torch.testing.assert_close(prior.x, _t(z_ref), rtol=0, atol=1e-10)

    # Tolerance. ΦPΦᵀ with Φ the RK4 Jacobian is 4th order: measured ≤ 2e-11 here
    # ((‖F‖dt)⁵/120·‖P‖ ≈ 1.4e-10 allowed). The trapezoid Q_d ≈ ½(ΦQΦᵀ + Q)dt of
    # ∫ Φ(dt,s) Q Φ(dt,s)ᵀ ds errs by dt³/12·g''(ξ), g'' = Φ[(F² − Ḟ)Q + 2FQFᵀ + Q(F² − Ḟ)ᵀ]Φᵀ
    # (Ḟ: F changes along the trajectory; at v0 = 0.05 the steep neuron makes it as large as F²).
    f0, F0 = _tanh_field(z0, u)
    _, F1 = _tanh_field(z_ref, u)
    F_dot = (F1 - F0) / DT
    A2 = F0 @ F0 - F_dot
    G = A2 @ Qc + 2 * F0 @ Qc @ F0.T + Qc @ A2.T
    f_norm = np.linalg.norm(F0, 2)
    trapezoid = DT**3 / 12 * math.exp(2 * f_norm * DT) * np.linalg.norm(G, 2)
    rk4 = (f_norm * DT) ** 5 / 120 * np.abs(P0).max()
    # 1.5: the dt⁴ terms of the trapezoid error and the variation of g'' over the interval.
    tol = 1.5 * trapezoid + rk4
    err = float(np.abs(prior.P.numpy() - P_ref).max())
    assert err <= tol, (err, tol)  # measured: 1.8e-7 / 5.4e-9 / 6.2e-9 vs tol 3e-7 / 9e-9 / 1e-8
    # Without process noise only the RK4 part is left.
    _, P_ref0 = _fine_reference(z0, P0, u, 0 * Qc, 1000)
    prior0 = predict(
        EKFState(_t(z0), _t(P0)), _t(u), _t(DT), torch.zeros(n, n), make_propagator(model, 1)
    )
    assert float(np.abs(prior0.P.numpy() - P_ref0).max()) <= rk4
    # The test can fail: a rectangle-rule Q_d = Q dt is far outside the tolerance.
    Phi = np.eye(n)
    Phi[:2] = make_propagator(model, 1)(_t(z0), _t(u), _t(DT))[1].numpy()
    wrong = Phi @ P0 @ Phi.T + Qc * DT
    assert np.abs(wrong - P_ref).max() > 10 * tol
    # And P⁻ is exactly symmetric.
    assert torch.equal(prior.P, prior.P.T)


# =============================================================================================
# update(): Joseph form, NIS, log-likelihood
# =============================================================================================
@pytest.mark.parametrize("measure", ["both", "position", "velocity"])
def test_update_joseph_equals_textbook_nis_and_loglik(measure: str) -> None:
    rng = np.random.default_rng(2)
    n = 5
    L = rng.standard_normal((n, n))
    P = L @ L.T / n + np.eye(n)  # well conditioned (cond ≈ 10)
    x = rng.standard_normal(n)
    H = measurement_matrix(measure, n).numpy()
    m = H.shape[0]
    R = np.diag([0.3, 0.5][:m])
    y = rng.standard_normal(m)

    post, inn = update(EKFState(_t(x), _t(P)), _t(y), _t(H), _t(R))

    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)  # textbook, with an explicit inverse on purpose
    e = y - H @ x
    torch.testing.assert_close(post.x, _t(x + K @ e), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(post.P, _t((np.eye(n) - K @ H) @ P), rtol=1e-12, atol=1e-12)
    assert torch.equal(post.P, post.P.T)
    assert bool((torch.linalg.eigvalsh(post.P) > 0).all())
    torch.testing.assert_close(inn.e, _t(e), rtol=0, atol=1e-15)
    torch.testing.assert_close(inn.S, _t(S), rtol=1e-14, atol=1e-14)
    nis = float(e @ np.linalg.solve(S, e))
    assert inn.nis.item() == pytest.approx(nis, rel=1e-12)
    logpdf = scipy.stats.multivariate_normal.logpdf(e, mean=np.zeros(m), cov=S)
    assert inn.loglik.item() == pytest.approx(logpdf, rel=1e-12)


def test_joseph_update_survives_cancellation_where_textbook_form_does_not() -> None:
    """The reason for Joseph form: a nearly exact measurement (R = 1e-10) of a state with
    variance 1e8. The posterior variance is P R/(P + R) ≈ 1e-10; the textbook (I − KH)P computes
    it as 1e8 − 1e8 = 0 (a singular P), Joseph's sum of PSD terms keeps K R Kᵀ ≈ R."""
    P = torch.diag(_t([1e8, 1.0]))
    P[0, 1] = P[1, 0] = 9.9999e3
    H = _t([[1.0, 0.0]])
    R = _t([[1e-10]])
    post, _ = update(EKFState(torch.zeros(2), P), _t([1.0]), H, R)
    assert torch.equal(post.P, post.P.T)
    assert post.P[0, 0].item() == pytest.approx(1e8 * 1e-10 / (1e8 + 1e-10), rel=1e-9)
    assert float(torch.linalg.eigvalsh(post.P).min()) > 0


def test_update_flags_an_indefinite_innovation_covariance() -> None:
    P = torch.eye(3)
    H = measurement_matrix("both", 3)
    R = torch.diag(_t([-5.0, 1.0]))  # S = HPHᵀ + R not positive definite
    _, inn = update(EKFState(torch.zeros(3), P), torch.ones(2), H, R)
    assert math.isnan(inn.nis.item())


def test_step_is_predict_then_update() -> None:
    model = _fine_model()
    n = 2 + model.num_parameters
    z = torch.cat([_t([0.1, 0.7]), model.get_theta()])
    P = torch.eye(n) * 0.01
    Q = torch.diag(torch.cat([_t([0.0, 1e-3]), torch.zeros(n - 2)]))
    H, R = measurement_matrix("both", n), torch.diag(_t([1e-3, 1e-2]))
    flow = make_propagator(model, 2)
    y = _t([0.11, 0.65])
    got, inn = step(EKFState(z, P), _t(0.05), y, _t(DT), Q, H, R, flow)
    want, inn2 = update(predict(EKFState(z, P), _t(0.05), _t(DT), Q, flow), y, H, R)
    assert torch.equal(got.x, want.x) and torch.equal(got.P, want.P)
    assert torch.equal(inn.nis, inn2.nis)


def test_measurement_matrix_selects_the_measured_states() -> None:
    n = 7
    torch.testing.assert_close(measurement_matrix("both", n), torch.eye(2, n), rtol=0, atol=0)
    torch.testing.assert_close(measurement_matrix("position", n), torch.eye(1, n), rtol=0, atol=0)
    torch.testing.assert_close(
        measurement_matrix("velocity", n), torch.eye(2, n)[1:], rtol=0, atol=0
    )
    with pytest.raises(TorchfricError, match=r"unknown measurement 'acceleration'.*position"):
        measurement_matrix("acceleration", n)


# =============================================================================================
# identify_ekf on short simulated experiments
# =============================================================================================
def _small_true() -> ArmModel:
    return ArmModel(
        OddTanhFriction(3, w1=[0.5, 5.0, 50.0], w2=[0.04, 0.05, 0.1]),
        inertia=0.0292,
        viscous=0.01,
        c_m=16.0,
    )


def _small_start() -> ArmModel:
    return ArmModel(
        OddTanhFriction(3, w1=[0.4, 6.0, 40.0], w2=[0.05, 0.04, 0.12]),
        inertia=0.035,
        viscous=0.012,
        c_m=16.0,
    )


def _simulated(n: int, *, phase: float = 0.0, v0: float = 0.0, name: str = "sim") -> Experiment:
    """Quantised positions of `_small_true`; velocity from the high-pass differentiator, or, when
    the run starts moving (v0 ≠ 0), the true velocity (a tachometer), so that q̇[0] = v0."""
    true = _small_true()
    t = torch.arange(n) * DT
    u = 0.02 * torch.sin(2 * math.pi * 2.0 * t + phase) + 0.01 * torch.sin(2 * math.pi * 7.0 * t)
    with torch.no_grad():
        x = simulate(true, t, u, _t([0.1 * phase, v0]), substeps=1)
    q = torch.round(x[:, 0] / 2e-4) * 2e-4
    if v0 != 0.0:
        return make_experiment(t, u, q, x[:, 1], name=name)
    return make_experiment(t, u, q, name=name).with_velocity()


@pytest.fixture(scope="module")
def short_exp() -> Experiment:
    return _simulated(250)


def _tuning(**kwargs) -> EKFTuning:
    # the eager step unless a test asks for the compiled one (the API's default since the layout
    # issue), so that compiled-versus-eager tests compare two paths; the numbers as written
    # (units = "absolute"), since these tests redo the paper's arithmetic with the given Q/R/P0
    base = {"passes": 3, "tolerance": 0.0, "p0_theta": 0.05, "compile": False, "units": "absolute"}
    return EKFTuning(**(base | kwargs))


def _initial_belief(model: ArmModel, exp: Experiment, tuning: EKFTuning, theta, P_theta):
    n = 2 + model.num_parameters
    P = torch.zeros(n, n)
    P[:2, :2] = torch.diag(_t(tuning.p0_state))
    P[2:, 2:] = P_theta
    return EKFState(torch.cat([torch.stack([exp.q[0], exp.qdot[0]]), theta]), P)


def _manual_pass(model, exps, tuning, theta, P_theta):
    """One pass by hand with run_pass: per experiment x and P_xx reset, cross terms zero,
    θ and P_θθ carried."""
    n = 2 + model.num_parameters
    Q = torch.diag(torch.cat([_t(tuning.q_state), torch.full((n - 2,), float(tuning.q_theta))]))
    H = measurement_matrix(tuning.measure, n)
    R = torch.diag(_t(tuning.r))
    step_fn = make_step(make_propagator(model, tuning.substeps))
    for exp in exps:
        y = torch.stack([exp.q, exp.qdot], dim=-1)
        state = _initial_belief(model, exp, tuning, theta, P_theta)
        state, _ = run_pass(state, exp.u, y, _t(exp.dt), Q, H, R, step_fn)
        theta, P_theta = state.x[2:].clone(), state.P[2:, 2:].clone()
    return theta, P_theta, state


class _Recorder(EKFCallback):
    def __init__(self, stop_after: int | None = None) -> None:
        self.records: list[PassRecord] = []
        self.thetas: list[torch.Tensor] = []
        self.P_thetas: list[torch.Tensor] = []
        self.progress: list[tuple[int, int, int]] = []
        self.stop_after = stop_after

    def on_progress(self, pass_index: int, samples_done: int, samples_total: int) -> None:
        self.progress.append((pass_index, samples_done, samples_total))

    def on_pass_end(self, record: PassRecord, result: EKFResult) -> bool | None:
        self.records.append(record)
        self.thetas.append(result.theta.clone())
        self.P_thetas.append(result.P_theta.clone())
        assert result.passes == record.index
        if self.stop_after is not None and record.index >= self.stop_after:
            return False
        return None


# =============================================================================================
# Iterative passes: reset of x and P_xx, θ and P_θθ carried; resume; early stop
# =============================================================================================
def test_passes_reset_state_and_carry_parameters(short_exp: Experiment) -> None:
    model = _small_start()
    before = model.get_theta()
    tuning = _tuning(passes=3, p0_state=(1e-6, 1e-3))  # P_xx ≠ 0: its reset is visible
    rec = _Recorder()
    result = identify_ekf(model, short_exp, tuning, callback=rec)
    assert torch.equal(model.get_theta(), before)  # the caller's model is not modified
    assert [r.index for r in rec.records] == [1, 2, 3]
    assert result.passes == 3 and not result.converged

    # The same passes by hand, with the documented reset: same arithmetic, so 1e-12.
    theta = before.clone()
    P_theta = torch.eye(model.num_parameters) * 0.05
    thetas_old = [theta]
    end_states = []
    for p in range(3):
        theta, P_theta, state = _manual_pass(model, [short_exp], tuning, theta, P_theta)
        end_states.append(state)
        torch.testing.assert_close(rec.thetas[p], theta, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(rec.P_thetas[p], P_theta, rtol=1e-12, atol=1e-15)
        thetas_old.append(theta)
        r = rec.records[p]
        assert r.samples == short_exp.n
        assert r.theta == pytest.approx(theta.tolist(), rel=1e-12, abs=1e-12)
        rel = float((theta - thetas_old[p]).norm() / thetas_old[p].norm())
        assert r.rel_change == pytest.approx(rel, rel=1e-9)
        assert r.trace_P_theta == pytest.approx(float(torch.trace(P_theta)), rel=1e-12)
        assert r.trace_P == pytest.approx(float(torch.trace(state.P)), rel=1e-12)
        physical = dict(zip(model.theta_names, model.to_physical(theta).tolist(), strict=True))
        assert r.parameters == pytest.approx(physical, rel=1e-12)
        assert len(r.innovation_rms) == 2 and all(v > 0 for v in r.innovation_rms)
        assert math.isfinite(r.nis) and r.nis > 0 and math.isfinite(r.loglik)
    torch.testing.assert_close(result.theta, rec.thetas[-1], rtol=0, atol=0)
    torch.testing.assert_close(result.model.get_theta(), result.theta, rtol=0, atol=0)

    # The reset matters: carrying x and all of P (cross terms included) from the end of pass 1
    # into pass 2 gives another θ.
    n = 2 + model.num_parameters
    y = torch.stack([short_exp.q, short_exp.qdot], dim=-1)
    no_reset, _ = run_pass(
        end_states[0],
        short_exp.u,
        y,
        _t(DT),
        torch.diag(torch.cat([_t(tuning.q_state), torch.zeros(n - 2)])),
        measurement_matrix("both", n),
        torch.diag(_t(tuning.r)),
        make_step(make_propagator(model, 1)),
    )
    assert float((no_reset.x[2:] - rec.thetas[1]).abs().max()) > 1e-6


def test_resume_after_one_pass_equals_an_uninterrupted_run(short_exp: Experiment) -> None:
    model = _small_start()
    full = identify_ekf(model, short_exp, _tuning(passes=2))
    first = identify_ekf(model, short_exp, _tuning(passes=1))
    assert first.passes == 1
    resumed = identify_ekf(
        model,
        short_exp,
        _tuning(passes=2),
        start=(first.theta, first.P_theta, first.history),
    )
    assert [r.index for r in resumed.history] == [1, 2]
    torch.testing.assert_close(resumed.theta, full.theta, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(resumed.P_theta, full.P_theta, rtol=1e-12, atol=1e-15)
    assert resumed.history[1].rel_change == pytest.approx(full.history[1].rel_change, rel=1e-9)
    # A resume with nothing left to do returns the start unchanged.
    done = identify_ekf(
        model, short_exp, _tuning(passes=2), start=(full.theta, full.P_theta, full.history)
    )
    assert done.passes == 2 and torch.equal(done.theta, full.theta)


def test_resume_after_a_rolled_back_pass_stops_converged(short_exp: Experiment) -> None:
    """A rolled-back pass ends the run, and counts as converged (the pass before it was the
    best fit), whatever the tolerance, even 0 (no early stop); a resume from that history must
    say the same as the run that wrote it and run nothing more."""
    model = _small_start()
    first = identify_ekf(model, short_exp, _tuning(passes=1))
    kept = first.history[-1]
    undone = dataclasses.replace(kept, index=2, rolled_back=True, loglik=kept.loglik - 10.0)
    for tolerance in (0.0, 1.0):
        resumed = identify_ekf(
            model,
            short_exp,
            _tuning(passes=4, tolerance=tolerance),
            start=(first.theta, first.P_theta, [kept, undone]),
        )
        assert resumed.passes == 2  # nothing more runs after a rollback
        assert resumed.converged is True
        assert torch.equal(resumed.theta, first.theta)
        assert torch.equal(resumed.P_theta, first.P_theta)


def test_early_stop_and_tolerance_zero(short_exp: Experiment) -> None:
    """Converged, and stop, after the first pass that raises the innovation log-likelihood by
    less than ``tolerance · k`` nats (k parameters); the first pass never does (it raises it
    from nothing)."""
    model = _small_start()
    k = model.num_parameters
    assert k == 8
    # tolerance 0 runs every pass; the first three are all this test reads (the pass count is
    # only the loop's bound: they are the same passes a longer run starts with)
    full = identify_ekf(model, short_exp, _tuning(passes=3, tolerance=0.0))
    gains = [b.loglik - a.loglik for a, b in zip(full.history[:-1], full.history[1:], strict=True)]
    # on this record: +6.7 then +0.73 nats; 0.5 nat × 8 parameters = 4 nats stops after pass 3,
    # and 1 nat × 8 = 8 nats after pass 2 (a flat tolerance of 1 nat would have gone on)
    assert 0.5 * k > gains[1] > 0.0 and 1.0 * k > gains[0] >= 0.5 * k and gains[0] > 1.0
    stopped = identify_ekf(model, short_exp, _tuning(passes=5, tolerance=0.5))
    assert stopped.passes == 3 and stopped.converged
    assert [r.loglik for r in stopped.history] == [r.loglik for r in full.history[:3]]
    sooner = identify_ekf(model, short_exp, _tuning(passes=5, tolerance=1.0))
    assert sooner.passes == 2 and sooner.converged
    # a huge tolerance still runs two passes: the first has no gain to judge
    loose = identify_ekf(model, short_exp, _tuning(passes=5, tolerance=1e9))
    assert loose.passes == 2 and loose.converged
    rec = _Recorder(stop_after=3)
    by_callback = identify_ekf(model, short_exp, _tuning(passes=5), callback=rec)
    assert by_callback.passes == 3 and len(rec.records) == 3 and not by_callback.converged
    torch.testing.assert_close(by_callback.theta, stopped.theta, rtol=0, atol=0)
    # tolerance = 0 disables the early stop even when the fit no longer changes at all
    frozen = identify_ekf(model, short_exp, _tuning(passes=2, tolerance=0.0, p0_theta=0.0))
    assert frozen.passes == 2 and not frozen.converged
    assert frozen.history[-1].rel_change == 0.0
    assert frozen.history[-1].loglik == frozen.history[0].loglik
    # ... which any tolerance > 0 calls converged after its second pass
    still = identify_ekf(model, short_exp, _tuning(passes=3, tolerance=1e-9, p0_theta=0.0))
    assert still.passes == 2 and still.converged
    # Resuming a converged history does not run more passes.
    again = identify_ekf(
        model,
        short_exp,
        _tuning(passes=5, tolerance=0.5),
        start=(stopped.theta, stopped.P_theta, stopped.history),
    )
    assert again.passes == 3 and again.converged
    assert torch.equal(again.theta, stopped.theta)


def test_progress_stretches_do_not_change_the_arithmetic(short_exp: Experiment) -> None:
    model = _small_start()
    whole = identify_ekf(model, short_exp, _tuning(passes=1))
    rec = _Recorder()
    chunked = identify_ekf(model, short_exp, _tuning(passes=1), callback=rec, progress_every=70)
    torch.testing.assert_close(chunked.theta, whole.theta, rtol=1e-13, atol=1e-14)
    torch.testing.assert_close(chunked.P_theta, whole.P_theta, rtol=1e-12, atol=1e-16)
    n = short_exp.n
    assert rec.progress == [(1, s, n) for s in (70, 140, 210, n)]
    a, b = chunked.history[0], whole.history[0]
    assert a.samples == b.samples == n
    assert a.innovation_rms == pytest.approx(b.innovation_rms, rel=1e-10)
    assert a.nis == pytest.approx(b.nis, rel=1e-10)
    assert a.loglik == pytest.approx(b.loglik, rel=1e-10)


# =============================================================================================
# The compiled fast path: a scan over chunks of samples (one C++ loop per chunk)
# =============================================================================================
@pytest.fixture(scope="module", params=["native", "inductor"])
def compiled_step(request):  # type: ignore[no-untyped-def]
    """`_small_start`'s step compiled with 64-sample chunks (one compile for the module), by
    each path: generated C (the default) and the Inductor scan."""
    model = _small_start()
    native = request.param == "native"
    step = make_step(make_propagator(model, 1), compile=True, chunk=64, native=native)
    return model, step, request.param


def _pass_inputs(model: ArmModel, exp: Experiment):  # type: ignore[no-untyped-def]
    tuning = _tuning()
    Q, _, H, R = tuning.matrices(model.num_parameters)
    belief = _initial_belief(
        model, exp, tuning, model.get_theta(), torch.eye(model.num_parameters) * 0.05
    )
    y = torch.stack([exp.q, exp.qdot], dim=-1)
    return belief, exp.u, y, _t(exp.dt), Q, H, R


def test_compiled_chunks_equal_the_eager_step(compiled_step, short_exp: Experiment) -> None:
    model, fast, path = compiled_step
    belief, u, y, dt, Q, H, R = _pass_inputs(model, short_exp)
    eager = make_step(make_propagator(model, 1))
    eager_state, eager_stats = run_pass(belief, u, y, dt, Q, H, R, eager)
    # 249 steps = three full 64-sample chunks and a padded fourth.
    state, stats = run_pass(belief, u, y, dt, Q, H, R, fast)
    assert fast.chunk.path == path, f"ran {fast.chunk.path}, not {path}"
    torch.testing.assert_close(state.x, eager_state.x, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(state.P, eager_state.P, rtol=1e-9, atol=1e-15)
    assert stats.samples == eager_stats.samples == short_exp.n
    torch.testing.assert_close(stats.sum_e2, eager_stats.sum_e2, rtol=1e-9, atol=0)
    assert stats.loglik == pytest.approx(eager_stats.loglik, rel=1e-10)
    assert stats.sum_nis == pytest.approx(eager_stats.sum_nis, rel=1e-9)
    # Continuing stretches, as identify_ekf's progress reports cut them, give the same pass.
    s1, a = run_pass(belief, u[:100], y[:100], dt, Q, H, R, fast)
    s2, b = run_pass(s1, u[99:], y[99:], dt, Q, H, R, fast, continuing=True, sample_offset=99)
    torch.testing.assert_close(s2.x, state.x, rtol=1e-12, atol=1e-14)
    assert a.samples + b.samples == short_exp.n
    assert a.loglik + b.loglik == pytest.approx(stats.loglik, rel=1e-12)


def test_compiled_chunk_names_the_failing_sample_and_keeps_the_belief_before_it(
    compiled_step, short_exp: Experiment
) -> None:
    model, fast, _ = compiled_step
    belief, u, y, dt, Q, H, R = _pass_inputs(model, short_exp)
    y = y.clone()
    y[137, 0] = math.inf  # in the third chunk, not at its start
    with pytest.raises(FilterFailure) as compiled_fail:
        run_pass(belief, u, y, dt, Q, H, R, fast, sample_offset=1000)
    with pytest.raises(FilterFailure) as eager_fail:
        run_pass(
            belief, u, y, dt, Q, H, R, make_step(make_propagator(model, 1)), sample_offset=1000
        )
    assert compiled_fail.value.sample == eager_fail.value.sample == 1137
    assert compiled_fail.value.reason == eager_fail.value.reason
    torch.testing.assert_close(
        compiled_fail.value.state.x, eager_fail.value.state.x, rtol=1e-9, atol=1e-12
    )


def test_identify_ekf_compiled_equals_eager(short_exp: Experiment) -> None:
    """The default fast path (`compile = true` in configs, 1000-sample chunks) through the
    whole identification, with progress stretches that do not align with the chunks."""
    model = _small_start()
    eager = identify_ekf(model, short_exp, _tuning(passes=2))
    fast = identify_ekf(model, short_exp, _tuning(passes=2, compile=True), progress_every=90)
    torch.testing.assert_close(fast.theta, eager.theta, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(fast.P_theta, eager.P_theta, rtol=1e-9, atol=1e-15)
    for a, b in zip(fast.history, eager.history, strict=True):
        assert a.loglik == pytest.approx(b.loglik, rel=1e-10) and a.samples == b.samples


def test_more_compiled_chunks_than_dynamos_per_code_limit_all_stay_compiled() -> None:
    """Every compiled chunk is the same closure code with another captured function; dynamo
    allows 8 compiled entries per code object, after which the ninth model in a process used
    to fall back to the eager loop (the ensemble benchmark's K = 64 ran at 10 k instead of
    200 k filter-steps/s). Our compiled calls now run without that limit: 10 chunks, all alive
    at once, all run compiled, and each computes its own function."""
    limit = torch._dynamo.config.recompile_limit
    chunks = []
    for i in range(limit + 2):

        def one(x: torch.Tensor, a: torch.Tensor, c: torch.Tensor, i: int = i):  # type: ignore[no-untyped-def]
            y = x * c + a + i
            return (y,), (y,)

        chunks.append(make_chunk(one))
    xs = (torch.ones(4, 3, dtype=torch.float64),)
    valid = torch.ones(4, dtype=torch.bool)
    for i, chunk in enumerate(chunks):
        (x,), (ys,) = chunk((torch.zeros(3),), xs, valid, (torch.tensor(0.5),))
        assert chunk.chosen[0] is not chunk.eager, f"chunk {i} fell back to the eager loop"
        expect = torch.zeros(3)
        for _ in range(4):
            expect = expect * 0.5 + 1.0 + i
        torch.testing.assert_close(x, expect, rtol=0, atol=1e-12)


# =============================================================================================
# Several experiments: θ shared, state re-initialised per experiment
# =============================================================================================
def test_several_experiments_share_theta_and_reset_the_state() -> None:
    e1 = _simulated(160, phase=0.0, name="one")
    e2 = _simulated(120, phase=1.3, v0=0.8, name="two")
    # The second starts somewhere else, and moving: its initial state must come from its data.
    assert float(e2.q[0]) != float(e1.q[-1]) and float(e2.qdot[0]) == 0.8
    model = _small_start()
    tuning = _tuning(passes=1)
    result = identify_ekf(model, [e1, e2], tuning)
    assert result.history[0].samples == e1.n + e2.n
    theta, P_theta, _ = _manual_pass(
        model, [e1, e2], tuning, model.get_theta(), torch.eye(model.num_parameters) * 0.05
    )
    torch.testing.assert_close(result.theta, theta, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(result.P_theta, P_theta, rtol=1e-12, atol=1e-15)
    # The order of the experiments matters (θ is carried from one to the next).
    swapped = identify_ekf(model, [e2, e1], tuning)
    assert float((swapped.theta - result.theta).abs().max()) > 1e-8


# =============================================================================================
# Measurement variants through identify_ekf
# =============================================================================================
@pytest.mark.parametrize(("measure", "r"), [("position", (1e-3,)), ("velocity", (1e-2,))])
def test_single_channel_measurements_run(measure: str, r: tuple[float, ...]) -> None:
    exp = _simulated(150)
    result = identify_ekf(_small_start(), exp, _tuning(passes=1, measure=measure, r=r))
    rec = result.history[0]
    assert len(rec.innovation_rms) == 1 and rec.samples == exp.n
    assert bool(torch.isfinite(result.theta).all())
    assert 0 < rec.nis < 10


def test_position_only_needs_no_velocity() -> None:
    exp = _simulated(150)
    bare = Experiment(t=exp.t, u=exp.u, q=exp.q, name="bare")
    result = identify_ekf(_small_start(), bare, _tuning(passes=1, measure="position", r=(1e-3,)))
    assert result.passes == 1 and bool(torch.isfinite(result.theta).all())


# =============================================================================================
# Divergence and bad tuning, by message
# =============================================================================================
def test_theta_leaving_its_box_names_pass_experiment_and_sample(short_exp: Experiment) -> None:
    model = _small_start()
    # |W1[3]| = 40 > 10 from the start: the first update already leaves the box.
    with pytest.raises(DivergenceError) as info:
        identify_ekf(model, short_exp, _tuning(theta_bound=10.0))
    msg = str(info.value)
    assert "pass 1" in msg and "experiment 'sim'" in msg and "sample 0" in msg
    assert "left the box" in msg and "parameter 2" in msg
    last = info.value.last_good
    assert isinstance(last, EKFResult)
    assert torch.equal(last.theta, model.get_theta()) and last.history == []
    assert isinstance(info.value, TorchfricError)


def test_divergence_in_a_later_pass_keeps_the_previous_passes(short_exp: Experiment) -> None:
    model = _small_start()
    first = identify_ekf(model, short_exp, _tuning(passes=1))
    with pytest.raises(DivergenceError, match=r"pass 2, experiment 'sim', sample 0") as info:
        identify_ekf(
            model,
            short_exp,
            _tuning(passes=3, theta_bound=1.0),
            start=(first.theta, first.P_theta, first.history),
        )
    last = info.value.last_good
    assert torch.equal(last.theta, first.theta) and torch.equal(last.P_theta, first.P_theta)
    assert [r.index for r in last.history] == [1]
    torch.testing.assert_close(last.model.get_theta(), first.theta, rtol=0, atol=0)


def test_nan_from_exp_overflow_is_a_divergence(short_exp: Experiment) -> None:
    model = _small_start()
    theta = model.get_theta()
    theta[model.theta_names.index("inertia")] = -1000.0  # M = exp(−1000) = 0: q̈ = ±inf
    model.set_theta(theta)
    with pytest.raises(DivergenceError, match=r"pass 1, experiment 'sim', sample 1 .*NaN/inf"):
        identify_ekf(model, short_exp, _tuning())


def test_inf_in_unvalidated_data_is_a_divergence_at_that_sample(short_exp: Experiment) -> None:
    q = short_exp.q.clone()
    q[137] = math.inf
    bad = Experiment(t=short_exp.t, u=short_exp.u, q=q, qdot=short_exp.qdot, name="bad")
    with pytest.raises(DivergenceError, match=r"experiment 'bad', sample 137 \(t = 0\.1370 s"):
        identify_ekf(_small_start(), bad, _tuning(passes=1), progress_every=100)


def test_divergence_in_second_experiment_returns_a_consistent_last_good() -> None:
    e1 = _simulated(120, name="one")
    e2 = _simulated(120, phase=0.7, name="two")
    u = e2.u.clone()
    u[40] = math.nan  # unvalidated: the prediction of sample 41 becomes NaN
    e2 = Experiment(t=e2.t, u=u, q=e2.q, qdot=e2.qdot, name="two")
    model = _small_start()
    with pytest.raises(DivergenceError, match=r"pass 1, experiment 'two', sample 41") as info:
        identify_ekf(model, [e1, e2], _tuning(passes=1))
    last = info.value.last_good
    # Nothing completed: the last good result is the initial guess, θ and P_θθ alike.
    assert torch.equal(last.theta, model.get_theta())
    torch.testing.assert_close(last.P_theta, torch.eye(model.num_parameters) * 0.05, rtol=0, atol=0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"p0_theta": -1.0}, r"p0_theta must be finite variances >= 0, got -1\.0"),
        ({"p0_theta": (1.0,) * 5}, r"p0_theta needs 1 or 8 values, got 5"),
        ({"q_theta": (0.0,) * 9}, r"q_theta needs 1 or 8 values, got 9"),
        ({"q_theta": -1e-3}, r"q_theta must be finite variances >= 0"),
        ({"q_state": (0.0, -1e-3)}, r"q_state must be finite variances >= 0"),
        ({"p0_state": (0.0, math.nan)}, r"p0_state must be finite variances >= 0"),
        ({"p0_state": (0.0, 0.0, 0.0)}, r"p0_state needs 1 or 2 values, got 3"),
        ({"r": (-1e-3, 1e-2)}, r"r must be positive measurement variances"),
        ({"r": (0.0, 1e-2)}, r"r must be positive measurement variances"),
        ({"r": (1e-3,)}, r"r has 1 values but measure = 'both' measures 2 channel\(s\); give 2"),
        (
            {"measure": "position", "r": (1e-3, 1e-2)},
            r"r has 2 values but measure = 'position' measures 1 channel\(s\); give 1",
        ),
        ({"measure": "accel"}, r"measure = 'accel' is not known; choose one of \['both'"),
        ({"passes": 0}, r"passes must be an integer >= 1, got 0"),
        ({"passes": 2.5}, r"passes must be an integer >= 1, got 2\.5"),
        ({"tolerance": -0.1}, r"tolerance must be >= 0 \(0 disables early stop\), got -0\.1"),
        ({"tolerance": math.nan}, r"tolerance must be >= 0"),
        ({"substeps": 0}, r"substeps must be an integer >= 1, got 0"),
        ({"theta_bound": 0.0}, r"theta_bound must be > 0, got 0\.0"),
    ],
)
def test_bad_tuning_is_rejected_by_message(short_exp, kwargs: dict, match: str) -> None:
    with pytest.raises(TorchfricError, match=match):
        identify_ekf(_small_start(), short_exp, EKFTuning(**kwargs))


def test_velocity_measured_without_velocity_names_the_fix(short_exp: Experiment) -> None:
    bare = Experiment(t=short_exp.t, u=short_exp.u, q=short_exp.q, name="raw")
    for measure, r in (("both", (1e-3, 1e-2)), ("velocity", (1e-2,))):
        with pytest.raises(
            TorchfricError,
            match=rf"experiment 'raw' has no velocity but measure = '{measure}' needs one; "
            r"reconstruct it first \(Experiment\.with_velocity\) or use measure = 'position'",
        ):
            identify_ekf(_small_start(), bare, EKFTuning(measure=measure, r=r))


def test_no_experiments_is_an_error() -> None:
    with pytest.raises(TorchfricError, match="at least one experiment"):
        identify_ekf(_small_start(), [], EKFTuning())
