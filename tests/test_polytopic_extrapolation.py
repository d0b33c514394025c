"""The polytopic model's affine continuation beyond its outer centres (issue 23, item 2).

With ``extrapolation="affine"`` (the default) the outer pair's validity is one-sided, so far from
the data the curve is the outer local model ``a_m (v − c_m) + b_m`` whatever the variances; the
paper's Gaussians (``"gaussian"``) hand it to the widest local model instead.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchfric import TorchfricError
from torchfric.models.arm import ArmModel
from torchfric.models.friction import PolytopicFriction


def _random_model(n: int, gen: torch.Generator, *, signed_centres: bool = True):  # type: ignore[no-untyped-def]
    """Random parameters over wide ranges: centres of either sign, variances over 6 decades."""
    m = (n - 1) // 2
    a = 3.0 * torch.randn(m + 1, generator=gen)
    b = 3.0 * torch.randn(m, generator=gen)
    c = 5.0 * (torch.randn(m, generator=gen) if signed_centres else torch.rand(m, generator=gen))
    sigma = 10.0 ** (6.0 * torch.rand(m + 1, generator=gen) - 4.0)  # 1e-4 ... 1e2
    return PolytopicFriction(n, a=a, b=b, c=c, sigma=sigma), (a, b, c, sigma)


def _np_affine(v: np.ndarray, a, b, c, sigma) -> np.ndarray:
    """The construction written out literally: the paper's Gaussians, except that the outer
    pair's validity is exp(−½ min(v − c_m, 0)² / σ_m) and its mirror exp(−½ max(v + c_m, 0)² / σ_m)."""
    m = len(b)
    out = np.zeros_like(v)
    for j, vj in enumerate(v):
        rho = [math.exp(-0.5 * vj**2 / sigma[0])]
        local = [a[0] * vj]
        for k in range(m):
            plus, minus = vj - c[k], vj + c[k]
            if k == m - 1:
                plus, minus = min(plus, 0.0), max(minus, 0.0)
            rho += [
                math.exp(-0.5 * plus**2 / sigma[k + 1]),
                math.exp(-0.5 * minus**2 / sigma[k + 1]),
            ]
            local += [a[k + 1] * (vj - c[k]) + b[k], a[k + 1] * (vj + c[k]) - b[k]]
        out[j] = float(np.dot(np.array(rho) / sum(rho), local))
    return out


@pytest.mark.parametrize("n", [3, 5, 7])
def test_matches_the_construction_written_out(n: int) -> None:
    m = (n - 1) // 2
    rng = np.random.default_rng(n)
    a, b = rng.normal(size=m + 1), rng.normal(size=m)
    c, sigma = np.sort(rng.uniform(0.2, 2.0, size=m)), rng.uniform(0.1, 1.5, size=m + 1)
    f = PolytopicFriction(n, a=a.tolist(), b=b.tolist(), c=c.tolist(), sigma=sigma.tolist())
    v = np.linspace(-6.0, 6.0, 121)
    got = f(torch.tensor(v)).detach()
    torch.testing.assert_close(got, torch.tensor(_np_affine(v, a, b, c, sigma)))


@pytest.mark.parametrize("n", [3, 5, 7, 9])
def test_exactly_the_outer_local_model_beyond_the_centres(n: int) -> None:
    gen = torch.Generator().manual_seed(100 + n)
    for _ in range(20):
        f, (a, b, c, sigma) = _random_model(n, gen)
        # 12 standard deviations of the widest model past the farthest centre: every other
        # validity is below exp(−72) of the outer one's, far under the rounding of a double.
        start = float(c.abs().max() + 12.0 * sigma.max().sqrt())
        v = start + torch.linspace(0.0, 50.0, 201, dtype=torch.float64)
        v = torch.cat([v, torch.tensor([1e3, 1e6]) + start])
        with torch.no_grad():
            pos, neg = f(v), f(-v)
        outer = a[-1] * (v - c[-1]) + b[-1]
        scale = float(a.abs().max()) * (v.abs() + float(c.abs().max())) + float(b.abs().max())
        assert bool(((pos - outer).abs() <= 1e-13 * scale).all()), (pos - outer).abs().max()
        # and its mirror image for v → −∞
        assert bool(((neg + outer).abs() <= 1e-13 * scale).all())
        # a straight line: second differences vanish to rounding on the uniform grid
        grid = pos[:201]
        second = grid[2:] - 2.0 * grid[1:-1] + grid[:-2]
        assert bool((second.abs() <= 1e-12 * scale[1:200]).all()), second.abs().max()


def test_the_widest_model_no_longer_takes_over() -> None:
    # A wide, steep centre model: the paper's construction follows a1·v far out, ours the
    # outer model. Beyond the outer centre the data had the slope a2, not a1.
    kw = {"a": [5.0, 0.01], "b": [0.3], "c": [1.0], "sigma": [4.0, 0.01]}
    affine = PolytopicFriction(3, **kw)
    paper = PolytopicFriction(3, **kw, extrapolation="gaussian")
    v = torch.tensor([20.0, 50.0])
    with torch.no_grad():
        torch.testing.assert_close(affine(v), 0.01 * (v - 1.0) + 0.3, rtol=1e-14, atol=0.0)
        torch.testing.assert_close(paper(v), 5.0 * v, rtol=1e-14, atol=0.0)
        # Below the outer centre both are the same curve wherever the one-sided part is inert.
        inner = torch.linspace(-0.2, 0.2, 9, dtype=torch.float64)
        assert float((affine(inner) - paper(inner)).abs().max()) < 1e-12


@pytest.mark.parametrize("n", [1, 3, 5, 7, 9])
def test_odd_to_the_last_bit_and_zero_at_zero(n: int) -> None:
    gen = torch.Generator().manual_seed(n)
    for _ in range(50):
        f, (_, _, c, _) = _random_model(n, gen)
        v = torch.cat(
            [
                20.0 * torch.randn(64, generator=gen, dtype=torch.float64),
                c,  # at the centres, where the one-sided validity switches
                torch.tensor([1e-300, 1e-8, 1e6, 1e12]),
            ]
        )
        with torch.no_grad():
            assert torch.equal(f(-v), -f(v))
            assert f(torch.zeros(())).item() == 0.0
            assert bool((f(torch.zeros(3)) == 0).all())


def test_n1_is_the_centre_model_either_way() -> None:
    v = torch.linspace(-1e3, 1e3, 101, dtype=torch.float64)
    kw = {"a": [0.7], "sigma": [0.2]}
    with torch.no_grad():
        affine = PolytopicFriction(1, **kw)(v)
        paper = PolytopicFriction(1, **kw, extrapolation="gaussian")(v)
    assert torch.equal(affine, paper)
    torch.testing.assert_close(affine, 0.7 * v, rtol=1e-15, atol=0.0)


@pytest.mark.parametrize("n", [3, 5, 7])
def test_finite_values_and_gradients_far_out(n: int) -> None:
    gen = torch.Generator().manual_seed(7 * n)
    for _ in range(20):
        f, _ = _random_model(n, gen)
        v = torch.tensor([-1e6, -1e3, -1.0, 0.0, 1.0, 1e3, 1e6], requires_grad=True)
        out = f(v)
        assert bool(torch.isfinite(out).all())
        grads = torch.autograd.grad(out.sum(), [v, *f.parameters()])
        for g in grads:
            assert bool(torch.isfinite(g).all()), g


def test_slope_far_out_is_the_outer_slope_and_continuous_at_the_centre() -> None:
    f = PolytopicFriction(5, a=[2.0, 0.3, 0.05], b=[0.2, 0.4], c=[0.5, 2.0], sigma=[0.1, 0.2, 0.5])
    v = torch.tensor([1e6, -1e6, 40.0], dtype=torch.float64, requires_grad=True)
    (dv,) = torch.autograd.grad(f(v).sum(), v)
    torch.testing.assert_close(dv, torch.full((3,), 0.05, dtype=torch.float64), rtol=1e-12, atol=0)
    # The one-sided validity is C¹: dC/dv just below and just above c_m agree with the
    # central difference there (a kink would show up as a jump of O(1) between them).
    h = 1e-6
    x = torch.tensor([2.0 - 1e-9, 2.0, 2.0 + 1e-9], dtype=torch.float64, requires_grad=True)
    (dx,) = torch.autograd.grad(f(x).sum(), x)
    with torch.no_grad():
        central = (f(torch.tensor(2.0 + h)) - f(torch.tensor(2.0 - h))) / (2 * h)
    torch.testing.assert_close(dx, central.expand(3), rtol=1e-6, atol=1e-9)


def test_the_construction_survives_a_checkpoint_spec() -> None:
    for kind in ("affine", "gaussian"):
        f = PolytopicFriction(
            3, a=[5.0, 0.01], b=[0.3], c=[1.0], sigma=[4.0, 0.01], extrapolation=kind
        )
        arm = ArmModel(f, inertia=0.03, viscous=None, c_m=16.0)
        again = ArmModel.from_spec(arm.spec())
        assert again.friction.extrapolation == kind
        v = torch.tensor([-30.0, 0.5, 30.0])
        with torch.no_grad():
            torch.testing.assert_close(again.friction(v), f(v), rtol=1e-15, atol=0.0)


def test_an_unknown_construction_is_refused_in_one_line() -> None:
    with pytest.raises(
        TorchfricError, match="extrapolation must be one of 'affine', 'gaussian'"
    ) as e:
        PolytopicFriction(3, extrapolation="linear")
    assert "\n" not in str(e.value)
