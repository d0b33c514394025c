"""Tests of torchfric.models.arm.ArmModel: the paper's parameter vectors, θ bookkeeping (log storage,
physical values, round trips), the vector field against its closed form, spec round trips, bad
input by message, and autograd Jacobians of f against analytic Jacobians derived by hand for the
tanh and the polytopic model."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.func import jacrev

from torchfric.errors import TorchfricError
from torchfric.models.arm import ArmModel
from torchfric.models.friction import (
    CoulombFriction,
    OddTanhFriction,
    PolytopicFriction,
    StribeckFriction,
)


def _tanh_arm(**kwargs) -> ArmModel:
    friction = OddTanhFriction(3, w1=[0.8, 4.0, 25.0], w2=[0.05, -0.02, 0.03])
    return ArmModel(friction, inertia=0.05, viscous=0.02, c_m=1.6, **kwargs)


def _poly_arm(n: int = 3, **kwargs) -> ArmModel:
    m = (n - 1) // 2
    friction = PolytopicFriction(
        n,
        a=[0.05 * (j + 1) * (-1) ** j for j in range(m + 1)],
        b=[0.1 + 0.05 * j for j in range(m)],
        c=[0.4 * (j + 1) for j in range(m)],
        sigma=[0.3 + 0.1 * j for j in range(m + 1)],
    )
    return ArmModel(friction, inertia=0.04, viscous=None, c_m=2.0, **kwargs)


# -- the paper's parameter vectors ----------------------------------------------------------------
def test_tanh_arm_has_the_papers_eight_parameters() -> None:
    arm = ArmModel(OddTanhFriction(3), inertia=0.05, viscous=0.01)
    # Paper §3.1: θ = [W1ᵀ W2 b M]ᵀ.
    assert arm.theta_names == [
        "W1[1]",
        "W1[2]",
        "W1[3]",
        "W2[1]",
        "W2[2]",
        "W2[3]",
        "viscous",
        "inertia",
    ]
    assert arm.num_parameters == 8
    assert arm.get_theta().shape == (8,)


def test_polytopic_arm_has_the_papers_seven_parameters() -> None:
    arm = ArmModel(PolytopicFriction(3), inertia=0.05, viscous=None)
    # Paper §3.2: θ = [a1 a2 b2 c2 σ1 σ2 M]ᵀ (no separate viscous b).
    assert arm.theta_names == ["a1", "a2", "b2", "c2", "sigma1", "sigma2", "inertia"]
    assert arm.num_parameters == 7


def test_optional_terms_extend_theta_in_documented_order() -> None:
    arm = ArmModel(
        CoulombFriction(),
        inertia=0.05,
        viscous=0.01,
        offset=-3.2,
        gravity=0.4,
        c_m=16.0,
        estimate_c_m=True,
    )
    assert arm.theta_names == ["Fc", "viscous", "inertia", "offset", "gravity", "c_m"]
    assert arm.log_mask().tolist() == [True, True, True, False, True, True]
    phys = arm.physical_parameters()
    assert phys == pytest.approx(
        {"Fc": 0.1, "viscous": 0.01, "inertia": 0.05, "offset": -3.2, "gravity": 0.4, "c_m": 16.0}
    )


# -- θ bookkeeping --------------------------------------------------------------------------------
def test_log_space_storage_of_inertia_and_viscous() -> None:
    arm = ArmModel(OddTanhFriction(3), inertia=0.05, viscous=0.01)
    theta = arm.get_theta()
    torch.testing.assert_close(theta[-2:], torch.tensor([math.log(0.01), math.log(0.05)]))
    torch.testing.assert_close(arm.inertia, torch.tensor(0.05))
    torch.testing.assert_close(arm.viscous, torch.tensor(0.01))
    assert arm.inertia.shape == ()

    raw = ArmModel(OddTanhFriction(3), inertia=0.05, viscous=0.01, log_positive=False)
    torch.testing.assert_close(raw.get_theta()[-2:], torch.tensor([0.01, 0.05]))
    assert not bool(raw.log_mask().any())


def test_zero_viscous_allowed_only_without_log_storage() -> None:
    arm = ArmModel(OddTanhFriction(3), viscous=0.0, log_positive=False)
    assert float(arm.viscous.detach()) == 0.0
    with pytest.raises(TorchfricError, match=r"viscous must be > 0, got 0.*set viscous to None"):
        ArmModel(OddTanhFriction(3), viscous=0.0)


def test_get_set_theta_round_trip() -> None:
    arm = _tanh_arm(offset=0.1, gravity=0.3)
    theta = torch.randn(arm.num_parameters)
    assert arm.set_theta(theta) is arm
    torch.testing.assert_close(arm.get_theta(), theta, rtol=0.0, atol=0.0)
    # get_theta is a detached copy: changing it does not touch the module.
    got = arm.get_theta()
    got += 1.0
    torch.testing.assert_close(arm.get_theta(), theta, rtol=0.0, atol=0.0)
    torch.testing.assert_close(arm.inertia, theta[-3].exp())
    torch.testing.assert_close(arm.offset, theta[-2])
    torch.testing.assert_close(arm.friction.W1.detach(), theta[:3])


def test_to_and_from_physical_are_inverse() -> None:
    arm = _poly_arm(5, offset=-0.2, gravity=0.5)
    theta = torch.randn(3, arm.num_parameters)  # batch of θ
    phys = arm.to_physical(theta)
    mask = arm.log_mask()
    torch.testing.assert_close(phys[:, mask], theta[:, mask].exp())
    torch.testing.assert_close(phys[:, ~mask], theta[:, ~mask])
    torch.testing.assert_close(arm.from_physical(phys), theta)
    names = arm.theta_names
    values = arm.physical_parameters()
    assert list(values) == names
    torch.testing.assert_close(
        torch.tensor([values[n] for n in names]), arm.to_physical(arm.get_theta())
    )


def test_set_theta_wrong_length_errors_with_names() -> None:
    arm = _tanh_arm()
    with pytest.raises(TorchfricError, match=r"theta has 7 entries but this model has 8 \(W1\[1\]"):
        arm.set_theta(torch.zeros(7))
    with pytest.raises(TorchfricError, match=r"theta has 9 entries"):
        arm.set_theta(torch.zeros(9))


# -- the vector field -----------------------------------------------------------------------------
def _closed_form(arm: ArmModel, x: np.ndarray, u: np.ndarray, friction_np) -> np.ndarray:
    p = arm.physical_parameters()
    q, v = x[..., 0], x[..., 1]
    c_m = p.get("c_m", float(arm.c_m.detach()))
    torque = (
        c_m * u
        - p.get("viscous", 0.0) * v
        - friction_np(v)
        - p.get("offset", 0.0)
        - p.get("gravity", 0.0) * np.sin(q)
    )
    return np.stack([v, torque / p["inertia"]], axis=-1)


def _np_tanh(arm: ArmModel):
    w1 = arm.friction.W1.detach().numpy()
    w2 = arm.friction.W2.detach().numpy()
    return lambda v: (np.tanh(v[..., None] * w1) * w2).sum(-1)


def test_vector_field_matches_closed_form_with_offset_and_gravity() -> None:
    arm = _tanh_arm(offset=-0.3, gravity=0.7)
    x = torch.randn(4, 3, 2) * torch.tensor([2.0, 1.5])
    u = torch.randn(4, 3)
    out = arm.vector_field(x, u)
    assert out.shape == (4, 3, 2)
    expected = _closed_form(arm, x.numpy(), u.numpy(), _np_tanh(arm))
    torch.testing.assert_close(out.detach(), torch.tensor(expected))
    # forward() is the same field.
    torch.testing.assert_close(arm(x, u), out)


def test_vector_field_with_explicit_theta_and_estimated_c_m() -> None:
    arm = _tanh_arm(offset=0.2, estimate_c_m=True)
    theta = arm.get_theta() + 0.1 * torch.randn(arm.num_parameters)
    x, u = torch.randn(5, 2), torch.randn(5)
    out = arm.vector_field(x, u, theta)
    arm.set_theta(theta)
    expected = _closed_form(arm, x.numpy(), u.numpy(), _np_tanh(arm))
    torch.testing.assert_close(out, torch.tensor(expected))


def test_vector_field_broadcasts_scalar_input() -> None:
    arm = _tanh_arm()
    x = torch.randn(6, 2)
    out = arm.vector_field(x, torch.tensor(0.5))
    torch.testing.assert_close(out, arm.vector_field(x, torch.full((6,), 0.5)))


def test_friction_torque_and_friction() -> None:
    arm = _tanh_arm(offset=-0.25, gravity=0.5)
    v = torch.linspace(-3.0, 3.0, 13).reshape(13, 1).expand(13, 2)
    c = _np_tanh(arm)(v.numpy())
    torch.testing.assert_close(arm.friction(v).detach(), torch.tensor(c))
    expected = 0.02 * v + torch.tensor(c) - 0.25  # b v + C(v) + offset; gravity is not friction
    torch.testing.assert_close(arm.friction_torque(v).detach(), expected)
    assert arm.friction_torque(v).shape == v.shape
    # Without viscous and offset, the total friction is the black box alone.
    poly = _poly_arm()
    torch.testing.assert_close(poly.friction_torque(v), poly.friction(v))


# -- bad input ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"inertia": -0.1}, r"inertia must be > 0, got -0.1"),
        ({"inertia": 0.0}, r"inertia must be > 0, got 0.0"),
        ({"inertia": float("nan")}, r"inertia must be finite, got nan"),
        ({"inertia": float("inf")}, r"inertia must be finite"),
        ({"inertia": "heavy"}, r"inertia must be a number, got 'heavy'"),
        ({"viscous": -0.01}, r"viscous must be > 0"),
        ({"c_m": 0.0}, r"c_m must be > 0"),
        ({"c_m": 0.0, "estimate_c_m": True}, r"c_m must be > 0"),
        ({"gravity": -1.0}, r"gravity must be > 0"),
        ({"offset": float("nan")}, r"offset must be finite"),
    ],
)
def test_invalid_arm_values(kwargs: dict, pattern: str) -> None:
    with pytest.raises(TorchfricError, match=pattern):
        ArmModel(OddTanhFriction(3), **kwargs)


@pytest.mark.parametrize("friction", [torch.nn.Linear(1, 1), lambda v: v, "tanh", None])
def test_friction_must_be_a_friction_module(friction) -> None:
    with pytest.raises(TorchfricError, match=r"friction must be a torchfric Friction module"):
        ArmModel(friction)


# -- spec round trip ------------------------------------------------------------------------------
SPEC_CASES = {
    "tanh": lambda: ArmModel(
        OddTanhFriction(3, w1=[0.3, 2.0, 9.0], w2=[0.1, -0.05, 0.02]),
        inertia=0.07,
        viscous=0.03,
        c_m=3.0,
    ),
    "tanh-offset-gravity-cm": lambda: ArmModel(
        OddTanhFriction(2, w1=[1.0, 5.0], w2=[0.2, 0.1]),
        inertia=0.07,
        viscous=0.03,
        c_m=3.0,
        offset=-0.4,
        gravity=0.6,
        estimate_c_m=True,
    ),
    "tanh-raw": lambda: ArmModel(OddTanhFriction(3), viscous=0.0, offset=0.1, log_positive=False),
    "polytopic": lambda: ArmModel(
        PolytopicFriction(5, a=[0.1, 0.2, 0.05], b=[0.3, 0.5], c=[0.4, 1.1], sigma=[0.2, 0.3, 0.4]),
        inertia=0.02,
        viscous=None,
        gravity=0.2,
    ),
    "polytopic-1": lambda: ArmModel(PolytopicFriction(1, a=[0.4], sigma=[2.0]), viscous=None),
    "polytopic-raw": lambda: ArmModel(
        PolytopicFriction(3, sigma=[0.3, 0.6], log_positive=False), viscous=0.01, offset=0.05
    ),
    "coulomb": lambda: ArmModel(
        CoulombFriction(fc=0.4, eps=0.05),
        inertia=0.1,
        viscous=0.02,
        offset=0.3,
        estimate_c_m=True,
        c_m=0.5,
    ),
    "stribeck": lambda: ArmModel(
        StribeckFriction(fc=0.1, fs=0.3, vs=0.2, eps=0.02, log_positive=False),
        inertia=0.1,
        viscous=0.02,
        gravity=1.5,
        c_m=2.5,
    ),
}


@pytest.mark.parametrize("case", sorted(SPEC_CASES))
def test_spec_round_trip_reproduces_vector_field(case: str) -> None:
    arm = SPEC_CASES[case]()
    # Move θ away from the constructor values so that the spec must carry the numbers.
    arm.set_theta(arm.get_theta() + 0.05 * torch.randn(arm.num_parameters))
    clone = ArmModel.from_spec(arm.spec())
    assert type(clone.friction) is type(arm.friction)
    assert clone.theta_names == arm.theta_names
    assert clone.log_mask().tolist() == arm.log_mask().tolist()
    assert clone.friction.init_kwargs() == arm.friction.init_kwargs()
    # exp/log round trips of log-stored entries cost a few ulps.
    torch.testing.assert_close(clone.get_theta(), arm.get_theta(), rtol=1e-13, atol=1e-15)
    x = torch.randn(20, 2) * torch.tensor([3.0, 2.0])
    u = torch.randn(20)
    torch.testing.assert_close(
        clone.vector_field(x, u), arm.vector_field(x, u), rtol=1e-12, atol=1e-13
    )
    torch.testing.assert_close(clone.c_m, arm.c_m)


# -- autograd Jacobian against analytic Jacobians -------------------------------------------------
def _autograd_jacobian(arm: ArmModel, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    z = torch.cat([x, arm.get_theta()])
    return jacrev(lambda zz: arm.vector_field(zz[:2], u, zz[2:]))(z)


def _assemble(arm: ArmModel, x: np.ndarray, u: float, dcdv: float, dc_dfric: np.ndarray, c: float):
    """Rows [∂q̇/∂z, ∂q̈/∂z] for z = [q, q̇, θ], given C, ∂C/∂v and ∂C/∂(friction θ)."""
    p = arm.physical_parameters()
    q, v = x
    big_m = p["inertia"]
    b, off, g = p.get("viscous", 0.0), p.get("offset", 0.0), p.get("gravity", 0.0)
    torque = float(arm.c_m.detach()) * u - b * v - c - off - g * math.sin(q)
    k = arm.num_parameters
    jac = np.zeros((2, 2 + k))
    jac[0, 1] = 1.0  # d q̇ / d q̇
    jac[1, 0] = -g * math.cos(q) / big_m
    jac[1, 1] = (-b - dcdv) / big_m
    kf = arm.friction.num_parameters
    jac[1, 2 : 2 + kf] = -dc_dfric / big_m
    for j, name in enumerate(arm.theta_names[kf:]):
        col = 2 + kf + j
        if name == "viscous":  # log b: ∂/∂(log b) = b ∂/∂b
            jac[1, col] = -v * b / big_m
        elif name == "inertia":  # q̈ = T e^{−r}: ∂q̈/∂r = −T/M
            jac[1, col] = -torque / big_m
        elif name == "offset":  # raw, signed
            jac[1, col] = -1.0 / big_m
        elif name == "gravity":  # log g_c
            jac[1, col] = -g * math.sin(q) / big_m
        else:  # pragma: no cover - not used here
            raise AssertionError(name)
    return jac


def _tanh_derivatives(arm: ArmModel, v: float) -> tuple[float, float, np.ndarray]:
    w1 = arm.friction.W1.detach().numpy()
    w2 = arm.friction.W2.detach().numpy()
    th = np.tanh(w1 * v)
    sech2 = 1.0 - th**2  # d/dz tanh z = 1 − tanh² z
    c = float(w2 @ th)
    dcdv = float(np.sum(w2 * w1 * sech2))
    dc_dw1 = w2 * v * sech2
    dc_dw2 = th
    return c, dcdv, np.concatenate([dc_dw1, dc_dw2])


def _polytopic_derivatives(arm: ArmModel, v: float) -> tuple[float, float, np.ndarray]:
    f = arm.friction
    m = f.m
    p = {k: t.detach().numpy() for k, t in f.physical_parameters().items()}
    a, b, c, s = p["a"], p["b"], p["c"], p["sigma"]
    # Full tables of the n local models: centre, then +c_k, then the mirrored −c_k.
    centres = np.concatenate([[0.0], c, -c])
    slopes = np.concatenate([a[:1], a[1:], a[1:]])
    offsets = np.concatenate([[0.0], b, -b])
    var = np.concatenate([s[:1], s[1:], s[1:]])
    d = v - centres
    # The distance inside log ρ_i: d itself, except for the outer pair of the affine
    # continuation, whose validity is flat beyond its centre (min(d, 0) and max(d, 0)).
    e = d.copy()
    if f.extrapolation == "affine" and m > 0:
        e[m], e[2 * m] = min(d[m], 0.0), max(d[2 * m], 0.0)
    ell = -0.5 * e**2 / var  # log ρ_i
    w = np.exp(ell - ell.max())
    w /= w.sum()
    g = slopes * d + offsets  # local affine models
    cv = float(w @ g)
    # ∂w_i/∂ℓ_j = w_i (δ_ij − w_j)  ⇒  ∂C/∂ℓ_i = w_i (g_i − C).
    dc_dell = w * (g - cv)
    dcdv = float(w @ slopes + dc_dell @ (-e / var))  # ∂ℓ_i/∂v = −e_i/σ_i
    d_slope = w * d
    d_offset = w
    d_centre = -w * slopes + dc_dell * e / var  # ∂d_i/∂c_i = −1
    d_var = dc_dell * 0.5 * e**2 / var**2
    pos, neg = slice(1, m + 1), slice(m + 1, None)
    grads = np.concatenate(
        [
            [d_slope[0]],
            d_slope[pos] + d_slope[neg],  # a_k shared by the pair
            d_offset[pos] - d_offset[neg],  # b_k and −b_k
            d_centre[pos] - d_centre[neg],  # c_k and −c_k
            [d_var[0] * s[0]],  # log σ: chain rule × σ
            (d_var[pos] + d_var[neg]) * s[1:],
        ]
    )
    return cv, dcdv, grads


@pytest.mark.parametrize("extras", [{}, {"offset": -0.3, "gravity": 0.8}])
def test_autograd_jacobian_matches_analytic_tanh(extras: dict) -> None:
    arm = _tanh_arm(**extras)
    for x_list, u in [([0.3, 0.05], 0.2), ([-1.2, -0.4], -0.7), ([2.0, 1.3], 0.0)]:
        x = torch.tensor(x_list)
        got = _autograd_jacobian(arm, x, torch.tensor(u))
        c, dcdv, dc_dfric = _tanh_derivatives(arm, x_list[1])
        expected = _assemble(arm, np.array(x_list), u, dcdv, dc_dfric, c)
        torch.testing.assert_close(got, torch.tensor(expected))


@pytest.mark.parametrize("n", [3, 5])
@pytest.mark.parametrize("extras", [{}, {"offset": 0.2, "gravity": 0.5}])
def test_autograd_jacobian_matches_analytic_polytopic(n: int, extras: dict) -> None:
    arm = _poly_arm(n, **extras)
    for x_list, u in [([0.3, 0.05], 0.2), ([-1.2, -0.6], -0.7), ([2.0, 1.1], 0.4)]:
        x = torch.tensor(x_list)
        got = _autograd_jacobian(arm, x, torch.tensor(u))
        c, dcdv, dc_dfric = _polytopic_derivatives(arm, x_list[1])
        expected = _assemble(arm, np.array(x_list), u, dcdv, dc_dfric, c)
        torch.testing.assert_close(got, torch.tensor(expected))


def test_analytic_polytopic_derivatives_agree_with_finite_differences() -> None:
    # Guards the hand derivation itself (so the Jacobian test compares against a correct truth).
    arm = _poly_arm(5)
    v, h = 0.37, 1e-6
    _, dcdv, grads = _polytopic_derivatives(arm, v)
    f = arm.friction
    raw = f.raw_vector().detach()

    def c_at(r: torch.Tensor, vel: float) -> float:
        return float(f.evaluate(torch.tensor(vel), f.split(r)))

    fd_v = (c_at(raw, v + h) - c_at(raw, v - h)) / (2 * h)
    eye = torch.eye(raw.numel())
    fd = [(c_at(raw + h * e, v) - c_at(raw - h * e, v)) / (2 * h) for e in eye]
    # Central differences with h = 1e-6: truncation ~h² and rounding ~1e-16/h ≈ 1e-10.
    torch.testing.assert_close(torch.tensor(dcdv), torch.tensor(fd_v), rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(torch.tensor(grads), torch.tensor(fd), rtol=1e-7, atol=1e-9)
