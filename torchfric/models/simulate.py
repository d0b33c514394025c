"""Open-loop simulation of an `ArmModel` through `torchdiffeq.odeint` with zero-order-hold input.

The input is an *exact* zero-order hold: every solver stage inside sample interval ``[t_k,
t_{k+1}]`` sees ``u_k``, including the stage at the interval's end. torchdiffeq's fixed-grid
solvers evaluate the first stage of a step at ``nextafter(t0, +inf)`` and the last at
``nextafter(t1, −inf)`` when ``perturb=True``; the input lookup compares those times with the
sample grid itself (``searchsorted``), never a rounded ``(t − t0)/dt``, so no stage at ``t_{k+1}``
picks up ``u_{k+1}``. Each sample interval is split into `substeps` equal solver steps on a grid
that contains the sample times exactly, so the returned states are the solver's own, not
interpolated.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor, nn

from ..errors import TorchfricError
from .arm import ArmModel

__all__ = [
    "simulate",
    "rk4_step",
    "solver_step",
    "full_state",
    "steady_bristles",
    "auto_substeps",
    "filter_substeps",
    "AUTO_SUBSTEPS",
    "BRISTLE_OMEGA_H",
    "stiffness_speeds",
    "friction_stiffness",
    "bristle_stiffness",
    "sample_grid",
    "SOLVERS",
    "ENGINES",
    "Engine",
    "register_engine",
    "odeint_engine",
    "ZOHField",
]

# Fixed-grid solvers and the largest stable |λ h| on the negative real axis we allow for them
# (the theoretical limits are 2, 2 and 2.78; a margin keeps stiff friction well damped).
SOLVERS: dict[str, float] = {"euler": 1.0, "midpoint": 1.5, "rk4": 2.0}


class ZOHField(nn.Module):
    """``ẋ = f(x, u(t); θ)`` with ``u(t) = u_k`` for ``t ∈ [t_k, t_{k+1})`` (torchdiffeq signature)."""

    def __init__(self, model: ArmModel, t: Tensor, u: Tensor, theta: Tensor | None) -> None:
        super().__init__()
        self.model = model
        self.t = t
        self.u = u
        # θ is constant over the integration: split it into physical parameters once.
        self.fric, self.arm = model.split(model.theta_vector() if theta is None else theta)
        self.last = t.numel() - 1

    def forward(self, time: Tensor, x: Tensor) -> Tensor:
        k = torch.searchsorted(self.t, time.reshape(1), right=True) - 1
        k = int(k.clamp(0, self.last))
        return self.model.dynamics(x, self.u[k], self.fric, self.arm)


Engine = Callable[..., Tensor]
"""``engine(model, t, u, x0, theta, *, grid, substeps, method) -> states``: one way to run
`simulate`'s checked problem. `theta` is θ `(k,)` (the model's own when the caller gave none),
`grid` the solver grid (`sample_grid`, `substeps` solver steps per sample interval), `method`
one of `SOLVERS`; it returns the states at the sample times `t`, as `simulate` does. An engine
with a true attribute ``builds_grid`` gets ``grid=None`` and builds what it needs of the grid
itself (the compiled engine, a block at a time: the whole grid of a 20-minute record at 64
sub-steps is 0.6 GB)."""


def odeint_engine(
    model: ArmModel,
    t: Tensor,
    u: Tensor,
    x0: Tensor,
    theta: Tensor,
    *,
    grid: Tensor,
    substeps: int,
    method: str,
) -> Tensor:
    """The "odeint" engine: torchdiffeq's fixed-grid `method` on `grid` with the exact
    zero-order hold of `ZOHField` (differentiable by autograd; the reference)."""
    if model.state_size != 2:
        return _stepped(model, u, x0, theta, grid, substeps)
    field = ZOHField(model, t, u, theta)
    options = {"grid_constructor": lambda _f, _y0, _t: grid, "perturb": True}
    from torchdiffeq import odeint  # on use: it imports scipy.integrate (0.4 s)

    return odeint(field, x0, t, method=method, options=options)


# The simulation engines by name, in the manner of torchdiffeq's solver table. "odeint":
# torchdiffeq (differentiable, the reference), always here. "compiled": the same RK4 (3/8 rule)
# steps on the same grid as a compiled scan over 1000 solver steps per call; agrees with
# "odeint" to rounding (tested). Its gradient (θ and x0) is the discrete adjoint of those steps:
# a second compiled scan runs backwards through the stored solver states with the autograd VJP
# of one step, so it equals backpropagation through odeint's rk4 to rounding (tested). It lives
# in `torchfric.accel.simulation`, which registers it (`register_engine`) when `torchfric.accel`
# is imported, as importing `torchfric` does; models never import accel.
ENGINES: dict[str, Engine] = {"odeint": odeint_engine}

# Engines that another part of torchfric registers, and the module that does.
_REGISTERED_BY = {"compiled": "torchfric.accel"}


def _stepped(
    model: ArmModel, u: Tensor, x0: Tensor, theta: Tensor, grid: Tensor, substeps: int
) -> Tensor:
    """A dynamic model's reference simulation: `solver_step` over `grid`, u held per sample, as
    a Python loop (differentiable by autograd). Returns every state at the sample times."""
    fric, arm = model.split(theta)
    hs = grid[1:] - grid[:-1]
    x, out = x0, [x0]
    for i in range(hs.numel()):
        x = solver_step(model, x, u[i // substeps], hs[i], fric, arm)
        if (i + 1) % substeps == 0:
            out.append(x)
    return torch.stack(out)


def register_engine(name: str, engine: Engine) -> None:
    """Make `engine` (see `Engine`) available as ``simulate(..., engine=name)``; a later
    registration under the same name replaces the earlier one."""
    if not isinstance(name, str) or not name:
        raise TorchfricError(f"an engine name must be a non-empty string, got {name!r}")
    if not callable(engine):
        raise TorchfricError(f"engine {name!r} must be callable, got {type(engine).__name__}")
    ENGINES[name] = engine


def _engine(name: str) -> Engine:
    """The registered engine `name`, or a one-line error saying why there is none. An engine
    that another part of torchfric registers (`_REGISTERED_BY`) is registered here on first
    use, by importing that module (``import torchfric`` is lazy and no longer imports it)."""
    if name not in ENGINES and name in _REGISTERED_BY:
        import importlib

        importlib.import_module(_REGISTERED_BY[name])
    if name in ENGINES:
        return ENGINES[name]
    if name in _REGISTERED_BY:
        raise TorchfricError(
            f"simulation engine {name!r} is not registered: import {_REGISTERED_BY[name]} "
            "to register it"
        )
    raise TorchfricError(f"unknown simulation engine {name!r}; choose one of {tuple(ENGINES)}")


def sample_grid(t: Tensor, substeps: int) -> Tensor:
    """Solver grid `((N−1)·S + 1,)` that splits every sample interval into S equal steps and
    contains every sample time exactly (so states at the samples are not interpolated)."""
    frac = torch.arange(substeps, dtype=t.dtype) / substeps
    inner = (t[:-1, None] + (t[1:] - t[:-1])[:, None] * frac).reshape(-1)
    return torch.cat([inner, t[-1:]])


def auto_substeps(
    model: ArmModel,
    dt: float,
    method: str = "rk4",
    *,
    theta: Tensor | None = None,
    max_substeps: int = 64,
) -> int:
    """Smallest sub-step count that keeps the explicit solver stable for the model's stiffest
    friction slope: ``S = ⌈λ·dt / c⌉`` with ``λ = max |∂q̈/∂q̇|`` over velocities from 1e-4 to 1e3
    and `c` the solver's allowed ``|λh|`` (`SOLVERS`), for the model's own θ or a given one."""
    theta = (model.theta_vector() if theta is None else theta).detach()
    if model.state_size != 2:
        return _bristle_substeps(model, dt, theta, max_substeps)
    lam = friction_stiffness(model, theta)
    return int(min(max(1, math.ceil(lam * dt / SOLVERS[method])), max_substeps))


AUTO_SUBSTEPS = 16
"""The most RK4 sub-steps ``estimator.substeps = "auto"`` gives the filter (`filter_substeps`'
default cap): a pass costs about that many passes of one sub-step, and each new count builds its
generated step once (tanh(3) at 16: about 15 s, then cached); a run whose model needs more is
warned about at its end."""


def filter_substeps(
    model: ArmModel, dt: float, *, theta: Tensor | None = None, max_substeps: int = AUTO_SUBSTEPS
) -> int:
    """The RK4 sub-steps ``estimator.substeps = "auto"`` gives the EKF's prediction of a static
    model: the fewest that keep RK4 stable, ``|λ h| <= SOLVERS["rk4"]``, on its steepest
    friction slope at θ (`friction_stiffness`: `auto_substeps`' own count). A step past the
    limit is not a small error: the filter then cannot follow the model it fits, and its passes
    can move θ away from stiff friction (on one Stribeck axis whose true law the model held:
    inertia +14 %, docs/results.md). A dynamic model's step (`ArmModel.substep`, semi-implicit
    in the bristles) is stable at any stiffness: 1."""
    if model.state_size != 2:
        return 1
    return auto_substeps(model, dt, "rk4", theta=theta, max_substeps=max_substeps)


# A dynamic model's sub-step keeps ω h <= this, ω = sqrt(σ0/M) the bristle resonance: its
# stiff parts are exact or implicit at any h, the resonance is what h must resolve (on the rig,
# 2 sub-steps per ms: open-loop FIT 99.98 % against the rig's own 10 sub-steps; 1: 99.92 %).
BRISTLE_OMEGA_H = 0.1


def _bristle_substeps(model: ArmModel, dt: float, theta: Tensor, max_substeps: int) -> int:
    """`auto_substeps` of a dynamic model: ``S = ⌈ω dt / 0.1⌉`` with ``ω = sqrt(σ0/M)``."""
    return int(min(max(1, math.ceil(bristle_stiffness(model, theta) * dt)), max_substeps))


def bristle_stiffness(model: ArmModel, theta: Tensor) -> float:
    """A dynamic model's sub-steps per second of `auto_substeps`, ``ω / 0.1`` with
    ``ω = sqrt(σ0/M)`` its bristle resonance; a one-line error when it is not finite."""
    arm = model.split(theta)[1]
    rate = float(torch.sqrt(arm["lugre_sigma0"] / arm["inertia"])) / BRISTLE_OMEGA_H
    if not math.isfinite(rate):
        raise TorchfricError(
            "the model's bristle stiffness is not finite; check the parameters (NaN or inf in θ)"
        )
    return rate


def stiffness_speeds() -> Tensor:
    """The 401 velocities `friction_stiffness` reads the friction's slope at: 0 and ±1e-4 … 1e3,
    200 per side, evenly spaced in log."""
    mags = torch.logspace(-4, 3, 200, dtype=torch.float64)
    return torch.cat([-mags.flip(0), torch.zeros(1, dtype=torch.float64), mags])


def friction_stiffness(model: ArmModel, theta: Tensor) -> float:
    """λ = max |∂q̈/∂q̇| over |q̇| in [1e-4, 1e3] for θ `theta`: the stiffness `auto_substeps`
    (and the exported module's own rule) sizes the sub-steps by. A one-line error when it is
    not finite."""
    v = stiffness_speeds().requires_grad_(True)
    with torch.enable_grad():
        (g,) = torch.autograd.grad(model.friction_torque(v, theta).sum(), v)
    lam = float(g.detach().abs().max() / model.split(theta)[1]["inertia"])
    if not math.isfinite(lam):
        raise TorchfricError(
            "the model's friction slope is not finite; check the parameters (NaN or inf in θ)"
        )
    return lam


def simulate(
    model: ArmModel,
    t: Tensor,
    u: Tensor,
    x0: Tensor,
    *,
    method: str = "rk4",
    substeps: int | str = "auto",
    theta: Tensor | None = None,
    max_substeps: int = 64,
    engine: str = "odeint",
) -> Tensor:
    """Simulate ``ẋ = f(x, u; θ)`` from `x0` at the sample times `t` with zero-order-hold `u`.

    Args:
        model: the arm.
        t: `(N,)` strictly increasing sample times.
        u: `(N,)` input, or `(N, B)` for a batch of B runs.
        x0: `(2,)` initial ``[q, q̇]``, or `(B, 2)`; a dynamic model starts its bristle state
            at the steady deflection of q̇ (`full_state`), or takes `(…, 3)` ``[q, q̇, z]``.
        method: fixed-grid solver, one of `SOLVERS` ("rk4" default); a dynamic model always
            takes its own stiff-stable step (`solver_step`), whatever the method.
        substeps: solver steps per sample interval, or "auto" (`auto_substeps`).
        theta: optional θ `(k,)` in estimation coordinates (default: the model's own, differentiable).
        engine: "odeint" (torchdiffeq, default) or "compiled" (`ENGINES`: the same rk4 steps as
            a compiled scan, batches included; gradients in θ and `x0` by a compiled discrete
            adjoint, none in `t` or `u`; another solver goes through odeint), or any engine
            added with `register_engine`.

    Returns:
        `(N, 2)` (or `(N, B, 2)`) states ``[q, q̇]`` at the sample times; row 0 is `x0`.
        A dynamic model's internal state (z) is not returned.
    """
    if method not in SOLVERS:
        raise TorchfricError(f"unknown solver {method!r}; choose one of {sorted(SOLVERS)}")
    t = torch.as_tensor(t, dtype=torch.float64)
    u = torch.as_tensor(u, dtype=torch.float64)
    x0 = torch.as_tensor(x0, dtype=torch.float64)
    if t.ndim != 1 or t.numel() < 2:
        raise TorchfricError(
            f"t must be a 1-D tensor of at least 2 samples, got shape {tuple(t.shape)}"
        )
    if u.shape[0] != t.numel():
        raise TorchfricError(
            f"u has {u.shape[0]} samples but t has {t.numel()}; give one input per sample"
        )
    if x0.shape[-1] not in (2, model.state_size):
        whole = " or 3 [q, qdot, z]" if model.state_size == 3 else ""
        raise TorchfricError(
            f"x0 must end in 2 entries [q, qdot]{whole}, got shape {tuple(x0.shape)}"
        )
    if not bool((t[1:] > t[:-1]).all()):
        raise TorchfricError("t must be strictly increasing")
    if theta is not None and theta.shape[-1] != model.num_parameters:
        raise TorchfricError(
            f"theta has {theta.shape[-1]} entries but this model has {model.num_parameters} "
            f"({', '.join(model.theta_names)})"
        )
    if substeps == "auto":
        dt = float((t[1:] - t[:-1]).max())  # the longest interval sets the stability limit
        steps = auto_substeps(model, dt, method, theta=theta, max_substeps=max_substeps)
    elif isinstance(substeps, int) and not isinstance(substeps, bool) and substeps >= 1:
        steps = substeps
    else:
        raise TorchfricError(f"substeps must be a positive integer or 'auto', got {substeps!r}")
    run = _engine(engine)
    grid = None if getattr(run, "builds_grid", False) else sample_grid(t, steps)
    th = model.theta_vector() if theta is None else theta
    x0 = full_state(model, x0, th)
    states = run(model, t, u, x0, th, grid=grid, substeps=steps, method=method)
    return states[..., :2] if model.state_size != 2 else states


def full_state(model: ArmModel, x0: Tensor, theta: Tensor) -> Tensor:
    """`x0 (..., 2)` ``[q, q̇]`` as the model's whole state: unchanged for a static model; for a
    dynamic one with the bristles at the steady deflection of q̇ appended (0 at rest). An
    `x0` that already holds the whole state is returned as it is."""
    if x0.shape[-1] == model.state_size:
        return x0
    z = steady_bristles(model, x0[..., 1], *model.split(theta))
    return torch.cat([x0, z.unsqueeze(-1)], dim=-1)


def steady_bristles(model: ArmModel, v: Tensor, fric, arm) -> Tensor:  # type: ignore[no-untyped-def]
    """A dynamic model's steady bristle deflection at velocity `v`, ``sign(v) g(v) / σ0`` (0 at
    rest), for the physical dicts of `ArmModel.split`."""
    return model.black_box(v, fric, arm) / arm["lugre_sigma0"]


def solver_step(
    model: ArmModel, x: Tensor, u: Tensor, h: Tensor | float, fric, arm, method: str = "rk4"
) -> Tensor:  # type: ignore[no-untyped-def]
    """One solver step of the model with held input `u`: for a static model `method`'s step as
    torchdiffeq's fixed-grid solver takes it (`rk4_step`; euler ``x + h f(x)``; midpoint
    ``x + h f(x + h/2 f(x))``), the stiff-stable `ArmModel.substep` for a dynamic one (state
    ``[q, q̇, z]``) whatever the method."""
    if model.state_size != 2:
        return model.substep(x, u, h, fric, arm)
    if method == "rk4":
        return rk4_step(model, x, u, h, fric, arm)
    k1 = model.dynamics(x, u, fric, arm)
    if method == "midpoint":
        return x + h * model.dynamics(x + k1 * (0.5 * h), u, fric, arm)
    return x + h * k1


def rk4_step(model: ArmModel, x: Tensor, u: Tensor, h: Tensor | float, fric, arm) -> Tensor:  # type: ignore[no-untyped-def]
    """One classical RK4 (3/8 rule) step of length `h` with held input `u`, as torchdiffeq's
    ``rk4`` takes it; `fric`, `arm` from `model.split(θ)`."""
    k1 = model.dynamics(x, u, fric, arm)
    k2 = model.dynamics(x + h * k1 / 3.0, u, fric, arm)
    k3 = model.dynamics(x + h * (k2 - k1 / 3.0), u, fric, arm)
    k4 = model.dynamics(x + h * (k1 - k2 + k3), u, fric, arm)
    return x + (k1 + 3.0 * (k2 + k3) + k4) * h * 0.125
