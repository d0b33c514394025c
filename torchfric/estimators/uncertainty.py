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
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import TorchfricError
from ..models.arm import ArmModel

__all__ = [
    "SIGMA_SOURCES",
    "friction_jacobian",
    "friction_band",
    "friction_samples",
    "parameter_std",
    "physical_std",
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
