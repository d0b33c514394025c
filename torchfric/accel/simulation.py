"""The "compiled" simulation engine: `simulate`'s rk4 as compiled chunks of solver steps.

The same RK4 (3/8 rule) steps (`torchfric.models.simulate.rk4_step`) on the same grid as the
"odeint" engine, run by `torchfric.accel.chunks.make_chunk` over `CHUNK` solver steps per call
(generated C first, the Inductor scan where that cannot serve a shape); it agrees with "odeint"
to rounding. Its gradient in θ and x0 is the discrete adjoint of those steps: a second compiled
scan runs backwards through the stored solver states with the autograd VJP of one step, so it
equals backpropagation through odeint's rk4 to rounding. Importing this module registers the
engine with `torchfric.models.simulate.register_engine` (`torchfric.accel` imports it).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import TorchfricError
from ..models.arm import ArmModel
from ..models.simulate import odeint_engine, register_engine, sample_grid, solver_step
from .chunks import chunk_options, fused_matmul, make_chunk, run_chunks, step_key, structure_key

__all__ = ["rk4_chunk", "rk4_members_chunk", "compiled_engine"]

# Compiled rk4 chunks by (structure_key, direction): (the model they were made for, chunk).
_RK4_CHUNKS: dict[tuple[str, str], tuple[ArmModel, object]] = {}


def rk4_chunk(model: ArmModel, direction: str = "forward"):  # type: ignore[no-untyped-def]
    """`make_chunk` of `rk4_step`, compiled once per process and model *structure*
    (`structure_key`: θ is an input, so the fitted models of successive passes or epochs share
    it).

    - ``"forward"``: ``chunk((x,), (u (C, ...), h (C,)), valid, (θ,)) -> ((x,), (states (C, ...),))``,
      each step with its own held input and length.
    - ``"backward"``: the discrete adjoint, run over the steps in reverse order:
      ``chunk((λ, g_θ), (x_k (C, ...), u (C, ...), h (C,), g_k (C, ...)), valid, (θ,))``. With λ
      the loss gradient with respect to the state after step k, one step gives
      ``λ ← g_k + (∂x_{k+1}/∂x_k)ᵀ λ`` and ``g_θ ← g_θ + (∂x_{k+1}/∂θ)ᵀ λ`` (the VJP of
      `rk4_step` by autograd), `g_k` being the loss's direct gradient with respect to x_k.
    """
    key = (structure_key(model), direction)
    if key not in _RK4_CHUNKS:
        one = _forward_step(model) if direction == "forward" else _adjoint_step(model)
        # Its loops run over 2 states and a few parameters, like the fused EKF step's.
        # Generated C first (`torchfric.accel.native`; a batch of B runs is B copies of the
        # step in one function), the Inductor scan where that cannot serve a shape.
        chunk = make_chunk(one, options=chunk_options(fused_matmul), native=True,
                           key=step_key("rk4 step", direction, key[0]))  # fmt: skip
        _RK4_CHUNKS[key] = (model, chunk)
    return _RK4_CHUNKS[key][1]


def rk4_members_chunk(model: ArmModel, theta_per_member: bool):  # type: ignore[no-untyped-def]
    """`rk4_chunk`'s forward step for a batch of runs, each with its own state and input (and
    θ, with `theta_per_member`): ``chunk((x (B, s),), (u (C, B), h (C,)), valid, (θ,))``. The
    generated code is traced for one run and runs four to a SIMD vector, split across the
    cores (`make_native_chunk`'s members), so a batch of any size shares one small library.
    The batched step traced whole instead was B copies of the step in one function: 64 LuGre
    windows of ``model.dynamic = "auto"`` were 11,500 statements and 11 s of gcc. Each run's
    steps are the same operations either way: the same numbers to the last bit (tested)."""
    key = (structure_key(model), f"forward, members{', theta' if theta_per_member else ''}")
    if key not in _RK4_CHUNKS:
        chunk = make_chunk(_forward_step(model), options=chunk_options(fused_matmul), native=True,
                           members=True, member_consts=(theta_per_member,), member_xs=(True, False),
                           key=step_key("rk4 step", key[1], key[0]))  # fmt: skip
        _RK4_CHUNKS[key] = (model, chunk)
    return _RK4_CHUNKS[key][1]


def _forward_step(model: ArmModel):  # type: ignore[no-untyped-def]
    """One rk4 step as a chunk function: ``(x, u, h, θ) -> ((x',), (x',))``."""

    def one(x: Tensor, u: Tensor, h: Tensor, theta: Tensor):  # type: ignore[no-untyped-def]
        x1 = solver_step(model, x, u, h, *model.split(theta))
        return (x1,), (x1,)

    return one


def _adjoint_step(model: ArmModel):  # type: ignore[no-untyped-def]
    """One step of the discrete adjoint as a chunk function:
    ``(λ, g_θ, x, u, h, g, θ) -> ((g + (∂x'/∂x)ᵀ λ, g_θ + (∂x'/∂θ)ᵀ λ), ())``."""

    def one(lam: Tensor, g_theta: Tensor, x: Tensor, u: Tensor, h: Tensor, g: Tensor,
            theta: Tensor):  # type: ignore[no-untyped-def]  # fmt: skip
        def step(x_: Tensor, th: Tensor) -> Tensor:
            return solver_step(model, x_, u, h, *model.split(th))

        _, pull = torch.func.vjp(step, x, theta)
        d_x, d_theta = pull(lam)
        return (g + d_x, g_theta + d_theta), ()

    return one


def _rk4_states(model: ArmModel, theta: Tensor, x0: Tensor, us: Tensor, hs: Tensor) -> Tensor:
    """Every solver state ``(T+1, [B,] 2)`` from `x0` over the steps ``(us, hs)``; no gradient."""
    (_,), (states,) = run_chunks(rk4_chunk(model), (x0.clone(),), (us, hs), (theta,))
    return torch.cat([x0.unsqueeze(0), states])


# Solver steps per block of a simulation without gradient (`_sampled_states`).
_BLOCK = 50_000


def _sampled_states(
    model: ArmModel, theta: Tensor, x0: Tensor, t: Tensor, u: Tensor, substeps: int
) -> Tensor:
    """The states at the sample times ``(n, [B,] state)`` from `x0`, `u` held per interval
    ``(n − 1, [B])`` of `t`, `substeps` solver steps per interval on `sample_grid`'s grid:
    `_rk4_states`' steps (a batch through `rk4_members_chunk`), run by blocks of about
    `_BLOCK` solver steps that keep only each interval's last state (a copy: a strided view
    would keep the whole block's sub-steps alive). Each block builds its own piece of the grid:
    the whole grid and its steps are two arrays of ``(n − 1)·substeps`` (1.2 GB for a 20-minute record at 64 sub-steps). A
    simulation needs no gradient through the sub-steps, and keeping them cost ``substeps``
    times the result: a 20-minute record's 9-member selection at 64 sub-steps grew by 0.46 GB
    a block of 50 k intervals, to 1.9 GiB, when the views kept them. The same steps in the
    same order: the same numbers to the last bit (a block's grid is the whole grid's piece,
    element for element)."""
    if x0.dim() == 2:  # a batch of B runs: u and θ with B rows, or one for all
        B = x0.shape[0]
        u = u[:, None] if u.dim() == 1 else u
        theta = theta[0] if theta.dim() == 2 and theta.shape[0] == 1 else theta
        rows = {"u": u.shape[1], **({"theta": theta.shape[0]} if theta.dim() == 2 else {})}
        wrong = {k: n for k, n in rows.items() if n not in (1, B)}
        if wrong:
            raise TorchfricError(f"a batch of {B} simulations (x0 {tuple(x0.shape)}) got "
                                 f"{', '.join(f'{k} with {n} runs' for k, n in wrong.items())}"
                                 f"; give each {B} runs or 1 for all")  # fmt: skip
        u = u.expand(-1, B)
        chunk = rk4_members_chunk(model, theta.dim() == 2)
    else:
        chunk = rk4_chunk(model)
    out, x = [x0.unsqueeze(0)], x0.clone()
    intervals = max(1, _BLOCK // substeps)
    for i in range(0, u.shape[0], intervals):
        j = min(i + intervals, u.shape[0])
        us = u[i:j].repeat_interleave(substeps, dim=0)
        grid = sample_grid(t[i : j + 1], substeps)
        (x,), (states,) = run_chunks(chunk, (x,), (us, grid[1:] - grid[:-1]), (theta,))
        out.append(states[substeps - 1 :: substeps].clone() if substeps > 1 else states)
    return torch.cat(out)


class _CompiledRK4(torch.autograd.Function):
    """All solver states ``(T+1, [B,] 2)`` of rk4 from `x0` over the steps ``(us, hs)``, with
    the exact gradient of that discrete map by a compiled reverse scan (`rk4_chunk`)."""

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
        (lam, g_theta), _ = run_chunks(
            rk4_chunk(ctx.model, "backward"), carry, xs, (th,), reverse=True
        )
        return g_theta, lam, None, None, None


def compiled_engine(
    model: ArmModel,
    t: Tensor,
    u: Tensor,
    x0: Tensor,
    theta: Tensor,
    *,
    grid: Tensor | None,
    substeps: int,
    method: str,
) -> Tensor:
    """The "compiled" engine (`torchfric.models.simulate.Engine`): rk4 on `sample_grid`'s
    grid (`substeps` solver steps per sample) through `rk4_chunk`, differentiable in θ and x0
    (`_CompiledRK4`) when either needs a gradient; another `method` goes through
    `odeint_engine`. It builds the grid itself (`builds_grid`): without a gradient, a block at
    a time."""
    n = t.numel()
    if not (torch.is_grad_enabled() and (theta.requires_grad or x0.requires_grad)) and (
        method == "rk4" or model.state_size != 2
    ):
        with torch.no_grad():
            return _sampled_states(model, theta.detach(), x0.detach(), t, u[:-1], substeps)[:n]
    grid = sample_grid(t, substeps) if grid is None else grid
    if method != "rk4" and model.state_size == 2:
        return odeint_engine(model, t, u, x0, theta, grid=grid, substeps=substeps, method=method)
    hs = grid[1:] - grid[:-1]
    us = u[:-1].repeat_interleave(substeps, dim=0)  # u_k held over its interval's sub-steps
    states = _CompiledRK4.apply(theta, x0, us, hs, model)
    return states[::substeps][:n]


compiled_engine.builds_grid = True  # type: ignore[attr-defined]
register_engine("compiled", compiled_engine)
