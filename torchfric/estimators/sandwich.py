"""The statistics of a sandwich covariance, shared by the prediction-error (`covariance`) and
the simulation-error (`oe_covariance`) forms.

- `PEMCovariance`: what either returns — the covariance ``I⁻¹ J I⁻¹``, the information I, the
  score's long-run covariance J, the gradient and Newton step, the correlation matrix and the
  `Identifiability` report.
- `long_run_covariance`: J from scores summed over blocks of consecutive samples, with a
  Bartlett kernel whose lag count follows Andrews' AR(1) plug-in (``1.1447 (α̂ B)^{1/3}``,
  between 1 and B/4), never pairing blocks of two experiments. About `BLOCKS` blocks per run:
  with ~30 blocks of 1000 samples the estimate was too noisy (±2σ coverage of a white-box
  model 85–90 % over 100 fits); with ~256 it was 96–98 %.
- `_inverse`: ``I⁻¹`` on unit-diagonal scaling, directions below `CONDITION_LIMIT` of the
  largest eigenvalue left out (a pseudo-inverse), reported by `identifiability` by name; the
  entries `at_bound` (a neuron's slope pinned at its floor) held: the others' σ given them
  (inverted with the rest, one got a variance of 1e283 and the band ±5e53 N m).
- `viscous_share` (from `uncertainty`, named here too): the tanh neurons that still rise over
  the data's upper speeds and so take part of b's slope (`ViscousShare`, joined to the report
  by the run's confidence stage): a bias the covariance cannot show.

Why this size: one statistic, the sandwich, and the report read off it; both estimators use it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from .uncertainty import VISCOUS_SHARE_LIMIT, VISCOUS_SHARE_SIGMA, ViscousShare, viscous_share

__all__ = [
    "BLOCKS",
    "CONDITION_LIMIT",
    "CORRELATION_LIMIT",
    "Identifiability",
    "PEMCovariance",
    "VISCOUS_SHARE_LIMIT",
    "VISCOUS_SHARE_SIGMA",
    "ViscousShare",
    "at_bound",
    "held_entries",
    "identifiability",
    "long_run_covariance",
    "score_sums",
    "viscous_share",
]

CORRELATION_LIMIT = 0.99
"""|ρ| above which two parameters are reported as not separately identifiable."""
CONDITION_LIMIT = 1e-8
"""A direction of the scaled information with eigenvalue below this fraction of the largest is
reported as not identifiable."""
STEEP_LIMIT = 5.0
"""A tanh neuron whose input weight times the stick speed (`prefit.stick_band`) exceeds this
is a step at every speed the criterion sees (tanh 5 = 0.99991): its steepness is held, like an
entry at its floor (`held_entries`). Left free, the polish drove such a weight from 300 to
2·10⁵ along a direction where ℓ is flat and rough to 0.3 nats (where each sample falls on the
step), and the σ it reported moved up to 3.7× with a 1e-12 change of θ (docs/results.md)."""
BOUND_SLOPE = 1e-6
"""A bounded entry of θ whose value moves less than this per unit of θ sits at its bound
(`at_bound`)."""


@dataclass
class Identifiability:
    """Which parameters the data cannot separate.

    ``pairs``: ``(name_i, name_j, ρ)`` with ``|ρ| > CORRELATION_LIMIT``; ``directions``: for each
    near-null direction of the scaled information, the names that make it up (largest
    components first) and its relative eigenvalue; ``shares``: the tanh neurons that take part
    of b (`viscous_share`); ``messages``: one line each."""

    pairs: list[tuple[str, str, float]] = field(default_factory=list)
    directions: list[tuple[list[str], float]] = field(default_factory=list)
    shares: list[ViscousShare] = field(default_factory=list)
    held: list[str] = field(default_factory=list)
    steep: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not (self.pairs or self.directions or self.shares or self.held or self.steep)

    @property
    def groups(self) -> list[tuple[list[str], str]]:
        """The strongly correlated pairs joined into groups (connected components), with the
        largest |ρ| in each, then each near-null direction not already inside a group, then
        each entry held at its bound, then each neuron held as a step, then each neuron that
        takes part of b: the names and how they were found."""
        held = [([n], "held at its lower bound") for n in self.held]
        held += [([n], "held: a step at every moving speed") for n in self.steep]
        return self._collinear() + held + [(list(s.names), s.how) for s in self.shares]

    def _collinear(self) -> list[tuple[list[str], str]]:
        """`groups` of the covariance alone (the pairs and the near-null directions)."""
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
        for a, _b, r in self.pairs:
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
        for names, how in self._collinear():
            if len(names) == 1:
                out.append(
                    f"{names[0]} is not determined by this data ({how}): its value is the "
                    "start's or the estimator's drift, and it has no σ; fix it, drop the term, or "
                    "excite the machine where it acts"
                )
                continue
            listed = ", ".join(names[:-1]) + f" and {names[-1]}"
            out.append(
                f"{listed} are not separately identifiable from this data ({how}): they trade "
                "off against each other, only their combination is determined; fix one, use a "
                "smaller model, or excite the machine so that they act differently"
            )
        out += [
            f"{n} sits at its lower bound (model.saturation / v95): held there, without σ; the "
            "other σ and the curve's band take it as fixed (a neuron at its floor is unused, its "
            "W2 near 0, or shares the viscous slope, which a viscous line then names)"
            for n in self.held
        ]
        out += [
            f"{n} makes its neuron a step at every speed the criterion sees (its rise lies inside "
            "the stick band): held there, without σ; the data see the step's height (W2), not "
            "how steep it is, and the other σ and the curve's band take it as fixed"
            for n in self.steep
        ]
        return out + [s.message for s in self.shares]

    def to_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "correlation_limit": CORRELATION_LIMIT,
            "condition_limit": CONDITION_LIMIT,
            "pairs": [{"a": a, "b": b, "rho": r} for a, b, r in self.pairs],
            "directions": [{"parameters": n, "relative_eigenvalue": e} for n, e in self.directions],
            "share_limit": VISCOUS_SHARE_LIMIT,
            "share_sigma_limit": VISCOUS_SHARE_SIGMA,
            "viscous_shares": [s.to_dict() for s in self.shares],
            "held_at_bound": list(self.held),
            "held_steep": list(self.steep),
            "messages": self.messages,
        }


def identifiability(
    information: Tensor, cov: Tensor, names: Sequence[str], held: Tensor | None = None,
    steep: Tensor | None = None,
) -> Identifiability:  # fmt: skip
    """Near-collinear parameter pairs (|ρ| of `cov` above `CORRELATION_LIMIT`), near-null
    directions of `information` scaled to unit diagonal (eigenvalue below `CONDITION_LIMIT`
    of the largest) among the entries held neither at their floor (`held`, bool `(k,)`) nor as
    a step (`steep`; both from `held_entries`), and those held."""
    none = torch.zeros(len(names), dtype=torch.bool)
    held, steep = (none if m is None else m.to(torch.bool) for m in (held, steep))
    free = ~(held | steep)
    out = Identifiability(held=[n for n, h in zip(names, held.tolist(), strict=True) if h],
                          steep=[n for n, s in zip(names, steep.tolist(), strict=True) if s])  # fmt: skip
    names = [n for n, f in zip(names, free.tolist(), strict=True) if f]
    information, cov = information[free][:, free], cov[free][:, free]
    d = torch.diagonal(cov).clamp_min(0.0).sqrt()
    denom = d[:, None] * d[None, :]
    corr = torch.where(denom > 0, cov / torch.where(denom > 0, denom, 1.0), 0.0)
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
    def held(self) -> Tensor:
        """`(k,)` bool: the entries held out of the inverse (at their floor or as a step,
        `held_entries`), as `identifiability` names them."""
        gone = {*self.identifiability.held, *self.identifiability.steep}
        return torch.tensor([n in gone for n in self.names], dtype=torch.bool)

    def determined(self, offset: Tensor) -> Tensor:
        """`offset` (estimation coordinates) along the directions this information determines
        only: ``I⁺ I offset`` over the free entries (`_inverse`: near-null directions out),
        0 on the `held` ones. Along those the σ are 0 by construction (`identifiability`
        reports them instead), and a distance between two estimates there is where an optimiser
        wandered on a flat likelihood, not an error of the estimate."""
        held = self.held
        offset = torch.where(held, 0.0, torch.as_tensor(offset, dtype=self.information.dtype))
        return _inverse(self.information, held) @ (self.information @ offset)

    @property
    def newton_sigma(self) -> Tensor:
        return self.newton / self.std.clamp_min(1e-300)

    @property
    def correlation(self) -> Tensor:
        """`(k, k)`; rows and columns of a parameter with σ = 0 (no information) are 0."""
        d = self.std
        denom = d[:, None] * d[None, :]
        return torch.where(denom > 0, self.cov / torch.where(denom > 0, denom, 1.0), 0.0)

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


BLOCKS = 256
"""About this many blocks of consecutive samples carry the score's long-run covariance: with
~30 blocks of 1000 samples its estimate was too noisy (±2σ coverage of a white-box model
85–90 % over 100 fits); with ~256 it was 96–98 %."""
_RHO_MAX = 0.95  # bound of the block scores' lag-one autocorrelation in the plug-in


def long_run_covariance(scores: Tensor, segment: Tensor | None = None) -> tuple[Tensor, int]:
    """The long-run covariance `(k, k)` of the sum of the block scores `(B, k)` (centred), with
    a Bartlett kernel whose lag count comes from Andrews' AR(1) plug-in (`_bandwidth`); lags
    never pair blocks of different experiments (`segment` `(B,)`, each block's experiment).
    Returns ``(J, lags)``."""
    segment = torch.zeros(scores.shape[0], dtype=torch.long) if segment is None else segment
    lags = _bandwidth(scores, segment)
    return _long_run(scores, segment, lags), lags


def _bartlett(scores: Tensor) -> tuple[Tensor, int]:
    """`long_run_covariance` of one experiment's block scores."""
    return long_run_covariance(scores)


def _lagged(c: Tensor, segment: Tensor, lag: int) -> Tensor:
    """``Σ_b c_{b+lag} c_bᵀ`` `(k, k)` over block pairs of the same experiment."""
    same = (segment[lag:] == segment[:-lag]).to(c.dtype)[:, None]
    return (c[lag:] * same).T @ c[:-lag]


def _bandwidth(scores: Tensor, segment: Tensor) -> int:
    """Bartlett lags by Andrews' AR(1) plug-in on the centred block scores (module docstring):
    ``S = 1.1447 (α̂ B)^{1/3}``, lags ``⌊S⌋`` between 1 and ``B / 4``."""
    B = scores.shape[0]
    cap = max(1, B // 4)
    if B < 3:
        return min(1, max(B - 1, 0))
    c = scores - scores.mean(0, keepdim=True)
    var = (c * c).sum(0)
    cross = torch.diagonal(_lagged(c, segment, 1))
    live = var > 1e-300 * var.max().clamp_min(1e-300)
    if not bool(live.any()):
        return 1
    rho = (cross[live] / var[live]).clamp(-_RHO_MAX, _RHO_MAX)
    alpha = float((4.0 * rho**2 / ((1.0 - rho) ** 2 * (1.0 + rho) ** 2)).mean())
    S = 1.1447 * (alpha * B) ** (1.0 / 3.0)
    return int(min(cap, max(1, math.floor(S))))


def _long_run(scores: Tensor, segment: Tensor, lags: int) -> Tensor:
    """Long-run covariance `(k, k)` of the sum of the block scores `(B, k)` (centred), Bartlett
    weights ``1 − j/(L+1)`` over `lags` L, with no products across experiments."""
    B = scores.shape[0]
    c = scores - scores.mean(0, keepdim=True)
    J = c.T @ c
    for lag in range(1, min(lags, B - 1) + 1):
        G = _lagged(c, segment, lag)
        J = J + (1.0 - lag / (lags + 1.0)) * (G + G.T)
    J = J * (B / max(B - 1, 1))
    return 0.5 * (J + J.T)


def at_bound(model: Any, theta: Tensor, stick_speed: float | None = None) -> Tensor:
    """`(k,)` bool: the entries of θ held out of the inverse (`_inverse`), either of
    `held_entries`."""
    floor, steep = held_entries(model, theta, stick_speed)
    return floor | steep


def held_entries(
    model: Any, theta: Tensor, stick_speed: float | None = None
) -> tuple[Tensor, Tensor]:
    """`(k,)` bool twice: the entries of θ stored above a lower bound (a tanh neuron's input
    weight above `min_slope`) that are pinned at it (their value moves less than `BOUND_SLOPE`
    per unit of θ), and those whose neuron is a step at every speed the criterion sees (input
    weight × `stick_speed` above `STEEP_LIMIT`; none without a `stick_speed`)."""
    theta = theta.reshape(-1)
    bounded = model.friction.flat_bounded()
    mask = torch.zeros(theta.numel(), dtype=torch.bool)
    mask[: bounded.numel()] = bounded
    floor = mask & (model.physical_slope(theta) < BOUND_SLOPE)
    if stick_speed is None:
        return floor, torch.zeros_like(floor)
    return floor, mask & ~floor & (model.to_physical(theta) * stick_speed > STEEP_LIMIT)


def sandwich(information: Tensor, J: Tensor, held: Tensor | None) -> tuple[Tensor, Tensor]:
    """``(I⁻¹, I⁻¹ J I⁻¹)`` symmetrised, with `_inverse` (the entries `held` left out)."""
    inv = _inverse(information, held)
    cov = inv @ J @ inv
    return inv, 0.5 * (cov + cov.T)


def _inverse(information: Tensor, held: Tensor | None = None) -> Tensor:
    """``I⁻¹`` by a symmetric eigen-decomposition on unit-diagonal scaling; directions with a
    non-positive or negligible eigenvalue get no inverse (a pseudo-inverse): they are reported
    by `identifiability`, not hidden behind a huge σ. The entries `held` (bool `(k,)`,
    `at_bound`) are left out: their rows and columns are zero."""
    k = information.shape[0]
    idx = torch.arange(k) if held is None else (~held.to(torch.bool)).nonzero()[:, 0]
    out = torch.zeros_like(information)
    if idx.numel():
        out[idx[:, None], idx] = _pinv(information[idx][:, idx])
    return out


def _pinv(information: Tensor) -> Tensor:
    d = torch.diagonal(information).abs().clamp_min(1e-300).sqrt()
    scaled = information / (d[:, None] * d[None, :])
    evals, evecs = torch.linalg.eigh(0.5 * (scaled + scaled.T))
    top = float(evals.abs().max()) or 1.0
    keep = evals > CONDITION_LIMIT * top
    inv_e = torch.where(keep, 1.0 / torch.where(keep, evals, torch.ones_like(evals)), 0.0)
    inv_scaled = (evecs * inv_e) @ evecs.T
    return inv_scaled / (d[:, None] * d[None, :])


def score_sums(
    base: list[tuple[Tensor, Tensor]],
    De: list[Tensor],
    block: int | None,
) -> tuple[Tensor, list[Tensor], list[int], float, int]:
    """From the innovations at θ and their sensitivities `De` (`covariance._sensitivities`): the
    information, the block scores and each block's experiment, ``−½ V`` and the sample count
    (`torchfric.estimators.covariance.pem_covariance`). Taken block by block: no per-sample
    score array of the whole record."""
    k = De[0].shape[1]
    info = torch.zeros(k, k, dtype=torch.float64)
    block_scores: list[Tensor] = []
    segment: list[int] = []
    loglik, samples = 0.0, 0
    size = block or max(1, sum(int(e.numel()) for e, _ in base) // BLOCKS)
    for i, (e, S) in enumerate(base):
        # V = Σ e²/S with the weights 1/S held (the filter's S depends on θ only through P):
        # per sample the score −e ∂e / S and the Gauss–Newton information ∂eᵀ∂e / S
        for eb, Sb, Db in zip(torch.split(e, size), torch.split(S, size), torch.split(De[i], size),
                              strict=True):  # fmt: skip
            block_scores.append((-(eb / Sb)[:, None] * Db).sum(0))
            info += (Db / Sb[:, None]).T @ Db
            segment.append(i)
        loglik += float(-0.5 * (e * e / S).sum())
        samples += e.numel()
    return info, block_scores, segment, loglik, samples
