"""Uncertainty of an identified friction curve from the EKF's parameter covariance (delta method).

The augmented-state EKF ends with a covariance ``P_θθ`` `(k, k)` over the flat parameter vector
θ in *estimation coordinates* (`ArmModel.get_theta`: log for M, b and the polytopic variances).
To first order, the total friction ``F(v; θ) = b v + C(v; θ) + offset`` at velocities ``v`` then
has the covariance

    Cov[F(v)] ≈ J P_θθ Jᵀ,          J = ∂F(v; θ)/∂θ  `(N, k)`, taken with respect to θ *as stored*

(`friction_jacobian`, by autograd of `ArmModel.friction_torque(v, θ)`), so the Jacobian carries the chain rule
through the exponentials of the log-stored entries. The band is exact when F is affine in θ (e.g.
only the output weights W2 of the tanh network uncertain) and an approximation otherwise.

The band is as good as the covariance given (`SIGMA_SOURCES`): a run's checkpoint holds its
sandwich covariance; the filter's own ``P_θθ`` (a checkpoint without one) has absorbed the data
once per pass and knows nothing about structural error, so it is narrower than the real error.

`viscous_share` names the bias the covariance cannot show: tanh neurons that still rise over
the data's upper speeds and so take part of b's slope (joined to the identifiability report).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..errors import TorchfricError
from ..models.arm import ArmModel
from .settings import speed_quantiles

__all__ = [
    "SIGMA_SOURCES",
    "VISCOUS_SHARE_LIMIT",
    "VISCOUS_SHARE_SIGMA",
    "ViscousShare",
    "friction_jacobian",
    "friction_band",
    "friction_samples",
    "parameter_std",
    "physical_std",
    "viscous_share",
]


SIGMA_SOURCES: dict[str, str] = {
    "sandwich": "the run's sandwich covariance of its one-step prediction error at this θ "
    "(I⁻¹JI⁻¹ over the identification records; a static model's over the samples where the "
    "axis moves), plus the distance to the run's other estimate "
    "where the kept pass and the likelihood's optimum differ",
    "sandwich_simulation": "the run's sandwich covariance of its simulation error at this θ "
    "(output error)",
    "filter": "the filter's own P_θθ, narrower than the real error as a rule",
}
"""Where a run's σ come from, by its covariance's method (metrics.json ``covariance.method``,
`torchfric.estimators.sandwich.PEMCovariance.method`); "filter": a run or checkpoint without a
covariance of its own. `evaluate` and report.html say it beside the σ."""


def _check(model: ArmModel, P_theta: Tensor | None, theta: Tensor | None) -> Tensor:
    if not isinstance(model, ArmModel):
        raise TorchfricError(f"model must be a torchfric ArmModel, got {type(model).__name__}")
    k = model.num_parameters
    th = model.get_theta() if theta is None else torch.as_tensor(theta, dtype=torch.float64)
    if th.shape != (k,):
        raise TorchfricError(
            f"theta has shape {tuple(th.shape)} but this model has {k} parameters "
            f"({', '.join(model.theta_names)}); give a ({k},) vector in estimation coordinates"
        )
    if P_theta is not None:
        P = torch.as_tensor(P_theta)
        if P.shape != (k, k):
            raise TorchfricError(
                f"P_theta has shape {tuple(P.shape)} but this model has {k} parameters "
                f"({', '.join(model.theta_names)}); give the ({k}, {k}) covariance over θ, e.g. "
                'read_checkpoint(path)["estimator"]["state"]["P_theta"]'
            )
        if not torch.isfinite(P).all():
            raise TorchfricError("P_theta contains NaN or inf; give a finite covariance")
    return th


def friction_jacobian(model: ArmModel, v: Tensor, theta: Tensor | None = None) -> Tensor:
    """``J = ∂F(v; θ)/∂θ`` `(N, k)` of the total friction at velocities `v` `(N,)`.

    θ is in estimation coordinates (default: the model's own); column j belongs to
    ``model.theta_names[j]`` (columns of parameters that F does not depend on, like M, are 0).
    """
    th = _check(model, None, theta)
    v = torch.as_tensor(v, dtype=torch.float64).reshape(-1)
    # Column by column, as forward mode would, but with plain autograd: g(w) = Jᵀ w is linear in
    # w, so ∂g_j/∂w = J[:, j] (k backward passes for k parameters, not N for N velocities).
    # torch.func.jacrev cost 0.7 s on its first call and jacfwd/forward_ad 0.85 s (it
    # jit-scripts torch's JVP decompositions on import, with a deprecation warning); this
    # costs 0.2 s once, then a few ms.
    with torch.enable_grad():
        th = th.detach().clone().requires_grad_(True)
        F = model.friction_torque(v, th)
        w = torch.zeros_like(F, requires_grad=True)
        # (a scalar output, not grad_outputs=w: given grad_outputs, autograd imports sympy on
        # its first call in a process, 0.3 s)
        (g,) = torch.autograd.grad((F * w).sum(), th, create_graph=True)
        cols = []
        for j in range(th.numel()):
            if not g[j].requires_grad:  # F does not depend on θ_j at all
                cols.append(torch.zeros_like(F))
                continue
            (col,) = torch.autograd.grad(g[j], w, retain_graph=True, allow_unused=True)
            cols.append(torch.zeros_like(F) if col is None else col)
    return torch.stack(cols, dim=1).detach()


@torch.no_grad()
def friction_band(
    model: ArmModel, P_theta: Tensor, v: Tensor, *, theta: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Delta-method mean and standard deviation of the total friction at velocities `v`.

    Args:
        model: the identified model; its θ is the linearisation point unless `theta` is given.
        P_theta: `(k, k)` covariance of θ in estimation coordinates (the EKF checkpoint's
            ``["estimator"]["state"]["P_theta"]``).
        v: `(N,)` velocities.
        theta: optional `(k,)` θ (estimation coordinates) to use instead of the model's.

    Returns:
        ``(mean, std)``, each `(N,)`: ``F(v; θ)`` and ``sqrt(diag(J P_θθ Jᵀ))``. A ±2·std band is
        the usual ≈ 95 % interval of a Gaussian belief.
    """
    th = _check(model, P_theta, theta)
    v = torch.as_tensor(v, dtype=torch.float64).reshape(-1)
    P = torch.as_tensor(P_theta, dtype=torch.float64)
    P = 0.5 * (P + P.T)  # symmetrise: the filter keeps P symmetric only to rounding
    J = friction_jacobian(model, v, th)
    # Var[F(v_n)] = J_n P J_nᵀ, one row at a time (no (N, N) matrix)
    var = torch.einsum("ni,ij,nj->n", J, P, J)
    mean = model.friction_torque(v, th).detach()
    return mean, var.clamp_min(0.0).sqrt()


@torch.no_grad()
def friction_samples(
    model: ArmModel,
    P_theta: Tensor,
    v: Tensor,
    *,
    samples: int = 1000,
    generator: torch.Generator | None = None,
    theta: Tensor | None = None,
) -> Tensor:
    """Monte-Carlo friction curves `(samples, N)` for θ ~ N(θ̂, P_θθ) in estimation coordinates.

    The reference the delta method approximates; useful to check a band where F is strongly
    non-linear in θ. A positive semi-definite `P_theta` is factored by its eigen-decomposition
    (negative rounding-level eigenvalues are clipped to 0).
    """
    th = _check(model, P_theta, theta)
    if not isinstance(samples, int) or isinstance(samples, bool) or samples < 1:
        raise TorchfricError(f"samples must be an integer >= 1, got {samples!r}")
    v = torch.as_tensor(v, dtype=torch.float64).reshape(-1)
    P = torch.as_tensor(P_theta, dtype=torch.float64)
    evals, evecs = torch.linalg.eigh(0.5 * (P + P.T))
    # θ_s = θ̂ + V diag(sqrt(λ)) z,  z ~ N(0, I)
    L = evecs * evals.clamp_min(0.0).sqrt()
    z = torch.randn(samples, th.numel(), generator=generator, dtype=torch.float64)
    thetas = th + z @ L.T
    return torch.stack([model.friction_torque(v, t) for t in thetas])


@torch.no_grad()
def parameter_std(
    model: ArmModel, P_theta: Tensor, *, theta: Tensor | None = None
) -> dict[str, float]:
    """Standard deviation of each physical parameter, by name (``model.theta_names``).

    The physical values are θ itself, or ``exp(θ_j)`` for the log-stored entries
    (`ArmModel.to_physical`, element by element), so the delta method is exact in form:
    ``σ_j = sqrt(P_jj)`` or ``exp(θ_j)·sqrt(P_jj)``. Like `friction_band`, this is the filter's
    own belief (see the module's note on reading it).
    """
    th = _check(model, P_theta, theta)
    P = torch.as_tensor(P_theta, dtype=torch.float64)
    std = physical_std(model, th, torch.diagonal(P))
    return dict(zip(model.theta_names, std.tolist(), strict=True))


def physical_std(model: ArmModel, theta: Tensor, variances: Tensor) -> Tensor:
    """`parameter_std` as tensors, for a batch: θ `(..., k)` and the variances ``diag P_θθ``
    `(..., k)` → the physical parameters' σ `(..., k)`."""
    scale = model.physical_slope(theta)
    return scale * variances.clamp_min(0.0).sqrt()


VISCOUS_SHARE_LIMIT = 0.05
"""|s_j / b| above which a tanh neuron's slope over the data's upper speeds takes part of the
viscous term b (`viscous_share`; with |s_j| above `VISCOUS_SHARE_SIGMA` σ_b too)."""
VISCOUS_SHARE_SIGMA = 3.0
"""|s_j / σ_b| above which a neuron's share of b is reported (with `VISCOUS_SHARE_LIMIT`)."""
_W1 = re.compile(r"W1\[(\d+)\]")


@dataclass(frozen=True)
class ViscousShare:
    """The tanh neurons that, together, still rise over the data's upper speeds
    (`viscous_share`).

    ``names``: ``("viscous", "W1[j]", "W2[j]", …)`` as θ names them, the neurons that carry the
    slope (largest first); ``slope``: their net mean slope ``Σ s_j`` between ``v_half`` and
    ``v95``, the 95th percentile of |q̇| and its half; ``viscous``, ``viscous_std``: b and its σ."""

    names: tuple[str, ...]
    slope: float
    viscous: float
    viscous_std: float
    v_half: float
    v95: float

    @property
    def share(self) -> float:
        """``s_j / b``."""
        return self.slope / self.viscous

    @property
    def sigmas(self) -> float:
        """``s_j / σ_b``."""
        return self.slope / self.viscous_std

    @property
    def how(self) -> str:
        return f"slope {100 * self.share:.0f} % of b between v95/2 and v95"

    @property
    def message(self) -> str:
        w1s = self.names[1::2]
        which = " and ".join(n[3:-1] for n in w1s)
        one = len(w1s) == 1
        return (
            f"viscous and neuron{'' if one else 's'} {which} ({', '.join(self.names[1:])}) are "
            "not separately identifiable over this data's speeds: the "
            f"{'neuron' + chr(39) + 's tanh still rises' if one else 'neurons still rise'} between "
            f"v95/2 = {self.v_half:.3g} and v95 = {self.v95:.3g} ({'its' if one else 'their net'} "
            f"slope there is {100 * self.share:.0f} % of b, {abs(self.sigmas):.0f} σ_b), so "
            f"b = {self.viscous:.3g} is not the viscous term alone; raise model.saturation (to "
            "twice its value, 6 for the default 3) so that every neuron saturates below half "
            "the data's top speed"
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "parameters": list(self.names),
            "slope": self.slope,
            "share": self.share,
            "sigmas": self.sigmas,
            "viscous": self.viscous,
            "viscous_std": self.viscous_std,
            "v_half": self.v_half,
            "v95": self.v95,
        }


def viscous_share(
    values: Mapping[str, float], speeds: Tensor, *, viscous_std: float | None
) -> list[ViscousShare]:
    """The tanh neurons that take part of the viscous term's slope over the data's upper speeds.

    For each neuron j (θ names ``W1[j]``, ``W2[j]``), its mean slope over the upper half of
    the data's speeds, from v95/2 to v95 (v95 the 95th percentile of ``|speeds|``)::

        s_j = W2_j (tanh(W1_j v95) − tanh(W1_j v95/2)) / (v95/2)

    and their net slope ``S = Σ s_j`` (what the curve adds to b there) is reported when
    ``|S| > VISCOUS_SHARE_LIMIT |b|`` and ``|S| > VISCOUS_SHARE_SIGMA σ_b``, naming the neurons
    with ``|s_j| >= 1 %`` of b. The net, not each neuron: two slow neurons whose slopes cancel
    (measured: +23 % and −24 % of b, b within 1.5 σ) leave b the slope there. The upper half of
    the speed range, not of the samples: on a stick-slip record the median speed is near rest
    (a linear axis: v50 4e-5 against v95 0.23 m/s), and a neuron that draws the Stribeck dip
    there would be counted as slope. In a fit that separates them every neuron is saturated
    there and the friction's slope is b alone; the bound ``W1_j > saturation / v95`` saturates
    a neuron at v95, not over the upper half of the speeds. Measured: on 12 seeds of a user's
    rotary axis (b = 0.002, v95 6.73 rad/s) one fit kept a neuron at its bound (W1 = 0.464,
    W2 = −0.009: −6.6 % of b, 9.6 σ_b) with b 47 σ off, its correlations below 0.99, and
    nothing else is named; on the 40 tanh and LuGre runs of the coverage study, nothing; on a
    linear axis (b = 8 N s/m) a fit with b = 1.23 is named (+423 %), its refit with
    ``model.saturation = 6`` (b = 7.88) is not.
    A LuGre sliding curve is C held at ``C(v_s)`` below its stick velocity (``lugre_vstick``):
    C is read at ``max(v, v_s)`` there.

    Args:
        values: θ in physical units by name (`ArmModel.physical_parameters`).
        speeds: the identification data's velocity, any shape.
        viscous_std: σ_b; ``None`` or 0 (b has no σ: the report names it as not determined)
            reports nothing.

    Returns ``[]``, or one `ViscousShare` when the net slope is over both limits; always ``[]``
    for a model without ``viscous`` or without tanh neurons (polytopic, Coulomb, Stribeck).
    """
    b = values.get("viscous")
    if b is None or not b > 0 or not viscous_std or not math.isfinite(viscous_std):
        return []
    found = speed_quantiles(speeds, [0.5, 0.95])
    if found is None:
        return []
    v50, v95 = found
    v_half = 0.5 * v95
    if not v95 > v50:  # speeds that do not spread: no slope to tell apart
        return []
    stick = values.get("lugre_vstick", 0.0)
    lo, hi = max(v_half, stick), max(v95, stick)
    slopes = []
    for name, w1 in values.items():
        match = _W1.fullmatch(name)
        w2_name = f"W2[{match[1]}]" if match else ""
        if w2_name not in values:
            continue
        # s_j = W2_j (tanh(W1_j v95) − tanh(W1_j v95/2)) / (v95/2)
        s = values[w2_name] * (math.tanh(w1 * hi) - math.tanh(w1 * lo)) / (v95 - v_half)
        slopes.append((s, name, w2_name))
    net = sum(s for s, _, _ in slopes)
    if not (abs(net) > VISCOUS_SHARE_LIMIT * b and abs(net) > VISCOUS_SHARE_SIGMA * viscous_std):
        return []
    carry = sorted((x for x in slopes if abs(x[0]) >= 0.01 * b), key=lambda x: -abs(x[0]))
    names = ("viscous", *(n for _, w1, w2 in carry or slopes[:1] for n in (w1, w2)))
    return [ViscousShare(names, net, b, viscous_std, v_half, v95)]
