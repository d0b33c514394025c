"""Augmented-state continuous–discrete extended Kalman filter (Hensen et al. §4).

The state ``x* = [q, q̇, θ]`` (size ``n = 2 + k``) follows ``ẋ = f(x, u; θ) + w``, ``θ̇ = 0``,
with white process noise of continuous intensity ``Q`` and sampled measurements
``y_k = H x*_k + v_k``, ``v_k ~ N(0, R)``.

**Prediction scheme** (one sample interval ``dt``, zero-order-hold ``u_k``): the mean follows
``S`` classical RK4 (3/8-rule) sub-steps of the augmented field. The transition matrix
``Φ = ∂x*_{k+1}/∂x*_k`` is the Jacobian of that RK4 map, computed by `torch.func.jacrev`.
Differentiating a Runge–Kutta map equals applying the same Runge–Kutta scheme to the variational
equation ``Φ̇ = F Φ`` with ``F = ∂f*/∂x*`` along the trajectory, so
``P⁻ = Φ P Φᵀ + Q_d`` is the 4th-order solution of ``Ṗ = F P + P Fᵀ`` plus the noise term
``Q_d = ∫₀^dt Φ(s) Q Φ(s)ᵀ ds``, approximated by the trapezoid rule
``Q_d ≈ ½ (Φ Q Φᵀ + Q) dt`` (error ``O(dt³)`` per step in a term that is itself ``O(dt)``).
`tests/test_ekf.py` checks this against a fine-step Euler integration of ``Ṗ = FP + PFᵀ + Q``.

**Update**: Joseph form ``P = (I − KH) P⁻ (I − KH)ᵀ + K R Kᵀ`` with the gain from a Cholesky
solve (no explicit inverse), P symmetrised. The innovation, its covariance, the normalised
innovation squared (NIS) and the Gaussian log-likelihood are returned as diagnostics.

The per-sample functions are pure functions of tensors (`predict`, `update`, `step`); the pass
loop (`run_pass`) and the iterative off-line identification (`identify_ekf`, in
`identify.py`) are thin layers around them. Compiling the step (`make_step` with ``compile``)
is `torchfric.accel`'s: this module only hands it the plain per-sample function.
`make_fixed_theta_step` is the same filter with θ held, on the states alone.

Why this size: the filter's arithmetic (predict, update, the step in its two forms, the health
check and the pass loop that reports a failure) is one piece that every estimator runs.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from ..accel import (
    CHUNK,
    Step,
    chunk_options,
    compile_step,
    fused_matmul,
    iter_chunks,
    product_name,
    step_key,
)
from ..errors import TorchfricError
from ..models.arm import ArmModel
from .propagation import MatMul, Propagator, make_propagator, matmul_for, stage_jacobians

__all__ = [
    "EKFState",
    "Innovation",
    "MEASUREMENTS",
    "measurement_matrix",
    "make_propagator",
    "make_step",
    "make_fixed_theta_step",
    "fixed_theta_chunks",
    "FIXED_CHUNK",
    "matmul_for",
    "StepFn",
    "MatMul",
    "Propagator",
    "stage_jacobians",
    "predict",
    "update",
    "step",
    "healthy",
    "PassStats",
    "FilterFailure",
    "run_pass",
]

# Which of [q, q̇] are measured, by config name.
MEASUREMENTS: dict[str, tuple[int, ...]] = {"both": (0, 1), "position": (0,), "velocity": (1,)}

_LOG_2PI = math.log(2.0 * math.pi)


class EKFState(NamedTuple):
    """Filter belief: mean `x (n,)` = [q, q̇, θ] and covariance `P (n, n)`."""

    x: Tensor
    P: Tensor


class Innovation(NamedTuple):
    """Diagnostics of one update: innovation `e (m,)`, its covariance `S (m, m)`,
    ``nis = eᵀ S⁻¹ e`` and ``loglik = −½ (nis + log det S + m log 2π)``."""

    e: Tensor
    S: Tensor
    nis: Tensor
    loglik: Tensor


def _cholesky(S: Tensor) -> list[list[Tensor]]:
    """Lower Cholesky factor of the small SPD `S (m, m)` as an unrolled table ``L[i][j]``
    (i ≥ j; 0-d tensors). `m` (1 or 2 here) is fixed when the step is traced, so the loops
    vanish in a compiled graph. Not positive definite: a diagonal entry becomes NaN."""
    m = S.shape[-1]
    L: list[list[Tensor]] = [[S.new_zeros(())] * m for _ in range(m)]
    for j in range(m):
        s = S[j, j]
        for p in range(j):
            s = s - L[j][p] * L[j][p]
        L[j][j] = torch.sqrt(s)
        for i in range(j + 1, m):
            s = S[i, j]
            for p in range(j):
                s = s - L[i][p] * L[j][p]
            L[i][j] = s / L[j][j]
    return L


def _cholesky_solve(L: list[list[Tensor]], B: Tensor) -> Tensor:
    """``S⁻¹ B`` for `B (m, r)` from `_cholesky`'s factor: forward then back substitution."""
    m = len(L)
    z: list[Tensor] = []
    for i in range(m):
        s = B[i]
        for p in range(i):
            s = s - L[i][p] * z[p]
        z.append(s / L[i][i])
    w: list[Tensor] = [B[0]] * m
    for i in reversed(range(m)):
        s = z[i]
        for p in range(i + 1, m):
            s = s - L[p][i] * w[p]
        w[i] = s / L[i][i]
    return torch.stack(w)


def measurement_matrix(measure: str, n: int) -> Tensor:
    """`H (m, n)` selecting the measured entries of [q, q̇] from the augmented state."""
    if measure not in MEASUREMENTS:
        raise TorchfricError(
            f"unknown measurement {measure!r}; choose one of {sorted(MEASUREMENTS)}"
        )
    idx = MEASUREMENTS[measure]
    H = torch.zeros(len(idx), n, dtype=torch.float64)
    for row, col in enumerate(idx):
        H[row, col] = 1.0
    return H


def predict(
    state: EKFState, u: Tensor, dt: Tensor, Q: Tensor, flow: Propagator, mm: MatMul = fused_matmul
) -> EKFState:
    """Propagate the belief over one sample interval with held input `u`.

    `Q (n, n)` continuous process-noise intensity; `flow` from `make_propagator`.
    Returns the prior ``(x⁻, P⁻)``.
    """
    x, P = state
    # Φ_x = ∂x_{k+1}/∂x*_k (s, n) of the RK4 map (s = 2 states, 3 for a dynamic model); θ rows
    # are the identity (θ̇ = 0), so Φ = [Φ_x; 0 I] and
    # Φ M Φᵀ = [[Φ_x M Φ_xᵀ, (Φ_x M)_θ], [(Φ_x M)_θᵀ, M_θθ]]: the same product as the full one,
    # with about 2s·n² instead of 2n³ multiplications.
    x_next, jac_x = flow(x, u, dt)
    s = jac_x.shape[0]
    x_prior = torch.cat([x_next, x[s:]])

    def sandwich(M: Tensor) -> Tensor:
        AM = mm(jac_x, M)  # (s, n)
        top = torch.cat([mm(AM, jac_x.T), AM[:, s:]], dim=1)
        return torch.cat([top, torch.cat([AM[:, s:].T, M[s:, s:]], dim=1)], dim=0)

    # P⁻ = Φ P Φᵀ + ½ (Φ Q Φᵀ + Q) dt
    P_prior = sandwich(P) + 0.5 * (sandwich(Q) + Q) * dt
    return EKFState(x_prior, 0.5 * (P_prior + P_prior.T))


def update(
    state: EKFState, y: Tensor, H: Tensor, R: Tensor, mm: MatMul = fused_matmul
) -> tuple[EKFState, Innovation]:
    """Measurement update with `y (m,)`, `H (m, n)`, `R (m, m)`; Joseph form."""
    x, P = state
    m = y.shape[0]
    PHt = mm(P, H.T)
    # S = H P Hᵀ + R, innovation e = y − H x
    S = mm(H, PHt) + R
    S = 0.5 * (S + S.T)
    e = y - (H * x).sum(-1)
    L = _cholesky(S)
    # K = P Hᵀ S⁻¹ via the Cholesky factor (S symmetric: K = (S⁻¹ H P)ᵀ).
    K = _cholesky_solve(L, PHt.T).T
    x_post = x + (K * e).sum(-1)
    # Joseph form: P = (I − KH) P (I − KH)ᵀ + K R Kᵀ, each factor applied as a rank-m
    # correction: M = (I − KH) P = P − K (H P), then M (I − KH)ᵀ = M − (M Hᵀ) Kᵀ.
    M = P - mm(K, mm(H, P))
    P_post = M - mm(mm(M, H.T), K.T) + mm(mm(K, R), K.T)
    P_post = 0.5 * (P_post + P_post.T)
    # NIS = eᵀ S⁻¹ e ; log det S = 2 Σ log diag L. S not positive definite: L has NaN on its
    # diagonal, so nis and loglik are NaN, which `healthy` reports.
    w = _cholesky_solve(L, e.unsqueeze(-1)).squeeze(-1)
    nis = (e * w).sum()
    logdet = 2.0 * torch.log(torch.stack([L[i][i] for i in range(m)])).sum()
    loglik = -0.5 * (nis + logdet + m * _LOG_2PI)
    return EKFState(x_post, P_post), Innovation(e, S, nis, loglik)


def step(
    state: EKFState,
    u_prev: Tensor,
    y: Tensor,
    dt: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    flow: Propagator,
    mm: MatMul = fused_matmul,
) -> tuple[EKFState, Innovation]:
    """One sample: `predict` over the interval with `u_prev`, then `update` with `y`."""
    return update(predict(state, u_prev, dt, Q, flow, mm), y, H, R, mm)


StepFn = Callable[..., tuple[Tensor, Tensor, Tensor, Tensor, Tensor]]


def make_step(
    flow: Propagator,
    *,
    compile: bool = False,
    chunk: int = CHUNK,
    mm: MatMul | None = None,
    native: bool = True,
) -> Step:
    """The per-sample step as a function of tensors only, optionally compiled.

    The model is captured in `flow`. With `compile`, the step is also compiled as a loop over
    `chunk` samples (`torchfric.accel.compile_step`: `torch._higher_order_ops.scan` under
    `torch.compile`, Inductor with its C++ wrapper, so the loop over samples runs in C++ and
    the whole step is one fused kernel). It compiles on the first call, once per process and
    model; if compilation fails for any reason the eager function is used from then on — same
    arithmetic. `mm` is the matrix product of predict and update (default: the one `flow` was
    made with). With `native` (the default) the chunk is first tried as generated C
    (`torchfric.accel.make_chunk`), the fastest path; ``native=False`` keeps the Inductor scan
    (benchmarks compare the two).
    """
    mm = mm or getattr(flow, "mm", fused_matmul)
    states = getattr(flow, "states", 2)  # entries of x before θ (3 with a bristle state)

    def eager(
        x: Tensor,
        P: Tensor,
        u: Tensor,
        y: Tensor,
        dt: Tensor,
        Q: Tensor,
        H: Tensor,
        R: Tensor,
        bound: Tensor,
    ):  # type: ignore[no-untyped-def]
        state, inn = step(EKFState(x, P), u, y, dt, Q, H, R, flow, mm)
        return state.x, state.P, inn.e, inn.nis, inn.loglik, healthy(state, inn, bound, states)

    if not compile:
        out = Step(eager)
    else:  # carry: (x, P); per-sample outputs: (e, nis, loglik, ok)
        out = compile_step(eager, carry=2, size=chunk, options=chunk_options(mm), native=native,
                           key=step_key("ekf step", getattr(flow, "key", None), product_name(mm)))  # fmt: skip
    out.states = states  # type: ignore[attr-defined]  # for run_pass's messages
    return out


def make_fixed_theta_step(model: ArmModel, substeps: int) -> StepFn:
    """The filter with θ held fixed, on the model's states alone, vectorised over members.

    ``fn(x (K,s), P (K,s,s), u, y (m,), dt, θ (K,k), Q (K,s,s), H (m,s), R (K,m,m), bound)
    -> (x⁺, P⁺, e (K,m), nis (K,), loglik (K,), ok (K,))``, s = `model.state_size`; its `.key`
    names its code (`torchfric.accel.step_key`).

    The augmented filter with ``P_θθ = 0`` and no process noise on θ is this filter: its θ rows
    and columns of P stay exactly 0, so each product of `predict` and `update` adds exact zeros
    to the state block's terms, in the same order. Carrying only the ``s × s`` block skips them
    and the θ columns of Φ (the traced graph never asks for them, so the generated code does
    not compute them): the same numbers bit for bit (tested), at about half the work. The
    prediction-error stage (`torchfric.estimators.covariance`) runs its sensitivity filters,
    its noise-model grid and its trial steps through it."""
    from torch.func import vmap

    flow = make_propagator(model, substeps)
    mm, s = flow.mm, model.state_size  # type: ignore[attr-defined]

    def one(x, P, u, y, dt, theta, Q, H, R, bound):  # type: ignore[no-untyped-def]
        x_next, jac = flow(torch.cat([x, theta]), u, dt)
        A = jac[:, :s]
        AP, AQ = mm(A, P), mm(A, Q)
        P_prior = mm(AP, A.T) + 0.5 * (mm(AQ, A.T) + Q) * dt
        prior = EKFState(x_next, 0.5 * (P_prior + P_prior.T))
        state, inn = update(prior, y, H, R, mm)
        return state.x, state.P, inn.e, inn.nis, inn.loglik, healthy(state, inn, bound, s)

    out = vmap(one, in_dims=(0, 0, None, None, None, 0, 0, None, 0, None))
    out.key = step_key("fixed-θ step", flow.key, product_name(mm))  # type: ignore[attr-defined]
    return out


# Samples per call of the fixed-θ steps' C (not the numbers): 8 filters over 1000 samples took
# less than the 2 ms from which `torchfric.accel.native` splits members across the cores.
FIXED_CHUNK = 8192


def fixed_theta_chunks(fn: Callable, base: StepFn, *, carry: int, name: str, compile: bool) -> Step:
    """`fn` — a wrapper of the `make_fixed_theta_step` step `base` with its arguments — as a
    `Step`: with `compile`, the generated code over `FIXED_CHUNK` samples a call, θ, Q and R
    per filter and dt, H and the bound shared; else the eager function."""
    if not compile:
        return Step(fn)
    members = (False, True, True, False, True, False)  # dt, θ, Q, H, R, bound
    return compile_step(fn, carry=carry, size=FIXED_CHUNK, members=True, member_consts=members,
                        key=step_key(name, base.key))  # type: ignore[attr-defined]  # fmt: skip


@dataclass
class PassStats:
    """Accumulated diagnostics of one pass over one experiment (sums; see `run_pass`)."""

    samples: int = 0
    sum_e2: Tensor | None = None  # (m,) Σ e²
    sum_nis: float = 0.0
    loglik: float = 0.0


class FilterFailure(Exception):
    """Internal: a non-finite or non-PSD belief at `sample` (converted to DivergenceError)."""

    def __init__(self, sample: int, reason: str, state: EKFState) -> None:
        super().__init__(reason)
        self.sample = sample
        self.reason = reason
        self.state = state


def healthy(state: EKFState, inn: Innovation, bound: Tensor, states: int = 2) -> Tensor:
    """0-d bool: finite belief, finite NIS (S positive definite), no negative variance, θ (the
    entries after the first `states`) in its box."""
    x, P = state
    d = torch.diagonal(P)
    ok = (
        torch.isfinite(x).all()
        & torch.isfinite(P).all()
        & torch.isfinite(inn.nis)
        & (d >= -1e-9 * (1.0 + d.abs().max())).all()
    )
    return ok & (x[states:].abs() <= bound).all() if x.shape[-1] > states else ok


def _check(state: EKFState, inn: Innovation, theta_bound: float, states: int = 2) -> str | None:
    """Reason the belief is unusable, or None. Cheap enough for every sample in eager mode."""
    x, P = state
    if not bool(torch.isfinite(x).all()):
        return "the state estimate became NaN/inf"
    if not bool(torch.isfinite(P).all()):
        return "the covariance P became NaN/inf"
    if not bool(torch.isfinite(inn.nis)):
        return "the innovation covariance S is not positive definite"
    if bool((torch.diagonal(P) < -1e-9 * (1.0 + torch.diagonal(P).abs().max())).any()):
        return "the covariance P is not positive semi-definite (negative variance)"
    theta = x[states:]
    if bool((theta.abs() > theta_bound).any()):
        j = int((theta.abs() > theta_bound).nonzero()[0, 0])
        return f"parameter {j} left the box |θ| <= {theta_bound:g} (value {float(theta[j]):.4g})"
    return None


def run_pass(
    state: EKFState,
    u: Tensor,
    y: Tensor,
    dt: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    step_fn: StepFn,
    *,
    theta_bound: float = 1e6,
    continuing: bool = False,
    sample_offset: int = 0,
) -> tuple[EKFState, PassStats]:
    """Filter a stretch of samples: `u (N,)` inputs, `y (N, m)` measurements.

    Fresh (`continuing=False`): update with `y[0]`, then predict/update for samples 1…N−1.
    Continuing a previous stretch whose last sample was `y[0]`: only the predict/update steps.
    Returns the final belief and summed diagnostics. Raises `FilterFailure` naming the first bad
    sample (offset by `sample_offset`). A `Step` with a compiled `chunk` filters `Step.size`
    samples per call and checks health once per chunk; on a failure the chunk is replayed with
    the eager step to name the sample and keep the belief before it.
    """
    stats = PassStats(sum_e2=torch.zeros(y.shape[1], dtype=torch.float64))
    states = getattr(step_fn, "states", 2)
    sum_e2 = torch.zeros(y.shape[1], dtype=torch.float64)
    sum_nis = torch.zeros((), dtype=torch.float64)
    loglik = torch.zeros((), dtype=torch.float64)
    if not continuing:
        new_state, inn = update(state, y[0], H, R)
        reason = _check(new_state, inn, theta_bound, states)
        if reason:
            raise FilterFailure(sample_offset, reason, state)
        state = new_state
        sum_e2, sum_nis, loglik = inn.e * inn.e, inn.nis, inn.loglik
        stats.samples = 1
    bound = torch.tensor(theta_bound, dtype=torch.float64)
    chunk = getattr(step_fn, "chunk", None)
    if chunk is not None:
        # sample k = 1 + i is driven by u[k − 1] and measured by y[k]
        for i, n, xs, valid in iter_chunks((u[:-1], y[1:]), step_fn.size):  # type: ignore[attr-defined]
            (x, P), (e, nis, ll, ok) = chunk((state.x, state.P), xs, valid, (dt, Q, H, R, bound))
            ok = ok[:n]
            if not bool(ok.all()):
                _replay_failure(state, u, y, 1 + i, int((~ok).nonzero()[0, 0]), dt, Q, H, R,
                                bound, step_fn, theta_bound, sample_offset)  # fmt: skip
            state = EKFState(x, P)
            sum_e2 = sum_e2 + (e[:n] * e[:n]).sum(0)
            sum_nis = sum_nis + nis[:n].sum()
            loglik = loglik + ll[:n].sum()
    else:
        for k in range(1, y.shape[0]):
            x, P, e, nis, ll, ok = step_fn(state.x, state.P, u[k - 1], y[k], dt, Q, H, R, bound)
            # Checked every sample (one sync), so a failure names the exact sample.
            if not bool(ok):
                reason = _failure_reason(x, P, e, nis, ll, theta_bound, states)
                raise FilterFailure(sample_offset + k, reason or _UNHEALTHY, state)
            state = EKFState(x, P)
            sum_e2 = sum_e2 + e * e
            sum_nis = sum_nis + nis
            loglik = loglik + ll
    stats.samples += y.shape[0] - 1
    stats.sum_e2 = sum_e2
    stats.sum_nis = float(sum_nis)
    stats.loglik = float(loglik)
    return state, stats


_UNHEALTHY = "the filter became unhealthy"


def _failure_reason(
    x: Tensor, P: Tensor, e: Tensor, nis: Tensor, ll: Tensor, theta_bound: float, states: int
) -> str | None:
    """`_check`'s message for one step's outputs (None when every check passes)."""
    return _check(EKFState(x, P), Innovation(e, e.new_empty(0), nis, ll), theta_bound, states)


def _replay_failure(
    state: EKFState,
    u: Tensor,
    y: Tensor,
    k0: int,
    bad: int,
    dt: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    bound: Tensor,
    step_fn: StepFn,
    theta_bound: float,
    sample_offset: int,
) -> None:
    """A compiled chunk starting at sample `k0` from `state` went unhealthy at its index `bad`:
    replay it with the eager step and raise `FilterFailure` for the first bad sample, with the
    belief before it. The two paths agree to rounding, so the eager replay normally fails at
    the same sample; if it fails earlier it names that one."""
    eager = step_fn.eager  # type: ignore[attr-defined]
    for k in range(k0, k0 + bad + 1):
        x, P, e, nis, ll, ok = eager(state.x, state.P, u[k - 1], y[k], dt, Q, H, R, bound)
        reason = _failure_reason(x, P, e, nis, ll, theta_bound, getattr(step_fn, "states", 2))
        if reason or k == k0 + bad:
            raise FilterFailure(sample_offset + k, reason or _UNHEALTHY, state)
        state = EKFState(x, P)
