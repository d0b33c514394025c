"""The generated step on an NVIDIA GPU: the scalar program, one ensemble member per CUDA thread.

An ensemble's members never share data, so the scalar program that `emit` writes for the CPU
(one member at a time, the loop over the chunk's samples inside) runs unchanged as a CUDA
kernel whose threads are the members (a grid-stride loop over them). It is compiled at run
time by NVRTC (`torch.cuda._compile_kernel`, present in torch ≥ 2.8) without fused
multiply-adds, so each operation rounds as the CPU's generated C (built with
``-ffp-contract=off``) rounds it; the maths functions (tanh, exp, …) are CUDA's, which may
differ from the C library's in the last bit. One kernel launch runs a whole chunk of samples.

The carry stays on the device from chunk to chunk (the caller moves it back at the end of an
experiment); constants are copied to the device once and kept while the same tensor is passed.
A kernel is built once per process for each shape (one member's shapes, dtypes and the 0/1
structure of Q, H, R: `_structure`, as on the CPU). Anything that stops this path (no CUDA
device, no NVRTC, a step that cannot be translated) raises `NativeUnavailable`, and
`torchfric.accel.make_chunk` runs the chunk on the CPU instead, with a one-line notice.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from .cache import _warn_once
from .emit import _source
from .scalar import NativeUnavailable

__all__ = ["MEMBERS_PER_CORE", "gpu_worth_it", "make_cuda_chunk", "on_device"]

# Threads per block: members are independent and each thread's work is long and serial, so a
# small block spreads a few hundred members over many multiprocessors.
_BLOCK = 64
# One GPU thread filters a member at about 30–70 k steps/s (H200, tanh(3)); one CPU core runs
# 1.5–3 M filter-steps/s of the generated C: the GPU gains from about 50 members per CPU core
# on (benchmarks/device_speed.py, H200 against 16 cores: 0.28× at 100 members, 1.33× at 1000),
# so a smaller batch stays on the CPU.
MEMBERS_PER_CORE = 48


def gpu_worth_it(members: int) -> bool:
    """Whether `members` filters run faster on the GPU than on this process's CPU cores."""
    from . import _cores

    return members >= MEMBERS_PER_CORE * _cores()


def _kernel(fn: Callable, carry: tuple, xs: tuple, consts: tuple, flags: tuple, fixed: list):
    """Trace `fn` for one member (CPU tensors), emit its CUDA form and compile it with NVRTC."""
    compile_kernel = getattr(torch.cuda, "_compile_kernel", None)
    if compile_kernel is None:
        raise NativeUnavailable(f"torch {torch.__version__} has no NVRTC entry point")
    one_c = [c[:1] for c in carry]
    one_k = [k[:1] if f else k for k, f in zip(consts, flags, strict=True)]
    src, shapes, _, _ = _source(
        fn, one_c, [x[0] for x in xs], one_k, flags, fixed, members=True, target="cuda"
    )
    if shapes:
        raise NativeUnavailable("the GPU path runs steps without per-sample outputs")
    try:
        return compile_kernel(src, "torchfric_chunk", nvcc_options=["--fmad=false"])
    except Exception as exc:  # noqa: BLE001 - whatever NVRTC or the driver says stops this path
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise NativeUnavailable(f"NVRTC could not build the step: {first}") from exc


class _Resident:
    """Device copies of constant tensors, kept while the caller passes the same tensor (the
    ensemble's Q and R are one object for the whole run)."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.kept: list[tuple[Tensor, int, Tensor]] = []

    def __call__(self, t: Tensor) -> Tensor:
        if t.device == self.device:
            return t.contiguous()
        for src, version, copy in self.kept:
            if src is t and t._version == version:
                return copy
        copy = t.detach().to(self.device).contiguous()
        self.kept = [*self.kept[-15:], (t, t._version, copy)]
        return copy


def make_cuda_chunk(
    fn: Callable, *, member_consts: Sequence[bool] = (), device: torch.device
) -> Callable:
    """`torchfric.accel.make_chunk`'s ``chunk(carry, xs, valid, consts) -> (carry, ())`` for an
    ensemble's step (every carry tensor with the member axis K first; the consts flagged in
    `member_consts` too; no per-sample outputs), run on the CUDA `device`. The carry comes back
    on the device; inputs may be on the CPU or the device. Raises `NativeUnavailable` (before
    launching anything) when this path cannot run the step."""
    from . import _shape_key, _Structures

    built: dict[tuple, Callable] = {}
    failed: dict[tuple, NativeUnavailable] = {}
    resident = _Resident(device)
    structures = _Structures()

    def chunk(carry, xs, valid, consts):  # type: ignore[no-untyped-def]
        if not torch.cuda.is_available():
            raise NativeUnavailable("no CUDA device is available")
        carry, xs, consts = tuple(carry), tuple(xs), tuple(consts)
        flags = tuple(member_consts) + (False,) * (len(consts) - len(member_consts))
        K, C = carry[0].shape[0], valid.shape[0]
        # the 0/1 structure is read on the CPU (consts usually are there: `.cpu()` is then them)
        host = tuple(k if k.device.type == "cpu" else k.detach().cpu() for k in consts)
        fixed = structures(host, flags)
        shape = _shape_key(carry, xs, host, flags, fixed, True, (False,) * len(xs))
        if shape in failed:
            raise failed[shape]
        if shape not in built:
            try:
                cpu_carry = tuple(c.detach().cpu() for c in carry)
                cpu_xs = tuple(x.detach().cpu() for x in xs)
                built[shape] = _kernel(fn, cpu_carry, cpu_xs, host, flags, fixed)
            except NativeUnavailable as exc:
                failed[shape] = exc
                raise
        new = [c.detach().to(device, copy=True).contiguous() for c in carry]
        ins = [x.detach().to(device).contiguous() for x in xs]
        v = valid.to(device=device, dtype=torch.uint8).contiguous()
        ks = [resident(k) for k in consts]
        table = torch.tensor([t.data_ptr() for t in (*new, *ins, v, *ks)], dtype=torch.int64).to(
            device
        )
        with torch.cuda.device(device):
            built[shape](grid=(-(-K // _BLOCK), 1, 1), block=(_BLOCK, 1, 1),
                         args=[0, K, K, C, table])  # fmt: skip
        return tuple(new), ()

    chunk.native = True  # type: ignore[attr-defined]
    return chunk


def on_device(
    fn: Callable, member_consts: Sequence[bool], device: torch.device, on_cpu: Callable
) -> Callable:
    """`torchfric.accel.make_chunk` on a CUDA device: `make_cuda_chunk` for a batch large enough
    to gain there (`gpu_worth_it`), else `on_cpu` (the CPU's chunk, given the carry moved back);
    either choice of the CPU is announced once per process and reason (`NativeCacheWarning`).
    `.path` says which ran last ("cuda", or the CPU chunk's path)."""
    kernel = make_cuda_chunk(fn, member_consts=tuple(member_consts), device=device)
    reasons: list[str] = []

    def chunk(carry, xs, valid, consts):  # type: ignore[no-untyped-def]
        K = carry[0].shape[0]
        try:
            if not gpu_worth_it(K):
                raise NativeUnavailable(
                    f"{K} filters, fewer than {MEMBERS_PER_CORE} per CPU core, where the GPU "
                    "does not gain"
                )
            out = kernel(carry, xs, valid, consts)
            chunk.path = "cuda"  # type: ignore[attr-defined]
            return out
        except NativeUnavailable as exc:
            if str(exc) not in reasons:
                reasons.append(str(exc))
                _warn_once("device", str(exc), f"{device}: {exc}; the filters run on the CPU")
        out = on_cpu(tuple(c.cpu() for c in carry), xs, valid, consts)
        chunk.path = on_cpu.path  # type: ignore[attr-defined]
        return out

    chunk.path = None  # type: ignore[attr-defined]
    chunk.why_not_device = reasons  # type: ignore[attr-defined]
    return chunk
