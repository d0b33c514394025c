"""Friction models C(v): odd in the velocity v and zero at v = 0 for *every* parameter value.

Every model is an `nn.Module` that maps a velocity tensor of any shape to a torque tensor of the
same shape. Parameters are stored in *estimation coordinates*: parameters that must stay
positive (variances, Coulomb levels) are stored as their logarithm when `log_positive=True`, so
that an unconstrained estimator (EKF, gradient descent) can never make them negative. The pure
method `evaluate(v, params)` takes *physical* values; `forward(v)` evaluates the module's own.

Models (registry name in brackets, as used by `model.friction` in a config):

- `OddTanhFriction` ("tanh"): ``C(v) = W2ᵀ tanh(W1 v)``, no biases (Hensen et al. §3.1).
- `PolytopicFriction` ("polytopic"): Gaussian-weighted local affine models with the mirrored-pair
  construction of §3.2; beyond the outermost centres the outer pair continues as straight lines.
- `CoulombFriction` ("coulomb"): ``C(v) = Fc tanh(v/ε)``; with the arm's viscous ``b`` this is
  the Coulomb+viscous white-box baseline.
- `StribeckFriction` ("stribeck"): ``C(v) = (Fc + (Fs − Fc) exp(−(v/vs)²)) tanh(v/ε)``.

Why this size: one registry of curves that share the odd-by-construction contract and the
physical ↔ estimation coordinates; each class is short, and a reader compares them side by side.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from ..errors import TorchfricError

__all__ = [
    "Friction",
    "OddTanhFriction",
    "PolytopicFriction",
    "CoulombFriction",
    "StribeckFriction",
    "FRICTIONS",
    "make_friction",
]

_EXTRAPOLATIONS: tuple[str, ...] = ("affine", "gaussian")
"""`PolytopicFriction`'s validity constructions beyond the outer centres (see its docstring)."""


def _as_vector(value: Sequence[float] | Tensor | float, n: int, name: str) -> Tensor:
    """Parameter initial value as a float64 vector `(n,)`, with a clear error on a size mismatch."""
    t = torch.as_tensor(value, dtype=torch.float64).reshape(-1).clone()
    if t.numel() == 1 and n != 1:
        t = t.expand(n).clone()
    if t.numel() != n:
        raise TorchfricError(
            f"{name} needs {n} values, got {t.numel()} ({value!r}); give a list of length {n}"
        )
    if not torch.isfinite(t).all():
        raise TorchfricError(f"{name} must be finite, got {value!r}")
    return t


class Friction(nn.Module):
    """Base class of odd friction models.

    Subclasses declare their parameters with `_add(name, value, positive=...)` in the order
    that the flat parameter vector uses, and implement `evaluate`.
    """

    kind: ClassVar[str] = ""

    def __init__(self, *, log_positive: bool = True) -> None:
        super().__init__()
        self.log_positive = bool(log_positive)
        # (name, size, positive) in flat-vector order.
        self._spec: list[tuple[str, int, bool]] = []
        # Element names in flat order, e.g. ["W1[1]", "W1[2]", ...]; set by subclasses via _add.
        self._element_names: list[str] = []

    # -- parameter bookkeeping ---------------------------------------------------------------
    def _add(self, name: str, value: Tensor, *, positive: bool, labels: list[str]) -> None:
        if positive:
            if (value <= 0).any():
                raise TorchfricError(
                    f"{type(self).__name__}: {name} must be positive, got {value.tolist()}; "
                    "give strictly positive values"
                )
            raw = value.log() if self.log_positive else value
        else:
            raw = value
        self.register_parameter(name, nn.Parameter(raw.clone()))
        self._spec.append((name, value.numel(), positive))
        self._element_names.extend(labels)

    @property
    def element_names(self) -> list[str]:
        """Names of the scalar parameters in flat-vector order (physical meaning, not log)."""
        return list(self._element_names)

    @property
    def num_parameters(self) -> int:
        return sum(size for _, size, _ in self._spec)

    def positive_mask(self) -> Tensor:
        """`(k,)` bool: which flat entries are stored in log space."""
        out = []
        for _, size, positive in self._spec:
            out.extend([positive and self.log_positive] * size)
        return torch.tensor(out, dtype=torch.bool)

    def raw_vector(self) -> Tensor:
        """`(k,)` the parameters in estimation coordinates (differentiable, not detached)."""
        return torch.cat([getattr(self, name).reshape(-1) for name, _, _ in self._spec])

    def split(self, raw: Tensor) -> dict[str, Tensor]:
        """Physical parameter dict from raw vectors `(..., k)` in estimation coordinates
        (a leading batch of parameter sets is allowed; `evaluate` broadcasts it against v)."""
        out: dict[str, Tensor] = {}
        i = 0
        for name, size, positive in self._spec:
            chunk = raw[..., i : i + size]
            if positive and self.log_positive:
                out[name] = chunk.exp()
            else:
                out[name] = self._bounded(name, chunk) if name in self._bounds else chunk
            i += size
        return out

    # -- bounded linear parameters ---------------------------------------------------------------
    # A parameter with a lower bound ``lo`` (`_bounds[name]`, declared by a subclass) is stored
    # as r with value ``lo + lo·softplus(r/lo)``: above the bound for every r, and ≈ ``lo + r``
    # (the raw value, as unbounded) once well above it, so that an estimator's variances and
    # steps keep their meaning there; the slope falls to 0 only right at the bound.
    @property
    def _bounds(self) -> dict[str, float]:
        return {}

    def _bounded(self, name: str, r: Tensor) -> Tensor:
        lo = self._bounds[name]
        x = r / lo
        # softplus(x) = max(x, 0) + log(1 + e^−|x|), in the elementwise operations that the
        # generated C of `torchfric.native` translates (it has no softplus)
        return lo + lo * (x.clamp_min(0.0) + torch.log1p(torch.exp(-x.abs())))

    def flat_to_physical(self, raw: Tensor) -> Tensor:
        """`(..., k)` the flat parameters in physical units (`split`, flattened)."""
        return torch.cat([v.reshape(*raw.shape[:-1], -1) for v in self.split(raw).values()], -1)

    def flat_from_physical(self, values: Tensor) -> Tensor:
        """Inverse of `flat_to_physical`."""
        out, i = [], 0
        for name, size, positive in self._spec:
            chunk = values[..., i : i + size]
            if positive and self.log_positive:
                out.append(chunk.clamp_min(1e-300).log())
            elif name in self._bounds:
                lo = self._bounds[name]
                excess = ((chunk - lo) / lo).clamp_min(1e-300)
                # r = lo·log(expm1(excess)), written stably for a large excess
                out.append(lo * (excess + torch.log(-torch.expm1(-excess))))
            else:
                out.append(chunk)
            i += size
        return torch.cat(out, -1)

    def flat_slope(self, raw: Tensor) -> Tensor:
        """`(..., k)` d(physical)/d(raw), element by element (for the delta method)."""
        out, i = [], 0
        for name, size, positive in self._spec:
            chunk = raw[..., i : i + size]
            if positive and self.log_positive:
                out.append(chunk.exp())
            elif name in self._bounds:
                out.append(torch.sigmoid(chunk / self._bounds[name]))
            else:
                out.append(torch.ones_like(chunk))
            i += size
        return torch.cat(out, -1)

    def flat_bounded(self) -> Tensor:
        """`(k,)` bool: the flat entries stored above a lower bound (`_bounded`)."""
        return torch.cat([torch.full((size,), name in self._bounds) for name, size, _ in self._spec]
                         or [torch.zeros(0, dtype=torch.bool)])  # fmt: skip

    def physical_parameters(self) -> dict[str, Tensor]:
        """The module's own parameters in physical units (differentiable)."""
        return self.split(self.raw_vector())

    def forward(self, v: Tensor) -> Tensor:
        """`C(v)` for a velocity tensor of any shape, same shape out."""
        return self.evaluate(v, self.physical_parameters())

    def evaluate(self, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:  # pragma: no cover
        raise NotImplementedError

    def init_kwargs(self) -> dict[str, Any]:
        """Constructor arguments (besides the parameter values) that rebuild this module."""
        return {"log_positive": self.log_positive}

    @property
    def size(self) -> int:
        return 0

    def extra_repr(self) -> str:
        vals = {
            k: [round(float(x), 6) for x in v.reshape(-1)]
            for k, v in self.physical_parameters().items()
        }
        return ", ".join(f"{k}={v}" for k, v in vals.items())


class OddTanhFriction(Friction):
    """One-hidden-layer network without biases, ``C(v) = Σ_j W2_j tanh(W1_j v)`` (paper §3.1).

    Odd and zero at zero for every (W1, W2) because tanh is odd and there are no biases.

    Args:
        n: number of hidden neurons (3 in the paper: 6 parameters).
        w1, w2: initial weights `(n,)`. Defaults spread the slopes W1 logarithmically over
            `[0.1, 30] / velocity_scale` (from an almost-viscous to a Coulomb-like neuron; with
            `min_slope`, above it) and give each neuron `torque_scale / n`.
        min_slope: 0 (the paper's free weights), or a lower bound on every input weight,
            ``W1_j > min_slope`` [1/velocity] (stored as r with ``W1 = lo + lo·softplus(r/lo)``,
            ``lo = min_slope``). A run sets it to ``saturation / v_data`` (`model.saturation`,
            3 by default, over the data's velocity scale): every neuron is then saturated to
            within ``1 − tanh(3) = 0.5 %`` at the data's typical top speed, so that no neuron
            stays linear over the whole data and the total friction's slope at the top speeds
            is ``b`` alone. A neuron that saturates only near that speed can still share b's
            slope over the upper half of the data; a run checks for it and says so
            (`torchfric.estimators.uncertainty.viscous_share`). The sign of a neuron lives in W2.
    """

    kind = "tanh"

    def __init__(
        self,
        n: int = 3,
        *,
        w1: Sequence[float] | Tensor | None = None,
        w2: Sequence[float] | Tensor | None = None,
        velocity_scale: float = 1.0,
        torque_scale: float = 0.1,
        log_positive: bool = True,
        min_slope: float = 0.0,
    ) -> None:
        super().__init__(log_positive=log_positive)
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise TorchfricError(f"OddTanhFriction needs n >= 1 neurons, got {n!r}")
        if not (
            isinstance(min_slope, (int, float)) and math.isfinite(min_slope) and min_slope >= 0
        ):
            raise TorchfricError(f"OddTanhFriction min_slope must be >= 0, got {min_slope!r}")
        self.n = n
        self.min_slope = float(min_slope)
        if w1 is None:
            w1 = torch.logspace(-1.0, math.log10(30.0), n, dtype=torch.float64) / velocity_scale
            w1 = w1 + 1.5 * self.min_slope
        if w2 is None:
            w2 = torch.full((n,), torque_scale / n, dtype=torch.float64)
        w1 = _as_vector(w1, n, "W1")
        if self.min_slope:
            if bool((w1 <= self.min_slope).any()):
                raise TorchfricError(
                    f"OddTanhFriction W1 must be above min_slope = {self.min_slope:g}, got "
                    f"{w1.tolist()}; give larger input weights"
                )
            w1 = self.flat_from_physical_w1(w1)
        self._add("W1", w1, positive=False, labels=[f"W1[{j + 1}]" for j in range(n)])
        self._add(
            "W2", _as_vector(w2, n, "W2"), positive=False, labels=[f"W2[{j + 1}]" for j in range(n)]
        )

    @property
    def size(self) -> int:
        return self.n

    @property
    def _bounds(self) -> dict[str, float]:
        return {"W1": self.min_slope} if self.min_slope else {}

    def flat_from_physical_w1(self, w1: Tensor) -> Tensor:
        """Stored r of physical input weights `w1` above `min_slope`."""
        lo = self.min_slope
        excess = ((w1 - lo) / lo).clamp_min(1e-300)
        return lo * (excess + torch.log(-torch.expm1(-excess)))

    def init_kwargs(self) -> dict[str, Any]:
        extra = {"min_slope": self.min_slope} if self.min_slope else {}
        return {**super().init_kwargs(), **extra}

    def evaluate(self, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        # C(v) = W2ᵀ tanh(W1 v), broadcast over any leading shape of v.
        return (torch.tanh(v.unsqueeze(-1) * p["W1"]) * p["W2"]).sum(-1)


class PolytopicFriction(Friction):
    """Gaussian-weighted local affine friction models (paper §3.2), odd by construction.

    ``C(v) = Σ_i w_i(v) (a_i (v − c_i) + b_i)``, ``w_i = ρ_i / Σ_j ρ_j``,
    ``ρ_i = exp(−½ (v − c_i)² / σ_i)``. The centre model has ``c = 0, b = 0``; the other
    ``n − 1`` come in mirrored pairs ``(c, −c)`` sharing variance σ and slope a, with offsets
    ``(b, −b)``. For n = 3 the parameters are exactly a1, a2, b2, c2, σ1, σ2.

    Extrapolation: with the paper's Gaussians (``extrapolation="gaussian"``) the local model
    with the widest σ takes every velocity far from all centres, whatever its slope, so the
    curve can run away just beyond the data. The default ``extrapolation="affine"`` makes the
    validity of the outermost pair one-sided: ``log ρ = −½ min(v − c_m, 0)² / σ_m`` for the
    model at ``+c_m`` (weight 1 everywhere beyond its centre) and the mirror image
    ``−½ max(v + c_m, 0)² / σ_m`` for the one at ``−c_m``. Every other validity still decays
    like a Gaussian, so beyond the outer centres the normalised weight of the outer model tends
    to 1 and ``C(v) → a_m (v − c_m) + b_m`` (its mirror for v → −∞) for every σ: the outer
    local models continue the curve as straight lines, exactly (to rounding) from a few of the
    widest other model's standard deviations past the outermost centre on. Below the outer
    centres the curve is the paper's. ``n = 1`` (the centre model alone) is ``a1 v`` either way.
    The construction is C¹ (the one-sided validity has a continuous slope at its centre).

    Args:
        n: odd number of local models (>= 1).
        a: slopes `(m+1,)` (centre first), b: offsets `(m,)`, c: centres `(m,)`,
            sigma: variances `(m+1,)`, with m = (n−1)/2. Defaults place the pair centres evenly
            over `(0, velocity_scale]`, variances so that neighbours overlap, offsets at
            `torque_scale`.
        extrapolation: ``"affine"`` (default: the outer pair holds beyond the outer centres) or
            ``"gaussian"`` (the paper's validity functions, unchanged).
    """

    kind = "polytopic"

    def __init__(
        self,
        n: int = 3,
        *,
        a: Sequence[float] | Tensor | None = None,
        b: Sequence[float] | Tensor | None = None,
        c: Sequence[float] | Tensor | None = None,
        sigma: Sequence[float] | Tensor | None = None,
        velocity_scale: float = 1.0,
        torque_scale: float = 0.1,
        log_positive: bool = True,
        extrapolation: str = "affine",
    ) -> None:
        super().__init__(log_positive=log_positive)
        if not isinstance(n, int) or isinstance(n, bool) or n < 1 or n % 2 == 0:
            raise TorchfricError(
                f"PolytopicFriction needs an odd number of local models n >= 1 (1, 3, 5, ...), "
                f"got {n!r}"
            )
        if extrapolation not in _EXTRAPOLATIONS:
            raise TorchfricError(
                f"PolytopicFriction extrapolation must be one of "
                f"{', '.join(map(repr, _EXTRAPOLATIONS))}, got {extrapolation!r}"
            )
        self.extrapolation = extrapolation
        self.n = n
        m = (n - 1) // 2
        self.m = m
        spacing = velocity_scale / max(m, 1)
        if c is None:
            c = torch.arange(1, m + 1, dtype=torch.float64) * spacing
        if a is None:
            a = torch.full((m + 1,), 0.1 * torque_scale / velocity_scale, dtype=torch.float64)
        if b is None:
            b = torch.full((m,), torque_scale, dtype=torch.float64)
        if sigma is None:
            sigma = torch.full((m + 1,), (0.5 * spacing) ** 2, dtype=torch.float64)
        idx = range(2, m + 2)
        self._add(
            "a", _as_vector(a, m + 1, "a"), positive=False, labels=["a1", *[f"a{i}" for i in idx]]
        )
        self._add("b", _as_vector(b, m, "b"), positive=False, labels=[f"b{i}" for i in idx])
        self._add("c", _as_vector(c, m, "c"), positive=False, labels=[f"c{i}" for i in idx])
        self._add(
            "sigma",
            _as_vector(sigma, m + 1, "sigma"),
            positive=True,
            labels=["sigma1", *[f"sigma{i}" for i in idx]],
        )

    @property
    def size(self) -> int:
        return self.n

    def init_kwargs(self) -> dict[str, Any]:
        return {**super().init_kwargs(), "extrapolation": self.extrapolation}

    def evaluate(self, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        a, b, c, s = p["a"], p["b"], p["c"], p["sigma"]
        zero = torch.zeros_like(a[..., :1])
        # Full local-model tables (..., n): centre model first, then the +c and mirrored −c halves.
        centres = torch.cat([zero, c, -c], dim=-1)
        slopes = torch.cat([a, a[..., 1:]], dim=-1)
        offsets = torch.cat([zero, b, -b], dim=-1)
        variances = torch.cat([s, s[..., 1:]], dim=-1)
        d = v.unsqueeze(-1) - centres
        # w_i = ρ_i / Σ ρ_j with log ρ_i = −½ (v − c_i)² / σ_i, shifted by the largest log ρ
        # (a softmax, stable far from all centres). Written per local model rather than as
        # torch.softmax: over a last axis of 3–9 entries that kernel costs 5x these elementwise
        # operations (the pre-fit's batched Jacobian spent 60 % of its time there), and the sum
        # adds each mirrored pair first, so that w(−v) is w(v) mirrored to the last bit.
        m = self.m
        logs = list((-0.5 * d * d / variances).unbind(-1))
        if self.extrapolation == "affine" and m > 0:
            # The outer pair's validity is flat beyond its centre (log ρ = 0 there), so that
            # pair takes over far out. The −c_m side is the +c_m side mirrored bit for bit:
            # at −v its distance is −(v − c_m) exactly, and clamp_min(−x, 0) = −clamp_max(x, 0).
            outer, mirror = d[..., m].clamp_max(0.0), d[..., 2 * m].clamp_min(0.0)
            logs[m] = -0.5 * outer * outer / s[..., m]
            logs[2 * m] = -0.5 * mirror * mirror / s[..., m]
        top = functools.reduce(torch.maximum, logs)
        rho = [torch.exp(z - top) for z in logs]
        total = rho[0]
        for i in range(1, m + 1):
            total = total + (rho[i] + rho[m + i])
        terms = torch.stack(rho, dim=-1) / total.unsqueeze(-1) * (slopes * d + offsets)
        # Add each mirrored pair first: C(−v) = −C(v) and C(0) = 0 exactly in floating point.
        return terms[..., 0] + (terms[..., 1 : m + 1] + terms[..., m + 1 :]).sum(-1)


class CoulombFriction(Friction):
    """Smooth Coulomb friction ``C(v) = Fc tanh(v/ε)``; with the arm's ``b`` the classic baseline.

    `eps` [velocity units] sets the width of the smooth sign and is fixed (not estimated).
    """

    kind = "coulomb"

    def __init__(
        self, n: int = 1, *, fc: float = 0.1, eps: float = 1e-2, log_positive: bool = True
    ) -> None:
        super().__init__(log_positive=log_positive)
        if eps <= 0:
            raise TorchfricError(f"CoulombFriction eps must be positive, got {eps!r}")
        self.eps = float(eps)
        self._add("Fc", _as_vector(fc, 1, "Fc"), positive=True, labels=["Fc"])

    def evaluate(self, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        return p["Fc"][..., 0] * torch.tanh(v / self.eps)

    def init_kwargs(self) -> dict[str, Any]:
        return {**super().init_kwargs(), "eps": self.eps}


class StribeckFriction(Friction):
    """Stribeck curve with smooth sign, ``C(v) = (Fc + (Fs − Fc) exp(−(v/vs)²)) tanh(v/ε)``.

    Odd because the bracket is even in v and tanh is odd. Fc, Fs, vs are positive.
    """

    kind = "stribeck"

    def __init__(
        self,
        n: int = 1,
        *,
        fc: float = 0.1,
        fs: float = 0.15,
        vs: float = 0.5,
        eps: float = 1e-2,
        log_positive: bool = True,
    ) -> None:
        super().__init__(log_positive=log_positive)
        if eps <= 0:
            raise TorchfricError(f"StribeckFriction eps must be positive, got {eps!r}")
        self.eps = float(eps)
        self._add("Fc", _as_vector(fc, 1, "Fc"), positive=True, labels=["Fc"])
        self._add("Fs", _as_vector(fs, 1, "Fs"), positive=True, labels=["Fs"])
        self._add("vs", _as_vector(vs, 1, "vs"), positive=True, labels=["vs"])

    def evaluate(self, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        fc, fs, vs = p["Fc"][..., 0], p["Fs"][..., 0], p["vs"][..., 0]
        level = fc + (fs - fc) * torch.exp(-((v / vs) ** 2))
        return level * torch.tanh(v / self.eps)

    def init_kwargs(self) -> dict[str, Any]:
        return {**super().init_kwargs(), "eps": self.eps}


FRICTIONS: dict[str, type[Friction]] = {
    cls.kind: cls for cls in (OddTanhFriction, PolytopicFriction, CoulombFriction, StribeckFriction)
}


def make_friction(kind: str, size: int = 3, **kwargs: Any) -> Friction:
    """Build a friction model by registry name (`"tanh"`, `"polytopic"`, `"coulomb"`, `"stribeck"`)."""
    try:
        cls = FRICTIONS[kind]
    except KeyError:
        raise TorchfricError(
            f"unknown friction model {kind!r}; choose one of {sorted(FRICTIONS)}"
        ) from None
    return cls(size, **kwargs)
