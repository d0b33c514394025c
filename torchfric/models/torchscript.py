"""Export an identified model as a TorchScript module that loads without torchfric.

The module offers ``simulate(t, u, x0) -> (q, qdot)``, ``simulate_batch(t, u, x0)``,
``field(x, u)`` (the vector field), ``friction(v)`` (total friction ``C(v) + b v + offset +
a |v|``, the terms the model has), ``substeps_for(t)`` and ``parameters`` (physical values by
name).

Nothing of the physics is written here a second time:

- the white-box terms are `torchfric.arm.arm_field` / `arm_friction`, the functions that
  `ArmModel.dynamics` and `ArmModel.friction_torque` call (TorchScript compiles them into the
  module);
- the black-box curve C(v) is the model's own `Friction.evaluate`, traced at the identified
  parameter values (physical values, exactly the ones `ArmModel.split` gives the simulator);
- the integrator repeats torchdiffeq's fixed-grid step (`torchfric.simulate` goes through
  ``odeint``) on the grid of `torchfric.simulate.sample_grid`, with exact zero-order hold.

The sub-step count follows the sample time the module is called with: with ``substeps="auto"``
it is `torchfric.simulate.auto_substeps`' rule ``S = min(max(1, ⌈λ·dt/c⌉), max_substeps)`` (λ the
model's stiffest friction slope over M, computed at export; dt the longest interval of the `t`
passed in), so the module simulates correctly at any sample time and agrees with
``torchfric.simulate(model, t, u, x0)`` to rounding. A fixed integer `substeps` is used as is,
like ``simulate(..., substeps=S)``.
"""

from __future__ import annotations

import io
import math
import pathlib
import warnings
from typing import Any

import torch
from torch import Tensor, nn

from ..errors import TorchfricError
from ..files import atomic_write_bytes
from .arm import ArmModel, arm_field, arm_friction, external_torque
from .lugre import (
    LUGRE_NAMES,
    bristle_field,
    bristle_solve,
    positive_level,
)
from .simulate import SOLVERS, bristle_stiffness, friction_stiffness

__all__ = ["ExportedArm", "export_model", "save_exported"]

_METHODS = {"euler": 0, "midpoint": 1, "rk4": 2}


class _FrictionCurve(nn.Module):
    """``C(v)`` of a `Friction` module at fixed physical parameter values (buffers named as the
    friction's parameters): the friction's own `evaluate`, for `torch.jit.trace` on 1-D `v`."""

    def __init__(self, model: ArmModel, fric: dict[str, Tensor]) -> None:
        super().__init__()
        self._names = list(fric)
        for name, value in fric.items():
            self.register_buffer(name, value.detach().clone())
        # A bound method, not a submodule: the trace records its operations only.
        self._evaluate = model.friction.evaluate

    def forward(self, v: Tensor) -> Tensor:
        return self._evaluate(v, {name: getattr(self, name) for name in self._names})


def _trace_curve(model: ArmModel, fric: dict[str, Tensor]) -> torch.jit.ScriptModule:
    curve = _FrictionCurve(model, fric)
    example = torch.linspace(-2.0, 2.0, 7, dtype=torch.float64)
    checks = [
        (torch.linspace(-50.0, 50.0, 101, dtype=torch.float64),),
        (torch.zeros(1, dtype=torch.float64),),
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            traced = torch.jit.trace(curve, (example,), check_inputs=checks)
        except Exception as exc:  # a friction whose evaluate the tracer cannot follow
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise TorchfricError(
                f"cannot export the {model.friction.kind!r} friction as TorchScript ({first})"
            ) from None
    return traced


class ExportedArm(nn.Module):
    """Self-contained arm simulator (TorchScript-compatible; physical parameter values).

    Args:
        model: the identified arm; its current θ is frozen into the module.
        substeps: solver steps per sample interval, or ``"auto"`` (chosen per call from the
            sample time, `torchfric.simulate.auto_substeps`' rule).
        method: fixed-grid solver, one of `torchfric.simulate.SOLVERS` (as in `simulate`).
        max_substeps: cap of the automatic count (`simulate`'s `max_substeps`).
        dt: the sample time of the training data, kept as metadata (``nominal_dt``; 0 = unknown);
            the module simulates at whatever sample time `t` has.
    """

    def __init__(
        self,
        model: ArmModel,
        substeps: int | str = "auto",
        *,
        method: str = "rk4",
        max_substeps: int = 64,
        dt: float | None = None,
    ) -> None:
        super().__init__()
        if not isinstance(model, ArmModel):
            raise TorchfricError(f"model must be a torchfric ArmModel, got {type(model).__name__}")
        if method not in _METHODS:
            raise TorchfricError(f"unknown solver {method!r}; choose one of {sorted(SOLVERS)}")
        if substeps == "auto":
            fixed = 0
        elif isinstance(substeps, int) and not isinstance(substeps, bool) and substeps >= 1:
            fixed = int(substeps)
        else:
            raise TorchfricError(f"substeps must be a positive integer or 'auto', got {substeps!r}")
        if isinstance(max_substeps, bool) or not isinstance(max_substeps, int) or max_substeps < 1:
            raise TorchfricError(f"max_substeps must be a positive integer, got {max_substeps!r}")
        theta = model.get_theta()
        if not bool(torch.isfinite(theta).all()):
            raise TorchfricError(
                "the model's θ holds NaN or inf; a checkpoint with such values cannot be exported"
            )
        with torch.no_grad():
            fric, arm = model.split(theta)
        self.kind = model.friction.kind
        self.method = _METHODS[method]
        self.method_name = method
        self.fixed_substeps = fixed
        self.max_substeps = int(max_substeps)
        self.stability = float(SOLVERS[method])
        # A dynamic model (bristle state z, `torchfric.models.lugre`): its own stiff-stable
        # step; `stiffness` then holds the rule's ω/c per unit dt (sub-steps = ⌈stiffness·dt⌉).
        self.dynamic = model.state_size != 2
        self.stiffness = (
            bristle_stiffness(model, theta) if self.dynamic else friction_stiffness(model, theta)
        )
        if self.dynamic:
            self.stability = 1.0
        self.nominal_dt = 0.0 if dt is None else float(dt)
        self.parameters_by_name = model.physical_parameters()
        self.curve = _trace_curve(model, fric)
        self.register_buffer("c_m", arm["c_m"].detach().clone().reshape(()))
        self.register_buffer("inertia", arm["inertia"].detach().clone().reshape(()))
        # Terms the model lacks stay None, exactly as in ArmModel.dynamics.
        for name in ("viscous", "offset", "gravity", "asymmetric", *LUGRE_NAMES):
            value = arm.get(name)
            self.register_buffer(name, None if value is None else value.detach().clone())
        zero = torch.zeros((), dtype=torch.float64)
        self.s0 = zero if self.lugre_sigma0 is None else self.lugre_sigma0.reshape(())
        self.s1 = zero if self.lugre_sigma1 is None else self.lugre_sigma1.reshape(())
        self.vs = zero if self.lugre_vstick is None else self.lugre_vstick.reshape(())

    def curve_of(self, v: Tensor) -> Tensor:
        """C(v) of the friction module alone, any shape."""
        return self.curve(v.reshape(-1)).reshape(v.shape)

    def level(self, v: Tensor) -> Tensor:
        """A dynamic model's sliding level g(v) (`torchfric.models.lugre.sliding_level`)."""
        return positive_level(self.curve_of(torch.maximum(v.abs(), self.vs)))

    def rate(self, v: Tensor) -> Tensor:
        """A dynamic model's bristle relaxation rate σ0 |v| / g(v)."""
        return self.s0 * v.abs() / self.level(v)

    def black_box(self, v: Tensor) -> Tensor:
        """C(v), or a dynamic model's sliding curve sign(v) g(v) (its steady state), any shape."""
        if self.dynamic:
            return torch.sign(v) * self.level(v)
        return self.curve_of(v)

    @torch.jit.export
    def friction(self, v: Tensor) -> Tensor:
        """Total friction C(v) + b v + offset + a |v| (the model's terms) at velocities v; a
        dynamic model's steady-state friction."""
        return arm_friction(v, self.black_box(v), self.viscous, self.offset, self.asymmetric)

    def external(self, x: Tensor, u: Tensor) -> Tensor:
        return external_torque(x, u, self.c_m, self.offset, self.gravity, self.asymmetric)

    @torch.jit.export
    def field(self, x: Tensor, u: Tensor) -> Tensor:
        """The vector field ẋ = f(x, u) for states x (..., 2) (a dynamic model: (..., 3),
        [q, qdot, z]) and input u (broadcast)."""
        if self.dynamic:
            f = self.external(x, u)
            g = self.level(x[..., 1])
            return bristle_field(x, f, g, self.s0, self.s1, self.inertia, self.viscous)
        return arm_field(
            x,
            u,
            self.black_box(x[..., 1]),
            self.c_m,
            self.inertia,
            self.viscous,
            self.offset,
            self.gravity,
            self.asymmetric,
        )

    @torch.jit.export
    def substeps_for(self, t: Tensor) -> int:
        """Solver steps per sample interval for sample times t: the fixed count, or
        min(max(1, ceil(stiffness * dt / stability)), max_substeps) with dt the longest interval."""
        if self.fixed_substeps > 0:
            return self.fixed_substeps
        dt = float((t[1:] - t[:-1]).max())
        return min(max(1, int(math.ceil(self.stiffness * dt / self.stability))), self.max_substeps)

    def step(self, x: Tensor, uk: Tensor, t0: Tensor, t1: Tensor) -> Tensor:
        """One solver step from t0 to t1 with held input uk (torchdiffeq's fixed-grid steps)."""
        h = t1 - t0
        if self.dynamic:
            return self.bristle_step(x, uk, h)
        k1 = self.field(x, uk)
        if self.method == 0:
            return x + h * k1
        if self.method == 1:
            half = 0.5 * h
            return x + h * self.field(x + k1 * half, uk)
        k2 = self.field(x + h * k1 * (1.0 / 3.0), uk)
        k3 = self.field(x + h * (k2 - k1 * (1.0 / 3.0)), uk)
        k4 = self.field(x + h * (k1 - k2 + k3), uk)
        return x + (k1 + 3.0 * (k2 + k3) + k4) * h * 0.125

    def bristle_step(self, x: Tensor, uk: Tensor, h: Tensor) -> Tensor:
        """A dynamic model's sub-step (`torchfric.models.lugre.lugre_substep`)."""
        v = x[..., 1]
        f = self.external(x, uk)
        m, b = self.inertia, self.viscous
        v_pred, _ = bristle_solve(x, f, self.rate(v), h, self.s0, self.s1, m, b)
        v1, z1 = bristle_solve(x, f, self.rate(0.5 * (v + v_pred)), h, self.s0, self.s1, m, b)
        return torch.stack([x[..., 0] + 0.5 * h * (v + v1), v1, z1], dim=-1)

    @torch.jit.export
    def simulate(self, t: Tensor, u: Tensor, x0: Tensor) -> tuple[Tensor, Tensor]:
        """States at the sample times t (N,) for ZOH input u (N,) from x0 = [q0, qdot0]."""
        out = self.simulate_batch(t, u, x0)
        return out[:, 0], out[:, 1]

    @torch.jit.export
    def simulate_batch(self, t: Tensor, u: Tensor, x0: Tensor) -> Tensor:
        """`simulate` for a batch: `u (N,)` or `(N, B)`, `x0 (2,)` or `(B, 2)` → `(N, [B,] 2)`."""
        t = t.to(torch.float64)
        u = u.to(torch.float64)
        x0 = x0.to(torch.float64)
        if t.dim() != 1 or t.shape[0] < 2:
            raise ValueError("t must be a 1-D tensor of at least 2 sample times")
        n = t.shape[0]
        if u.dim() == 0 or u.shape[0] != n:
            raise ValueError("u must have one input per sample time (u.shape[0] == t.shape[0])")
        if x0.dim() == 0 or x0.shape[-1] != 2:
            raise ValueError("x0 must end in 2 entries [q, qdot]")
        if not bool((t[1:] > t[:-1]).all()):
            raise ValueError("t must be strictly increasing")
        s = self.substeps_for(t)
        x = x0.clone()
        if self.dynamic:  # the bristles start at the steady deflection of qdot0 (0 at rest)
            z0 = self.black_box(x0[..., 1]) / self.s0
            x = torch.cat([x0, z0.unsqueeze(-1)], dim=-1)
        out = torch.empty([n] + x.shape, dtype=x0.dtype)
        out[0] = x
        for k in range(n - 1):
            span = t[k + 1] - t[k]
            uk = u[k]
            ta = t[k]
            for j in range(s):
                tb = t[k + 1] if j == s - 1 else t[k] + span * (float(j + 1) / s)
                x = self.step(x, uk, ta, tb)
                ta = tb
            out[k + 1] = x
        return out[..., :2]

    def forward(self, t: Tensor, u: Tensor, x0: Tensor) -> tuple[Tensor, Tensor]:
        return self.simulate(t, u, x0)


def export_model(
    model: ArmModel,
    *,
    dt: float | None = None,
    substeps: int | str = "auto",
    method: str = "rk4",
    max_substeps: int = 64,
) -> torch.jit.ScriptModule:
    """Script `model` as a self-contained simulator (`ExportedArm`).

    Args:
        model: the identified arm.
        dt: the training data's sample time, stored as ``nominal_dt`` (metadata only: with
            ``substeps="auto"`` the module picks its sub-steps from the `t` it is called with).
        substeps: ``"auto"`` (per call, `torchfric.simulate.auto_substeps`' rule) or a fixed
            positive integer.
        method: fixed-grid solver (`torchfric.simulate.SOLVERS`), as `simulate`'s `method`.
        max_substeps: cap of the automatic count, as `simulate`'s.
    """
    module = ExportedArm(model, substeps, method=method, max_substeps=max_substeps, dt=dt)
    with warnings.catch_warnings():
        # TorchScript is deprecated upstream but is still the format that loads without the
        # defining Python code (torch.export needs the class importable to re-trace).
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            return torch.jit.script(module)
        except Exception as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise TorchfricError(f"cannot script the model for export ({first})") from None


def save_exported(module: Any, path: str | pathlib.Path) -> None:
    """Write the scripted module atomically (temp file + rename; no temp file left behind)."""

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(module, buffer)
    atomic_write_bytes(path, buffer.getvalue())
