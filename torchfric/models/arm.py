"""The grey-box arm: ``M q̈ = c_m u − b q̇ − C(q̇; θ) − d(q)``, state ``x = [q, q̇]``.

Optional white-box terms: a constant offset, gravity ``g_c sin q`` and an even viscous term
``a |q̇|`` (``asymmetric``): with it, ``b q̇ + a |q̇|`` is a viscous friction with different slopes
``b + a`` (q̇ > 0) and ``b − a`` (q̇ < 0), Janot's Fv± form; the odd C and the offset then hold
the Coulomb levels Fc± (``Fc± sign q̇ = F̄c sign q̇ + ΔFc`` while moving).

`ArmModel` owns the white-box parameters (inertia M, viscous b, optional offset and gravity
terms, optionally c_m) and a black-box `Friction` module. All its estimable parameters form one
flat vector θ in *estimation coordinates* (log for positive parameters when `log_positive`);
`vector_field(x, u, theta)` is a pure function of that vector, which is what the EKF augments
and what `torch.func` differentiates. The same field serves simulation and output-error training
(with `theta=None` it uses the module's own, differentiable parameters).

Why this size: the one vector field and the θ layout it reads (split, physical values, specs)
must change together; LuGre's state and the stored friction are apart (`lugre`, `stored`).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from ..errors import TorchfricError
from .friction import Friction
from .lugre import DYNAMICS, LUGRE_NAMES, lugre_field, lugre_substep, sliding_curve
from .stored import stored_friction

__all__ = ["ArmModel", "arm_field", "arm_friction", "external_torque"]


# The arm's physics, written once. `ArmModel.dynamics` (simulation, EKF, output error, pre-fit)
# and `ArmModel.friction_torque` call these, and so does the TorchScript export
# (`torchfric.export`), which compiles them with the module: a term added here (in `arm_field`,
# `arm_friction` and, for dynamic models, `external_torque`) reaches every consumer. They are TorchScript-compatible plain functions (not scripted: autograd, torch.func
# and the native tracer see ordinary torch operations). Disabled terms are ``None`` (not zero),
# so that a model without a term computes exactly what it always did.


def arm_field(
    x: Tensor,
    u: Tensor,
    black_box: Tensor,
    c_m: Tensor,
    inertia: Tensor,
    viscous: Tensor | None = None,
    offset: Tensor | None = None,
    gravity: Tensor | None = None,
    asymmetric: Tensor | None = None,
) -> Tensor:
    """The vector field ``ẋ = [q̇, (c_m u − C(q̇) − b q̇ − offset − g_c sin q − a |q̇|) / M]``.

    Args:
        x: states `(..., 2)` ``[q, q̇]``.
        u: input, broadcast against ``x[..., 0]``.
        black_box: ``C(q̇)`` at ``x[..., 1]`` (the friction module's odd curve).
        c_m, inertia: motor constant and M (physical values).
        viscous, offset, gravity, asymmetric: b, the constant offset, ``g_c`` and ``a`` of the
            enabled white-box terms; ``None`` for a term the model does not have.

    Returns:
        ``ẋ`` `(..., 2)`.
    """
    q = x[..., 0]
    v = x[..., 1]
    torque = c_m * u - black_box
    if viscous is not None:
        torque = torque - viscous * v
    if offset is not None:
        torque = torque - offset
    if gravity is not None:
        torque = torque - gravity * torch.sin(q)
    if asymmetric is not None:
        torque = torque - asymmetric * v.abs()
    return torch.stack([v, torque / inertia], dim=-1)


def external_torque(
    x: Tensor,
    u: Tensor,
    c_m: Tensor,
    offset: Tensor | None = None,
    gravity: Tensor | None = None,
    asymmetric: Tensor | None = None,
) -> Tensor:
    """The torque of a dynamic model besides its bristles and b q̇: ``c_m u − offset − g_c sin q
    − a |q̇|``, the white-box terms of `arm_field` (a term added there goes here too; kept apart,
    not shared, so that a static model's sums keep their order to the last bit)."""
    torque = c_m * u
    if offset is not None:
        torque = torque - offset
    if gravity is not None:
        torque = torque - gravity * torch.sin(x[..., 0])
    if asymmetric is not None:
        torque = torque - asymmetric * x[..., 1].abs()
    return torque


def arm_friction(
    v: Tensor,
    black_box: Tensor,
    viscous: Tensor | None = None,
    offset: Tensor | None = None,
    asymmetric: Tensor | None = None,
) -> Tensor:
    """Total velocity-dependent friction ``C(v) + b v + offset + a |v|`` (terms as in `arm_field`;
    `black_box` is ``C(v)``)."""
    out = black_box
    if viscous is not None:
        out = out + viscous * v
    if offset is not None:
        out = out + offset
    if asymmetric is not None:
        out = out + asymmetric * v.abs()
    return out


class ArmModel(nn.Module):
    """Rotating arm (or linear axis) with friction.

    ``d/dt [q, q̇] = [q̇, (c_m u − b q̇ − C(q̇) − offset − g_c sin q) / M]``

    Args:
        friction: the black-box friction `C(v)`.
        inertia: M > 0 (kg m² for an arm, kg for a linear axis).
        viscous: b >= 0, or ``None`` to leave the viscous term out (the polytopic model carries its
            own slopes, paper §3.2); ``None`` removes b from θ.
        c_m: motor constant (input → torque); known unless `estimate_c_m`.
        offset: constant torque/force offset (EMPS has −3.2 N); ``None`` = off (not in θ).
        gravity: ``g_c = m g l`` of an unbalanced arm, torque ``g_c sin q``; ``None`` = off.
        asymmetric: ``a`` of the even viscous term ``a |q̇|`` (any sign: half the difference of
            the two directions' viscous slopes); ``None`` = off (not in θ).
        estimate_c_m: put c_m in θ (log space when `log_positive`).
        log_positive: store M, b, g_c, c_m as logarithms in θ so estimators cannot make them negative.
        dynamic: "none" (static friction, state [q, q̇]) or "lugre": a bristle state z
            (`torchfric.models.lugre`), state [q, q̇, z], whose sliding curve is the friction
            module's; σ0 [N m/rad], σ1 [N m s/rad] and the stick velocity v_s [rad/s]
            (`sigma0`, `sigma1`, `stick_velocity`, > 0) join θ as ``lugre_sigma0``,
            ``lugre_sigma1``, ``lugre_vstick`` (a polytopic curve has a ``sigma1`` of its own).

    θ order: friction parameters (the friction's own order), then b, M, offset, gravity,
    asymmetric, c_m, σ0, σ1, v_s (each only when enabled) —
    the paper's ``θ = [W1ᵀ W2 b M]ᵀ`` for the tanh model.
    """

    def __init__(
        self,
        friction: Friction,
        inertia: float = 0.03,
        viscous: float | None = 0.01,
        c_m: float = 1.0,
        *,
        offset: float | None = None,
        gravity: float | None = None,
        estimate_c_m: bool = False,
        log_positive: bool = True,
        asymmetric: float | None = None,
        dynamic: str = "none",
        sigma0: float = 1e3,
        sigma1: float = 1.0,
        stick_velocity: float = 0.05,
    ) -> None:
        super().__init__()
        if dynamic not in DYNAMICS:
            raise TorchfricError(f"dynamic = {dynamic!r} is not known; choose one of {DYNAMICS}")
        self.dynamic = dynamic
        if not isinstance(friction, Friction):
            raise TorchfricError(
                f"friction must be a torchfric Friction module, got {type(friction).__name__}"
            )
        self.friction = friction
        self.log_positive = bool(log_positive)
        self.estimate_c_m = bool(estimate_c_m)
        # Arm parameters: (name, positive) in θ order after the friction block.
        self._arm_spec: list[tuple[str, bool]] = []
        if viscous is not None:
            self._add("viscous", viscous, positive=True, allow_zero=not self.log_positive)
        self._add("inertia", inertia, positive=True)
        if offset is not None:
            self._add("offset", offset, positive=False)
        if gravity is not None:
            self._add("gravity", gravity, positive=True)
        if asymmetric is not None:
            self._add("asymmetric", asymmetric, positive=False)
        if estimate_c_m:
            self._add("c_m", c_m, positive=True)
        else:
            self._check_value("c_m", c_m, positive=True)
            self.register_buffer("c_m_fixed", torch.tensor(float(c_m), dtype=torch.float64))
        if dynamic == "lugre":
            self._add("lugre_sigma0", sigma0, positive=True)
            self._add("lugre_sigma1", sigma1, positive=True)
            self._add("lugre_vstick", stick_velocity, positive=True)
        self._k_friction = friction.num_parameters

    # -- construction helpers ----------------------------------------------------------------
    @staticmethod
    def _check_value(name: str, value: Any, *, positive: bool, allow_zero: bool = False) -> float:
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise TorchfricError(f"{name} must be a number, got {value!r}") from None
        if not torch.isfinite(torch.tensor(v)):
            raise TorchfricError(f"{name} must be finite, got {value!r}")
        if positive and (v < 0 or (v == 0 and not allow_zero)):
            raise TorchfricError(
                f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {value!r}"
                + (
                    "; with log_positive a zero value cannot be represented: give a small positive"
                    " guess or set viscous to None"
                    if name == "viscous" and v == 0
                    else ""
                )
            )
        return v

    def _add(self, name: str, value: Any, *, positive: bool, allow_zero: bool = False) -> None:
        v = self._check_value(name, value, positive=positive, allow_zero=allow_zero)
        t = torch.tensor(v, dtype=torch.float64)
        raw = t.log() if (positive and self.log_positive) else t
        self.register_parameter(f"raw_{name}", nn.Parameter(raw.reshape(1)))
        self._arm_spec.append((name, positive))

    # -- the flat parameter vector -------------------------------------------------------------
    @property
    def theta_names(self) -> list[str]:
        """Names of θ's entries, physical meaning (e.g. ``W1[1]``, ``viscous``, ``inertia``)."""
        return self.friction.element_names + [name for name, _ in self._arm_spec]

    @property
    def num_parameters(self) -> int:
        return self._k_friction + len(self._arm_spec)

    def log_mask(self) -> Tensor:
        """`(k,)` bool: entries of θ stored as logarithms."""
        arm = [positive and self.log_positive for _, positive in self._arm_spec]
        return torch.cat([self.friction.positive_mask(), torch.tensor(arm, dtype=torch.bool)])

    def theta_vector(self) -> Tensor:
        """`(k,)` θ in estimation coordinates, differentiable w.r.t. the module's parameters."""
        return torch.cat(
            [self.friction.raw_vector()] + [getattr(self, f"raw_{n}") for n, _ in self._arm_spec]
        )

    def get_theta(self) -> Tensor:
        """`(k,)` a detached copy of θ in estimation coordinates."""
        return self.theta_vector().detach().clone()

    @torch.no_grad()
    def set_theta(self, theta: Tensor) -> ArmModel:
        """Write θ `(k,)` (estimation coordinates) back into the module; returns self."""
        theta = torch.as_tensor(theta, dtype=torch.float64).reshape(-1)
        if theta.numel() != self.num_parameters:
            raise TorchfricError(
                f"theta has {theta.numel()} entries but this model has {self.num_parameters} "
                f"({', '.join(self.theta_names)})"
            )
        i = 0
        for name, size, _ in self.friction._spec:
            p = getattr(self.friction, name)
            p.copy_(theta[i : i + size].reshape(p.shape))
            i += size
        for name, _ in self._arm_spec:
            getattr(self, f"raw_{name}").copy_(theta[i : i + 1])
            i += 1
        return self

    def _per_entry(self, theta: Tensor, friction: Any, arm: Any) -> Tensor:
        """θ `(..., k)` mapped entry by entry: the friction block by `friction`, the arm block
        by ``arm(values, log_mask)``."""
        kf = self._k_friction
        return torch.cat(
            [friction(theta[..., :kf]), arm(theta[..., kf:], self.log_mask()[kf:])], -1
        )

    def to_physical(self, theta: Tensor) -> Tensor:
        """`(..., k)` θ in physical units (exp of the log-stored entries; a bounded tanh slope
        through its softplus, `OddTanhFriction.min_slope`)."""
        return self._per_entry(theta, self.friction.flat_to_physical,
                               lambda a, m: torch.where(m, a.exp(), a))  # fmt: skip

    def from_physical(self, values: Tensor) -> Tensor:
        """Inverse of `to_physical`."""
        return self._per_entry(values, self.friction.flat_from_physical,
                               lambda a, m: torch.where(m, a.clamp_min(1e-300).log(), a))  # fmt: skip

    def physical_slope(self, theta: Tensor) -> Tensor:
        """`(..., k)` d(physical value)/dθ entry by entry (the delta method's scale)."""
        return self._per_entry(theta, self.friction.flat_slope,
                               lambda a, m: torch.where(m, a.exp(), torch.ones_like(a)))  # fmt: skip

    def split(self, theta: Tensor) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """θ `(..., k)` → (friction parameters, arm parameters) as physical-valued dicts; a leading
        batch of parameter sets broadcasts against a batch of states in `dynamics`."""
        kf = self._k_friction
        fric = self.friction.split(theta[..., :kf])
        arm: dict[str, Tensor] = {}
        for j, (name, positive) in enumerate(self._arm_spec):
            r = theta[..., kf + j]
            arm[name] = r.exp() if (positive and self.log_positive) else r
        if not self.estimate_c_m:
            arm["c_m"] = self.c_m_fixed
        return fric, arm

    # -- dynamics ------------------------------------------------------------------------------
    @property
    def state_size(self) -> int:
        """Entries of the state: 2 ([q, q̇]), or 3 ([q, q̇, z]) for a dynamic friction model."""
        return 3 if self.dynamic == "lugre" else 2

    def vector_field(self, x: Tensor, u: Tensor, theta: Tensor | None = None) -> Tensor:
        """``f(x, u; θ)``: `x (..., 2)`, `u (...)` (broadcast), θ `(k,)` → `ẋ (..., 2)`.

        ``q̈ = (c_m u − b q̇ − C(q̇) − offset − g_c sin q) / M``.
        """
        if theta is None:
            theta = self.theta_vector()
        return self.dynamics(x, u, *self.split(theta))

    def dynamics(
        self, x: Tensor, u: Tensor, fric: dict[str, Tensor], arm: dict[str, Tensor]
    ) -> Tensor:
        """`vector_field` with θ already split into physical dicts (`split`): hoist the split out
        of inner loops, where θ is constant. A dynamic model's field (`lugre_field`) is stiff:
        simulation and the EKF step it with `substep`."""
        if self.dynamic == "lugre":
            return lugre_field(self.friction, x, _external(x, u, arm), fric, arm)
        return arm_field(
            x,
            u,
            self.friction.evaluate(x[..., 1], fric),
            arm["c_m"],
            arm["inertia"],
            arm.get("viscous"),
            arm.get("offset"),
            arm.get("gravity"),
            arm.get("asymmetric"),
        )

    def substep(
        self,
        x: Tensor,
        u: Tensor,
        h: Tensor | float,
        fric: dict[str, Tensor],
        arm: dict[str, Tensor],
    ) -> Tensor:
        """One step of a dynamic model's stiff-stable integrator (`lugre_substep`), `x (..., 3)`."""
        return lugre_substep(self.friction, x, _external(x, u, arm), h, fric, arm)

    def black_box(self, v: Tensor, fric: dict[str, Tensor], arm: dict[str, Tensor]) -> Tensor:
        """The velocity-dependent part of the (steady-state) friction besides the white-box
        terms: the module's ``C(v)``, or for a dynamic model its sliding curve ``sign(v) g(v)``
        (`torchfric.models.lugre`); `fric`, `arm` from `split`."""
        if self.dynamic == "lugre":
            return sliding_curve(self.friction, v, fric, arm["lugre_vstick"])
        return self.friction.evaluate(v, fric)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return self.vector_field(x, u)

    def friction_torque(self, v: Tensor, theta: Tensor | None = None) -> Tensor:
        """Total velocity-dependent friction ``b v + C(v) + offset [+ a |v|]`` at velocities `v`,
        for the module's own θ or a given θ `(k,)` (estimation coordinates). For a dynamic model,
        its steady-state curve (C replaced by `black_box`'s sliding curve)."""
        return self.total_friction(v, *self.split(self.theta_vector() if theta is None else theta))

    def total_friction(self, v: Tensor, fric: dict[str, Tensor], arm: dict[str, Tensor]) -> Tensor:
        """`friction_torque` with θ already split into physical dicts (`split`)."""
        return arm_friction(
            v, self.black_box(v, fric, arm), arm.get("viscous"), arm.get("offset"),
            arm.get("asymmetric"),
        )  # fmt: skip

    def max_slope(self, v_max: float, n: int = 401) -> float:
        """Largest ``|∂q̈/∂q̇|`` over ``|v| <= v_max`` [1/s]: the stiffness that limits explicit steps."""
        v = torch.linspace(-v_max, v_max, n, dtype=torch.float64).requires_grad_(True)
        with torch.enable_grad():
            total = self.friction_torque(v).sum()
            (g,) = torch.autograd.grad(total, v)
        return float(g.abs().max() / self.inertia)

    # -- physical values -------------------------------------------------------------------------
    def _arm_value(self, name: str) -> Tensor:
        _, arm = self.split(self.theta_vector())
        return arm[name].reshape(()) if name in arm else torch.zeros((), dtype=torch.float64)

    @property
    def inertia(self) -> Tensor:
        return self._arm_value("inertia")

    @property
    def viscous(self) -> Tensor:
        return self._arm_value("viscous")

    @property
    def offset(self) -> Tensor:
        return self._arm_value("offset")

    @property
    def gravity(self) -> Tensor:
        return self._arm_value("gravity")

    @property
    def c_m(self) -> Tensor:
        return self._arm_value("c_m")

    def physical_parameters(self) -> dict[str, float]:
        """Every estimable parameter by name, in physical units, as plain floats."""
        values = self.to_physical(self.get_theta())
        return {name: float(v) for name, v in zip(self.theta_names, values, strict=True)}

    def static_twin(self) -> ArmModel:
        """A static copy (no bristles) with the same friction and white-box values: its θ is
        this θ without σ0 and σ1 (they come last)."""
        spec = self.spec()
        spec.pop("dynamic", None)
        spec["arm"] = {k: v for k, v in spec["arm"].items() if k not in LUGRE_NAMES}
        return ArmModel.from_spec(spec).set_theta(self.get_theta()[: self._static_size])

    def with_static(self, static: ArmModel) -> ArmModel:
        """A copy of this dynamic model with the θ of `static` (a `static_twin`-shaped model)
        and this model's σ0, σ1."""
        theta = torch.cat([static.get_theta(), self.get_theta()[self._static_size :]])
        return ArmModel.from_spec(self.spec()).set_theta(theta)

    @property
    def _static_size(self) -> int:
        return self.num_parameters - (len(LUGRE_NAMES) if self.dynamic == "lugre" else 0)

    # -- (de)serialisation -----------------------------------------------------------------------
    def spec(self) -> dict[str, Any]:
        """Plain-type description that `from_spec` rebuilds the model from (values included)."""
        fric = {k: v.detach().clone() for k, v in self.friction.physical_parameters().items()}
        return {
            "friction": {
                "kind": self.friction.kind,
                "size": self.friction.size or 1,
                "kwargs": self.friction.init_kwargs(),
                "values": {k: v.tolist() for k, v in fric.items()},
            },
            "arm": {name: float(self._arm_value(name).detach()) for name, _ in self._arm_spec},
            "viscous_enabled": "viscous" in dict(self._arm_spec),
            "c_m": float(self.c_m.detach()),
            "estimate_c_m": self.estimate_c_m,
            "log_positive": self.log_positive,
            # only for a dynamic model: a static model's spec (and structure key) is as before
            **({"dynamic": self.dynamic} if self.dynamic != "none" else {}),
        }

    @classmethod
    def from_spec(cls, spec: dict[str, Any]) -> ArmModel:
        friction = stored_friction(spec["friction"], spec["log_positive"])
        arm = {
            k: (
                max(v, _TINY)
                if k in ("inertia", "viscous", "gravity", "c_m", *LUGRE_NAMES)
                and spec["log_positive"]
                else v
            )
            for k, v in spec["arm"].items()
        }
        return cls(
            friction,
            inertia=arm["inertia"],
            viscous=arm.get("viscous") if spec["viscous_enabled"] else None,
            c_m=spec["c_m"],
            offset=arm.get("offset"),
            gravity=arm.get("gravity"),
            estimate_c_m=spec["estimate_c_m"],
            log_positive=spec["log_positive"],
            asymmetric=arm.get("asymmetric"),
            **(
                {
                    "dynamic": "lugre",
                    "sigma0": arm["lugre_sigma0"],
                    "sigma1": arm["lugre_sigma1"],
                    "stick_velocity": arm["lugre_vstick"],
                }
                if spec.get("dynamic", "none") == "lugre"
                else {}
            ),
        )


def _external(x: Tensor, u: Tensor, arm: dict[str, Tensor]) -> Tensor:
    """`external_torque` with the terms of a split θ (`ArmModel.split`)."""
    return external_torque(
        x, u, arm["c_m"], arm.get("offset"), arm.get("gravity"), arm.get("asymmetric")
    )


_TINY = 5e-324  # smallest positive double
