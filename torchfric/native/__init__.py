"""Native code for the filter's per-sample loop, generated from its traced autograd graph.

The EKF step on a 10-state model is a few thousand floating-point operations on matrices of
2–20 entries. Run through torch, each of those operations, or each fused kernel of a compiled
graph, carries a per-call cost far above its arithmetic, and that cost, not the arithmetic, was
the filter's speed limit. This module removes it without giving up autograd:

1. **Trace.** The step (with its `torch.func` Jacobians) is traced once by
   `torch.fx.experimental.proxy_tensor.make_fx` into a graph of ATen operations with the shapes
   of one sample.
2. **Scalarise** (`scalar`, `aten`). The graph is evaluated on arrays of *symbols* (`numpy`
   object arrays holding `_Sym` nodes), so views, broadcasts, reductions and products become a
   DAG of scalar operations. Equal sub-expressions are shared (commutative ones whatever their
   operand order); products with the constants 0 and 1 (identity blocks, padding, and the
   entries of Q, H, R that are exactly 0 or 1, `_structure`) are folded.
3. **Emit and compile** (`emit`). The DAG becomes one straight-line C function body inside a
   loop over the chunk's samples; for ensembles, four members per SIMD vector and the members
   split across threads. It is compiled once with the system C compiler into a shared library
   kept in a cache folder keyed by the source's hash, so later processes only re-trace.

The arithmetic is the traced graph's, operation by operation, in IEEE double precision (no
fast-math): results agree with the eager step to rounding. `make_native_chunk` has the calling
convention of `torchfric.ekf.make_chunk`; anything it cannot translate (an operation outside its
table, no C compiler, tensors off the CPU, a step too large to compile quickly) raises
`NativeUnavailable` and the caller falls back to the next path.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .emit import _source
from .scalar import NativeUnavailable

__all__ = ["NativeUnavailable", "make_native_chunk", "cache_dir", "compiler"]


def cache_dir() -> Path:
    """Where compiled libraries are kept: ``$TORCHFRIC_CACHE`` or ``~/.cache/torchfric/native``."""
    env = os.environ.get("TORCHFRIC_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "torchfric" / "native"


def compiler() -> str | None:
    """The C compiler used (``$CC``, else cc/gcc/clang on the PATH), or None."""
    import shutil

    for name in [os.environ.get("CC"), "cc", "gcc", "clang"]:
        if name and shutil.which(name):
            return name
    return None


# -march=native: 1.6x faster than the generic target on the step (tanh(3)); no fast-math and no
# contraction into FMAs, so the arithmetic stays the traced graph's, operation by operation.
# A compiler that rejects a flag of the first set (-march=native on some ARM toolchains) gets
# the second.
_FLAGS = ["-O2", "-march=native", "-fno-fast-math", "-ffp-contract=off", "-fPIC", "-shared"]
_PORTABLE_FLAGS = ["-O2", "-fno-fast-math", "-ffp-contract=off", "-fPIC", "-shared"]
_LOADED: dict[str, ctypes.CDLL] = {}
_LOCK = threading.Lock()


@functools.cache
def _cpu() -> str:
    """The processor's identity (-march=native code must not move to another CPU model)."""
    import platform

    try:
        info = Path("/proc/cpuinfo").read_text()
        return next(
            (ln for ln in info.splitlines() if ln.startswith(("flags", "Features"))), info[:500]
        )
    except OSError:
        return platform.processor() + platform.machine()


def _build(source: str) -> ctypes.CDLL:
    """Compile `source` once (cached on disk by the hash of source, flags, compiler and CPU)
    and load it: with `_FLAGS`, or `_PORTABLE_FLAGS` where the compiler rejects those."""
    cc = compiler()
    if cc is None:
        raise NativeUnavailable("no C compiler found (set CC)")
    errors: list[str] = []
    for flags in (_FLAGS, _PORTABLE_FLAGS):
        ident = " ".join([*flags, cc, sys.platform, _cpu()])
        key = hashlib.sha256((source + ident).encode()).hexdigest()[:24]
        with _LOCK:
            if key not in _LOADED:
                lib = cache_dir() / f"step_{key}.so"
                if not lib.exists():
                    failure = _compile(cc, flags, source, lib)
                    if failure:
                        errors.append(failure)
                        continue
                handle = ctypes.CDLL(str(lib))
                handle.torchfric_chunk.argtypes = [
                    *[ctypes.c_int64] * 4,
                    ctypes.POINTER(ctypes.c_void_p),
                ]
                handle.torchfric_chunk.restype = None
                _LOADED[key] = handle
            return _LOADED[key]
    raise NativeUnavailable(f"C compiler failed: {errors[-1]}")


def _compile(cc: str, flags: list[str], source: str, lib: Path) -> str | None:
    """Build `source` into `lib` (atomically: other processes see all of it or nothing); the
    compiler's complaint when it fails."""
    folder = lib.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=folder) as tmp:
            src = Path(tmp) / "step.c"
            src.write_text(source)
            out = Path(tmp) / "step.so"
            run = subprocess.run([cc, *flags, str(src), "-o", str(out), "-lm"],
                                 capture_output=True, text=True)  # fmt: skip
            if run.returncode != 0:
                return run.stderr.strip()[:300] or f"{cc} exited with {run.returncode}"
            os.replace(out, lib)
    except OSError as exc:
        raise NativeUnavailable(f"cannot build in {folder}: {exc}") from exc
    return None


def _structure(k: Tensor, batched: bool) -> dict[int, float]:
    """The entries of const `k` that are exactly 0 or 1 (for every member when `batched`):
    compiled in as constants, so the products they take part in fold away (H = [I 0] and the
    paper's Q = diag(0, q, 0, …) are almost all zeros and ones). They are part of the compiled
    code's key: a const with another pattern gets code of its own."""
    if k.dtype != torch.float64 or k.numel() > 4096:
        return {}
    # numpy: this runs on every chunk call, and torch's per-operation cost was 10 % of a
    # 1000-sample chunk of the single filter
    a = k.detach().numpy()
    flat = a.reshape(a.shape[0], -1) if batched else a.reshape(1, -1)
    out: dict[int, float] = {}
    for value in (0.0, 1.0):
        out.update(dict.fromkeys(np.flatnonzero((flat == value).all(0)).tolist(), value))
    return out


def _threads(members: int) -> int:
    """Threads for `members` independent filters: one per core this process may use (members
    never share data, so the result does not depend on the count), or
    ``$TORCHFRIC_NATIVE_THREADS``. Independent of torch's own thread pool, which the CLI keeps
    at one for its tiny tensors."""
    env = os.environ.get("TORCHFRIC_NATIVE_THREADS")
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(members, int(env) if env else cores))


def make_native_chunk(
    fn: Callable, *, members: bool = False, member_consts: Sequence[bool] = ()
) -> Callable:
    """`torchfric.ekf.make_chunk`'s ``chunk(carry, xs, valid, consts) -> (carry, outs)`` as
    generated C (see the module docstring), built on the first call for that call's shapes.

    With `members`, every carry tensor and each const flagged in `member_consts` has a leading
    member axis K; `fn` is traced for one member (that axis kept at size 1) and the members run
    independently, split across the cores (`_threads`). Per-sample outputs then have shape
    ``(C, K, ...)``, as the scan of the batched function gives them. Raises
    `NativeUnavailable` (before touching anything) when the function cannot be translated.
    """
    built: dict[tuple, tuple[ctypes.CDLL, list, list, int]] = {}
    failed: dict[tuple, NativeUnavailable] = {}

    def chunk(carry, xs, valid, consts):  # type: ignore[no-untyped-def]
        carry, xs, consts = tuple(carry), tuple(xs), tuple(consts)
        off_cpu = {str(t.device) for t in (*carry, *xs, *consts, valid) if t.device.type != "cpu"}
        if off_cpu:
            raise NativeUnavailable(
                f"tensors on {sorted(off_cpu)}: the generated code runs on the CPU"
            )
        flags = tuple(member_consts) + (False,) * (len(consts) - len(member_consts))
        K = carry[0].shape[0] if members else 1
        C = valid.shape[0]
        fixed = [_structure(k, members and f) for k, f in zip(consts, flags, strict=True)]
        # one member's shapes: ensembles of any size share the code (and the trace)
        per_member = [c.shape[1:] if members else c.shape for c in carry]
        per_member += [x.shape[1:] for x in xs]
        per_member += [
            k.shape[1:] if members and f else k.shape for k, f in zip(consts, flags, strict=True)
        ]
        key = (tuple(per_member), tuple(t.dtype for t in (*carry, *xs, *consts)),
               tuple(tuple(sorted(f.items())) for f in fixed))  # fmt: skip
        if key in failed:  # this shape was tried: the same reason, without tracing again
            raise failed[key]
        if key not in built:
            if compiler() is None:
                raise NativeUnavailable("no C compiler found (set CC)")
            one_c = [c[:1] if members else c for c in carry]
            one_k = [k[:1] if (members and f) else k for k, f in zip(consts, flags, strict=True)]
            try:
                src, shapes, dtypes, lanes = _source(
                    fn, one_c, [x[0] for x in xs], one_k,
                    flags if members else (False,) * len(consts), fixed, members=members,
                )  # fmt: skip
                built[key] = (_build(src), shapes, dtypes, lanes)
            except NativeUnavailable as exc:
                failed[key] = exc
                raise
        lib, shapes, dtypes, lanes = built[key]
        new = [c.detach().clone().contiguous() for c in carry]
        ins = [x.detach().contiguous() for x in xs]
        ks = [k.detach().contiguous() for k in consts]
        v = valid.to(torch.uint8).contiguous()
        outs = [
            # stacked along the samples as the scan stacks them: (C, K, ...) for members
            # (traced with the member axis at size 1), (C, ...) otherwise
            torch.empty((C, K, *s[1:]) if members else (C, *s), dtype=d)
            for s, d in zip(shapes, dtypes, strict=True)
        ]
        ptrs = (ctypes.c_void_p * (len(new) + len(ins) + 1 + len(ks) + len(outs)))(
            *[t.data_ptr() for t in (*new, *ins, v, *ks, *outs)]
        )
        blocks = -(-K // lanes)  # groups of `lanes` members, split evenly across threads
        threads = _threads(blocks)
        if threads == 1:
            lib.torchfric_chunk(0, K, K, C, ptrs)
        else:
            bounds = [min(K, blocks * i // threads * lanes) for i in range(threads + 1)]
            workers = [threading.Thread(target=lib.torchfric_chunk, args=(a, b, K, C, ptrs))
                       for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]  # fmt: skip
            for w in workers:
                w.start()
            for w in workers:
                w.join()
        return tuple(new), tuple(outs)

    chunk.native = True  # type: ignore[attr-defined]
    return chunk
