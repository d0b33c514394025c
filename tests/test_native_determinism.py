"""Repeatability with the generated-C path on: the same inputs give bit-identical results,
call after call, whatever the allocator's blocks held before.

The pre-fit once returned another θ every few calls in one process (and across processes),
with the native path on: its linear skeleton's `torch.linalg.lstsq` used the default "gelsy"
driver, whose pivot array torch hands to LAPACK uninitialised (pytorch#71222). The native
path's allocations changed what that block held; the Levenberg–Marquardt refinement then
amplified the last-bit difference of the skeleton into another θ. The generated code itself
is checked here too: its rows equal the eager ones to rounding and are bit-identical call after
call, for member counts that do and do not fill the SIMD lanes.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchfric import ArmModel, make_experiment, make_friction, prefit
from torchfric.accel import native
from torchfric.data.rig import rig_experiment
from torchfric.estimators.ensemble import EnsembleSpec, identify_ekf_ensemble, make_masked_step
from torchfric.estimators.identify import EKFTuning
from torchfric.estimators.metrics import window_initial_state
from torchfric.models.friction import OddTanhFriction

pytestmark = pytest.mark.skipif(native.compiler() is None, reason="no C compiler here")


@pytest.fixture(scope="module")
def identification():
    d = rig_experiment("identification")
    return make_experiment(d["t"], d["u"], d["q"], name="identification")


def _dirty_heap(seed: int) -> None:
    """Leave small freed blocks holding nonzero integers, as other code running in between
    (the native path's own allocations, say) may: an uninitialised read then sees them."""
    for n in range(1, 17):
        for fill in (seed + 1, -(seed + 7), 1 << (seed % 30)):
            block = torch.full((n,), fill, dtype=torch.int32)
            del block


def _bits(t: torch.Tensor) -> list[str]:
    return [float.hex(float(v)) for v in t.flatten().tolist()]


@pytest.mark.parametrize("terms", [{}, {"offset": 0.0, "gravity": 0.01, "asymmetric": 0.0}])
def test_linear_skeleton_does_not_depend_on_the_allocators_history(
    identification, terms: dict
) -> None:
    from torchfric.estimators.prefit import _linear_skeleton, _regression_data

    arm = ArmModel(make_friction("tanh", 3), c_m=16.0, **terms)
    q, v, a, u = _regression_data([identification], 50.0, 0.02)
    first = None
    for seed in range(12):
        _dirty_heap(seed)
        got = {k: float.hex(x) for k, x in _linear_skeleton(arm, q, v, a, u).items()}
        first = first or got
        assert got == first, f"after dirty blocks #{seed}"


def test_window_initial_state_does_not_depend_on_the_allocators_history() -> None:
    q = torch.sin(torch.linspace(0.0, 1.0, 20)) + 1e-7 * torch.arange(20.0) ** 2
    first = None
    for seed in range(12):
        _dirty_heap(seed)
        got = _bits(window_initial_state(q, 1e-3, 20))
        first = first or got
        assert got == first


@pytest.mark.parametrize("kind", ["tanh", "polytopic"])
def test_prefit_repeated_is_bit_identical_with_the_native_rows(
    identification, kind: str, native_cache, monkeypatch
) -> None:
    import importlib

    prefit_module = importlib.import_module("torchfric.estimators.prefit")
    monkeypatch.setattr(prefit_module, "_ROW_CHUNKS", {})  # built here, in this test's cache
    rows: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
    real = prefit_module._native_rows

    def watched(model, sample_residual, x, u, a, jacobian, residuals):  # type: ignore[no-untyped-def]
        jac, res = real(model, sample_residual, x, u, a, jacobian, residuals)

        def check(native_fn, eager_fn):  # type: ignore[no-untyped-def]
            def evaluate(theta):  # type: ignore[no-untyped-def]
                got, again = native_fn(theta), native_fn(theta.clone())
                assert torch.equal(got, again), "the generated rows changed between two calls"
                if len(rows) < 24:  # the eager rows cost more than the whole native pre-fit
                    # copies: the LM updates its residuals in place
                    rows.append((theta.clone(), got.clone(), eager_fn(theta)))
                return got

            return evaluate

        return check(jac, jacobian), check(res, residuals)

    monkeypatch.setattr(prefit_module, "_native_rows", watched)
    arm = ArmModel(make_friction(kind, 3), c_m=16.0)
    thetas = []
    for seed in range(5):
        _dirty_heap(seed)
        thetas.append(_bits(prefit(arm, identification).model.get_theta()))
    assert all(t == thetas[0] for t in thetas), "the pre-fit's θ changed from call to call"
    assert rows and all(math.isfinite(float(got.abs().max())) for _, got, _ in rows)
    # the generated rows against the eager `vmap` forms: normwise per row, to rounding
    for theta, got, want in rows:
        err = (got - want).flatten(1).norm(dim=1) / want.flatten(1).norm(dim=1).clamp_min(1e-300)
        assert float(err.max()) <= 1e-12, f"K = {theta.shape[0]}: {float(err.max()):.3g}"
    assert next(iter(prefit_module._ROW_CHUNKS.values()))[1].native  # the native chunks served


def _ensemble_chunk_inputs(K: int, n: int = 41):  # type: ignore[no-untyped-def]
    model = ArmModel(
        OddTanhFriction(3, w1=[0.4, 6.0, 40.0], w2=[0.05, 0.04, 0.12]),
        inertia=0.035, viscous=0.012, c_m=16.0,
    )  # fmt: skip
    k = model.num_parameters
    Q, _, H, R = EKFTuning(p0_theta=0.05).matrices(k)
    g = torch.Generator().manual_seed(K)
    t = torch.arange(n) * 1e-3
    u = 0.3 * torch.sin(2 * math.pi * 3.0 * t) + 0.05 * torch.randn(n, generator=g)
    y = torch.stack([0.2 * torch.sin(2 * math.pi * 1.5 * t),
                     0.6 * math.pi * torch.cos(2 * math.pi * 1.5 * t)], 1)  # fmt: skip
    theta = model.get_theta().repeat(K, 1) * (1.0 + 0.1 * torch.rand(K, k, generator=g))
    x0 = torch.cat([y[0].expand(K, 2), theta], 1)
    P0 = torch.block_diag(torch.zeros(2, 2), 0.05 * torch.eye(k)).repeat(K, 1, 1)
    carry = (x0, P0, torch.ones(K, dtype=torch.bool), torch.full((K,), -1),
             torch.zeros(K, 2), torch.zeros(K), torch.zeros(K))  # fmt: skip
    scales = torch.logspace(-1, 1, K)
    consts = (torch.tensor(1e-3), Q * scales[:, None, None], H, R * scales[:, None, None],
              torch.tensor(1e6))  # fmt: skip
    xs = (torch.arange(1, n), u[:-1], y[1:].clone())
    valid = torch.ones(n - 1, dtype=torch.bool)
    valid[-3:] = False  # padding at the end of the chunk
    return model, carry, xs, valid, consts


@pytest.mark.parametrize("K", [1, 5, 7, 8])
@pytest.mark.parametrize("threads", ["1", "2"])
def test_ensemble_chunk_repeated_is_bit_identical_and_equals_eager(
    K: int, threads: str, worker_cache, monkeypatch
) -> None:
    """Member counts that do not fill the last SIMD vector (lanes: 4) included: each member's
    result, in whichever lane and thread, is bit-identical call after call and equals the eager
    step to rounding. (Every K shares one library: built once per worker, `worker_cache`.)"""
    monkeypatch.setenv("TORCHFRIC_NATIVE_THREADS", threads)
    model, carry, xs, valid, consts = _ensemble_chunk_inputs(K)
    step = make_masked_step(model, 1, compile=True)
    runs = []
    for seed in range(5):
        _dirty_heap(seed)
        got, _ = step.chunk(carry, xs, valid, consts)
        assert step.chunk.path == "native", step.chunk.why_not_native
        runs.append(got)
    for got in runs[1:]:
        for a, b in zip(got, runs[0], strict=True):
            assert torch.equal(a, b) or (a.dtype.is_floating_point and _bits(a) == _bits(b))
    want = carry
    for i in range(int(valid.sum())):
        want = step.eager(*want, xs[0][i], xs[1][i], xs[2][i], *consts)
    for a, b in zip(runs[0], want, strict=True):
        if a.dtype == torch.float64:
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12 * float(b.abs().max()))
        else:
            assert torch.equal(a, b)
    # each member alone gives what it gives in the batch, in whichever lane it sat
    for m in range(K):
        alone_carry = tuple(c[m : m + 1] for c in carry)
        alone_consts = (consts[0], consts[1][m : m + 1], consts[2], consts[3][m : m + 1], consts[4])
        alone, _ = step.chunk(alone_carry, xs, valid, alone_consts)
        for a, b in zip(alone, runs[0], strict=True):
            assert torch.equal(a[0], b[m]) or _bits(a[0]) == _bits(b[m])


def test_ensemble_identification_repeated_is_bit_identical(identification, worker_cache) -> None:
    """Five members (not a multiple of the lane width): the whole ensemble, pass loop and
    selection included, gives bit-identical θ run after run."""
    data = make_experiment(
        identification.t[:1500], identification.u[:1500], identification.q[:1500], name="short"
    ).with_velocity()
    model = ArmModel(make_friction("tanh", 3), c_m=16.0)
    runs = []
    for seed in range(5):
        _dirty_heap(seed)
        out = identify_ekf_ensemble(
            model, data, EKFTuning(passes=2), EnsembleSpec(members=5, seed=3)
        )
        runs.append((out.best, _bits(out.thetas), _bits(out.P_thetas)))
    assert all(r == runs[0] for r in runs[1:])
