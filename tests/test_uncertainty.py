"""Delta-method band of the friction curve (torchfric.estimators.uncertainty) against exact references."""

from __future__ import annotations

import pytest
import torch

from torchfric import ArmModel, OddTanhFriction, PolytopicFriction, TorchfricError
from torchfric.estimators.uncertainty import friction_band, friction_jacobian, friction_samples


def tanh_arm() -> ArmModel:
    return ArmModel(
        OddTanhFriction(3, w1=[1.0, 2.0, 50.0], w2=[0.05, -0.2, 0.3]),
        inertia=0.03,
        viscous=0.01,
        c_m=16.0,
    )


def w2_only_covariance(arm: ArmModel) -> torch.Tensor:
    """A random SPD covariance on the W2 block only: F is affine in θ there."""
    g = torch.Generator().manual_seed(1)
    A = torch.randn(3, 3, generator=g, dtype=torch.float64) * 0.01
    P = torch.zeros(arm.num_parameters, arm.num_parameters, dtype=torch.float64)
    P[3:6, 3:6] = A @ A.T + 1e-5 * torch.eye(3)
    return P


def test_jacobian_matches_closed_form_in_estimation_coordinates() -> None:
    arm = tanh_arm()
    v = torch.linspace(-12.0, 12.0, 41)
    J = friction_jacobian(arm, v)
    w1 = torch.tensor([1.0, 2.0, 50.0])
    w2 = torch.tensor([0.05, -0.2, 0.3])
    s = torch.tanh(v[:, None] * w1)
    torch.testing.assert_close(J[:, 3:6], s)  # ∂F/∂W2 = tanh(W1 v)
    torch.testing.assert_close(J[:, 0:3], w2 * v[:, None] * (1 - s**2))  # ∂F/∂W1
    # viscous is stored as log b: ∂(b v)/∂ log b = b v (the chain rule through exp)
    torch.testing.assert_close(J[:, 6], 0.01 * v)
    torch.testing.assert_close(J[:, 7], torch.zeros_like(v))  # F does not depend on M


def test_band_is_exact_where_friction_is_affine_in_theta() -> None:
    arm = tanh_arm()
    P = w2_only_covariance(arm)
    v = torch.linspace(-12.0, 12.0, 41)
    mean, std = friction_band(arm, P, v)
    s = torch.tanh(v[:, None] * torch.tensor([1.0, 2.0, 50.0]))
    exact = torch.einsum("ni,ij,nj->n", s, P[3:6, 3:6], s).sqrt()
    torch.testing.assert_close(std, exact)
    torch.testing.assert_close(mean, arm.friction_torque(v).detach())
    # The Monte-Carlo spread agrees within its sampling error: for n samples the relative
    # standard error of a sample std is ≈ 1/sqrt(2n) = 1.1 % at n = 4000; allow 5 σ.
    g = torch.Generator().manual_seed(0)
    curves = friction_samples(arm, P, v, samples=4000, generator=g)
    torch.testing.assert_close(curves.std(0), std, rtol=0.06, atol=1e-12)
    torch.testing.assert_close(curves.mean(0), mean, rtol=0.0, atol=float(4 * std.max() / 60))


def test_band_approximates_monte_carlo_for_small_nonlinear_uncertainty() -> None:
    arm = ArmModel(
        PolytopicFriction(3, a=[0.02, 0.01], b=[0.15], c=[0.8], sigma=[0.3, 0.5]),
        inertia=0.03,
        viscous=None,
        c_m=16.0,
    )
    k = arm.num_parameters
    P = torch.diag(torch.tensor([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4, 1e-6]))
    assert P.shape == (k, k)
    v = torch.linspace(-5.0, 5.0, 31)
    v = v[v.abs() > 0.2]  # away from v = 0, where F(0) = 0 exactly and the std is 0
    _, std = friction_band(arm, P, v)
    g = torch.Generator().manual_seed(0)
    curves = friction_samples(arm, P, v, samples=4000, generator=g)
    # First order is not exact here; with relative parameter std ≤ 1 % the second-order terms
    # are a few % of the band, and sampling adds ≈ 1 % (see above): 10 % relative.
    torch.testing.assert_close(curves.std(0), std, rtol=0.1, atol=1e-9)


def test_zero_covariance_gives_zero_band_and_zero_at_zero_velocity() -> None:
    arm = tanh_arm()
    k = arm.num_parameters
    _, std0 = friction_band(arm, torch.zeros(k, k), torch.linspace(-5, 5, 11))
    assert float(std0.abs().max()) == 0.0
    _, std = friction_band(arm, torch.eye(k), torch.tensor([0.0, 1.0]))
    assert float(std[0]) == 0.0 and float(std[1]) > 0.0  # C(0) = 0 for every θ


def test_wrong_shapes_are_refused_with_the_fix() -> None:
    arm = tanh_arm()
    with pytest.raises(TorchfricError, match=r"P_theta has shape \(3, 3\).*8 parameters"):
        friction_band(arm, torch.eye(3), torch.zeros(4))
    with pytest.raises(TorchfricError, match=r"theta has shape \(2,\)"):
        friction_band(arm, torch.eye(8), torch.zeros(4), theta=torch.zeros(2))
    with pytest.raises(TorchfricError, match="NaN or inf"):
        friction_band(arm, torch.full((8, 8), float("nan")), torch.zeros(4))
    with pytest.raises(TorchfricError, match="samples must be"):
        friction_samples(arm, torch.eye(8), torch.zeros(4), samples=0)
