"""The chunk compiler: one sample's function run over many samples per compiled call.

Every compiled loop of torchfric — the EKF step, the ensemble's masked step, the rk4 simulation
and its adjoint — has the same shape: a per-sample function ``fn(*carry, *x, *consts) ->
(carry', outs)`` scanned along a leading sample axis. `make_chunk` turns such a function into
``chunk(carry, xs, valid, consts) -> (carry, outs)`` over `CHUNK` samples at a time, through
three paths, each the fallback of the one before, all with the same arithmetic:

1. **native**: generated C (`torchfric.accel.native.make_native_chunk`), the fastest;
2. **inductor**: `torch._higher_order_ops.scan` under `torch.compile` (Inductor, C++ wrapper);
3. **eager**: a Python loop over the samples.

`compile_with_fallback` is the compile-once-or-fall-back-to-eager wrapper under the last two;
`compile_step` bundles a per-sample step and its chunk into a `Step`; `iter_chunks` and
`run_chunks` feed a long sequence through a chunk, padding the last call. `structure_key` keys
the per-model caches of compiled code, so models that differ only in θ share them.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import inspect
import json
import os
import secrets
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

if TYPE_CHECKING:
    from ..models.arm import ArmModel

__all__ = [
    "CHUNK",
    "Step",
    "compile_step",
    "fused_matmul",
    "chunk_options",
    "make_chunk",
    "compile_with_fallback",
    "pad_rows",
    "iter_chunks",
    "run_chunks",
    "structure_key",
    "step_key",
    "product_name",
]

# Samples per compiled call of `Step.chunk`: large enough that the per-call cost (guards,
# argument handling) is spread thin, small enough that padding the last chunk of a pass costs
# little. One size for every data set, so a process compiles the chunk once per model.
CHUNK = 1000


def fused_matmul(A: Tensor, B: Tensor) -> Tensor:
    """``A @ B`` for the filter's small matrices, written as a broadcast product and a sum.

    Same product as `torch.matmul`; the form lets Inductor fuse it into the step's one C++
    kernel instead of calling BLAS per product (each call costs microseconds for 10 × 10)."""
    return (A.unsqueeze(-1) * B.unsqueeze(-3)).sum(-2)


class Step:
    """A per-sample step and, when compiled, a scan of it over `size` samples at a time.

    Calling a `Step` runs one sample through `fast` (the compiled step, or `eager`). For the
    EKF (`torchfric.estimators.ekf.make_step`): ``step(x, P, u_prev, y, dt, Q, H, R, bound) ->
    (x⁺, P⁺, e, nis, loglik, ok)``; `ok` is the `healthy` flag. `eager` is the plain function.
    `chunk`, when set (compiled steps), filters `size` samples in one call (`make_chunk`):
    ``chunk((x, P), (u (C,), y (C, m)), valid (C,), (dt, Q, H, R, bound)) -> ((x, P),
    (e (C, m), nis (C,), loglik (C,), ok (C,)))``; padding samples (``valid = False``) leave the
    belief unchanged. `run_pass` uses `chunk` when it is there.
    """

    def __init__(
        self,
        eager: Callable,
        fast: Callable | None = None,
        chunk: Callable | None = None,
        size: int = 0,
    ) -> None:
        self.eager = eager
        self.fast = fast or eager
        self.chunk = chunk
        self.size = size

    def __call__(self, *args: Tensor):  # type: ignore[no-untyped-def]
        return self.fast(*args)


def compile_step(
    eager: Callable,
    *,
    carry: int,
    size: int = CHUNK,
    options: dict | None = None,
    native: bool = True,
    members: bool = False,
    member_consts: Sequence[bool] = (),
    key: str | None = None,
    device: torch.device | None = None,
) -> Step:
    """`eager` as a compiled `Step`: one sample through `compile_with_fallback`, and `size`
    samples per call through `make_chunk`.

    ``eager(*state, *x, *consts)`` returns a flat tuple whose first `carry` entries are the new
    state (threaded from sample to sample) and whose others are the sample's outputs. Both
    compile on the first call, once per process and model; if compilation fails for any reason
    the eager function is used from then on — same arithmetic. `options`, `native`, `members`,
    `member_consts`, `key` and `device` are `make_chunk`'s."""

    def one(*args: Tensor):  # type: ignore[no-untyped-def]
        out = eager(*args)
        return tuple(out[:carry]), tuple(out[carry:])

    scan = make_chunk(one, options=options, native=native, members=members,
                      member_consts=member_consts, key=key, device=device)  # fmt: skip
    return Step(eager, compile_with_fallback(eager), scan, size)


def chunk_options(mm: Callable[[Tensor, Tensor], Tensor]) -> dict:
    """Inductor options for a compiled chunk of steps that use the matrix product `mm`.

    Always the C++ wrapper (the loop over samples in C++). With `fused_matmul` also scalar code
    (``cpp.simdlen = 1``): the fused step's loops run over 2–20 elements, where SIMD tails cost
    more than they save — tanh(3), one filter: 36 k against 31 k steps/s; an ensemble of 256
    (vmapped, so still the same short loops per member): 272 k against 155 k filter-steps/s.
    """
    options: dict = {"cpp_wrapper": True}
    if mm is fused_matmul:
        options["cpp.simdlen"] = 1
    return options


def make_chunk(
    fn: Callable,
    *,
    options: dict | None = None,
    native: bool = False,
    members: bool = False,
    member_consts: Sequence[bool] = (),
    key: str | None = None,
    device: torch.device | None = None,
    member_xs: Sequence[bool] = (),
) -> Callable:
    """`fn` applied along chunks of samples as one compiled call, with an eager fallback.

    ``fn(*carry, *x, *consts) -> (carry', outs)`` is one sample: `carry` a tuple of tensors
    threaded from sample to sample, `x` the sample's slices, `consts` the same every sample,
    `outs` a tuple of per-sample tensors. The returned ``chunk(carry, xs, valid, consts) ->
    (carry, outs)`` takes `xs` with a leading sample axis C and returns each of `outs` stacked
    along C; a sample with ``valid = False`` (padding) leaves the carry as it was (its `outs`
    are computed but meaningless). Compiled as `torch._higher_order_ops.scan` under
    `torch.compile` with Inductor `options`, through `compile_with_fallback`.

    With `native`, the chunk is first tried as generated C (`torchfric.accel.native`: the
    traced step as straight-line scalar code, 20-40x faster than the Inductor scan for the
    filter); when that path cannot translate `fn` it falls back to the Inductor scan, and that
    to the eager loop. `members`, `member_consts` and `key` (what `fn`'s code depends on: a
    later process then finds its generated code without tracing) are `make_native_chunk`'s (for ensembles:
    `fn` is then the batched step, which the native path traces for one member; the Inductor
    and eager paths call it on the whole batch). The returned function's `.path` says which
    path ran last: "cuda", "native", "inductor" or "eager".

    With a CUDA `device` (ensembles only: `members`, no per-sample outputs), the chunk first
    runs as the generated step on that GPU (`torchfric.accel.native.cuda`: one member per
    thread; the carry comes back on the device); where that path cannot run, the CPU paths
    above take over, announced once (`NativeCacheWarning`).

    `member_xs` marks the per-sample inputs that are one per member (``(C, K, ...)``: a batch of
    simulations, each under its own input); the CPU paths serve them, a CUDA `device` does not.
    """
    if device is not None and device.type == "cuda" and not any(member_xs):
        from .native.cuda import on_device

        cpu = make_chunk(fn, options=options, native=native, members=members,
                         member_consts=member_consts, key=key)  # fmt: skip
        return on_device(fn, member_consts, device, cpu)
    inductor = _inductor_chunk(fn, options)
    if not native:
        return _tagged(inductor)
    from .native import NativeUnavailable, make_native_chunk

    generated = make_native_chunk(fn, members=members, member_consts=tuple(member_consts),
                                  member_xs=tuple(member_xs), key=key)  # fmt: skip
    reasons: list[str] = []

    def chunk(carry, xs, valid, consts):  # type: ignore[no-untyped-def]
        try:
            out = generated(carry, xs, valid, consts)
            chunk.path = "native"  # type: ignore[attr-defined]
            return out
        except NativeUnavailable as exc:  # this shape (remembered per shape): the next path
            if str(exc) not in reasons:
                reasons.append(str(exc))
        out = inductor(carry, xs, valid, consts)
        chunk.path = _path_of(inductor)  # type: ignore[attr-defined]
        return out

    chunk.path = None  # type: ignore[attr-defined]
    chunk.why_not_native = reasons  # type: ignore[attr-defined]
    return chunk


def _inductor_chunk(fn: Callable, options: dict | None) -> Callable:
    """`make_chunk`'s second and third paths: the scan of `fn` under `torch.compile`, falling
    back to a Python loop over the samples (`compile_with_fallback`)."""

    def traced(carry, xs, valid, consts):  # type: ignore[no-untyped-def]
        from torch._higher_order_ops import scan

        def body(c, inp):  # type: ignore[no-untyped-def]
            *x, v = inp
            # The scan's body may not alias its inputs: the constants enter as fresh copies.
            new, outs = fn(*c, *x, *(k.clone() for k in consts))
            new = tuple(torch.where(v, a, b) for a, b in zip(new, c, strict=True))
            # `v` is always an output: scan needs one even when `fn` has none.
            return new, (*(o.clone() for o in outs), v.clone())

        c, outs = scan(body, tuple(carry), (*xs, valid))
        return c, tuple(outs[:-1])

    def loop(carry, xs, valid, consts):  # type: ignore[no-untyped-def]
        carry, collected = tuple(carry), []
        for *x, v in zip(*xs, valid, strict=True):
            new, outs = fn(*carry, *x, *consts)
            if bool(v):
                carry = tuple(new)
            collected.append(outs)
        return carry, tuple(torch.stack(o) for o in zip(*collected, strict=True))

    return compile_with_fallback(loop, traced, options=options)


def _path_of(fast: Callable) -> str | None:
    """ "inductor" or "eager" for a `compile_with_fallback` function once it has run."""
    chosen = fast.chosen  # type: ignore[attr-defined]
    if not chosen:
        return None
    return "eager" if chosen[0] is fast.eager else "inductor"  # type: ignore[attr-defined]


def _tagged(fast: Callable) -> Callable:
    """`fast` with a `.path` attribute that reads which path it took (see `make_chunk`)."""

    def chunk(*args):  # type: ignore[no-untyped-def]
        out = fast(*args)
        chunk.path = _path_of(fast)  # type: ignore[attr-defined]
        return out

    chunk.path = None  # type: ignore[attr-defined]
    chunk.chosen = fast.chosen  # type: ignore[attr-defined]
    chunk.eager = fast.eager  # type: ignore[attr-defined]
    return chunk


@contextlib.contextmanager
def _unlimited_recompiles() -> Iterator[None]:
    """Lift dynamo's per-code-object recompile limit while one of our compiled calls runs.

    Dynamo keeps its compiled entries on the *code object* and allows at most
    ``torch._dynamo.config.recompile_limit`` (8) per code object. Every step, ensemble and rk4
    chunk is the same closure code (`_inductor_chunk`'s) with other captured models and
    shapes, so the ninth compiled model in a process used to fall back to the eager loop
    (measured: an ensemble of 64 at 10 k instead of 200 k filter-steps/s in
    `benchmarks/ekf_speed.py`).
    Entries stay shared, so a step re-made for the same model still finds its compiled code.
    The user's own compiled code keeps the limit they set."""
    cfg = torch._dynamo.config
    saved = cfg.recompile_limit, cfg.accumulated_recompile_limit
    cfg.recompile_limit = cfg.accumulated_recompile_limit = 1 << 30
    try:
        yield
    finally:
        cfg.recompile_limit, cfg.accumulated_recompile_limit = saved


def compile_with_fallback(
    eager: Callable, traced: Callable | None = None, *, options: dict | None = None
) -> Callable:
    """`traced` (default: `eager`) through `torch.compile` (Inductor, full graph, static
    shapes, `options`), compiled on the first call; if compilation fails for any reason `eager`
    is used from then on — same arithmetic. The returned function carries `.eager` and
    `.chosen` (the function in use)."""
    chosen: list[Callable] = []
    made: list[Callable] = []

    def compiled(*args: Tensor):  # type: ignore[no-untyped-def]
        # `torch.compile` itself is made here, on the first call: it imports dynamo (about a
        # second), which a run whose chunks all take the native path never needs.
        if not made:
            made.append(torch.compile(traced or eager, dynamic=False, fullgraph=True,
                                      options=options))  # fmt: skip
        with _unlimited_recompiles():  # (a new shape later recompiles under the same rule)
            return made[0](*args)

    def fast(*args: Tensor):  # type: ignore[no-untyped-def]
        if chosen:
            return chosen[0](*args)
        try:
            with warnings.catch_warnings():
                # Inductor's own deprecation notices are not the user's business.
                warnings.simplefilter("ignore", FutureWarning)
                out = compiled(*args)
            chosen.append(compiled)
        except Exception:  # noqa: BLE001 - any compiler failure means: use the eager step
            out = eager(*args)
            chosen.append(eager)
        return out

    fast.eager = eager  # type: ignore[attr-defined]
    fast.chosen = chosen  # type: ignore[attr-defined]
    return fast


def pad_rows(a: Tensor, size: int) -> Tensor:
    """`a` extended to `size` rows by repeating its last row (padding the scan never uses)."""
    if a.shape[0] == size:
        return a
    return torch.cat([a, a[-1:].expand(size - a.shape[0], *a.shape[1:])])


def iter_chunks(
    xs: tuple[Tensor, ...], size: int
) -> Iterator[tuple[int, int, tuple[Tensor, ...], Tensor]]:
    """The inputs of successive `make_chunk` calls along the leading axis of `xs`:
    ``(start, m, padded xs (size rows each), valid (size,))`` with the last chunk's `m` real
    rows padded by `pad_rows` and marked invalid."""
    total = xs[0].shape[0]
    for i in range(0, total, size):
        m = min(size, total - i)
        yield i, m, tuple(pad_rows(a[i : i + m], size) for a in xs), torch.arange(size) < m


def run_chunks(
    chunk: Callable,
    carry: tuple[Tensor, ...],
    xs: tuple[Tensor, ...],
    consts: tuple[Tensor, ...],
    *,
    size: int = CHUNK,
    reverse: bool = False,
) -> tuple[Any, tuple[Tensor, ...]]:
    """Apply a `make_chunk` function along the leading axis of `xs` (T rows), `size` rows per
    call (the last call padded), backwards when `reverse`; returns the final carry and each
    per-row output (T rows, in the order the rows were run)."""
    if reverse:
        xs = tuple(a.flip(0) for a in xs)
    outs: list[tuple[Tensor, ...]] = []
    for _, m, part, valid in iter_chunks(xs, size):
        carry, o = chunk(carry, part, valid, consts)
        outs.append(tuple(a[:m] for a in o))
    joined = tuple(torch.cat(cols) for cols in zip(*outs, strict=True)) if outs else ()
    return carry, joined


def step_key(kind: str, *parts: Any) -> str | None:
    """`compile_step`'s `key` for a step of `kind` whose code depends on `parts` (JSON-able: a
    `structure_key`, sub-steps, a `product_name`); None when a part is None (not nameable)."""
    return None if any(p is None for p in parts) else json.dumps([kind, *parts])


def product_name(mm: Callable) -> str | None:
    """The name of a step's matrix product for `step_key`: "fused" (`fused_matmul`), "matmul"
    (`torch.matmul`), None for any other."""
    return "fused" if mm is fused_matmul else "matmul" if mm is torch.matmul else None


def structure_key(model: ArmModel) -> str:
    """What fixes a model's compiled code: its spec without θ's values, the classes of its
    modules and, for classes defined outside torchfric (a user's own friction), a digest of
    their source file. The key of the per-model caches of compiled chunks (θ is an input of
    those, so the fitted models of successive passes or epochs share them), in this process and,
    through the native code's aliases, in later ones."""
    spec = model.spec()
    spec["friction"] = {k: v for k, v in spec["friction"].items() if k != "values"}
    # θ's physical values go; which white-box terms the arm has (offset, gravity, asymmetric,
    # c_m, the bristles') stays: they change the code, not only θ's length
    spec["arm"] = sorted(spec.get("arm", {}))
    classes = {c for m in model.modules() for c in type(m).__mro__ if c.__module__ != "builtins"}
    classes = {c for c in classes if not c.__module__.startswith("torch.")}
    spec["classes"] = sorted(
        f"{c.__module__}.{c.__qualname__}: {_methods_digest(c)}" for c in classes
    )
    spec["code"] = sorted(filter(None, (_foreign_source(c) for c in classes)))
    return json.dumps(spec, sort_keys=True, default=str)


def _methods_digest(cls: type) -> str:
    """A digest of the code of `cls`'s own methods as they are now (a method replaced at run
    time changes it)."""
    h = hashlib.sha256()
    for name, member in sorted(vars(cls).items()):
        for fn in (member, getattr(member, "__func__", None), getattr(member, "fget", None)):
            code = getattr(fn, "__code__", None)
            if code is not None:
                h.update(name.encode() + b"\0")
                _hash_code(h, code)
    return h.hexdigest()[:16]


def _hash_code(h: Any, code: Any) -> None:
    """Feed a code object (its bytecode, names and constants, nested code included) to `h`."""
    h.update(code.co_code + repr(code.co_names).encode())
    for const in code.co_consts:
        if hasattr(const, "co_code"):
            _hash_code(h, const)
        elif isinstance(const, frozenset):  # its order follows the process's hash seed
            h.update(repr(sorted(map(repr, const))).encode())
        else:
            h.update(repr(const).encode())


def _foreign_source(cls: type) -> str | None:
    """SHA-256 of the file that defines `cls` when that is not torchfric's own (whose code is
    part of every alias already); of the class's source where there is no file (a notebook);
    where neither can be read, a token of this process, so that no later process reuses code
    made for it. None for torchfric's and torch's classes."""
    if cls.__module__.startswith(("torchfric.", "torch.")):
        return None
    path = getattr(sys.modules.get(cls.__module__), "__file__", None)
    if path and os.path.isfile(path):
        st = os.stat(path)
        return _file_digest(path, st.st_mtime_ns, st.st_size)
    try:
        return hashlib.sha256(inspect.getsource(cls).encode()).hexdigest()
    except (OSError, TypeError):
        return f"{cls.__module__}.{cls.__qualname__} in process {_PROCESS_TOKEN}"


_PROCESS_TOKEN = secrets.token_hex(8)


@functools.cache
def _file_digest(path: str, mtime_ns: int, size: int) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()
