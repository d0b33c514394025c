"""Tests of torchfric.models.friction: oddness and zero-at-zero for every parameter value (hypothesis),
agreement with literal numpy re-implementations of the paper's formulas (Hensen et al. §3.1,
§3.2) and the white-box closed forms, parameter bookkeeping (counts, names, log storage),
gradcheck, shapes, and every bad-input message."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchfric.errors import TorchfricError
from torchfric.models.friction import (
    FRICTIONS,
    CoulombFriction,
    Friction,
    OddTanhFriction,
    PolytopicFriction,
    StribeckFriction,
    make_friction,
)

PROPERTY = settings(max_examples=60, deadline=None)

# Oddness is exact in exact arithmetic; in float64 the two evaluations differ only by rounding
# (reduction order inside softmax/sum), i.e. ~1e-16 of the magnitude of the summed terms.
ODD_RTOL = 1e-12


def _finite(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


def _vec(n: int, lo: float, hi: float) -> st.SearchStrategy[list[float]]:
    return st.lists(_finite(lo, hi), min_size=n, max_size=n)


velocities = st.lists(_finite(-100.0, 100.0), min_size=1, max_size=20)


@st.composite
def tanh_models(draw: st.DrawFn) -> tuple[Friction, float]:
    n = draw(st.integers(1, 6))
    w1, w2 = draw(_vec(n, -50.0, 50.0)), draw(_vec(n, -10.0, 10.0))
    return OddTanhFriction(n, w1=w1, w2=w2), sum(abs(w) for w in w2)


@st.composite
def polytopic_models(draw: st.DrawFn, sizes: tuple[int, ...] = (1, 3, 5, 7)) -> tuple:
    n = draw(st.sampled_from(sizes))
    m = (n - 1) // 2
    a, b = draw(_vec(m + 1, -10.0, 10.0)), draw(_vec(m, -10.0, 10.0))
    c, sigma = draw(_vec(m, -10.0, 10.0)), draw(_vec(m + 1, 1e-3, 100.0))
    log_positive = draw(st.booleans())
    f = PolytopicFriction(n, a=a, b=b, c=c, sigma=sigma, log_positive=log_positive)
    # |every local model| <= max|a| (|v| + max|c|) + max|b|: the scale of the rounding error.
    return f, (max(map(abs, a)), max(map(abs, c), default=0.0), max(map(abs, b), default=0.0))


@st.composite
def coulomb_models(draw: st.DrawFn) -> tuple[Friction, float]:
    fc, eps = draw(_finite(1e-3, 10.0)), draw(_finite(1e-4, 1.0))
    return CoulombFriction(fc=fc, eps=eps, log_positive=draw(st.booleans())), fc


@st.composite
def stribeck_models(draw: st.DrawFn) -> tuple[Friction, float]:
    fc, fs = draw(_finite(1e-3, 10.0)), draw(_finite(1e-3, 10.0))
    vs, eps = draw(_finite(1e-3, 10.0)), draw(_finite(1e-4, 1.0))
    f = StribeckFriction(fc=fc, fs=fs, vs=vs, eps=eps, log_positive=draw(st.booleans()))
    return f, max(fc, fs)


def _check_odd(f: Friction, v: torch.Tensor, scale: torch.Tensor | float) -> None:
    with torch.no_grad():
        out_pos, out_neg = f(v), f(-v)
    # C(−v) = −C(v) up to rounding relative to the magnitude of the terms.
    assert bool(((out_pos + out_neg).abs() <= ODD_RTOL * scale).all()), (out_pos, out_neg)
    assert bool(torch.isfinite(out_pos).all())


def _check_zero(f: Friction) -> None:
    with torch.no_grad():
        assert f(torch.zeros(())).item() == 0.0
        assert bool((f(torch.zeros(4)) == 0).all())


# -- odd and zero at zero for every parameter value -----------------------------------------------
@PROPERTY
@given(model=tanh_models(), v=velocities)
def test_tanh_odd_and_zero_at_zero(model: tuple, v: list[float]) -> None:
    f, scale = model
    _check_odd(f, torch.tensor(v), scale)
    _check_zero(f)


@PROPERTY
@given(model=polytopic_models(), v=velocities)
def test_polytopic_odd(model: tuple, v: list[float]) -> None:
    f, (a_max, c_max, b_max) = model
    vt = torch.tensor(v)
    _check_odd(f, vt, a_max * (vt.abs() + c_max) + b_max)
    # The weights' normaliser adds each mirrored pair first and the terms are summed pairwise,
    # so C(−v) = −C(v) holds to the last bit, not only to rounding.
    with torch.no_grad():
        assert torch.equal(f(-vt), -f(vt))


@PROPERTY
@given(model=polytopic_models(sizes=(1, 3)))
def test_polytopic_zero_at_zero_small(model: tuple) -> None:
    _check_zero(model[0])


@pytest.mark.parametrize("n", [5, 7])
def test_polytopic_zero_at_zero_exactly_larger_models(n: int) -> None:
    m = (n - 1) // 2
    gen = torch.Generator().manual_seed(1)
    values = []
    for _ in range(50):
        f = PolytopicFriction(
            n,
            a=torch.randn(m + 1, generator=gen),
            b=torch.randn(m, generator=gen),
            c=torch.randn(m, generator=gen),
            sigma=torch.rand(m + 1, generator=gen) + 0.1,
        )
        with torch.no_grad():
            values.append(f(torch.zeros(())).item())
    # The paper's equilibrium property: C(0) = 0 for every parameter value, exactly.
    assert values == [0.0] * len(values)


@PROPERTY
@given(model=coulomb_models(), v=velocities)
def test_coulomb_odd_and_zero_at_zero(model: tuple, v: list[float]) -> None:
    f, scale = model
    _check_odd(f, torch.tensor(v), scale)
    _check_zero(f)


@PROPERTY
@given(model=stribeck_models(), v=velocities)
def test_stribeck_odd_and_zero_at_zero(model: tuple, v: list[float]) -> None:
    f, scale = model
    _check_odd(f, torch.tensor(v), scale)
    _check_zero(f)


@pytest.mark.parametrize("kind", sorted(FRICTIONS))
def test_default_models_from_registry_odd_and_zero(kind: str) -> None:
    f = make_friction(kind, 3)
    v = torch.linspace(-5.0, 5.0, 41)
    torch.testing.assert_close(f(-v), -f(v), rtol=0.0, atol=1e-15)
    _check_zero(f)


# -- agreement with the paper's formulas and the closed forms -------------------------------------
def _np_polytopic(v: np.ndarray, a, b, c, sigma) -> np.ndarray:
    """Literal paper §3.2: model 1 has c = 0, b = 0; the pairs (c, -c), (b, -b) share a, sigma."""
    models = [(0.0, sigma[0], a[0], 0.0)]
    for k in range(len(b)):
        models.append((c[k], sigma[k + 1], a[k + 1], b[k]))
        models.append((-c[k], sigma[k + 1], a[k + 1], -b[k]))
    out = np.zeros_like(v)
    for j, vj in enumerate(v):
        rho = np.array([math.exp(-0.5 * (vj - ci) ** 2 / si) for ci, si, _, _ in models])
        w = rho / rho.sum()
        local = np.array([ai * (vj - ci) + bi for ci, _, ai, bi in models])
        out[j] = float(np.dot(w, local))
    return out


@pytest.mark.parametrize("n", [1, 3, 5, 7])
def test_polytopic_matches_paper_formula(n: int) -> None:
    m = (n - 1) // 2
    rng = np.random.default_rng(n)
    a, b = rng.normal(size=m + 1), rng.normal(size=m)
    c, sigma = rng.uniform(0.2, 2.0, size=m), rng.uniform(0.1, 1.5, size=m + 1)
    f = PolytopicFriction(
        n, a=a.tolist(), b=b.tolist(), c=c.tolist(), sigma=sigma.tolist(), extrapolation="gaussian"
    )
    v = np.linspace(-4.0, 4.0, 81)
    got = f(torch.tensor(v)).detach()
    torch.testing.assert_close(got, torch.tensor(_np_polytopic(v, a, b, c, sigma)))


def test_polytopic_n3_by_hand() -> None:
    # n = 3 written out: weights of the models at 0, +c, -c.
    a1, a2, b2, c2, s1, s2 = 0.3, 0.05, 0.2, 0.7, 0.4, 0.25
    f = PolytopicFriction(3, a=[a1, a2], b=[b2], c=[c2], sigma=[s1, s2])
    v = 0.37
    r0 = math.exp(-0.5 * v**2 / s1)
    rp = math.exp(-0.5 * (v - c2) ** 2 / s2)
    rm = math.exp(-0.5 * (v + c2) ** 2 / s2)
    expected = (r0 * a1 * v + rp * (a2 * (v - c2) + b2) + rm * (a2 * (v + c2) - b2)) / (
        r0 + rp + rm
    )
    torch.testing.assert_close(f(torch.tensor(v)), torch.tensor(expected))


def test_polytopic_far_from_all_centres_is_finite() -> None:
    # Literal exp(-½ d²/σ) underflows to 0/0 here; the model must stay finite and follow the
    # nearest (outermost) local affine model.
    f = PolytopicFriction(3, a=[0.1, 0.02], b=[0.3], c=[1.0], sigma=[0.01, 0.01])
    v = torch.tensor([-300.0, 300.0])
    torch.testing.assert_close(f(v), torch.tensor([-(0.02 * 299.0 + 0.3), 0.02 * 299.0 + 0.3]))


@pytest.mark.parametrize("n", [1, 3, 6])
def test_tanh_matches_numpy(n: int) -> None:
    rng = np.random.default_rng(n)
    w1, w2 = rng.normal(scale=5.0, size=n), rng.normal(size=n)
    f = OddTanhFriction(n, w1=w1.tolist(), w2=w2.tolist())
    v = np.linspace(-3.0, 3.0, 61)
    expected = np.tanh(np.outer(v, w1)) @ w2  # W2ᵀ tanh(W1 v) for each v
    torch.testing.assert_close(f(torch.tensor(v)).detach(), torch.tensor(expected))


def test_tanh_sigma_is_papers_squashing_function() -> None:
    # Paper §3.1: σ(z) = 1 − 2/(e^{2z} + 1), i.e. tanh.
    f = OddTanhFriction(1, w1=[1.0], w2=[1.0])
    z = np.linspace(-3.0, 3.0, 13)
    expected = 1.0 - 2.0 / (np.exp(2.0 * z) + 1.0)
    torch.testing.assert_close(f(torch.tensor(z)).detach(), torch.tensor(expected))


def test_coulomb_closed_form() -> None:
    fc, eps = 0.7, 0.05
    f = CoulombFriction(fc=fc, eps=eps)
    v = np.linspace(-1.0, 1.0, 41)
    torch.testing.assert_close(f(torch.tensor(v)).detach(), torch.tensor(fc * np.tanh(v / eps)))


def test_stribeck_closed_form() -> None:
    fc, fs, vs, eps = 0.2, 0.5, 0.3, 0.01
    f = StribeckFriction(fc=fc, fs=fs, vs=vs, eps=eps)
    v = np.linspace(-2.0, 2.0, 81)
    expected = (fc + (fs - fc) * np.exp(-((v / vs) ** 2))) * np.tanh(v / eps)
    torch.testing.assert_close(f(torch.tensor(v)).detach(), torch.tensor(expected))
    # Far beyond vs only Coulomb is left; just past the smoothing width it is near the static level.
    torch.testing.assert_close(f(torch.tensor(20.0)), torch.tensor(fc))
    # ε = 0.01: at v = 0.1, tanh(10) = 1 − 4e-9 and exp(−(v/vs)²) = 0.895.
    torch.testing.assert_close(
        f(torch.tensor(0.1)),
        torch.tensor(fc + (fs - fc) * math.exp(-((0.1 / vs) ** 2))),
        rtol=1e-8,
        atol=0,
    )


@pytest.mark.parametrize(
    ("kind", "cls", "kwargs"),
    [
        ("tanh", OddTanhFriction, {"w1": [1.0, 2.0, 3.0], "w2": [0.1, 0.2, 0.3]}),
        (
            "polytopic",
            PolytopicFriction,
            {"a": [0.1, 0.2], "b": [0.3], "c": [0.5], "sigma": [0.2, 0.3]},
        ),
        ("coulomb", CoulombFriction, {"fc": 0.4, "eps": 0.02}),
        ("stribeck", StribeckFriction, {"fc": 0.1, "fs": 0.2, "vs": 0.3, "eps": 0.02}),
    ],
)
def test_make_friction_builds_the_same_model(kind: str, cls: type, kwargs: dict) -> None:
    size = 3
    f = make_friction(kind, size, **kwargs)
    assert type(f) is cls and f.kind == kind
    direct = cls(size, **kwargs)
    v = torch.linspace(-2.0, 2.0, 21)
    torch.testing.assert_close(f(v), direct(v), rtol=0.0, atol=0.0)


# -- parameter bookkeeping ------------------------------------------------------------------------
def test_tanh_parameter_count_and_names() -> None:
    f = OddTanhFriction(3)
    assert f.num_parameters == 6
    assert f.element_names == ["W1[1]", "W1[2]", "W1[3]", "W2[1]", "W2[2]", "W2[3]"]
    assert OddTanhFriction(7).num_parameters == 14


def test_polytopic_n3_has_exactly_the_papers_parameters() -> None:
    f = PolytopicFriction(3)
    assert f.element_names == ["a1", "a2", "b2", "c2", "sigma1", "sigma2"]
    assert f.num_parameters == 6


@pytest.mark.parametrize("n", [1, 3, 5, 7, 9])
def test_polytopic_parameter_count_formula(n: int) -> None:
    # m = (n−1)/2 pairs: a (m+1), b (m), c (m), sigma (m+1) → 4m + 2;
    # paper θ = [a1 a2i b2i c2i σ1 σ2i].
    m = (n - 1) // 2
    f = PolytopicFriction(n)
    assert f.num_parameters == 4 * m + 2 == len(f.element_names)
    assert f.raw_vector().shape == (4 * m + 2,)


def test_polytopic_n5_names() -> None:
    assert PolytopicFriction(5).element_names == [
        "a1",
        "a2",
        "a3",
        "b2",
        "b3",
        "c2",
        "c3",
        "sigma1",
        "sigma2",
        "sigma3",
    ]


def test_white_box_parameter_names() -> None:
    assert CoulombFriction().element_names == ["Fc"]
    assert StribeckFriction().element_names == ["Fc", "Fs", "vs"]


def test_scalar_value_broadcasts_to_all_neurons() -> None:
    f = OddTanhFriction(3, w1=2.0, w2=0.5)
    torch.testing.assert_close(f.physical_parameters()["W1"], torch.full((3,), 2.0))


def test_log_positive_storage_polytopic() -> None:
    sigma = [0.5, 2.0]
    f = PolytopicFriction(3, a=[0.1, 0.2], b=[0.3], c=[1.0], sigma=sigma)
    torch.testing.assert_close(f.sigma.detach(), torch.tensor(sigma).log())
    torch.testing.assert_close(f.physical_parameters()["sigma"].detach(), torch.tensor(sigma))
    assert f.positive_mask().tolist() == [False] * 4 + [True] * 2
    raw = f.raw_vector().detach()
    torch.testing.assert_close(
        raw, torch.tensor([0.1, 0.2, 0.3, 1.0, math.log(0.5), math.log(2.0)])
    )

    g = PolytopicFriction(3, a=[0.1, 0.2], b=[0.3], c=[1.0], sigma=sigma, log_positive=False)
    torch.testing.assert_close(g.sigma.detach(), torch.tensor(sigma))
    assert not bool(g.positive_mask().any())
    v = torch.linspace(-3.0, 3.0, 13)
    torch.testing.assert_close(f(v), g(v))


def test_log_positive_storage_white_box() -> None:
    f = StribeckFriction(fc=0.1, fs=0.3, vs=0.05)
    torch.testing.assert_close(f.raw_vector().detach(), torch.tensor([0.1, 0.3, 0.05]).log())
    assert f.positive_mask().tolist() == [True, True, True]
    c = CoulombFriction(fc=0.4, log_positive=False)
    torch.testing.assert_close(c.raw_vector().detach(), torch.tensor([0.4]))
    # tanh weights are signed: never stored in log space.
    assert not bool(OddTanhFriction(3).positive_mask().any())


def test_split_maps_raw_vector_to_physical() -> None:
    f = PolytopicFriction(3, a=[0.1, 0.2], b=[0.3], c=[1.0], sigma=[0.5, 2.0])
    raw = torch.tensor([1.0, 2.0, 3.0, 4.0, 0.0, math.log(3.0)])
    p = f.split(raw)
    torch.testing.assert_close(p["a"], torch.tensor([1.0, 2.0]))
    torch.testing.assert_close(p["b"], torch.tensor([3.0]))
    torch.testing.assert_close(p["c"], torch.tensor([4.0]))
    torch.testing.assert_close(p["sigma"], torch.tensor([1.0, 3.0]))


# -- gradients ------------------------------------------------------------------------------------
GRAD_MODELS = [
    lambda: OddTanhFriction(3, w1=[0.5, 2.0, 8.0], w2=[0.3, -0.2, 0.1]),
    lambda: PolytopicFriction(
        5, a=[0.1, 0.2, -0.1], b=[0.3, 0.1], c=[0.5, 1.2], sigma=[0.2, 0.3, 0.5]
    ),
    lambda: CoulombFriction(fc=0.4, eps=0.2),
    lambda: StribeckFriction(fc=0.1, fs=0.3, vs=0.4, eps=0.2),
]
GRAD_IDS = ["tanh", "polytopic", "coulomb", "stribeck"]


@pytest.mark.parametrize("make", GRAD_MODELS, ids=GRAD_IDS)
def test_gradcheck_wrt_velocity(make) -> None:
    f = make()
    v = torch.linspace(-2.0, 2.0, 9).requires_grad_(True)
    assert torch.autograd.gradcheck(f, (v,))


@pytest.mark.parametrize("make", GRAD_MODELS, ids=GRAD_IDS)
def test_gradcheck_wrt_parameters(make) -> None:
    f = make()
    v = torch.linspace(-2.0, 2.0, 9)
    raw = f.raw_vector().detach().clone().requires_grad_(True)
    # Through the estimation coordinates, i.e. including exp() of the log-stored entries.
    assert torch.autograd.gradcheck(lambda r: f.evaluate(v, f.split(r)), (raw,))


@pytest.mark.parametrize("make", GRAD_MODELS, ids=GRAD_IDS)
def test_forward_gradient_reaches_module_parameters(make) -> None:
    f = make()
    v = torch.linspace(-2.0, 2.0, 9)
    f(v).pow(2).sum().backward()
    got = torch.cat([p.grad.reshape(-1) for p in f.parameters()])
    raw = f.raw_vector().detach().clone().requires_grad_(True)
    (expected,) = torch.autograd.grad(f.evaluate(v, f.split(raw)).pow(2).sum(), raw)
    torch.testing.assert_close(got, expected)


# -- shapes ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", sorted(FRICTIONS))
@pytest.mark.parametrize("shape", [(), (5,), (3, 4), (2, 1, 3)])
def test_output_shape_matches_input(kind: str, shape: tuple[int, ...]) -> None:
    f = make_friction(kind, 3)
    v = torch.randn(shape)
    out = f(v)
    assert out.shape == v.shape
    # Elementwise: the same values as evaluating the flattened velocities one by one.
    flat = torch.stack([f(x) for x in v.reshape(-1)])
    torch.testing.assert_close(out.reshape(-1), flat)


# -- bad input ------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [2, 4, 0, -1, -3])
def test_polytopic_rejects_even_or_nonpositive_n(n: int) -> None:
    with pytest.raises(TorchfricError, match=r"odd number of local models n >= 1.*got " + str(n)):
        PolytopicFriction(n)


def test_polytopic_rejects_non_int_n() -> None:
    with pytest.raises(TorchfricError, match="odd number of local models"):
        PolytopicFriction(3.0)  # type: ignore[arg-type]
    with pytest.raises(TorchfricError, match="odd number of local models"):
        PolytopicFriction(True)  # type: ignore[arg-type]


@pytest.mark.parametrize("sigma", [[0.0, 1.0], [1.0, -0.5]])
def test_polytopic_rejects_nonpositive_sigma(sigma: list[float]) -> None:
    with pytest.raises(TorchfricError, match=r"sigma must be positive"):
        PolytopicFriction(3, sigma=sigma)


def test_polytopic_nonpositive_sigma_rejected_without_log_storage_too() -> None:
    with pytest.raises(TorchfricError, match=r"sigma must be positive"):
        PolytopicFriction(3, sigma=[0.0, 1.0], log_positive=False)


@pytest.mark.parametrize("n", [0, -2])
def test_tanh_rejects_nonpositive_n(n: int) -> None:
    with pytest.raises(
        TorchfricError, match=r"OddTanhFriction needs n >= 1 neurons, got " + str(n)
    ):
        OddTanhFriction(n)


@pytest.mark.parametrize(
    ("build", "pattern"),
    [
        (lambda: OddTanhFriction(3, w1=[1.0, 2.0]), r"W1 needs 3 values, got 2"),
        (lambda: OddTanhFriction(2, w2=[1.0, 2.0, 3.0]), r"W2 needs 2 values, got 3"),
        (lambda: PolytopicFriction(3, a=[0.1, 0.2, 0.3]), r"a needs 2 values, got 3"),
        (lambda: PolytopicFriction(5, b=[0.1, 0.2, 0.3]), r"b needs 2 values, got 3"),
        (lambda: PolytopicFriction(5, c=[0.1, 0.2, 0.3, 0.4]), r"c needs 2 values, got 4"),
        (lambda: PolytopicFriction(3, sigma=[0.1, 0.2, 0.3]), r"sigma needs 2 values, got 3"),
    ],
)
def test_wrong_vector_lengths(build, pattern: str) -> None:
    with pytest.raises(TorchfricError, match=pattern):
        build()


def test_non_finite_values_rejected() -> None:
    with pytest.raises(TorchfricError, match=r"W1 must be finite"):
        OddTanhFriction(2, w1=[1.0, float("nan")])
    with pytest.raises(TorchfricError, match=r"c must be finite"):
        PolytopicFriction(3, c=[float("inf")])


@pytest.mark.parametrize(
    ("build", "pattern"),
    [
        (lambda: CoulombFriction(fc=-0.1), r"Fc must be positive"),
        (lambda: CoulombFriction(eps=0.0), r"eps must be positive"),
        (lambda: StribeckFriction(fs=0.0), r"Fs must be positive"),
        (lambda: StribeckFriction(vs=-1.0), r"vs must be positive"),
        (lambda: StribeckFriction(eps=-1e-3), r"eps must be positive"),
    ],
)
def test_white_box_rejects_nonpositive(build, pattern: str) -> None:
    with pytest.raises(TorchfricError, match=pattern):
        build()


def test_make_friction_unknown_kind_lists_choices() -> None:
    with pytest.raises(TorchfricError, match=r"unknown friction model 'lugre'.*coulomb.*polytopic"):
        make_friction("lugre")
