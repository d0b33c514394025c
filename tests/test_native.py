"""The generated-C path (`torchfric.accel.native`) against the eager torch code it is traced from.

Truth is the eager function: every operation in the translation table, every friction model and
white-box term through the filter step, the ensemble's masked step member by member, and the
padding mask. Over ≤ 50 filter samples the two agree to rounding (DESIGN: compare filter
variants over short stretches; cond(P) ~ 1e12 amplifies rounding over thousands).
"""

from __future__ import annotations

import math

import pytest
import torch

from torchfric.accel import CHUNK, compile_step, make_chunk, native, step_key
from torchfric.accel.native import NativeUnavailable, make_native_chunk
from torchfric.estimators.ekf import make_fixed_theta_step, make_propagator, make_step
from torchfric.estimators.ensemble import make_batched_step, make_masked_step
from torchfric.estimators.identify import EKFTuning
from torchfric.models.arm import ArmModel
from torchfric.models.friction import (
    CoulombFriction,
    OddTanhFriction,
    PolytopicFriction,
    StribeckFriction,
)

pytestmark = pytest.mark.skipif(native.compiler() is None, reason="no C compiler here")


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Each test builds into its own cache folder (the cache itself is tested below)."""
    monkeypatch.setenv("TORCHFRIC_CACHE", str(tmp_path / "cache"))


def _loop(fn, carry, xs, valid, consts):  # type: ignore[no-untyped-def]
    """The reference: `fn` sample by sample in eager torch, padding samples skipped."""
    outs = []
    for i in range(valid.shape[0]):
        new, o = fn(*carry, *(x[i] for x in xs), *consts)
        if bool(valid[i]):
            carry = new
        outs.append(o)
    return carry, tuple(torch.stack(c) for c in zip(*outs, strict=True))


# ---------------------------------------------------------------------------------------------
# The translation table, operation by operation
# ---------------------------------------------------------------------------------------------
def _ops(x, v, a, c, w):  # type: ignore[no-untyped-def]
    """One sample using a broad slice of the ATen table: unary maths, broadcasting, reductions,
    views, concatenation, comparisons, masks and softmax (and their autograd backwards)."""
    y = torch.stack([torch.tanh(x[0]) * c, torch.exp(-x[1].abs()), torch.sqrt(x[2] * x[2] + 1.0)])
    y = y + torch.sin(v) * torch.cos(a) - torch.log1p(x.abs()) / (1.0 + torch.sigmoid(x))
    m = torch.outer(x, w)
    y = y + m.sum(0) - m.max() + m.amin(1) + torch.softmax(m, dim=1)[:, 0]
    y = torch.where(y > 0.5, y, -y) + torch.sign(x) * torch.clamp(x, -1.0, 1.0)
    y = y + torch.nn.functional.pad(x[1:], (1, 0)) + torch.cat([x[:1], x[1:].flip(0)])
    g = torch.func.grad(lambda z: (torch.tanh(z) * torch.softmax(z, 0)).sum() + z.pow(3).sum())(x)
    ok = torch.isfinite(y).all() & (y.abs() < 1e6).all()
    x1 = 0.5 * x + 0.1 * torch.tanh(y) + 0.01 * g
    return (x1,), (y, ok, m.argmax(), torch.maximum(x, a).diag_embed().diagonal())


def test_every_translated_operation_equals_eager() -> None:
    torch.manual_seed(3)
    C = 40
    carry = (torch.tensor([0.3, -1.2, 0.7]),)
    xs = (torch.randn(C, 3),)
    valid = torch.ones(C, dtype=torch.bool)
    valid[17] = False  # a padding sample mid-chunk leaves the carry as it was
    consts = (torch.tensor([0.5, -2.0, 1.5]), torch.tensor(0.8), torch.tensor([1.0, 0.0, -0.3]))
    chunk = make_native_chunk(_ops)
    (x_n,), outs_n = chunk(carry, xs, valid, consts)
    (x_e,), outs_e = _loop(_ops, carry, xs, valid, consts)
    torch.testing.assert_close(x_n, x_e, rtol=1e-13, atol=1e-15)
    for got, want in zip(outs_n, outs_e, strict=True):
        assert got.dtype == want.dtype and got.shape == want.shape
        torch.testing.assert_close(got, want, rtol=1e-13, atol=1e-15)


def test_structural_constants_are_part_of_the_key() -> None:
    """Entries equal to 0 or 1 in a constant are compiled in; a constant with another pattern
    must get code of its own, never the stale one."""

    def fn(x, u, A):  # type: ignore[no-untyped-def]
        x1 = A @ x + u
        return (x1,), (x1,)

    chunk = make_native_chunk(fn)
    carry, xs, valid = (
        (torch.tensor([1.0, 2.0]),),
        (torch.ones(5, 2),),
        torch.ones(5, dtype=torch.bool),
    )
    for A in (
        torch.eye(2),
        torch.tensor([[0.0, 1.0], [0.9, 0.0]]),
        torch.tensor([[0.5, 0.2], [1.0, 0.3]]),
    ):
        (x_n,), _ = chunk(carry, xs, valid, (A,))
        (x_e,), _ = _loop(fn, carry, xs, valid, (A,))
        torch.testing.assert_close(x_n, x_e, rtol=1e-15, atol=0)


# ---------------------------------------------------------------------------------------------
# The filter step, every friction model and white-box term
# ---------------------------------------------------------------------------------------------
def _models() -> dict[str, ArmModel]:
    tanh = OddTanhFriction(3, w1=[0.4, 6.0, 40.0], w2=[0.05, 0.04, 0.12])
    return {
        "tanh": ArmModel(tanh, inertia=0.035, viscous=0.012, c_m=16.0),
        "polytopic": ArmModel(PolytopicFriction(3), inertia=0.03, viscous=None, c_m=16.0),
        "polytopic5": ArmModel(PolytopicFriction(5), inertia=0.03, viscous=None, c_m=16.0),
        "coulomb": ArmModel(CoulombFriction(), inertia=0.03, viscous=0.01, c_m=16.0),
        "stribeck": ArmModel(StribeckFriction(), inertia=0.03, viscous=0.01, c_m=16.0),
        "white-box terms": ArmModel(
            OddTanhFriction(3),
            inertia=0.03,
            viscous=0.01,
            c_m=16.0,
            offset=-0.02,
            gravity=0.05,
            asymmetric=0.003,
            estimate_c_m=True,
        ),  # fmt: skip
        "lugre tanh": ArmModel(tanh, inertia=0.035, viscous=0.012, c_m=16.0, dynamic="lugre",
                               sigma0=1200.0, sigma1=11.0),  # fmt: skip
        "lugre polytopic + terms": ArmModel(
            PolytopicFriction(3), inertia=0.03, viscous=None, c_m=16.0, offset=-0.02,
            gravity=0.05, asymmetric=0.003, dynamic="lugre", sigma0=3e4, sigma1=40.0,
        ),  # fmt: skip
    }


def _stretch(n: int, m: int, seed: int = 0):  # type: ignore[no-untyped-def]
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n) * 1e-3
    u = 0.3 * torch.sin(2 * math.pi * 3.0 * t) + 0.05 * torch.randn(n, generator=g)
    q = 0.2 * torch.sin(2 * math.pi * 1.5 * t)
    qd = 0.2 * 2 * math.pi * 1.5 * torch.cos(2 * math.pi * 1.5 * t)
    y = torch.stack([q, qd], 1)
    return u, (y if m == 2 else y[:, :1] if m == 1 else y)


# The two axes are orthogonal: the friction model is in the propagator, the measurement in the
# update (H and R). Every model with both channels; position only (its own H, R and innovation
# shapes) on one static and one LuGre model, which also holds its third state.
CASES = [("both", name) for name in _models()] + [("position", "tanh"), ("position", "lugre tanh")]


@pytest.mark.parametrize(("measure", "name"), CASES, ids=[f"{m}-{n}" for m, n in CASES])
def test_native_filter_step_equals_eager(name: str, measure: str) -> None:
    model = _models()[name]
    k = model.num_parameters
    r = (1e-3,) if measure == "position" else (1e-3, 1e-2)
    tuning = EKFTuning(measure=measure, p0_theta=0.05, r=r)
    s = model.state_size  # 3 for a dynamic model: [q, q̇, z]
    Q, _, H, R = tuning.matrices(k, s)
    step = make_step(make_propagator(model, 2), compile=True)
    # 25 samples: an equality, sample by sample (the eager reference costs 0.1 s a sample)
    u, y = _stretch(26, H.shape[0])
    x0 = torch.cat([y[0, :1], torch.zeros(s - 1), model.get_theta()])
    p0_x = torch.tensor([1e-6, 1e-4, 1e-10][:s])
    P0 = torch.block_diag(torch.diag(p0_x), 0.05 * torch.eye(k))
    consts = (torch.tensor(1e-3), Q, H, R, torch.tensor(1e6))
    xs, valid = (u[:-1], y[1:]), torch.ones(25, dtype=torch.bool)
    (x_n, P_n), outs_n = step.chunk((x0, P0), xs, valid, consts)
    assert step.chunk.path == "native", step.chunk.why_not_native

    def one(x, P, u_, y_, *c):  # type: ignore[no-untyped-def]
        x1, P1, *d = step.eager(x, P, u_, y_, *c)
        return (x1, P1), tuple(d)

    (x_e, P_e), outs_e = _loop(one, (x0, P0), xs, valid, consts)
    torch.testing.assert_close(x_n, x_e, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(P_n, P_e, rtol=1e-9, atol=1e-15)
    for got, want in zip(outs_n, outs_e, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)
    assert bool(outs_n[3].all())


# ---------------------------------------------------------------------------------------------
# Ensembles: members in threads, each its own constants; a member that fails stays frozen
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("threads", ["1", "2"])
def test_native_ensemble_equals_the_batched_eager_step(threads: str, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setenv("TORCHFRIC_NATIVE_THREADS", threads)
    model = _models()["tanh"]
    k = model.num_parameters
    Q, _, H, R = EKFTuning(p0_theta=0.05).matrices(k)
    K = 5
    scales = torch.tensor([0.1, 1.0, 10.0, 1.0, 3.0])
    step = make_masked_step(model, 1, compile=True)
    u, y = _stretch(41, 2, seed=4)
    theta = model.get_theta().repeat(K, 1)
    theta[3, -1] += 0.5  # another start for member 3
    x0 = torch.cat([y[0].expand(K, 2), theta], 1)
    P0 = torch.block_diag(torch.zeros(2, 2), 0.05 * torch.eye(k)).repeat(K, 1, 1)
    carry = (x0, P0, torch.ones(K, dtype=torch.bool), torch.full((K,), -1),
             torch.zeros(K, 2), torch.zeros(K), torch.zeros(K))  # fmt: skip
    bound = torch.tensor(1e6)
    consts = (torch.tensor(1e-3), Q * scales[:, None, None], H, R * scales[:, None, None], bound)
    xs = (torch.arange(1, 41), u[:-1], y[1:].clone())
    valid = torch.ones(40, dtype=torch.bool)
    valid[-3:] = False  # padding at the end of the chunk
    got, _ = step.chunk(carry, xs, valid, consts)
    assert step.chunk.path == "native", step.chunk.why_not_native
    want = carry
    for i in range(37):
        want = step.eager(*want, xs[0][i], xs[1][i], xs[2][i], *consts)
    for a, b in zip(got, want, strict=True):
        if a.dtype == torch.float64:
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
        else:
            assert torch.equal(a, b)
    assert bool(got[2].all())


def test_native_ensemble_freezes_a_failing_member_like_eager() -> None:
    model = _models()["tanh"]
    k = model.num_parameters
    Q, _, H, R = EKFTuning(p0_theta=0.05).matrices(k)
    K = 3
    step = make_masked_step(model, 1, compile=True)
    u, y = _stretch(31, 2, seed=1)
    x0 = torch.cat([torch.zeros(K, 2), model.get_theta().repeat(K, 1)], 1)
    P0 = torch.block_diag(torch.zeros(2, 2), 0.05 * torch.eye(k)).repeat(K, 1, 1)
    carry = (x0, P0, torch.ones(K, dtype=torch.bool), torch.full((K,), -1),
             torch.zeros(K, 2), torch.zeros(K), torch.zeros(K))  # fmt: skip
    # member 1's R is negative: S is not positive definite at the first update
    r = torch.tensor([1.0, -1e6, 1.0])
    consts = (torch.tensor(1e-3), Q.repeat(K, 1, 1), H, R * r[:, None, None], torch.tensor(1e6))
    xs, valid = (torch.arange(1, 31), u[:-1], y[1:]), torch.ones(30, dtype=torch.bool)
    got, _ = step.chunk(carry, xs, valid, consts)
    assert step.chunk.path == "native"
    want = carry
    for i in range(30):
        want = step.eager(*want, xs[0][i], xs[1][i], xs[2][i], *consts)
    assert got[2].tolist() == want[2].tolist() == [True, False, True]
    assert got[3].tolist() == want[3].tolist() == [-1, 1, -1]
    torch.testing.assert_close(got[0], want[0], rtol=1e-9, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Fallbacks and the cache
# ---------------------------------------------------------------------------------------------
def test_untranslatable_function_falls_back_to_inductor_with_the_reason() -> None:
    def fn(x, c):  # type: ignore[no-untyped-def]
        x1 = torch.special.erf(x) * c  # erf is not in the table
        return (x1,), (x1,)

    with pytest.raises(NativeUnavailable, match="erf"):
        make_native_chunk(fn)(
            (torch.ones(2),), (), torch.ones(3, dtype=torch.bool), (torch.tensor(0.5),)
        )
    chunk = make_chunk(fn, native=True)
    (x,), (xs,) = chunk((torch.ones(2),), (), torch.ones(3, dtype=torch.bool), (torch.tensor(0.5),))
    assert chunk.path in ("inductor", "eager") and "erf" in chunk.why_not_native[0]
    expect = torch.ones(2)
    for _ in range(3):
        expect = torch.special.erf(expect) * 0.5
    torch.testing.assert_close(x, expect, rtol=1e-14, atol=0)


def test_no_compiler_means_the_inductor_path(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setattr(native, "compiler", lambda: None)

    def fn(x, c):  # type: ignore[no-untyped-def]
        return (x * c,), ()

    chunk = make_chunk(fn, native=True)
    (x,), _ = chunk((torch.ones(2),), (), torch.ones(4, dtype=torch.bool), (torch.tensor(0.5),))
    assert chunk.path in ("inductor", "eager") and "compiler" in chunk.why_not_native[0]
    torch.testing.assert_close(x, torch.full((2,), 0.0625), rtol=0, atol=0)


def test_compiled_code_is_cached_on_disk_and_reused(monkeypatch, tmp_path) -> None:  # type: ignore[no-untyped-def]
    def fn(x, c):  # type: ignore[no-untyped-def]
        return (torch.tanh(x) + c,), ()

    args = ((torch.ones(3),), (), torch.ones(4, dtype=torch.bool), (torch.tensor(0.25),))
    (first,), _ = make_native_chunk(fn)(*args)
    libs = list(native.cache_dir().glob("step_*.so"))
    assert len(libs) == 1
    # A new process has nothing loaded: it must find the library without compiling.
    monkeypatch.setattr(native.cache, "_LOADED", {})

    def no_compiler(*a, **k):  # type: ignore[no-untyped-def]
        raise AssertionError("compiled again instead of loading the cached library")

    monkeypatch.setattr(native.cache.subprocess, "run", no_compiler)
    (again,), _ = make_native_chunk(fn)(*args)
    assert torch.equal(first, again)
    assert list(native.cache_dir().glob("step_*.so")) == libs
    assert not list(native.cache_dir().glob("tmp*")), "a build folder was left behind"


def test_default_chunk_size_is_served_natively() -> None:
    """`make_step(compile=True)` with the default chunk (what `torchfric train` runs)."""
    model = _models()["tanh"]
    Q, _, H, R = EKFTuning().matrices(model.num_parameters)
    step = make_step(make_propagator(model, 1), compile=True)
    assert step.size == CHUNK
    u, y = _stretch(CHUNK + 1, 2)
    x0 = torch.cat([torch.zeros(2), model.get_theta()])
    P0 = torch.block_diag(torch.zeros(2, 2), torch.eye(model.num_parameters))
    step.chunk((x0, P0), (u[:-1], y[1:]), torch.ones(CHUNK, dtype=torch.bool),
               (torch.tensor(1e-3), Q, H, R, torch.tensor(1e6)))  # fmt: skip
    assert step.chunk.path == "native"


def test_members_with_per_sample_outputs_stack_them_as_the_scan_does() -> None:
    """Member mode with per-sample outputs (the SIMD program, stored lane by lane; K = 3 leaves
    one lane of the vector unused): the outputs are stacked `(C, K, ...)` as the scan of the
    batched function stacks them, each member's equal to its own loop."""

    def fn(x, u, a):  # type: ignore[no-untyped-def]
        x1 = torch.tanh(a * x) + u
        return (x1,), (x1.sum(-1),)

    K, C = 3, 6
    carry = (torch.arange(K * 2.0).reshape(K, 2),)
    xs, valid = (torch.linspace(0, 1, C),), torch.ones(C, dtype=torch.bool)
    a = torch.tensor([0.5, 1.0, 2.0]).reshape(K, 1)
    (x,), (s,) = make_native_chunk(fn, members=True, member_consts=(True,))(carry, xs, valid, (a,))
    assert s.shape == (C, K)
    for m in range(K):
        (x_e,), (s_e,) = _loop(fn, (carry[0][m : m + 1],), xs, valid, (a[m : m + 1],))
        torch.testing.assert_close(x[m : m + 1], x_e, rtol=1e-15, atol=0)
        torch.testing.assert_close(s[:, m], s_e[:, 0], rtol=1e-15, atol=0)


def test_a_step_above_the_size_ceiling_takes_the_inductor_path(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """gcc's time grows faster than the code; past `_MAX_STATEMENTS` the scan is Inductor's."""
    monkeypatch.setattr(native.emit, "_MAX_STATEMENTS", 5)

    def fn(x, c):  # type: ignore[no-untyped-def]
        x1 = torch.tanh(x * c + 1.0) * c
        return (x1,), ()

    chunk = make_chunk(fn, native=True)
    (x,), _ = chunk((torch.ones(3),), (), torch.ones(2, dtype=torch.bool), (torch.tensor(0.5),))
    assert chunk.path in ("inductor", "eager") and "scalar operations" in chunk.why_not_native[0]
    expect = torch.tanh(torch.tanh(torch.ones(3) * 0.5 + 1.0) * 0.5 * 0.5 + 1.0) * 0.5
    torch.testing.assert_close(x, expect, rtol=1e-15, atol=0)


def test_tensors_off_the_cpu_are_refused_before_any_pointer_is_taken() -> None:
    """Generated C reads raw CPU pointers: a tensor elsewhere (here the meta device, where a GPU
    would be) must send the chunk to the torch paths, never into the library."""

    def fn(x, c):  # type: ignore[no-untyped-def]
        return (x * c,), ()

    meta = torch.ones(2, device="meta")
    with pytest.raises(NativeUnavailable, match="runs on the CPU"):
        make_native_chunk(fn)((meta,), (), torch.ones(3, dtype=torch.bool), (torch.tensor(0.5),))


def test_a_compiler_that_rejects_the_fast_flags_gets_the_portable_ones(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """-march=native is not accepted everywhere: the build retries without it, and a compiler
    that fails on both says why (and the chunk falls back)."""
    monkeypatch.setattr(
        native.cache, "_FLAGS", [*native.cache._PORTABLE_FLAGS, "-fno-such-flag-here"]
    )

    def fn(x, c):  # type: ignore[no-untyped-def]
        return (torch.sin(x) * c,), ()

    args = ((torch.ones(2),), (), torch.ones(3, dtype=torch.bool), (torch.tensor(0.5),))
    (x,), _ = make_native_chunk(fn)(*args)
    expect = torch.ones(2)
    for _ in range(3):
        expect = torch.sin(expect) * 0.5
    torch.testing.assert_close(x, expect, rtol=1e-15, atol=0)
    monkeypatch.setattr(native.cache, "_PORTABLE_FLAGS", native.cache._FLAGS)
    monkeypatch.setattr(native.cache, "_LOADED", {})

    def other(x, c):  # type: ignore[no-untyped-def]
        return (torch.cos(x) * c,), ()

    with pytest.raises(NativeUnavailable, match="C compiler failed: .*no-such-flag"):
        make_native_chunk(other)(*args)


# ---------------------------------------------------------------------------------------------
# The filter with θ held: the augmented filter's state block, bit for bit
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["tanh", "lugre tanh"])
def test_fixed_theta_step_is_the_augmented_step_with_theta_held(name: str) -> None:
    """`make_fixed_theta_step` carries only the states' block of P; the augmented step with
    P_θθ = 0 and no process noise on θ carries zeros in the rest. Both as generated C, two
    members with their own θ, Q and R: every output equal to the last bit."""
    model = _models()[name]
    k, s, K = model.num_parameters, model.state_size, 2
    tuning = EKFTuning(measure="position", r=(1e-3,), q_theta=0.0)
    Q, P0_xx, H, R = tuning.matrices(k, s)
    scales = torch.tensor([1.0, 10.0])
    u, y = _stretch(61, 1, seed=3)
    theta = model.get_theta().repeat(K, 1)
    theta[1] *= 1.01
    x0 = torch.cat([y[0, :1], torch.zeros(s - 1)]).expand(K, s)
    p0_x = torch.diag(torch.tensor([1e-6, 1e-4, 1e-10][:s])).expand(K, s, s)
    xs, valid = (u[:-1], y[1:]), torch.ones(60, dtype=torch.bool)
    dt, bound = torch.tensor(1e-3), torch.tensor(1e300)
    Qk, Rk = Q * scales[:, None, None], R * scales[:, None, None]

    augmented = make_batched_step(model, 2)
    full = compile_step(augmented, carry=2, members=True, key=step_key("test aug", augmented.key),
                        member_consts=(False, True, False, True, False))  # fmt: skip
    P0 = torch.zeros(K, s + k, s + k)
    P0[:, :s, :s] = p0_x
    (x_a, P_a), outs_a = full.chunk((torch.cat([x0, theta], 1), P0), xs, valid, (dt, Qk, H, Rk, bound))

    fixed = make_fixed_theta_step(model, 2)
    held = compile_step(fixed, carry=2, members=True, key=step_key("test fixed", fixed.key),
                        member_consts=(False, True, True, False, True, False))  # fmt: skip
    consts = (dt, theta, Qk[:, :s, :s].contiguous(), H[:, :s].contiguous(), Rk, bound)
    (x_f, P_f), outs_f = held.chunk((x0.contiguous(), p0_x.contiguous()), xs, valid, consts)
    assert held.chunk.path == "native", held.chunk.why_not_native
    assert torch.equal(x_f, x_a[:, :s]) and torch.equal(x_a[:, s:], theta)
    assert torch.equal(P_f, P_a[:, :s, :s]) and not P_a[:, s:].any() and not P_a[:, :, s:].any()
    for got, want in zip(outs_f, outs_a, strict=True):
        assert torch.equal(got, want)
    assert bool(outs_f[3].all())
