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
   kept in a cache folder keyed by the source's hash. A step made with a structural `key`
   (all of torchfric's are) is also recorded under an *alias* of that key, so later processes
   load its library without tracing (`make_native_chunk`).

The arithmetic is the traced graph's, operation by operation, in IEEE double precision (no
fast-math): results agree with the eager step to rounding. `make_native_chunk` has the calling
convention of `torchfric.accel.make_chunk`; anything it cannot translate (an operation
outside its table, no C compiler, tensors off the CPU, a step too large to compile quickly)
raises `NativeUnavailable` and the caller falls back to the next path.

The compiled-code cache
-----------------------
Loading a shared library runs its code (its constructors run at ``dlopen``), so the cache is
treated as executable code and trusted only when nobody else could have written it. Where it
is (`cache_dir`), the permission rule, and the SHA-256 verification before every load are
described, and implemented, in `torchfric.accel.native.cache`.

* **Switches.** ``TORCHFRIC_NATIVE=0`` turns this path off (the chunk takes the Inductor/eager
  path and ``why_not_native`` says ``TORCHFRIC_NATIVE=0``); ``1``, empty or unset keep it on;
  any other value is a `torchfric.errors.TorchfricError`.
* **Notices.** The module prints nothing: it issues `NativeCacheWarning`, one line each, once
  per process and reason, attributed to the first caller outside torchfric. One when a cache
  folder or file is refused, or cannot be used or written (the run keeps the native path,
  built privately); one when the native path is lost for a reason of the environment (no C
  compiler, the compiler failing, not even the private folder writable: a full disk) and the
  run falls back to the much slower Inductor/eager path. Limits of the translation (an
  operation outside the table, a step above the size ceiling) and ``TORCHFRIC_NATIVE=0`` are
  not announced: ``why_not_native`` of `torchfric.accel.make_chunk`'s chunk has them.
"""

from __future__ import annotations

import ctypes
import operator
import os
import shutil
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from torch import Tensor

from ...environment import native_enabled
from .aliases import alias_key, find_alias, store_alias
from .cache import NativeCacheWarning, _build, _fallback, cache_dir
from .emit import _source
from .scalar import NativeUnavailable

__all__ = [
    "NativeCacheWarning",
    "NativeUnavailable",
    "make_native_chunk",
    "cache_dir",
    "compiler",
    "thread_count",
]


def compiler() -> str | None:
    """The C compiler used (``$CC``, else cc/gcc/clang on the PATH), or None."""
    for name in [os.environ.get("CC"), "cc", "gcc", "clang"]:
        if name and shutil.which(name):
            return name
    return None


def _require_compiler() -> str:
    """`compiler`, or the announced `NativeUnavailable` (`_fallback`) when there is none."""
    cc = compiler()
    if cc is None:
        raise _fallback("no-compiler", "no C compiler found (set CC)")
    return cc


def _enabled() -> bool:
    """``$TORCHFRIC_NATIVE`` (`torchfric.environment.native_enabled`: a bad value is a
    one-line `TorchfricError`)."""
    return native_enabled(os.environ.get("TORCHFRIC_NATIVE"))


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


def _cores() -> int:
    """The CPU cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def thread_count(members: int) -> int:
    """Threads for `members` independent filters: one per core this process may use (members
    never share data, so the result does not depend on the count), or
    ``$TORCHFRIC_NATIVE_THREADS``. Independent of torch's own thread pool, which the CLI keeps
    at one for its tiny tensors."""
    env = os.environ.get("TORCHFRIC_NATIVE_THREADS")
    return max(1, min(members, int(env) if env else _cores()))


class _Structures:
    """`_structure` of a call's consts, read again only when they change: a record's chunks
    pass the same consts, and reading their structure at every call was 5 % of a long run. The
    last consts are held (so their ids stay theirs) with their versions."""

    def __init__(self) -> None:
        self.last: tuple[tuple, tuple, list] | None = None

    def __call__(self, consts: tuple, batched: Sequence[bool]) -> list[dict[int, float]]:
        marks = tuple(k._version for k in consts)
        last = self.last
        if last is not None and last[1] == marks and all(map(operator.is_, last[0], consts)):
            return last[2]
        fixed = [_structure(k, b) for k, b in zip(consts, batched, strict=True)]
        self.last = (consts, marks, fixed)
        return fixed


# A call that takes less than this on one thread is not split: starting, joining and handing
# the GIL between threads costs about a tenth of a millisecond each, and the pre-fit's calls
# (0.5 ms of arithmetic, 160 of them) ran twice as long on two threads as on one.
_SPLIT_SECONDS = 2e-3
# Seconds per (group of members × sample) of each library, measured on one thread.
_UNIT_SECONDS: dict[ctypes.CDLL, float] = {}
# The threads a split call runs on, kept for the process: starting and joining a thread for
# each 1000-sample chunk cost 0.3 ms a call, a tenth of a 9-member ensemble's chunk.
_POOL: dict[int, ThreadPoolExecutor] = {}


def _pool(threads: int) -> ThreadPoolExecutor:
    """The process's pool of `threads` worker threads (made at its first use)."""
    if threads not in _POOL:
        _POOL[threads] = ThreadPoolExecutor(threads, thread_name_prefix="torchfric-native")
    return _POOL[threads]


# What one shape's translation gives: the loaded library, the per-sample outputs' shapes and
# dtypes (one member's), and the members per SIMD vector.
_Built = tuple[ctypes.CDLL, list, list, int]


def _require_cpu(tensors: Sequence[Tensor]) -> None:
    """`NativeUnavailable` when any of `tensors` is off the CPU (generated C reads raw CPU
    pointers), before any pointer is taken."""
    off_cpu = {str(t.device) for t in tensors if t.device.type != "cpu"}
    if off_cpu:
        raise NativeUnavailable(f"tensors on {sorted(off_cpu)}: the generated code runs on the CPU")


def _shape_key(
    carry: tuple, xs: tuple, consts: tuple, flags: tuple, fixed: list, members: bool,
    x_flags: tuple,
) -> tuple:  # fmt: skip
    """What the generated code depends on: one member's shapes (ensembles of any size share the
    code, and the trace), the dtypes, and the consts' 0/1 entries (`_structure`); which
    per-sample inputs are one per member (`x_flags`), when any is."""
    per_member = [c.shape[1:] if members else c.shape for c in carry]
    per_member += [x.shape[2:] if f else x.shape[1:] for x, f in zip(xs, x_flags, strict=True)]
    per_member += [
        k.shape[1:] if members and f else k.shape for k, f in zip(consts, flags, strict=True)
    ]
    key = (tuple(per_member), tuple(t.dtype for t in (*carry, *xs, *consts)),
           tuple(tuple(sorted(f.items())) for f in fixed))  # fmt: skip
    return (*key, tuple(x_flags)) if any(x_flags) else key


def _translate(
    fn: Callable,
    cc: str,
    carry: tuple,
    xs: tuple,
    consts: tuple,
    flags: tuple,
    fixed: list,
    members: bool,
    alias: str | None,
    x_flags: tuple,
) -> _Built:
    """Trace `fn` for one sample (and one member: the member axis kept at size 1, also on the
    per-member inputs `x_flags`), generate its C and build it with the C compiler `cc`
    (`_build`); recorded under `alias` when one is given. `NativeUnavailable` when it cannot be
    translated or built."""
    one_c = [c[:1] if members else c for c in carry]
    one_k = [k[:1] if (members and f) else k for k, f in zip(consts, flags, strict=True)]
    one_x = [x[0, :1] if f else x[0] for x, f in zip(xs, x_flags, strict=True)]
    src, shapes, dtypes, lanes = _source(
        fn, one_c, one_x, one_k,
        flags if members else (False,) * len(consts), fixed, members=members, member_xs=x_flags,
    )  # fmt: skip
    lib, library = _build(src, cc)
    if alias is not None:
        store_alias(alias, library, shapes, dtypes, lanes)
    return lib, shapes, dtypes, lanes


def _known(alias: str) -> _Built | None:
    """The library recorded under `alias` (`find_alias`), or None."""
    found = find_alias(alias)
    if found is None:
        return None
    lib, rec = found
    return (lib, [tuple(s) for s in rec["shapes"]],
            [getattr(torch, d) for d in rec["dtypes"]], rec["lanes"])  # fmt: skip


def _launch(lib: ctypes.CDLL, K: int, C: int, lanes: int, ptrs: ctypes.Array) -> None:
    """Run the library's chunk over `K` members and `C` samples: groups of `lanes` members,
    split evenly across `thread_count` threads; in this thread when there is one, or when the call
    is too short to gain from threads (`_SPLIT_SECONDS`, timed on this library's first call,
    unless ``$TORCHFRIC_NATIVE_THREADS`` sets the count)."""
    blocks = -(-K // lanes)  # groups of `lanes` members, split evenly across threads
    # one group (the single filter, a small ensemble) never splits: no thread count to look up
    # and no timing on this, the hottest call
    threads = 1 if blocks == 1 else thread_count(blocks)
    adaptive = threads > 1 and not os.environ.get("TORCHFRIC_NATIVE_THREADS")
    if adaptive:
        unit = _UNIT_SECONDS.get(lib)
        if unit is None or unit * blocks * C < _SPLIT_SECONDS:
            threads = 1
        t0 = time.perf_counter()
    if threads == 1:
        lib.torchfric_chunk(0, K, K, C, ptrs)
    else:
        bounds = [min(K, blocks * i // threads * lanes) for i in range(threads + 1)]
        pool = _pool(threads)
        parts = [pool.submit(lib.torchfric_chunk, a, b, K, C, ptrs)
                 for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]  # fmt: skip
        for part in parts:
            part.result()
    if adaptive:  # the one-thread cost (split: at most threads × the time), for the next choice
        _UNIT_SECONDS[lib] = (time.perf_counter() - t0) * threads / max(blocks * C, 1)


def _run(
    built: _Built,
    carry: tuple,
    xs: tuple,
    valid: Tensor,
    consts: tuple,
    K: int,
    C: int,
    members: bool,
) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
    """One chunk through the built library: the new carry (fresh tensors) and the per-sample
    outputs."""
    lib, shapes, dtypes, lanes = built
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
    _launch(lib, K, C, lanes, ptrs)
    return tuple(new), tuple(outs)


def make_native_chunk(
    fn: Callable,
    *,
    members: bool = False,
    member_consts: Sequence[bool] = (),
    member_xs: Sequence[bool] = (),
    key: str | None = None,
) -> Callable:
    """`torchfric.accel.make_chunk`'s ``chunk(carry, xs, valid, consts) -> (carry, outs)`` as
    generated C (see the module docstring), built on the first call for that call's shapes.

    With `members`, every carry tensor and each const flagged in `member_consts` has a leading
    member axis K; `fn` is traced for one member (that axis kept at size 1) and the members run
    independently, split across the cores (`thread_count`). Per-sample outputs then have shape
    ``(C, K, ...)``, as the scan of the batched function gives them; so do the per-sample
    inputs flagged in `member_xs` (one per member: a batch of simulations, each under its own
    input), which the others are not. Raises
    `NativeUnavailable` (before touching anything) when the function cannot be translated,
    or with the reason "TORCHFRIC_NATIVE=0" when that switch is set (read at every call);
    `torchfric.errors.TorchfricError`, here already, when ``$TORCHFRIC_NATIVE`` is neither
    0 nor 1.

    `key` describes everything `fn`'s code depends on besides its inputs' shapes, dtypes and
    0/1 structure (which are added): for torchfric's steps, the step's kind, the model's
    `torchfric.accel.structure_key` and settings such as the RK4 sub-steps. With it, a process
    finds the library an earlier one built without tracing `fn` (`aliases.find_alias`); without
    it, `fn` is traced in every process to find its library by the source's hash. The key must
    name everything: two functions with one key share one library.
    """
    _enabled()  # a bad value is the user's error: said when the step is made, not mid-run
    built: dict[tuple, _Built] = {}
    failed: dict[tuple, NativeUnavailable] = {}
    structures = _Structures()

    def chunk(carry, xs, valid, consts):  # type: ignore[no-untyped-def]
        if not _enabled():
            raise NativeUnavailable("TORCHFRIC_NATIVE=0")
        carry, xs, consts = tuple(carry), tuple(xs), tuple(consts)
        _require_cpu((*carry, *xs, *consts, valid))
        flags = tuple(member_consts) + (False,) * (len(consts) - len(member_consts))
        x_flags = tuple(member_xs) + (False,) * (len(xs) - len(member_xs))
        K = carry[0].shape[0] if members else 1
        C = valid.shape[0]
        if members and (
            any(x.shape[1] != K for x, f in zip(xs, x_flags, strict=True) if f)
            or any(k.shape[0] != K for k, f in zip(consts, flags, strict=True) if f)
        ):
            # the code reads each member's row: one missing would be read past the buffer
            raise NativeUnavailable(f"per-member inputs without the carry's {K} members")
        fixed = structures(consts, [members and f for f in flags])
        shape = _shape_key(carry, xs, consts, flags, fixed, members, x_flags)
        if shape in failed:  # this shape was tried: the same reason, without tracing again
            raise failed[shape]
        if shape not in built:
            cc = _require_compiler()  # not remembered in `failed`: checked again at the next call
            alias = None if key is None else alias_key(f"{key}\0{members}\0{shape!r}", cc)
            lib = None if alias is None else _known(alias)
            try:
                built[shape] = lib or _translate(
                    fn, cc, carry, xs, consts, flags, fixed, members, alias, x_flags
                )
            except NativeUnavailable as exc:
                failed[shape] = exc
                raise
        return _run(built[shape], carry, xs, valid, consts, K, C, members)

    chunk.native = True  # type: ignore[attr-defined]
    return chunk
