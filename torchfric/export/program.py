"""The identified model as plain C: its functions written from the one definition the simulator
uses, with the physical parameters as an array the C code reads.

`model_program` traces, for an `ArmModel`, the functions an FMU or a controller needs, each the
very torch code of `torchfric.simulate` or `ArmModel` (never written again by hand):

- ``tf_step(x, u, h, p, out)``: one solver step of length h with u held, the step
  `torchfric.simulate` takes for the run's `simulation.method` (`rk4_step`, torchdiffeq's
  euler and midpoint steps on `ArmModel.dynamics`; a dynamic model's `ArmModel.substep`);
- ``tf_field(x, u, p, out)``: ``ẋ = f(x, u; θ)`` (`ArmModel.dynamics`), for Model Exchange;
- ``tf_friction(x, u, p, out)``: the friction torque at a state: ``arm_friction`` of q̇ for a
  static model; ``c_m u − g_c sin q − M q̈`` for a dynamic one (bristles, σ1 ż, b q̇ and the
  white-box terms; q̈ from the field);
- ``tf_curve(v, p, out)``: `ArmModel.friction_torque`, the (steady-state) curve;
- ``tf_slope(v, p, out)``: its derivative in v, by `torch.func.grad` (the stiffness behind
  `torchfric.simulate.auto_substeps`);
- ``tf_bristle(v, p, out)``: a dynamic model's steady bristle deflection at q̇
  (`torchfric.simulate.full_state`).

The sub-step rule `tf_substeps(dt, p)` is `auto_substeps`' (``⌈λ dt / c⌉`` over the same 401
velocities, capped at 64; ``⌈ω dt / 0.1⌉`` for bristles), or the run's fixed count.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from ..accel.native.functions import c_function
from ..errors import TorchfricError
from ..models import ArmModel
from ..models.arm import external_torque
from ..models.simulate import (
    BRISTLE_OMEGA_H,
    SOLVERS,
    bristle_stiffness,
    friction_stiffness,
    solver_step,
    steady_bristles,
    stiffness_speeds,
)

__all__ = ["Parameter", "Program", "model_program", "MAX_SUBSTEPS"]

MAX_SUBSTEPS = 64
"""`torchfric.simulate`'s default cap of the automatic sub-step count."""

# What each of the arm's parameters is, for the FMU's descriptions and the C header's comments.
_ARM_TEXT = {
    "viscous": ("b, viscous friction coefficient", "torque/velocity"),
    "inertia": ("M, inertia (mass for a linear axis)", "inertia"),
    "offset": ("constant friction offset", "torque"),
    "gravity": ("g_c, gravity torque amplitude (g_c sin q)", "torque"),
    "asymmetric": ("a, asymmetric friction (a |qdot|)", "torque/velocity"),
    "c_m": ("c_m, motor constant: torque per unit of u", ""),
    "lugre_sigma0": ("sigma0, LuGre bristle stiffness", "torque/position"),
    "lugre_sigma1": ("sigma1, LuGre bristle damping", "torque/velocity"),
    "lugre_vstick": ("v_s, LuGre stick velocity", "velocity"),
}


@dataclass(frozen=True)
class Parameter:
    """One entry of the C parameter array: its name (θ's, or ``c_m``), value, what it is and
    the kind of unit it has (``"torque"``, ``"velocity"`` …, `torchfric.export.units`)."""

    name: str
    value: float
    description: str
    unit: str


@dataclass
class Program:
    """The model's C functions (`function`: the source of a static function ``tf_…``, traced
    when first asked for), its parameters in the order of the array ``p`` they read, and the
    facts an FMU needs about it."""

    tracers: dict[str, Callable[[], str]]
    parameters: list[Parameter]
    state_size: int
    dynamic: bool
    method: str
    fixed_substeps: int  # 0: the automatic rule
    stiffness: float  # the rule's rate at the identified values (`friction_stiffness`, `bristle_stiffness`)
    _sources: dict[str, str] = field(default_factory=dict)

    def function(self, name: str) -> str:
        """The C source of ``tf_<name>``-named function `name` (traced once)."""
        if name not in self._sources:
            self._sources[name] = self.tracers[name]()
        return self._sources[name]


def _layout(model: ArmModel) -> tuple[list[tuple[str, str, tuple[int, ...]]], Tensor]:
    """``(group, key, shape)`` of every physical tensor that `ArmModel.split` gives, in the
    order of the flat parameter array, and that array's values."""
    fric, arm = model.split(model.get_theta())
    layout = [("fric", k, tuple(v.shape)) for k, v in fric.items()]
    layout += [("arm", k, tuple(v.shape)) for k, v in arm.items()]
    values = torch.cat([v.detach().reshape(-1) for v in [*fric.values(), *arm.values()]])
    return layout, values.to(torch.float64)


def _split(layout: list[tuple[str, str, tuple[int, ...]]], p: Tensor):  # type: ignore[no-untyped-def]
    """The dicts `ArmModel.split` gives, rebuilt from the flat parameter array `p`."""
    fric: dict[str, Tensor] = {}
    arm: dict[str, Tensor] = {}
    i = 0
    for group, key, shape in layout:
        n = math.prod(shape)
        (fric if group == "fric" else arm)[key] = p[i : i + n].reshape(shape)
        i += n
    return fric, arm


def _parameters(model: ArmModel, layout, values: Tensor) -> list[Parameter]:  # type: ignore[no-untyped-def]
    names = list(model.friction.element_names)
    friction_size = sum(math.prod(s) for g, _, s in layout if g == "fric")
    if len(names) != friction_size:  # pragma: no cover - every friction module names its entries
        raise TorchfricError("the friction module's names do not match its parameters")
    names += [key for group, key, _ in layout if group == "arm"]
    out = []
    for j, (name, value) in enumerate(zip(names, values.tolist(), strict=True)):
        if j < friction_size:
            text, unit = f"friction curve parameter {name} ({model.friction.kind})", ""
        else:
            text, unit = _ARM_TEXT.get(name, (name, ""))
        out.append(Parameter(name, float(value), text, unit))
    return out


def _state_friction(model: ArmModel):  # type: ignore[no-untyped-def]
    """The friction torque at a state ``(x, u, fric, arm)``."""
    if model.state_size == 2:
        return lambda x, u, fric, arm: model.total_friction(x[1], fric, arm)

    def dynamic(x, u, fric, arm):  # type: ignore[no-untyped-def]
        accel = model.dynamics(x, u, fric, arm)[1]
        gravity = arm.get("gravity")
        drive = external_torque(x, u, arm["c_m"], None, gravity, None)
        return drive - arm["inertia"] * accel

    return dynamic


def model_program(model: ArmModel, *, method: str = "rk4", substeps: int | str = "auto") -> Program:
    """The C functions of `model` for solver `method` and the run's `substeps` (see the module
    docstring); a one-line error for a method or sub-step count `torchfric.simulate` refuses."""
    if method not in SOLVERS:
        raise TorchfricError(f"unknown solver {method!r}; choose one of {sorted(SOLVERS)}")
    fixed = 0 if substeps == "auto" else int(substeps)
    if substeps != "auto" and (isinstance(substeps, bool) or fixed < 1):
        raise TorchfricError(f"substeps must be a positive integer or 'auto', got {substeps!r}")
    layout, values = _layout(model)
    n = model.state_size
    x = torch.tensor([0.1, 0.3, 0.0][:n], dtype=torch.float64)
    if n == 3:
        x[2] = 1e-4
    u, h, v = (torch.tensor(c, dtype=torch.float64) for c in (0.5, 1e-4, 0.3))
    p = values.clone()
    at_state = _state_friction(model)

    def curve(v: Tensor, p: Tensor) -> Tensor:
        return model.total_friction(v, *_split(layout, p))

    specs: dict[str, tuple[Any, list[tuple[str, Tensor]]]] = {
        "tf_step": (lambda x, u, h, p: solver_step(model, x, u, h, *_split(layout, p), method),
                    [("x", x), ("u", u), ("h", h), ("p", p)]),
        "tf_field": (lambda x, u, p: model.dynamics(x, u, *_split(layout, p)),
                     [("x", x), ("u", u), ("p", p)]),
        "tf_friction": (lambda x, u, p: at_state(x, u, *_split(layout, p)),
                        [("x", x), ("u", u), ("p", p)]),
        "tf_curve": (curve, [("v", v), ("p", p)]),
        "tf_slope": (torch.func.grad(curve), [("v", v), ("p", p)]),
        "tf_bristle": (lambda v, p: steady_bristles(model, v, *_split(layout, p)),
                       [("v", v), ("p", p)]),
    }  # fmt: skip
    tracers = {name: _tracer(name, fn, args) for name, (fn, args) in specs.items()}
    theta = model.get_theta()
    rate = bristle_stiffness(model, theta) if n == 3 else friction_stiffness(model, theta)
    return Program(tracers, _parameters(model, layout, values), n, n == 3, method, fixed, rate)


def _tracer(name: str, fn: Any, args: list[tuple[str, Tensor]]) -> Callable[[], str]:
    return lambda: c_function(name, fn, args)


ADVANCE = """static void tf_advance(double *x, double u, double t, double H, int S, const double *p) {
  /* S solver steps from t over H with u held, on the simulator's grid: t + H i/S, its last
     point t + H */
  double next[TF_NX];
  for (int i = 0; i < S; ++i) {
    double a = t + H * ((double)i / S), b = i + 1 < S ? t + H * ((double)(i + 1) / S) : t + H;
    double h = b - a;
    tf_step(x, &u, &h, p, next);
    for (int j = 0; j < TF_NX; ++j) x[j] = next[j];
  }
}
"""
"""C of ``tf_advance(x, u, t, H, S, p)``: one sample interval H from t in `S` solver steps
(`tf_step`), the FMU's communication step and the C export's `NAME_step` alike."""


def substep_rule(program: Program, *, constant: bool = False) -> str:
    """C of ``static int tf_substeps(double dt, const double *p)``: the sub-steps per interval of
    `torchfric.simulate.auto_substeps` (or the run's fixed count) for parameters `p`; with
    `constant`, for the identified values only, from the rate `model_program` computed as
    `auto_substeps` does (the C export, whose parameters are constants: no slope scan per call)."""
    if program.fixed_substeps:
        return (
            "static int tf_substeps(double dt, const double *p) {\n"
            f"  (void)dt; (void)p; return {program.fixed_substeps};\n}}\n"
        )
    names = [q.name for q in program.parameters]
    inertia = names.index("inertia")
    head = "static int tf_substeps(double dt, const double *p) {\n  double s;\n"
    if constant:
        scale = "" if program.dynamic else f" / {SOLVERS[program.method]!r}"
        body = f"  (void)p;\n  s = ceil({program.stiffness!r} * dt{scale});\n"
    elif program.dynamic:  # `bristle_stiffness`: sqrt(σ0/M)/0.1 per second
        s0 = names.index("lugre_sigma0")
        body = f"  s = ceil(sqrt(p[{s0}] / p[{inertia}]) / {BRISTLE_OMEGA_H!r} * dt);\n"
    else:  # `friction_stiffness`: max |dF/dv| over the velocities of TF_SPEEDS, over M
        body = (
            "  double top = 0.0;\n"
            "  for (int i = 0; i < TF_NSPEEDS; ++i) {\n"
            "    double g;\n"
            "    tf_slope(&TF_SPEEDS[i], p, &g);\n"
            "    g = fabs(g);\n"
            "    if (g != g || g > top) top = g;\n"
            "  }\n"
            f"  s = ceil(top / p[{inertia}] * dt / {SOLVERS[program.method]!r});\n"
        )
    tail = (
        "  if (!(s >= 1.0)) s = 1.0;  /* also NaN: the caller checks the parameters */\n"
        f"  if (s > {MAX_SUBSTEPS}) s = {MAX_SUBSTEPS};\n"
        "  return (int)s;\n}\n"
    )
    return head + body + tail


def speed_table() -> str:
    """C of the 401 velocities `torchfric.simulate.friction_stiffness` reads the slope at."""
    v = stiffness_speeds().tolist()
    rows = [", ".join(repr(float(a)) for a in v[i : i + 4]) for i in range(0, len(v), 4)]
    return (
        f"#define TF_NSPEEDS {len(v)}\nstatic const double TF_SPEEDS[TF_NSPEEDS] = {{\n  "
        + ",\n  ".join(rows)
        + "\n};\n"
    )


def model_source(program: Program, *, guid: str, nominals: list[float], title: str) -> str:
    """The whole C file of the model (``torchfric_model.c`` of an FMU): sizes, parameter names
    and values, the velocity table, the functions and the sub-step rule."""
    names = [q.name for q in program.parameters]
    quoted = ", ".join('"' + n.replace("\\", "\\\\").replace('"', '\\"') + '"' for n in names)
    lines = [
        f"/* {title}: generated by torchfric from the model's torch code; do not edit. */",
        "#include <math.h>",
        "",
        f"#define TF_NX {program.state_size}",
        f'#define TF_NX_TEXT "{program.state_size}"',
        f"#define TF_NP {len(names)}",
        f"#define TF_INERTIA {names.index('inertia')}",
        f'#define TF_GUID "{guid}"',
        f"static const char *const TF_PARAM_NAMES[TF_NP] = {{{quoted}}};",
        "static const double TF_PARAM_START[TF_NP] = {"
        + ", ".join(repr(q.value) for q in program.parameters)
        + "};",
        "static const double TF_NOMINALS[TF_NX] = {" + ", ".join(map(repr, nominals)) + "};",
        "",
    ]
    automatic = not program.fixed_substeps and not program.dynamic
    if automatic:
        lines.append(speed_table())
    wanted = ["tf_step", "tf_field", "tf_friction"]
    wanted += ["tf_slope"] if automatic else []
    wanted += ["tf_bristle"] if program.dynamic else []
    lines += [program.function(name) for name in wanted]
    lines += [substep_rule(program), ADVANCE]
    return "\n".join(lines)
