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

import json
import math

import torch
from torch import Tensor, nn
from torchdiffeq import odeint

from ..errors import TorchfricError
from .arm import ArmModel

__all__ = ["simulate", "rk4_step", "auto_substeps", "sample_grid", "SOLVERS", "ENGINES"]

# "odeint": torchdiffeq (differentiable, the reference). "compiled": the same RK4 (3/8 rule)
# steps on the same grid as a `torch.compile`d scan over 1000 solver steps per call; agrees with
# "odeint" to rounding (tested). Its gradient (θ and x0) is the discrete adjoint of those steps:
# a second compiled scan runs backwards through the stored solver states with the autograd VJP
# of one step, so it equals backpropagation through odeint's rk4 to rounding (tested).
ENGINES = ("odeint", "compiled")
_CHUNK = 1000

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
    mags = torch.logspace(-4, 3, 200, dtype=torch.float64)
    v = torch.cat([-mags.flip(0), torch.zeros(1, dtype=torch.float64), mags]).requires_grad_(True)
    theta = (model.theta_vector() if theta is None else theta).detach()
    with torch.enable_grad():
        (g,) = torch.autograd.grad(model.friction_torque(v, theta).sum(), v)
    lam = float(g.detach().abs().max() / model.split(theta)[1]["inertia"])
    if not math.isfinite(lam):
        raise TorchfricError(
            "the model's friction slope is not finite; check the parameters (NaN or inf in θ)"
        )
    return int(min(max(1, math.ceil(lam * dt / SOLVERS[method])), max_substeps))


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
        x0: `(2,)` initial ``[q, q̇]``, or `(B, 2)`.
        method: fixed-grid solver, one of `SOLVERS` ("rk4" default).
        substeps: solver steps per sample interval, or "auto" (`auto_substeps`).
        theta: optional θ `(k,)` in estimation coordinates (default: the model's own, differentiable).
        engine: "odeint" (torchdiffeq, default) or "compiled" (`ENGINES`: the same rk4 steps as
            a compiled scan, batches included; gradients in θ and `x0` by a compiled discrete
            adjoint, none in `t` or `u`; another solver goes through odeint).

    Returns:
        `(N, 2)` (or `(N, B, 2)`) states ``[q, q̇]`` at the sample times; row 0 is `x0`.
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
    if x0.shape[-1] != 2:
        raise TorchfricError(f"x0 must end in 2 entries [q, qdot], got shape {tuple(x0.shape)}")
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
    if engine not in ENGINES:
        raise TorchfricError(f"unknown simulation engine {engine!r}; choose one of {ENGINES}")
    grid = sample_grid(t, steps)
    th = model.theta_vector() if theta is None else theta
    if engine == "compiled" and method == "rk4":
        return _compiled_rk4(model, grid, u, x0, th, steps)
    field = ZOHField(model, t, u, theta)
    options = {"grid_constructor": lambda _f, _y0, _t: grid, "perturb": True}
    return odeint(field, x0, t, method=method, options=options)


def rk4_step(model: ArmModel, x: Tensor, u: Tensor, h: Tensor | float, fric, arm) -> Tensor:  # type: ignore[no-untyped-def]
    """One classical RK4 (3/8 rule) step of length `h` with held input `u`, as torchdiffeq's
    ``rk4`` takes it; `fric`, `arm` from `model.split(θ)`."""
    k1 = model.dynamics(x, u, fric, arm)
    k2 = model.dynamics(x + h * k1 / 3.0, u, fric, arm)
    k3 = model.dynamics(x + h * (k2 - k1 / 3.0), u, fric, arm)
    k4 = model.dynamics(x + h * (k1 - k2 + k3), u, fric, arm)
    return x + (k1 + 3.0 * (k2 + k3) + k4) * h * 0.125


_RK4_CHUNKS: dict[tuple[str, str], object] = {}


def _structure_key(model: ArmModel) -> str:
    """What fixes a model's compiled code: its spec without θ's values."""
    spec = model.spec()
    spec["friction"] = {k: v for k, v in spec["friction"].items() if k != "values"}
    spec.pop("arm", None)  # θ's physical values; everything else fixes the structure
    return json.dumps(spec, sort_keys=True, default=str)


def _rk4_chunk(model: ArmModel, direction: str = "forward"):  # type: ignore[no-untyped-def]
    """`torchfric.ekf.make_chunk` of `rk4_step`, compiled once per process and model
    *structure* (θ is an input, so the fitted models of successive passes or epochs share it).

    - ``"forward"``: ``chunk((x,), (u (C, ...), h (C,)), valid, (θ,)) -> ((x,), (states (C, ...),))``,
      each step with its own held input and length.
    - ``"backward"``: the discrete adjoint, run over the steps in reverse order:
      ``chunk((λ, g_θ), (x_k (C, ...), u (C, ...), h (C,), g_k (C, ...)), valid, (θ,))``. With λ
      the loss gradient with respect to the state after step k, one step gives
      ``λ ← g_k + (∂x_{k+1}/∂x_k)ᵀ λ`` and ``g_θ ← g_θ + (∂x_{k+1}/∂θ)ᵀ λ`` (the VJP of
      `rk4_step` by autograd), `g_k` being the loss's direct gradient with respect to x_k.
    """
    key = (_structure_key(model), direction)
    if key not in _RK4_CHUNKS:
        from ..estimators.ekf import chunk_options, fused_matmul, make_chunk

        if direction == "forward":

            def one(x: Tensor, u: Tensor, h: Tensor, theta: Tensor):  # type: ignore[no-untyped-def]
                x1 = rk4_step(model, x, u, h, *model.split(theta))
                return (x1,), (x1,)

        else:

            def one(lam: Tensor, g_theta: Tensor, x: Tensor, u: Tensor, h: Tensor, g: Tensor,
                    theta: Tensor):  # type: ignore[no-untyped-def]  # fmt: skip
                def step(x_: Tensor, th: Tensor) -> Tensor:
                    return rk4_step(model, x_, u, h, *model.split(th))

                _, pull = torch.func.vjp(step, x, theta)
                d_x, d_theta = pull(lam)
                return (g + d_x, g_theta + d_theta), ()

        # Its loops run over 2 states and a few parameters, like the fused EKF step's.
        # Generated C first (`torchfric.native`; a batch of B runs is B copies of the step in
        # one function), the Inductor scan where that cannot serve a shape.
        chunk = make_chunk(one, options=chunk_options(fused_matmul), native=True)
        _RK4_CHUNKS[key] = (model, chunk)
    return _RK4_CHUNKS[key][1]  # type: ignore[index]


def _run_chunks(chunk, carry, xs, consts, *, reverse: bool = False):  # type: ignore[no-untyped-def]
    """Apply a `make_chunk` function along the leading axis of `xs` (T rows), `_CHUNK` rows per
    call (the last call padded); returns the final carry and each per-row output (T rows)."""
    from ..estimators.ekf import iter_chunks

    if reverse:
        xs = tuple(a.flip(0) for a in xs)
    outs: list[tuple[Tensor, ...]] = []
    for _, m, part, valid in iter_chunks(xs, _CHUNK):
        carry, o = chunk(carry, part, valid, consts)
        outs.append(tuple(a[:m] for a in o))
    joined = tuple(torch.cat(cols) for cols in zip(*outs, strict=True)) if outs else ()
    return carry, joined


def _rk4_states(model: ArmModel, theta: Tensor, x0: Tensor, us: Tensor, hs: Tensor) -> Tensor:
    """Every solver state ``(T+1, [B,] 2)`` from `x0` over the steps ``(us, hs)``; no gradient."""
    (_,), (states,) = _run_chunks(_rk4_chunk(model), (x0.clone(),), (us, hs), (theta,))
    return torch.cat([x0.unsqueeze(0), states])


class _CompiledRK4(torch.autograd.Function):
    """All solver states ``(T+1, [B,] 2)`` of rk4 from `x0` over the steps ``(us, hs)``, with
    the exact gradient of that discrete map by a compiled reverse scan (`_rk4_chunk`)."""

    @staticmethod
    def forward(ctx, theta: Tensor, x0: Tensor, us: Tensor, hs: Tensor, model: ArmModel) -> Tensor:  # type: ignore[no-untyped-def,override]
        th = theta.detach()
        states = _rk4_states(model, th, x0.detach(), us, hs)
        ctx.model = model
        ctx.save_for_backward(th, states, us, hs)
        return states

    @staticmethod
    def backward(ctx, g_states: Tensor):  # type: ignore[no-untyped-def,override]
        th, states, us, hs = ctx.saved_tensors
        carry = (g_states[-1].clone(), torch.zeros_like(th))
        xs = (states[:-1], us, hs, g_states[:-1])
        (lam, g_theta), _ = _run_chunks(
            _rk4_chunk(ctx.model, "backward"), carry, xs, (th,), reverse=True
        )
        return g_theta, lam, None, None, None


def _compiled_rk4(
    model: ArmModel, grid: Tensor, u: Tensor, x0: Tensor, theta: Tensor, steps: int
) -> Tensor:
    """`simulate`'s rk4 on `grid` (`steps` solver steps per sample) through `_rk4_chunk`;
    differentiable in θ and x0 (`_CompiledRK4`) when either needs a gradient."""
    n = (grid.numel() - 1) // steps + 1
    hs = grid[1:] - grid[:-1]
    us = u[:-1].repeat_interleave(steps, dim=0)  # u_k held over its interval's sub-steps
    if torch.is_grad_enabled() and (theta.requires_grad or x0.requires_grad):
        states = _CompiledRK4.apply(theta, x0, us, hs, model)
    else:
        with torch.no_grad():
            states = _rk4_states(model, theta.detach(), x0.detach(), us, hs)
    return states[::steps][:n]
