"""Parameter covariance from the prediction-error likelihood: what a ± σ should mean.

The augmented EKF ends every pass with a ``P_θθ``, but that is the filter's belief after it has
absorbed the same data once per pass under an assumed noise model (Q, R); on synthetic axes its
σ was 10–1000× narrower than the real error. The covariance reported instead is the one of the
*prediction-error estimate*: θ fixed, the filter on ``[q, q̇(, z)]`` alone yields one-step
innovations ``e_t(θ)`` with covariances ``S_t(θ)`` and the log-likelihood

    ℓ(θ) = Σ_t ℓ_t(θ),      ℓ_t = −½ (e_tᵀ S_t⁻¹ e_t + ln det S_t + m ln 2π)

over every sample of every identification record. At the kept θ̂ we compute

* the observed information ``I = −∇²ℓ(θ̂)`` (`k × k`), and
* the long-run covariance of the score ``J = Cov[Σ_t ∇ℓ_t]``, estimated from the scores of
  blocks of consecutive samples with a Bartlett (Newey–West) kernel over blocks,

and report the *sandwich* ``Cov[θ̂] = I⁻¹ J I⁻¹`` (White's robust form). Why not ``I⁻¹`` alone:
that is the covariance only when the likelihood is the data's true density. Here it is not: R
is a tuning (the paper's 1e-3 rad² is 10⁴ times an encoder's quantisation variance), the
reconstructed velocity shares the position's noise, and the innovations of a filter with
assumed Q and R are correlated over many samples. ``I⁻¹`` is then wrong in scale and shape;
the sandwich stays right in both, because ``J`` is measured from the data's own scores.

Derivatives are central differences of ℓ over a batch of fixed-θ filters (the ensemble's
compiled masked step, one member per perturbed θ, `P_θθ = 0` so that θ stays put): step
sizes are set from a first diagonal pass to about half a marginal standard deviation, where the
differences are far above rounding (ℓ is smooth in θ for a fixed data record) and truncation
is small. `tests/test_covariance.py` checks the derivatives against autograd's Hessian of the
same likelihood on a short record.

Directions the data cannot separate show up as a near-singular ``I``: the correlation matrix
of the covariance and the eigen-decomposition of the scaled information name them
(`Identifiability`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from ..accel import iter_chunks
from ..data import Experiment
from ..errors import TorchfricError
from ..models.arm import ArmModel
from .ensemble import _first_sample, make_masked_step
from .observers import Callback
from .passes import Filtering, initial_belief, measured_data
from .settings import EKFTuning

__all__ = [
    "FixedThetaLikelihood",
    "fixed_theta_loglik",
    "PEMCovariance",
    "Identifiability",
    "pem_covariance",
    "pem_refine",
    "identifiability",
    "CORRELATION_LIMIT",
    "CONDITION_LIMIT",
]

CORRELATION_LIMIT = 0.99
"""|ρ| above which two parameters are reported as not separately identifiable."""
CONDITION_LIMIT = 1e-8
"""A direction of the scaled information with eigenvalue below this fraction of the largest is
reported as not identifiable."""


@dataclass
class FixedThetaLikelihood:
    """The fixed-θ filter's log-likelihood for K parameter vectors.

    ``total`` `(K,)`: ℓ(θ_i) over every sample; ``blocks`` `(K, B)`: the same split into blocks of
    consecutive samples (``block`` samples each; an experiment's last block may be shorter);
    ``sum_nis`` `(K,)`; ``samples``: samples filtered; ``ok`` `(K,)`: the filter stayed healthy."""

    total: Tensor
    blocks: Tensor
    sum_nis: Tensor
    samples: int
    block: int
    ok: Tensor


def fixed_theta_loglik(
    model: ArmModel,
    experiments: Sequence[Experiment],
    tuning: EKFTuning,
    thetas: Tensor,
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
) -> FixedThetaLikelihood:
    """ℓ(θ_i) of the filter on ``[q, q̇(, z)]`` with θ held at each row of `thetas` `(K, k)`
    (estimation coordinates), under `tuning`'s Q and R scaled by `q_scale`, `r_scale`, in
    blocks of the compiled step's chunk (1000 samples) or, uncompiled, of 1000 samples."""
    thetas = torch.as_tensor(thetas, dtype=torch.float64)
    K, k = thetas.shape
    Q, P0_xx, H, R = tuning.matrices(k, model.state_size)
    Qk = (Q * q_scale).expand(K, -1, -1).clone()
    Rk = (R * r_scale).expand(K, -1, -1).clone()
    step_fn = make_masked_step(model, tuning.substeps, compile=tuning.compile)
    data = measured_data(list(experiments), tuning.measure)
    total_n = sum(e.n for e in experiments)
    f = Filtering(data, Qk, P0_xx, H, Rk, step_fn, 1e300, Callback(), 10**9, total_n)
    zero = torch.zeros(K, k, k, dtype=torch.float64)
    f64 = torch.float64
    good = torch.ones(K, dtype=torch.bool)
    fail_at = torch.full((K,), -1, dtype=torch.long)
    sum_nis_all = torch.zeros(K, dtype=f64)
    block = step_fn.size if step_fn.chunk is not None else 1000  # type: ignore[attr-defined]
    blocks: list[Tensor] = []
    bound = torch.tensor(1e300, dtype=f64)
    for exp, u, y in data:
        x, P = initial_belief(exp, thetas, zero, P0_xx)
        sums = [torch.zeros(K, H.shape[0], dtype=f64), torch.zeros(K, dtype=f64)]
        sums.append(torch.zeros(K, dtype=f64))
        carry = _first_sample((x, P, good, fail_at, *sums), y[0], f)
        consts = (torch.tensor(exp.dt, dtype=f64), Qk, H, Rk, bound)
        index = torch.arange(exp.n)
        last = torch.zeros(K, dtype=f64)
        if step_fn.chunk is not None:
            for _, _, xs, valid in iter_chunks((index[1:], u[:-1], y[1:]), block):
                carry, _ = step_fn.chunk(carry, xs, valid, consts)
                blocks.append(carry[6] - last)
                last = carry[6].clone()
        else:
            for j in range(1, exp.n):
                carry = step_fn(*carry, index[j], u[j - 1], y[j], *consts)
                if j % block == 0 or j == exp.n - 1:
                    blocks.append(carry[6] - last)
                    last = carry[6].clone()
        good, fail_at = carry[2], carry[3]
        sum_nis_all = sum_nis_all + carry[5]
    B = torch.stack(blocks, dim=1)
    return FixedThetaLikelihood(B.sum(1), B, sum_nis_all, total_n, block, good.clone())


@dataclass
class Identifiability:
    """Which parameters the data cannot separate.

    ``pairs``: ``(name_i, name_j, ρ)`` with ``|ρ| > CORRELATION_LIMIT``; ``directions``: for each
    near-null direction of the scaled information, the names that make it up (largest
    components first) and its relative eigenvalue; ``messages``: one line each."""

    pairs: list[tuple[str, str, float]] = field(default_factory=list)
    directions: list[tuple[list[str], float]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.pairs and not self.directions

    @property
    def groups(self) -> list[tuple[list[str], str]]:
        """The strongly correlated pairs joined into groups (connected components), with the
        largest |ρ| in each, then each near-null direction not already inside a group: the
        names and how they were found."""
        parent: dict[str, str] = {}

        def root(a: str) -> str:
            while parent.get(a, a) != a:
                a = parent[a]
            return a

        order: list[str] = []
        for a, b, _ in self.pairs:
            for n in (a, b):
                if n not in order:
                    order.append(n)
            parent[root(a)] = root(b)
        out: dict[str, tuple[list[str], float]] = {}
        for a, b, r in self.pairs:
            names, top = out.get(root(a), ([], 0.0))
            out[root(a)] = (names, max(top, abs(r)))
        for n in order:
            out[root(n)][0].append(n)
        groups = [(names, f"|ρ| up to {top:.4f}") for names, top in out.values()]
        seen = {n for names, _ in groups for n in names}
        for names, ev in self.directions:
            if not set(names) <= seen:
                groups.append((names, f"relative information {ev:.1e}"))
        return groups

    @property
    def messages(self) -> list[str]:
        """One line per group of parameters the data cannot separate."""
        out = []
        for names, how in self.groups:
            listed = ", ".join(names[:-1]) + f" and {names[-1]}" if len(names) > 1 else names[0]
            out.append(
                f"{listed} are not separately identifiable from this data ({how}): they trade "
                "off against each other, only their combination is determined; fix one, use a "
                "smaller model, or excite the machine so that they act differently"
            )
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "correlation_limit": CORRELATION_LIMIT,
            "condition_limit": CONDITION_LIMIT,
            "pairs": [{"a": a, "b": b, "rho": r} for a, b, r in self.pairs],
            "directions": [{"parameters": n, "relative_eigenvalue": e} for n, e in self.directions],
            "messages": self.messages,
        }


def identifiability(information: Tensor, cov: Tensor, names: Sequence[str]) -> Identifiability:
    """Near-collinear parameter pairs (|ρ| of `cov` above `CORRELATION_LIMIT`) and near-null
    directions of `information` scaled to unit diagonal (eigenvalue below `CONDITION_LIMIT`
    of the largest)."""
    out = Identifiability()
    d = torch.diagonal(cov).clamp_min(1e-300).sqrt()
    corr = cov / (d[:, None] * d[None, :])
    k = len(names)
    for i in range(k):
        for j in range(i + 1, k):
            r = float(corr[i, j])
            if abs(r) > CORRELATION_LIMIT:
                out.pairs.append((names[i], names[j], r))
    di = torch.diagonal(information).abs().clamp_min(1e-300).sqrt()
    scaled = information / (di[:, None] * di[None, :])
    evals, evecs = torch.linalg.eigh(0.5 * (scaled + scaled.T))
    top = float(evals.abs().max()) or 1.0
    for ev, vec in zip(evals.tolist(), evecs.T, strict=True):
        if ev < CONDITION_LIMIT * top:
            w = vec.abs()
            order = torch.argsort(w, descending=True).tolist()
            picked = [names[i] for i in order if w[i] >= 0.2 * w.max()]
            out.directions.append((picked, ev / top))
    return out


@dataclass
class PEMCovariance:
    """What `pem_covariance` returns (all in estimation coordinates, θ order of the model).

    ``cov`` the sandwich ``I⁻¹ J I⁻¹``; ``information`` ``I``; ``score_cov`` ``J``; ``gradient``
    ``∇ℓ(θ̂)``; ``newton`` the step ``I⁻¹ ∇ℓ`` to the likelihood's maximum (in units of each
    parameter's σ: ``newton_sigma``); ``loglik`` ℓ(θ̂); ``blocks`` and ``bandwidth`` of the
    score's long-run covariance."""

    theta: Tensor
    cov: Tensor
    information: Tensor
    score_cov: Tensor
    gradient: Tensor
    newton: Tensor
    loglik: float
    samples: int
    blocks: int
    bandwidth: int
    names: list[str]
    identifiability: Identifiability
    steps: Tensor | None = None  # the finite-difference steps used (estimation coordinates)
    method: str = "sandwich"

    @property
    def std(self) -> Tensor:
        return torch.diagonal(self.cov).clamp_min(0.0).sqrt()

    @property
    def newton_sigma(self) -> Tensor:
        return self.newton / self.std.clamp_min(1e-300)

    @property
    def correlation(self) -> Tensor:
        d = self.std.clamp_min(1e-300)
        return self.cov / (d[:, None] * d[None, :])

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "loglik": self.loglik,
            "samples": self.samples,
            "blocks": self.blocks,
            "bandwidth": self.bandwidth,
            "names": list(self.names),
            "correlation": self.correlation.tolist(),
            "newton_step_sigma": self.newton_sigma.tolist(),
        }


def _bartlett(scores: Tensor) -> tuple[Tensor, int]:
    """Long-run covariance `(k, k)` of the sum of the block scores `(B, k)` (centred), with a
    Bartlett kernel whose bandwidth follows Newey and West's rule ``⌊4 (B/100)^(2/9)⌋``
    (at least 1 block: neighbouring blocks share the filter's memory at their boundary)."""
    B = scores.shape[0]
    c = scores - scores.mean(0, keepdim=True)
    L = max(1, int(4.0 * (B / 100.0) ** (2.0 / 9.0)))
    L = min(L, max(B - 1, 0))
    J = c.T @ c
    for lag in range(1, L + 1):
        G = c[lag:].T @ c[:-lag]
        J = J + (1.0 - lag / (L + 1.0)) * (G + G.T)
    return J * (B / max(B - 1, 1)), L


def _inverse(information: Tensor) -> Tensor:
    """``I⁻¹`` by a symmetric eigen-decomposition on unit-diagonal scaling; directions with a
    non-positive or negligible eigenvalue get no inverse (a pseudo-inverse): they are reported
    by `identifiability`, not hidden behind a huge σ."""
    d = torch.diagonal(information).abs().clamp_min(1e-300).sqrt()
    scaled = information / (d[:, None] * d[None, :])
    evals, evecs = torch.linalg.eigh(0.5 * (scaled + scaled.T))
    top = float(evals.abs().max()) or 1.0
    keep = evals > CONDITION_LIMIT * top
    inv_e = torch.where(keep, 1.0 / torch.where(keep, evals, torch.ones_like(evals)), 0.0)
    inv_scaled = (evecs * inv_e) @ evecs.T
    return inv_scaled / (d[:, None] * d[None, :])


def pem_covariance(
    model: ArmModel,
    experiments: Sequence[Experiment],
    tuning: EKFTuning,
    theta: Tensor,
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    hint: Tensor | None = None,
    steps: Tensor | None = None,
) -> PEMCovariance:
    """The sandwich covariance of θ̂ = `theta` `(k,)` (module docstring).

    Args:
        model, experiments, tuning: the run's model, identification records and EKF tuning
            (with the kept member's `q_scale`, `r_scale`).
        theta: θ̂ in estimation coordinates.
        hint: `(k,)` a first guess of each parameter's standard deviation (the filter's
            ``sqrt(diag P_θθ)``); it only sets the first finite-difference steps.
        steps: `(k,)` the finite-difference steps to use as they are (an earlier result's
            ``steps``): the sizing stage is skipped.

    Raises:
        TorchfricError: the fixed-θ filter fails at θ̂ (it should not: the passes ran there).
    """
    theta = torch.as_tensor(theta, dtype=torch.float64).reshape(-1)
    k = theta.numel()
    names = model.theta_names
    floor = 1e-7 * torch.maximum(theta.abs(), torch.ones_like(theta))
    h0 = floor if hint is None else torch.maximum(torch.as_tensor(hint, dtype=torch.float64), floor)
    eye = torch.eye(k, dtype=torch.float64)

    def run(rows: Tensor) -> FixedThetaLikelihood:
        out = fixed_theta_loglik(
            model, experiments, tuning, rows, q_scale=q_scale, r_scale=r_scale
        )
        if not bool(out.ok[0]):
            raise TorchfricError(
                "the fixed-θ filter failed at the identified θ while computing its covariance; "
                "the run's θ is unusable for a σ (report it with the config that produced it)"
            )
        return out

    if steps is None:
        # Stage 1: the diagonal curvature with the hinted steps, to size the real steps.
        rows = torch.cat([theta[None], theta + h0[:, None] * eye, theta - h0[:, None] * eye])
        first = run(rows)
        l0, lp, lm = first.total[0], first.total[1 : k + 1], first.total[k + 1 :]
        curv = -(lp - 2.0 * l0 + lm) / (h0 * h0)
        ok = first.ok[1:].reshape(2, k).all(0) & torch.isfinite(curv) & (curv > 0)
        h = torch.maximum(torch.where(ok, 0.5 / curv.clamp_min(1e-300).sqrt(), h0), floor)
    else:
        h = torch.as_tensor(steps, dtype=torch.float64).clone()
    # Stage 2: axis and diagonal-pair members for the full Hessian; axis members give scores.
    ii, jj = torch.triu_indices(k, k, offset=1)
    hi, hj = h[:, None] * eye, h[:, None] * eye
    rows = [theta[None], theta + hi, theta - hi]
    if ii.numel():
        rows += [theta + hj[ii] + hj[jj], theta - hj[ii] - hj[jj]]
    second = run(torch.cat(rows))
    if not bool(second.ok.all()):
        bad = [names[int(j) % k] for j in torch.nonzero(~second.ok[1 : 2 * k + 1]).flatten()]
        raise TorchfricError(
            "the fixed-θ filter failed half a standard deviation away from the identified θ "
            f"(in {', '.join(sorted(set(bad))) or 'a parameter pair'}); the likelihood is not "
            "smooth there, so no σ can be given"
        )
    t = second.total
    L0, Lp, Lm = t[0], t[1 : k + 1], t[k + 1 : 2 * k + 1]
    hess = torch.zeros(k, k, dtype=torch.float64)
    hess[range(k), range(k)] = (Lp - 2.0 * L0 + Lm) / (h * h)
    if ii.numel():
        npair = ii.numel()
        Lpp, Lmm = t[2 * k + 1 : 2 * k + 1 + npair], t[2 * k + 1 + npair :]
        # ∂²ℓ/∂θi∂θj ≈ (ℓ(++) − ℓ(+i) − ℓ(+j) + 2ℓ0 − ℓ(−i) − ℓ(−j) + ℓ(−−)) / (2 hi hj)
        off = (Lpp - Lp[ii] - Lp[jj] + 2.0 * L0 - Lm[ii] - Lm[jj] + Lmm) / (2.0 * h[ii] * h[jj])
        hess[ii, jj] = off
        hess[jj, ii] = off
    information = -hess
    bp, bm = second.blocks[1 : k + 1], second.blocks[k + 1 : 2 * k + 1]
    scores = ((bp - bm) / (2.0 * h[:, None])).T  # (B, k)
    gradient = scores.sum(0)
    J, bandwidth = _bartlett(scores)
    inv = _inverse(information)
    cov = inv @ J @ inv
    cov = 0.5 * (cov + cov.T)
    newton = inv @ gradient
    return PEMCovariance(
        theta=theta.clone(),
        cov=cov,
        information=information,
        score_cov=J,
        gradient=gradient,
        newton=newton,
        loglik=float(L0),
        samples=second.samples,
        blocks=scores.shape[0],
        bandwidth=bandwidth,
        names=list(names),
        identifiability=identifiability(information, cov, names),
        steps=h,
    )


def pem_refine(
    model: ArmModel,
    experiments: Sequence[Experiment],
    tuning: EKFTuning,
    theta: Tensor,
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    hint: Tensor | None = None,
    iterations: int = 4,
    min_gain: float = 0.05,
) -> tuple[Tensor, PEMCovariance, list[float]]:
    """Newton steps on ℓ from `theta` to the prediction-error estimate, and its covariance.

    The EKF's passes end near, not at, the maximum of the fixed-θ likelihood (measured: the
    Newton step from a converged run's θ was up to 9 σ for curve parameters and 4–5 σ for b);
    the σ describe the spread of that maximum, so they can only cover the truth from there.
    Each iteration takes the step ``I⁻¹ ∇ℓ`` (the pseudo-inverse of `_inverse`: directions the
    data do not determine are not moved), tries it whole, halved and quartered in one batch,
    and keeps the best if it raises ℓ. It stops when the step's expected gain ``½ ∇ℓᵀ I⁻¹ ∇ℓ``
    falls below `min_gain` nats, when no trial raises ℓ, or after `iterations`.

    Returns ``(θ, covariance at θ, ℓ after each accepted step, the first at the start)``."""
    cov = pem_covariance(
        model, experiments, tuning, theta, q_scale=q_scale, r_scale=r_scale, hint=hint
    )
    theta = cov.theta
    trace = [cov.loglik]
    for _ in range(iterations):
        if 0.5 * float(cov.gradient @ cov.newton) < min_gain:
            break
        fractions = torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64)
        trials = theta + fractions[:, None] * cov.newton
        out = fixed_theta_loglik(
            model, experiments, tuning, trials, q_scale=q_scale, r_scale=r_scale
        )
        ll = torch.where(out.ok & torch.isfinite(out.total), out.total, -torch.inf)
        best = int(torch.argmax(ll))
        if not float(ll[best]) > cov.loglik:
            break
        theta = trials[best]
        cov = pem_covariance(
            model, experiments, tuning, theta, q_scale=q_scale, r_scale=r_scale, steps=cov.steps
        )
        trace.append(cov.loglik)
    return theta, cov, trace
