"""Ensembles on a CUDA GPU (`--device cuda`, `torchfric.accel.native.cuda`).

Truth here is the CPU's generated step. Everywhere: the CUDA form of the step, compiled as C++
by the host compiler behind a small shim that plays one GPU thread, gives the CPU chunk's
results bit for bit (the kernel's text is the CPU program's statements); `--device` is refused
with one line, before anything is written, where torch sees no GPU. Where a GPU is present
(skipped elsewhere): an ensemble filtered there equals the CPU's to rounding, a diverging member
is named at the same sample, and a step the GPU path cannot build falls back to the CPU with one
notice and the same result.
"""

from __future__ import annotations

import ctypes
import math
import shutil
import subprocess
import sys
import warnings

import pytest
import torch
from rig_configs import rig_config
from test_ensemble import _data, _true

from torchfric.accel.native import NativeCacheWarning, _structure
from torchfric.accel.native.emit import _source
from torchfric.errors import TorchfricError
from torchfric.estimators.ensemble import identify_ekf_ensemble, make_masked_step
from torchfric.estimators.identify import EKFTuning
from torchfric.estimators.passes import initial_belief, measured_data

F64 = torch.float64
CUDA = torch.cuda.is_available()
needs_gpu = pytest.mark.skipif(not CUDA, reason="no CUDA device")
needs_cxx = pytest.mark.skipif(shutil.which("g++") is None, reason="no host C++ compiler (g++)")

# One GPU thread on the host: the kernel's grid-stride loop then walks every member. The
# kernel's own typedefs of int64_t and uint8_t are renamed so they do not meet the system's.
_SHIM = r"""
#include <cmath>
#include <cstring>
#include <cstdint>
#define __global__
#define int64_t tf_i64
#define uint8_t tf_u8
struct tf_dim3 { long long x; };
static tf_dim3 blockIdx = {0}, blockDim = {1}, gridDim = {1}, threadIdx = {0};
static inline double __longlong_as_double(long long v) { double d; std::memcpy(&d, &v, 8); return d; }
#undef NAN
#undef INFINITY
"""


def _chunk_inputs(K: int, C: int = 200):  # type: ignore[no-untyped-def]
    """A rig record's first chunk for K members of differing θ and R, its last samples padding."""
    true = _true()
    exp = _data(true, n=C + 1)
    theta0 = true.get_theta()
    thetas = torch.stack([theta0 * (1 + 0.01 * i) for i in range(K)])
    tuning = EKFTuning()
    Q, P0, H, R = tuning.matrices(theta0.numel(), 2)
    Qk = Q.expand(K, *Q.shape).clone()
    Rk = R.expand(K, *R.shape) * torch.arange(1, K + 1, dtype=F64)[:, None, None]
    ((_, u, y),) = measured_data([exp], "both")
    x, P = initial_belief(exp, thetas, tuning.initial_P_theta(true, thetas), P0)
    carry = (x, P, torch.ones(K, dtype=torch.bool), torch.full((K,), -1),
             torch.zeros(K, 2, dtype=F64), torch.zeros(K, dtype=F64), torch.zeros(K, dtype=F64))  # fmt: skip
    xs = (torch.arange(1, C + 1), u[:C], y[1 : C + 1])
    valid = torch.ones(C, dtype=torch.bool)
    valid[-7:] = False
    consts = (torch.tensor(exp.dt), Qk, H, Rk.contiguous(), torch.tensor(1e6))
    return true, carry, xs, valid, consts


@needs_cxx
def test_the_cuda_form_of_the_step_equals_the_cpu_chunk_bit_for_bit(tmp_path) -> None:  # type: ignore[no-untyped-def]
    K = 5
    true, carry, xs, valid, consts = _chunk_inputs(K)
    step = make_masked_step(true, 1, compile=True)
    ref, _ = step.chunk(carry, xs, valid, consts)
    assert step.chunk.path == "native"
    flags = (False, True, False, True, False)
    fixed = [_structure(k, f) for k, f in zip(consts, flags, strict=True)]

    def one(*args):  # type: ignore[no-untyped-def]
        out = step.eager(*args)
        return tuple(out[:7]), tuple(out[7:])

    src, shapes, _, _ = _source(
        one, [c[:1] for c in carry], [a[0] for a in xs],
        [k[:1] if f else k for k, f in zip(consts, flags, strict=True)], flags, fixed,
        members=True, target="cuda",
    )  # fmt: skip
    assert shapes == [] and "__global__ void torchfric_chunk" in src and "#include" not in src
    cpp, lib_path = tmp_path / "step.cpp", tmp_path / "step.so"
    cpp.write_text(_SHIM + src)
    subprocess.run(["g++", "-O1", "-ffp-contract=off", "-fPIC", "-shared", "-o", str(lib_path),
                    str(cpp)], check=True, capture_output=True)  # fmt: skip
    lib = ctypes.CDLL(str(lib_path))
    new = [c.clone().contiguous() for c in carry]
    tensors = (*new, *xs, valid.to(torch.uint8), *consts)
    table = (ctypes.c_void_p * len(tensors))(*[t.data_ptr() for t in tensors])
    lib.torchfric_chunk(ctypes.c_int(0), ctypes.c_int(K), ctypes.c_int(K), ctypes.c_int(200), table)
    for a, b in zip(new, ref, strict=True):
        assert torch.equal(a, b)
    assert not bool(torch.equal(new[0], carry[0]))  # the chunk did move the belief


def test_device_names_are_checked_before_a_run() -> None:
    from torchfric.app.run import device_named

    assert device_named(None) is None and device_named("cpu") is None
    with pytest.raises(TorchfricError, match="not a device"):
        device_named("gpu0")
    with pytest.raises(TorchfricError, match="only cpu and cuda"):
        device_named("meta")
    if not CUDA:
        with pytest.raises(TorchfricError, match="sees no CUDA GPU.*leave --device out"):
            device_named("cuda")
    else:
        assert device_named("cuda").type == "cuda"
        with pytest.raises(TorchfricError, match="CUDA device"):
            device_named(f"cuda:{torch.cuda.device_count()}")


@pytest.mark.skipif(CUDA, reason="checks the refusal where no GPU is seen")
def test_train_with_device_cuda_without_a_gpu_is_one_line_and_writes_nothing(tmp_path) -> None:  # type: ignore[no-untyped-def]

    cfg = rig_config(tmp_path, estimator={"ensemble": 9, "passes": 1})
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "torchfric", "train", str(cfg), "--out", str(out), "--device",
         "cuda"], capture_output=True, text=True, cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode != 0
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "sees no CUDA GPU" in lines[0] and "Traceback" not in proc.stderr
    assert not out.exists()


@pytest.fixture
def any_batch_on_the_gpu(monkeypatch):  # type: ignore[no-untyped-def]
    """The GPU path for batches of any size (a real run keeps small ones on the CPU)."""
    from torchfric.accel.native import cuda

    monkeypatch.setattr(cuda, "MEMBERS_PER_CORE", 0)


@pytest.mark.parametrize("small", [True, False])
def test_where_the_gpu_cannot_serve_the_cpu_does_with_one_notice(small, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A batch too small to gain on the GPU, or no GPU at all: the CPU's chunk, its result, and
    one notice naming why."""
    from torchfric.accel.native import cuda

    if not small:
        if CUDA:
            pytest.skip("needs a machine without a GPU")
        monkeypatch.setattr(cuda, "MEMBERS_PER_CORE", 0)
    true, carry, xs, valid, consts = _chunk_inputs(3)
    ref, _ = make_masked_step(true, 1, compile=True).chunk(carry, xs, valid, consts)
    step = make_masked_step(true, 1, compile=True, device=torch.device("cuda"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out, _ = step.chunk(carry, xs, valid, consts)
        step.chunk(carry, xs, valid, consts)
    notes = [str(w.message) for w in caught if issubclass(w.category, NativeCacheWarning)]
    why = "fewer than 48 per CPU core" if small else "no CUDA device"
    assert len(notes) == 1 and why in notes[0] and "run on the CPU" in notes[0]
    assert step.chunk.path == "native"
    for a, b in zip(out, ref, strict=True):
        assert torch.equal(a, b)


def _ensemble(device, n: int = 300, **kw):  # type: ignore[no-untyped-def]
    true = _true()
    exp = _data(true, n=n, start=kw.pop("start", 500))
    theta0 = true.get_theta()
    thetas = kw.pop("thetas", None)
    if thetas is None:
        thetas = torch.stack([theta0 * (1 + 0.02 * i) for i in range(6)])
    scales = torch.linspace(1.0, 10.0, thetas.shape[0], dtype=F64)
    tuning = EKFTuning(passes=2, tolerance=0.0, **kw)
    return identify_ekf_ensemble(true, exp, tuning, members=(thetas, scales, scales.flip(0)),
                                 device=device)  # fmt: skip


@needs_gpu
@pytest.mark.usefixtures("any_batch_on_the_gpu")
def test_an_ensemble_on_the_gpu_equals_the_cpu_one() -> None:
    cpu, gpu = _ensemble(None, n=2300), _ensemble(torch.device("cuda"), n=2300)
    assert [m.status for m in gpu.members] == [m.status for m in cpu.members]
    torch.testing.assert_close(gpu.thetas, cpu.thetas, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(gpu.P_thetas, cpu.P_thetas, rtol=1e-8, atol=1e-14)
    for a, b in zip(gpu.members, cpu.members, strict=True):
        assert a.loglik == pytest.approx(b.loglik, rel=1e-10)
    assert gpu.best == cpu.best


@needs_gpu
@pytest.mark.usefixtures("any_batch_on_the_gpu")
def test_a_member_diverging_on_the_gpu_is_named_at_the_cpus_sample() -> None:
    true = _true()
    theta0 = true.get_theta()
    bad = theta0.clone()
    bad[true.theta_names.index("inertia")] += math.log(1e-6)
    thetas = torch.stack([theta0, bad, theta0 * 1.1])
    kw = {"theta_bound": 50.0, "units": "absolute", "start": 0}
    cpu = _ensemble(None, thetas=thetas, **dict(kw))
    gpu = _ensemble(torch.device("cuda"), thetas=thetas, **dict(kw))
    assert [m.status for m in gpu.members] == [m.status for m in cpu.members]
    assert gpu.members[1].status == "diverged" and gpu.members[1].reason == cpu.members[1].reason


@needs_gpu
@pytest.mark.usefixtures("any_batch_on_the_gpu")
def test_without_nvrtc_the_gpu_run_falls_back_to_the_cpu_with_one_notice(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    def broken(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise RuntimeError("nvrtc: error: planted failure")

    monkeypatch.setattr(torch.cuda, "_compile_kernel", broken)
    cpu = _ensemble(None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gpu = _ensemble(torch.device("cuda"))
    notes = [w for w in caught if issubclass(w.category, NativeCacheWarning)]
    assert len(notes) == 1 and "planted failure" in str(notes[0].message)
    assert "run on the CPU" in str(notes[0].message)
    torch.testing.assert_close(gpu.thetas, cpu.thetas, rtol=0, atol=0)
