"""LuGre dynamic friction around a learned sliding curve (``model.dynamic = "lugre"``).

The arm gains an unmeasured bristle state ``z``::

    ż = q̇ − σ0 |q̇| z / g(q̇),     F = σ0 z + σ1 ż (+ b q̇ + the white-box terms),

and ``M q̈ = c_m u − F``. The sliding curve g is the odd friction module's curve C (tanh or
polytopic) made positive, ``g(v) = sqrt(C(s)² + ε²)`` with ``s = max(|v|, v_s)``:

- g > 0 for every parameter value, by construction (no penalty), and even in v;
- in steady sliding ``z = sign(q̇) g(q̇)/σ0``, so the friction is ``sign(q̇) g(q̇) + b q̇``: the
  learned curve ``C(q̇) + b q̇`` wherever ``|q̇| >= v_s`` and C has the sign of q̇ (every physical
  friction curve), odd and zero at zero for any θ (`sliding_curve`);
- below the *stick velocity* v_s the curve is held at ``g(0) = |C(v_s)|``, the static friction.
  That is what makes the model stick: the bristle relaxation rate ``σ0 |q̇| / g`` vanishes at
  rest, so under a torque below g(0) the bristles deflect elastically (pre-sliding) instead of
  the arm creeping. Reading g at ``|q̇|`` alone would give ``g(0) = C(0) = 0``: a rate that stays
  at ``σ0/C'(0)`` at rest, and an arm that creeps at the speed where C equals the torque.
  v_s (> 0, log space) is estimated with σ0 and σ1 as ``lugre_vstick``.

σ0 is stiff (the bristle rate reaches 10⁴–10⁶ 1/s in sliding), so the state is not integrated by
explicit Runge–Kutta steps but by the synthetic rig's scheme (`torchfric.data.rig_model`), here
in torch operations: over a sub-step ``h`` with the bristle rate ``a`` frozen and the velocity
linear, ``ż = v − a z`` is solved exactly (exponential integrator), the friction enters through
the exact mean and increment of z, and the momentum balance is linear in the new velocity, so
one division solves it: stable at any stiffness, exact ``F = sign(v) g(v) + b v`` in steady
sliding. ``a`` is taken at the sub-step's midpoint velocity from a first solve with ``a(v)`` (a
predictor–corrector: second order). The map is differentiable (the EKF's Φ, output error's
gradients) and made of operations the native code generator translates.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .friction import Friction

__all__ = [
    "CLASS_NAMES",
    "DYNAMICS",
    "LUGRE_NAMES",
    "bristle_field",
    "bristle_solve",
    "bristle_travel",
    "bristles_seen",
    "bristles_timed",
    "stick_rate",
    "STICK_RATE_LIMIT",
    "positive_level",
    "sliding_level",
    "sliding_curve",
    "lugre_field",
    "lugre_substep",
]

# θ's names of σ0, σ1 and v_s (the polytopic curve's own variances are sigma1, sigma2, ...).
LUGRE_NAMES: tuple[str, str, str] = ("lugre_sigma0", "lugre_sigma1", "lugre_vstick")

# `model.dynamic` values: "none" (the static arm, state [q, q̇]) and "lugre" ([q, q̇, z]).
DYNAMICS: tuple[str, ...] = ("none", "lugre")
CLASS_NAMES: dict[str, str] = {"none": "static", "lugre": "LuGre"}
"""Each of `DYNAMICS` as summaries and reports name it."""


def positive_level(c: Tensor) -> Tensor:
    """``g = sqrt(c² + ε²) > 0`` from the curve's value c at ``s = max(|v|, v_s)``. ε = 1e-9
    (torque) is far below any physical friction level, yet keeps g > 0 where a curve crosses zero,
    so the bristle rate σ0 |q̇| / g stays finite; a literal, as TorchScript reads no globals."""
    return torch.sqrt(c * c + 1e-18)


def sliding_level(
    friction: Friction, v: Tensor, fric: dict[str, Tensor], v_stick: Tensor
) -> Tensor:
    """``g(v) = sqrt(C(max(|v|, v_s))² + ε²)`` (even, > 0) for physical parameters `fric` of the
    odd `friction` and the stick velocity ``v_s`` (C odd: ``|C(v)| = |C(|v|)|``)."""
    return positive_level(friction.evaluate(torch.maximum(v.abs(), v_stick), fric))


def sliding_curve(
    friction: Friction, v: Tensor, fric: dict[str, Tensor], v_stick: Tensor
) -> Tensor:
    """The dynamic model's steady-state friction without its white-box terms,
    ``sign(v) g(v)``: odd and zero at zero; ``C(v)`` where ``|v| >= v_s`` and C has v's sign."""
    return torch.sign(v) * sliding_level(friction, v, fric, v_stick)


def bristle_travel(friction: Friction, fric: dict[str, Tensor], arm: dict[str, Tensor]) -> float:
    """The bristles' travel through a velocity reversal, ``2 g(0)/σ0`` [position]: from the
    deflection that holds the static friction g(0) one way to the one that holds it the other.
    It is the pre-sliding motion a record must resolve for σ0 to be seen at all: a model whose
    travel is below the encoder's step moves through a reversal as the limit σ0 → ∞ does, which
    is a static model that sticks (`torchfric.estimators.sizing.compare_dynamics`)."""
    zero = torch.zeros(1, dtype=arm["lugre_sigma0"].dtype)
    level = sliding_level(friction, zero, fric, arm["lugre_vstick"])[0]
    return float(2.0 * level / arm["lugre_sigma0"])


STICK_RATE_LIMIT = 1.0
"""The fastest rate of a stuck axis on its bristles, times the sample time, above which a record
cannot see the bristles move (`stick_rate`): their transient is over within one sample."""


def stick_rate(arm: dict[str, Tensor]) -> float:
    """The fastest rate [1/s] of the axis stuck on its bristles, ``M ẍ + (σ1 + b) ẋ + σ0 x = 0``
    (the bristle state z and q move together while the axis sticks): the larger magnitude of
    its two roots, ``√(σ0/M)`` when they are complex.

    Pre-sliding is seen in time as well as in position: bristles whose transient is over
    within a couple of samples move through a reversal as the limit σ0 → ∞ does, a static
    model that sticks. On a heavy ball-screw table with static friction (a stiff regularised
    stiction law) the LuGre fits that won the windows settled at 1.6–4.5 per sample (their
    travel was 1–10 encoder steps); on five LuGre machines, 0.04–0.61 (docs/results.md,
    "Static, LuGre or auto")."""
    m, k = arm["inertia"], arm["lugre_sigma0"]
    c = arm["lugre_sigma1"] + (arm["viscous"] if "viscous" in arm else 0.0)
    a, b = float(c / m), float(k / m)
    disc = a * a - 4.0 * b
    return 0.5 * (a + math.sqrt(disc)) if disc > 0 else math.sqrt(b)


def bristles_timed(rate: float, dt: float) -> bool:
    """Whether a `stick_rate` is slow enough for records sampled every `dt` to see it (a NaN
    rate, from a failed fit, is not)."""
    return rate * dt <= STICK_RATE_LIMIT


def bristles_seen(travel: float, step: float, span: float = math.inf) -> bool:
    """Whether a `bristle_travel` spans the records' position `step` (a NaN step, a position
    that never moves, has no resolution to fall below) and stays below their position `span`.

    Both ends are limits the record cannot tell from another model: a travel below one step is
    σ0 → ∞, a static model that sticks; a travel beyond everything the record moves is σ0 → 0,
    bristles that never slide in it, so that its "friction" is a spring and a damper on the
    position (on a sticking axis nobody tuned on, such a fit predicted the held-out windows
    better than the static curve: docs/results.md, "Static, LuGre or auto")."""
    return not travel < step and travel < span


# The functions below are TorchScript-compatible (tensors and optional tensors only): the
# exported module (`torchfric.models.torchscript`) compiles them, so its steps are these very ones.


def bristle_field(
    x: Tensor,
    f: Tensor,
    g: Tensor,
    sigma0: Tensor,
    sigma1: Tensor,
    inertia: Tensor,
    viscous: Tensor | None = None,
) -> Tensor:
    """``ẋ = [q̇, (f − σ0 z − σ1 ż − b q̇)/M, ż]`` `(..., 3)` with ``ż = q̇ − σ0 |q̇| z / g`` for the
    external torque `f` and the sliding level ``g = g(q̇)``."""
    v, z = x[..., 1], x[..., 2]
    zdot = v - sigma0 * v.abs() * z / g
    force = sigma0 * z + sigma1 * zdot
    if viscous is not None:
        force = force + viscous * v
    return torch.stack([v, (f - force) / inertia, zdot], dim=-1)


def _weights(x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``E = e^{−x}``, ``φ = (1 − E)/x``, ``ψ = (1 − φ)/x``, ``χ = (1/2 − ψ)/x`` for x = a h ≥ 0,
    by their Taylor series below 1e-2 (closed forms there lose digits to cancellation); the
    closed-form branch reads a safe x where the series is used, so neither branch makes NaN
    (nor NaN gradients)."""
    small = x < 1e-2
    xs = torch.where(small, torch.ones_like(x), x)
    em1 = torch.expm1(-xs)
    phi_c = -em1 / xs
    psi_c = (1.0 - phi_c) / xs
    chi_c = (0.5 - psi_c) / xs
    xt = torch.where(small, x, torch.zeros_like(x))
    phi_s = 1.0 - xt * (0.5 - xt * (1.0 / 6.0 - xt * (1.0 / 24.0 - xt / 120.0)))
    psi_s = 0.5 - xt * (1.0 / 6.0 - xt * (1.0 / 24.0 - xt * (1.0 / 120.0 - xt / 720.0)))
    chi_s = 1.0 / 6.0 - xt * (1.0 / 24.0 - xt * (1.0 / 120.0 - xt * (1.0 / 720.0 - xt / 5040.0)))
    return (
        torch.where(small, 1.0 - xt * phi_s, 1.0 + em1),
        torch.where(small, phi_s, phi_c),
        torch.where(small, psi_s, psi_c),
        torch.where(small, chi_s, chi_c),
    )


def bristle_solve(
    x: Tensor,
    f: Tensor,
    a: Tensor,
    h: Tensor,
    sigma0: Tensor,
    sigma1: Tensor,
    inertia: Tensor,
    viscous: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """One sub-step ``h`` from `x (..., 3)` with the bristle rate `a` frozen and the external
    torque `f` held: the new ``(q̇, z)`` (see the module docstring)."""
    v, z = x[..., 1], x[..., 2]
    E, phi, psi, chi = _weights(a * h)
    vh = v * h
    z_mean0 = z * phi + vh * (psi - chi)  # mean of z over the step, without its v1 term
    dz0 = z * (E - 1.0) + vh * (phi - psi)  # z1 − z without its v1 term
    num = inertia * v + h * f - h * sigma0 * z_mean0 - sigma1 * dz0
    den = inertia + h * h * sigma0 * chi + sigma1 * h * psi
    if viscous is not None:
        half = 0.5 * h * viscous
        num = num - half * v
        den = den + half
    v1 = num / den
    return v1, z + dz0 + v1 * h * psi


def lugre_field(
    friction: Friction, x: Tensor, f: Tensor, fric: dict[str, Tensor], arm: dict[str, Tensor]
) -> Tensor:
    """The continuous vector field of the model `(..., 3)` under the external torque `f`
    (`torchfric.models.arm.external_torque`; `bristle_field`; stiff: for reference and tests,
    integrate it with `lugre_substep`)."""
    g = sliding_level(friction, x[..., 1], fric, arm["lugre_vstick"])
    return bristle_field(
        x, f, g, arm["lugre_sigma0"], arm["lugre_sigma1"], arm["inertia"], arm.get("viscous")
    )


def lugre_substep(
    friction: Friction,
    x: Tensor,
    f: Tensor,
    h: Tensor | float,
    fric: dict[str, Tensor],
    arm: dict[str, Tensor],
) -> Tensor:
    """One sub-step of length `h` from states `x (..., 3)` = [q, q̇, z] under the external torque
    `f` (`torchfric.models.arm.external_torque`, held over the step):
    the exponential bristle update with the rate at the midpoint velocity (predicted by a first
    solve with the rate at q̇), the momentum balance linear in the new velocity,
    ``q1 = q + h (v + v1)/2``."""
    v = x[..., 1]
    h = torch.as_tensor(h, dtype=x.dtype)
    s0, s1, M, b = arm["lugre_sigma0"], arm["lugre_sigma1"], arm["inertia"], arm.get("viscous")
    vs = arm["lugre_vstick"]

    def rate(w: Tensor) -> Tensor:  # the bristle relaxation rate σ0 |w| / g(w)
        return s0 * w.abs() / sliding_level(friction, w, fric, vs)

    v_pred, _ = bristle_solve(x, f, rate(v), h, s0, s1, M, b)
    mid = 0.5 * (v + v_pred)
    v1, z1 = bristle_solve(x, f, rate(mid), h, s0, s1, M, b)
    return torch.stack([x[..., 0] + 0.5 * h * (v + v1), v1, z1], dim=-1)
