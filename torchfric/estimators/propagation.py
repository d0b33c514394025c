"""The EKF's prediction maps: the sample-interval flow ``propagate(z, u, dt) -> (x_next, Φ_x)``
of a model, with the exact Jacobian of its integrator (`make_propagator`), and the small-matrix
product the filter uses (`matmul_for`). `torchfric.estimators.ekf` builds the filter on them.
How many RK4 sub-steps a sample takes under ``substeps = "auto"`` (`resolve_substeps` at the
start, `finer_steps` between passes) is here too.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor
from torch.func import grad

from ..accel import fused_matmul, product_name, step_key, structure_key
from ..data import Experiment
from ..models.arm import ArmModel
from ..models.simulate import filter_substeps

__all__ = [
    "MatMul", "Propagator", "make_propagator", "matmul_for", "stage_jacobians", "finer_steps",
    "resolve_substeps",
]  # fmt: skip


def stage_jacobians(model: ArmModel, X: Tensor, u: Tensor, theta: Tensor) -> Tensor:
    """Jacobians ``F_i = ∂f/∂[x, θ]`` `(S, 2, 2+k)` of the vector field at S states `X (S, 2)`.

    One forward and one reverse autograd pass for all S points and both rows: the points are
    stacked twice, row 0 of f is read from the first copy and row 1 from the second, and the
    rows do not interact, so the gradient of the sum holds each point's Jacobian rows.
    """
    S, k = X.shape[0], theta.shape[-1]

    def total(Z: Tensor) -> Tensor:
        out = model.dynamics(Z[:, :2], u, *model.split(Z[:, 2:]))
        return out[:S, 0].sum() + out[S:, 1].sum()

    Z = torch.cat([X, theta.expand(S, k)], dim=-1).repeat(2, 1)
    G = grad(total)(Z)
    return torch.stack([G[:S], G[S:]], dim=1)


Propagator = Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]
MatMul = Callable[[Tensor, Tensor], Tensor]


def matmul_for(n: int) -> MatMul:
    """The matrix product for an `n`-state filter: `fused_matmul` up to n = 20, where it lets
    the compiled step be one kernel (tanh(3), n = 10: 22 k steps/s vs 14 k with BLAS calls),
    `torch.matmul` above, where Inductor's plain loops lose to BLAS (tanh(10), n = 24: 8.6 k
    fused vs 17 k; tanh(30), n = 64: 430 vs 4 k; measured before predict/update used their
    structure, with `benchmarks/ekf_speed.py`'s single-filter pass)."""
    return fused_matmul if n <= 20 else torch.matmul


def make_propagator(model: ArmModel, substeps: int, *, mm: MatMul | None = None) -> Propagator:
    """The sample-interval map ``propagate(z, u, dt) -> (x_next (2,), Φ_x (2, n))``.

    `z (n,)` = [q, q̇, θ]; `S = substeps` RK4 (3/8 rule) steps with θ constant. Φ_x is the exact
    Jacobian of that RK4 map, assembled from the stage Jacobians ``F_i`` (autograd,
    `stage_jacobians`) by the RK4 recursion of the variational equation ``Φ̇ = F Φ``:
    ``D_1 = Φ, K_i = F_i^x D_i + F_i^θ E, D_2 = Φ + h K_1/3, D_3 = Φ + h (K_2 − K_1/3),
    D_4 = Φ + h (K_1 − K_2 + K_3), Φ ← Φ + h (K_1 + 3K_2 + 3K_3 + K_4)/8`` with ``E = ∂θ/∂z``.
    The tests' reference (`make_reference_flow` in tests/ekf_reference.py) gives the same Φ by
    `torch.func.jacrev` through the whole map.
    `mm` is the matrix product (default `matmul_for(n)`); the returned function carries it as
    `.mm` for `make_step`.
    """
    mm = mm or matmul_for(model.state_size + model.num_parameters)
    if model.state_size != 2:
        return _stepped_propagator(model, substeps, mm)

    def propagate(z: Tensor, u: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
        x, theta = z[:2], z[2:]
        n = z.shape[0]
        fric, arm = model.split(theta)
        h = dt / substeps
        Phi = torch.eye(2, n, dtype=z.dtype)
        for _ in range(substeps):
            # Mean: RK4 (3/8 rule) stages.
            k1 = model.dynamics(x, u, fric, arm)
            x2 = x + h * k1 / 3.0
            k2 = model.dynamics(x2, u, fric, arm)
            x3 = x + h * (k2 - k1 / 3.0)
            k3 = model.dynamics(x3, u, fric, arm)
            x4 = x + h * (k1 - k2 + k3)
            k4 = model.dynamics(x4, u, fric, arm)
            F = stage_jacobians(model, torch.stack([x, x2, x3, x4]), u, theta)
            Fx = F[:, :, :2]
            # F_i^θ E: the θ-columns placed into the augmented column space (2, n).
            Ft = torch.nn.functional.pad(F[:, :, 2:], (2, 0))
            K1 = mm(Fx[0], Phi) + Ft[0]
            K2 = mm(Fx[1], Phi + h * K1 / 3.0) + Ft[1]
            K3 = mm(Fx[2], Phi + h * (K2 - K1 / 3.0)) + Ft[2]
            K4 = mm(Fx[3], Phi + h * (K1 - K2 + K3)) + Ft[3]
            Phi = Phi + (K1 + 3.0 * (K2 + K3) + K4) * (h / 8.0)
            x = x + (k1 + 3.0 * (k2 + k3) + k4) * (h / 8.0)
        return x, Phi

    return _tagged(propagate, "rk4-3/8 propagator", model, substeps, mm)


def _stepped_propagator(model: ArmModel, substeps: int, mm: MatMul) -> Propagator:
    """`make_propagator` for a dynamic model (state ``[q, q̇, z]``): `substeps` steps of its
    stiff-stable integrator (`ArmModel.substep`) per sample interval, Φ_x `(3, n)` the exact
    Jacobian of that map by one reverse autograd pass, with `stage_jacobians`' device: the map
    runs on three copies of z and the gradient of the sum of copy i's entry i holds row i (no
    basis vectors, which the native code generator would have to translate)."""
    nx = model.state_size

    def rows(Z: Tensor, u: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
        x, theta = Z[:, :nx], Z[:, nx:]
        fric, arm = model.split(theta)
        h = dt / substeps
        for _ in range(substeps):
            x = model.substep(x, u, h, fric, arm)
        return sum(x[i, i] for i in range(nx)), x[0]

    def propagate(z: Tensor, u: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
        Phi, x = grad(rows, has_aux=True)(z.expand(nx, z.shape[0]), u, dt)
        return x, Phi

    return _tagged(propagate, "bristle propagator", model, substeps, mm)


def _tagged(
    propagate: Callable, name: str, model: ArmModel, substeps: int, mm: MatMul
) -> Propagator:
    """`propagate` carrying what `make_step` reads: its product `.mm`, the states before θ
    `.states`, and `.key`, what its code depends on (part of `compile_step`'s key; None for an
    unnamed product)."""
    propagate.mm = mm  # type: ignore[attr-defined]
    propagate.states = model.state_size  # type: ignore[attr-defined]
    propagate.key = step_key(name, structure_key(model), substeps, product_name(mm))  # type: ignore[attr-defined]
    return propagate


def finer_steps(
    filter_pass: Callable[[int], Any], f: Any, ledger: Any,
    exps: Sequence[Experiment], make: Callable[[int], Any], auto: bool,
) -> Callable[[int], Any]:  # fmt: skip
    """`filter_pass` (of `f`, a `passes.Filtering`, and its `passes.PassLedger` `ledger`), which
    under ``substeps = "auto"`` first gives `f` the step `make(n)` when the leading running
    member's θ (the highest likelihood so far; the start before the first pass) needs more RK4
    sub-steps than it has (`filter_substeps`, at most its `AUTO_SUBSTEPS`): the passes steepen the
    friction they start from, and a step that cannot follow its model moves θ away from stiff
    friction. The count only grows, and after a raise the running members' next pass is not
    judged against their passes at fewer sub-steps (another discretisation's likelihood: no
    rollback, no convergence by it). A member far off (an inertia 100 times too small) would
    ask for a step the others do not need, so only the lead counts."""
    if not auto:
        return filter_pass
    dt = max(e.dt for e in exps)

    def run(p: int) -> Any:
        running = torch.nonzero(ledger.running()).flatten()
        if running.numel() == 0:
            return filter_pass(p)
        lead = int(running[torch.argmax(ledger.best_ll[running])])
        theta = ledger.theta[lead]
        need = filter_substeps(ledger.model, dt, theta=theta)
        if need > f.substeps:  # ℓ of another discretisation: the next pass is not judged by it
            f.step_fn, f.substeps = make(need), need
            ledger.best_ll[running] = -math.inf
        return filter_pass(p)

    return run


def resolve_substeps(tuning: Any, model: ArmModel, experiments: Sequence[Experiment]) -> Any:
    """`tuning` (an `EKFTuning`) with ``substeps = "auto"`` replaced by the count
    `filter_substeps` gives `model` at its own θ for the records' longest sample interval; a
    tuning with a count as it is."""
    if tuning.substeps != "auto" or not experiments:
        return tuning
    steps = filter_substeps(model, max(e.dt for e in experiments))
    return dataclasses.replace(tuning, substeps=steps)
