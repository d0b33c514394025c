"""Export an identified model as a TorchScript module that loads without torchfric.

The module offers ``simulate(t, u, x0) -> (q, qdot)`` and ``friction(v)`` (total friction
``b v + C(v) + offset``). Its integrator is the same fixed-grid RK4 (3/8 rule) with the same
sub-steps and exact zero-order hold as `torchfric.simulate`, so the outputs agree to rounding.
"""

from __future__ import annotations

import pathlib
import warnings
from typing import Any

import torch
from torch import Tensor, nn

from .arm import ArmModel
from .errors import TorchfricError
from .simulate import auto_substeps

__all__ = ["ExportedArm", "export_model", "save_exported"]

_KINDS = {"tanh": 0, "polytopic": 1, "coulomb": 2, "stribeck": 3}


class ExportedArm(nn.Module):
    """Self-contained arm simulator (TorchScript-compatible; physical parameter values)."""

    def __init__(self, model: ArmModel, substeps: int) -> None:
        super().__init__()
        fr = model.friction
        p = {k: v.detach().clone() for k, v in fr.physical_parameters().items()}
        self.kind = _KINDS[fr.kind]
        self.substeps = int(substeps)
        self.eps = float(getattr(fr, "eps", 1.0))
        z = torch.zeros(1, dtype=torch.float64)
        self.register_buffer("w1", p.get("W1", z))
        self.register_buffer("w2", p.get("W2", z))
        if fr.kind == "polytopic":
            a, b, c, s = p["a"], p["b"], p["c"], p["sigma"]
            self.register_buffer("centres", torch.cat([torch.zeros(1, dtype=torch.float64), c, -c]))
            self.register_buffer("slopes", torch.cat([a, a[1:]]))
            self.register_buffer("offsets", torch.cat([torch.zeros(1, dtype=torch.float64), b, -b]))
            self.register_buffer("variances", torch.cat([s, s[1:]]))
        else:
            for name in ("centres", "slopes", "offsets", "variances"):
                self.register_buffer(name, z.clone())
        self.fc = float(p["Fc"][0]) if "Fc" in p else 0.0
        self.fs = float(p["Fs"][0]) if "Fs" in p else 0.0
        self.vs = float(p["vs"][0]) if "vs" in p else 1.0
        self.inertia = float(model.inertia.detach())
        self.viscous = float(model.viscous.detach())
        self.offset = float(model.offset.detach())
        self.gravity = float(model.gravity.detach())
        self.c_m = float(model.c_m.detach())

    def black_box(self, v: Tensor) -> Tensor:
        """C(v) alone."""
        if self.kind == 0:
            return (torch.tanh(v.unsqueeze(-1) * self.w1) * self.w2).sum(-1)
        if self.kind == 1:
            d = v.unsqueeze(-1) - self.centres
            w = torch.softmax(-0.5 * d * d / self.variances, dim=-1)
            return (w * (self.slopes * d + self.offsets)).sum(-1)
        if self.kind == 2:
            return self.fc * torch.tanh(v / self.eps)
        level = self.fc + (self.fs - self.fc) * torch.exp(-((v / self.vs) ** 2))
        return level * torch.tanh(v / self.eps)

    @torch.jit.export
    def friction(self, v: Tensor) -> Tensor:
        """Total friction b v + C(v) + offset at velocities v (any shape)."""
        return self.viscous * v + self.black_box(v) + self.offset

    def field(self, x: Tensor, u: Tensor) -> Tensor:
        q = x[..., 0]
        v = x[..., 1]
        torque = (
            self.c_m * u
            - self.black_box(v)
            - self.viscous * v
            - self.offset
            - self.gravity * torch.sin(q)
        )
        return torch.stack([v, torque / self.inertia], dim=-1)

    @torch.jit.export
    def simulate(self, t: Tensor, u: Tensor, x0: Tensor) -> tuple[Tensor, Tensor]:
        """States at the sample times t (N,) for ZOH input u (N,) from x0 = [q0, qdot0]."""
        out = self.simulate_batch(t, u, x0)
        return out[:, 0], out[:, 1]

    @torch.jit.export
    def simulate_batch(self, t: Tensor, u: Tensor, x0: Tensor) -> Tensor:
        """`simulate` for any batch shape: `u (N, ...)`, `x0 (..., 2)` → states `(N, ..., 2)`."""
        n = t.shape[0]
        out = torch.empty([n] + x0.shape, dtype=x0.dtype)
        x = x0.clone()
        out[0] = x
        s = self.substeps
        for k in range(n - 1):
            span = t[k + 1] - t[k]
            uk = u[k]
            for j in range(s):
                ta = t[k] + span * (float(j) / s)
                tb = t[k + 1] if j == s - 1 else t[k] + span * (float(j + 1) / s)
                h = tb - ta
                k1 = self.field(x, uk)
                k2 = self.field(x + h * k1 * (1.0 / 3.0), uk)
                k3 = self.field(x + h * (k2 - k1 * (1.0 / 3.0)), uk)
                k4 = self.field(x + h * (k1 - k2 + k3), uk)
                x = x + (k1 + 3.0 * (k2 + k3) + k4) * h * 0.125
            out[k + 1] = x
        return out

    def forward(self, t: Tensor, u: Tensor, x0: Tensor) -> tuple[Tensor, Tensor]:
        return self.simulate(t, u, x0)


def export_model(
    model: ArmModel, *, dt: float, substeps: int | str = "auto"
) -> torch.jit.ScriptModule:
    """Script `model` for simulation at sample time `dt` (sub-steps fixed at export)."""
    if substeps == "auto":
        steps = auto_substeps(model, dt)
    elif isinstance(substeps, int) and substeps >= 1:
        steps = substeps
    else:
        raise TorchfricError(f"substeps must be a positive integer or 'auto', got {substeps!r}")
    with warnings.catch_warnings():
        # TorchScript is deprecated upstream but is still the format that loads without the
        # defining Python code (torch.export needs the class importable to re-trace).
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.script(ExportedArm(model, steps))


def save_exported(module: Any, path: str | pathlib.Path) -> None:
    """Write the scripted module atomically (temp file + rename)."""
    import os

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(module, str(tmp))
    os.replace(tmp, path)
