"""Native code for the filter's per-sample loop, generated from its traced autograd graph.

The EKF step on a 10-state model is a few thousand floating-point operations on matrices of
2–20 entries. Run through torch, each of those operations, or each fused kernel of a compiled
graph, carries a per-call cost far above its arithmetic, and that cost, not the arithmetic, was
the filter's speed limit. This module removes it without giving up autograd:

1. **Trace.** The step (with its `torch.func` Jacobians) is traced once by
   `torch.fx.experimental.proxy_tensor.make_fx` into a graph of ATen operations with the shapes
   of one sample.
2. **Scalarise.** The graph is evaluated on arrays of *symbols* (`numpy` object arrays holding
   `_Sym` nodes), so views, broadcasts, reductions and products become a DAG of scalar
   operations. Equal sub-expressions are shared; products with the constants 0 and 1 (identity
   blocks, padding) are folded.
3. **Emit and compile.** The DAG becomes one straight-line C function body inside a loop over
   the chunk's samples (and, for ensembles, an outer loop over members split across threads).
   It is compiled once with the system C compiler into a shared library kept in a cache folder
   keyed by the source's hash, so later processes load it in milliseconds.

The arithmetic is the traced graph's, operation by operation, in IEEE double precision (no
fast-math): results agree with the eager step to rounding. `make_native_chunk` has the calling
convention of `torchfric.ekf.make_chunk`; anything it cannot translate (an operation outside its
table, no C compiler) raises `NativeUnavailable` and the caller falls back to the next path.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import math
import operator
import os
import subprocess
import sys
import tempfile
import threading
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["NativeUnavailable", "make_native_chunk", "cache_dir", "compiler"]


class NativeUnavailable(RuntimeError):
    """The native path cannot serve this function (unsupported operation, no C compiler…)."""


# ---------------------------------------------------------------------------------------------
# Scalar expression graph
# ---------------------------------------------------------------------------------------------

_C_TYPE = {"d": "double", "i": "int64_t", "b": "int"}


# Operations whose IEEE result does not depend on the operand order (exactly, not to rounding).
_COMMUTATIVE = frozenset({"add", "mul", "==", "!=", "&&", "||"})


def _order(a: Any) -> tuple:
    return (0, a.id, "") if isinstance(a, _Sym) else (1, 0, repr(a))


class _Graph:
    """Interned scalar nodes ``(op, args, dtype)``; ids are in topological order."""

    def __init__(self) -> None:
        self.nodes: list[tuple[str, tuple, str]] = []
        self.index: dict[tuple, _Sym] = {}

    def node(self, op: str, args: tuple, dtype: str) -> _Sym:
        if op in _COMMUTATIVE:  # a + b and b + a are the same double: one node for both
            args = tuple(sorted(args, key=_order))
        key = (
            op,
            tuple((a.id, None) if isinstance(a, _Sym) else (type(a), a) for a in args),
            dtype,
        )
        sym = self.index.get(key)
        if sym is None:
            sym = _Sym(self, len(self.nodes), dtype)
            self.nodes.append((op, args, dtype))
            self.index[key] = sym
        return sym


class _Sym:
    """One scalar of the traced computation (a node of `_Graph`)."""

    __slots__ = ("graph", "id", "dtype")

    def __init__(self, graph: _Graph, id: int, dtype: str) -> None:
        self.graph, self.id, self.dtype = graph, id, dtype

    # numpy's object-array reductions (np.sum) use these operators.
    def __add__(self, o: Any) -> Any:
        return _add(self, o)

    def __radd__(self, o: Any) -> Any:
        return _add(o, self)

    def __mul__(self, o: Any) -> Any:
        return _mul(self, o)

    def __rmul__(self, o: Any) -> Any:
        return _mul(o, self)


Scalar = Any  # _Sym | bool | int | float


def _dtype(a: Scalar) -> str:
    if isinstance(a, _Sym):
        return a.dtype
    if isinstance(a, (bool, np.bool_)):
        return "b"
    if isinstance(a, (int, np.integer)):
        return "i"
    return "d"


def _promote(*args: Scalar) -> str:
    kinds = {_dtype(a) for a in args}
    return "d" if "d" in kinds else "i" if "i" in kinds else "b"


def _graph_of(*args: Scalar) -> _Graph:
    for a in args:
        if isinstance(a, _Sym):
            return a.graph
    raise AssertionError("no symbol among the arguments")  # constants fold before this


def _const(a: Scalar) -> bool:
    return not isinstance(a, _Sym)


def _is(a: Scalar, value: float) -> bool:
    return _const(a) and not isinstance(a, bool) and a == value


def _to(a: Scalar, dtype: str) -> Scalar:
    """`a` as `dtype` ('d', 'i' or 'b'), folded for constants."""
    if _dtype(a) == dtype:
        return a
    if _const(a):
        return float(a) if dtype == "d" else int(a) if dtype == "i" else bool(a)
    return a.graph.node("cast", (a,), dtype)


def _num(a: Scalar) -> Scalar:
    """Booleans enter arithmetic as numbers (torch's type promotion)."""
    return _to(a, "i") if _dtype(a) == "b" else a


def _add(a: Scalar, b: Scalar) -> Scalar:
    a, b = _num(a), _num(b)
    if _const(a) and _const(b):
        return a + b
    if _is(a, 0) and _dtype(b) == _promote(a, b):
        return b
    if _is(b, 0) and _dtype(a) == _promote(a, b):
        return a
    return _graph_of(a, b).node("add", (a, b), _promote(a, b))


def _sub(a: Scalar, b: Scalar) -> Scalar:
    a, b = _num(a), _num(b)
    if _const(a) and _const(b):
        return a - b
    if _is(b, 0) and _dtype(a) == _promote(a, b):
        return a
    if _is(a, 0) and _dtype(b) == _promote(a, b):
        return _neg(b)
    return _graph_of(a, b).node("sub", (a, b), _promote(a, b))


def _mul(a: Scalar, b: Scalar) -> Scalar:
    # x * 0 = 0 and x * 1 = x: exact for finite x. A NaN or inf that this drops would also
    # reach the outputs through other terms, where the health check sees it.
    a, b = _num(a), _num(b)
    if _const(a) and _const(b):
        return a * b
    dt = _promote(a, b)
    if _is(a, 0) or _is(b, 0):
        return 0.0 if dt == "d" else 0
    if _is(a, 1) and _dtype(b) == dt:
        return b
    if _is(b, 1) and _dtype(a) == dt:
        return a
    if _is(a, -1):
        return _neg(_to(b, dt))
    if _is(b, -1):
        return _neg(_to(a, dt))
    return _graph_of(a, b).node("mul", (a, b), dt)


def _div(a: Scalar, b: Scalar) -> Scalar:
    a, b = _to(a, "d"), _to(b, "d")
    if _const(a) and _const(b):
        if b == 0:
            raise NativeUnavailable("division of constants by zero")
        return a / b
    if _is(b, 1):
        return a
    return _graph_of(a, b).node("div", (a, b), "d")


def _neg(a: Scalar) -> Scalar:
    a = _num(a)
    if _const(a):
        return -a
    if a.graph.nodes[a.id][0] == "neg":
        return a.graph.nodes[a.id][1][0]
    return a.graph.node("neg", (a,), a.dtype)


_MATH: dict[str, Callable[[float], float]] = {
    "exp": math.exp,
    "log": math.log,
    "sqrt": math.sqrt,
    "tanh": math.tanh,
    "sin": math.sin,
    "cos": math.cos,
    "fabs": abs,
    "expm1": math.expm1,
    "log1p": math.log1p,
}


def _unary(name: str) -> Callable[[Scalar], Scalar]:
    def f(a: Scalar) -> Scalar:
        a = _to(a, "d")
        if _const(a):
            try:
                return _MATH[name](a)
            except (ValueError, OverflowError):
                return math.nan
        return a.graph.node(name, (a,), "d")

    return f


def _compare(op: str) -> Callable[[Scalar, Scalar], Scalar]:
    py = {"<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge,
          "==": operator.eq, "!=": operator.ne}[op]  # fmt: skip

    def f(a: Scalar, b: Scalar) -> Scalar:
        a, b = _num(a), _num(b)
        if _const(a) and _const(b):
            return bool(py(a, b))
        return _graph_of(a, b).node(op, (a, b), "b")

    return f


def _and(a: Scalar, b: Scalar) -> Scalar:
    if _const(a):
        return _to(b, "b") if a else False
    if _const(b):
        return _to(a, "b") if b else False
    return a.graph.node("&&", (_to(a, "b"), _to(b, "b")), "b")


def _or(a: Scalar, b: Scalar) -> Scalar:
    if _const(a):
        return True if a else _to(b, "b")
    if _const(b):
        return True if b else _to(a, "b")
    return a.graph.node("||", (_to(a, "b"), _to(b, "b")), "b")


def _not(a: Scalar) -> Scalar:
    if _const(a):
        return not a
    return a.graph.node("!", (_to(a, "b"),), "b")


def _where(c: Scalar, a: Scalar, b: Scalar) -> Scalar:
    dt = _promote(a, b)
    a, b = _to(a, dt), _to(b, dt)
    if _const(c):
        return a if c else b
    if a is b or (_const(a) and _const(b) and a == b and not math.isnan(float(a))):
        return a
    return c.graph.node("?:", (_to(c, "b"), a, b), dt)


def _maximum(a: Scalar, b: Scalar) -> Scalar:
    # NaN-propagating like torch.maximum
    dt = _promote(a, b)
    a, b = _to(a, dt), _to(b, dt)
    if _const(a) and _const(b):
        return math.nan if math.isnan(a) or math.isnan(b) else max(a, b)
    return _graph_of(a, b).node("max", (a, b), dt)


def _minimum(a: Scalar, b: Scalar) -> Scalar:
    dt = _promote(a, b)
    a, b = _to(a, dt), _to(b, dt)
    if _const(a) and _const(b):
        return math.nan if math.isnan(a) or math.isnan(b) else min(a, b)
    return _graph_of(a, b).node("min", (a, b), dt)


def _sign(a: Scalar) -> Scalar:
    a = _num(a)
    if _const(a):
        return float((a > 0) - (a < 0)) if _dtype(a) == "d" else (a > 0) - (a < 0)
    return a.graph.node("sign", (a,), a.dtype)


def _pow(a: Scalar, b: Scalar) -> Scalar:
    if _is(b, 2):
        return _mul(a, a)
    if _is(b, 1):
        return _to(a, "d")
    if _is(b, 0.5):
        return _unary("sqrt")(a)
    a, b = _to(a, "d"), _to(b, "d")
    if _const(a) and _const(b):
        return a**b
    return _graph_of(a, b).node("pow", (a, b), "d")


# numpy ufuncs over object arrays of scalars (broadcasting included)
def _lift(fn: Callable, nin: int) -> Callable[..., np.ndarray]:
    uf = np.frompyfunc(fn, nin, 1)

    def f(*arrays: Any) -> np.ndarray:
        return _arr(uf(*arrays))

    return f


def _arr(a: Any) -> np.ndarray:
    """`a` as an object array (0-d results of numpy ops come back as bare scalars)."""
    if isinstance(a, np.ndarray):
        return a if a.dtype == object else a.astype(object)
    out = np.empty((), dtype=object)
    out[()] = a
    return out


def _fill(shape: Sequence[int], value: Scalar) -> np.ndarray:
    out = np.empty(tuple(shape), dtype=object)
    out.fill(value)
    return out


def _reduce(fn: Callable, a: np.ndarray, dims: Any, keepdim: bool) -> np.ndarray:
    """Sequential reduction of `a` over `dims` (all when None or empty) with `fn`."""
    nd = a.ndim
    if dims is None or (isinstance(dims, (list, tuple)) and len(dims) == 0):
        dims = list(range(nd))
    elif isinstance(dims, int):
        dims = [dims]
    dims = sorted(d % nd for d in dims) if nd else []
    if not dims:
        return a.copy()
    moved = np.moveaxis(a, dims, list(range(nd - len(dims), nd)))
    keep = moved.shape[: nd - len(dims)]
    flat = moved.reshape(*keep, -1)
    out = np.empty(keep, dtype=object)
    for idx in np.ndindex(*keep):
        out[idx] = functools.reduce(fn, flat[idx])
    if keepdim:
        for d in dims:
            out = np.expand_dims(out, d)
    return out


# ---------------------------------------------------------------------------------------------
# ATen operations on symbol arrays
# ---------------------------------------------------------------------------------------------

_add_a = _lift(_add, 2)
_sub_a = _lift(_sub, 2)
_mul_a = _lift(_mul, 2)
_div_a = _lift(_div, 2)
_where_a = _lift(_where, 3)


def _dtype_code(dtype: torch.dtype | None, default: str = "d") -> str:
    if dtype is None:
        return default
    if dtype == torch.bool:
        return "b"
    if dtype in (torch.int64, torch.int32, torch.int16, torch.int8, torch.uint8):
        return "i"
    if dtype in (torch.float64, torch.float32):
        return "d"
    raise NativeUnavailable(f"dtype {dtype}")


def _zero(code: str) -> Scalar:
    return 0.0 if code == "d" else 0 if code == "i" else False


def _one(code: str) -> Scalar:
    return 1.0 if code == "d" else 1 if code == "i" else True


def _arr_dtype(a: np.ndarray) -> str:
    return _promote(*a.flat) if a.size else "d"


def _slice(a: np.ndarray, dim: int = 0, start: Any = None, end: Any = None, step: int = 1):
    idx = [slice(None)] * a.ndim
    idx[dim] = slice(start, end, step)
    return a[tuple(idx)]


def _put(out: np.ndarray, idx: tuple, value: np.ndarray) -> None:
    """``out[idx] = value`` element by element (numpy would store a 0-d object array that
    lands in a single slot as the array itself, not its element)."""
    target = out[idx]
    if isinstance(target, np.ndarray) and target.ndim:
        target[...] = value  # a view: numpy copies the elements
    else:
        out[idx] = _arr(value)[()]


def _slice_backward(g, sizes, dim, start, end, step):  # type: ignore[no-untyped-def]
    out = _fill(sizes, 0.0)
    idx = [slice(None)] * len(sizes)
    idx[dim] = slice(start, end, step)
    _put(out, tuple(idx), g)
    return out


def _select_backward(g, sizes, dim, index):  # type: ignore[no-untyped-def]
    out = _fill(sizes, 0.0)
    idx: list[Any] = [slice(None)] * len(sizes)
    idx[dim] = index
    _put(out, tuple(idx), g)
    return out


def _expand(a: np.ndarray, size: Sequence[int], implicit: bool = False) -> np.ndarray:
    lead = len(size) - a.ndim
    shape = [a.shape[i - lead] if (s == -1 and i >= lead) else s for i, s in enumerate(size)]
    return np.broadcast_to(a, shape).copy()


def _pad(a: np.ndarray, pad: Sequence[int], value: float = 0.0) -> np.ndarray:
    widths = [(0, 0)] * a.ndim
    for i in range(len(pad) // 2):
        widths[a.ndim - 1 - i] = (pad[2 * i], pad[2 * i + 1])
    if any(w < 0 for pair in widths for w in pair):
        raise NativeUnavailable("negative padding")
    out = _fill([s + lo + hi for s, (lo, hi) in zip(a.shape, widths, strict=True)], value)
    _put(out, tuple(slice(lo, lo + s) for s, (lo, _) in zip(a.shape, widths, strict=True)), a)
    return out


def _softmax(a: np.ndarray, dim: int, half: bool = False) -> np.ndarray:
    m = _reduce(_maximum, a, [dim], True)
    e = _lift(_unary("exp"), 1)(_sub_a(a, m))
    return _div_a(e, _reduce(_add, e, [dim], True))


def _softmax_backward(g: np.ndarray, y: np.ndarray, dim: int, dtype: Any = None) -> np.ndarray:
    gy = _mul_a(g, y)
    return _mul_a(y, _sub_a(g, _reduce(_add, gy, [dim], True)))


def _tanh_backward(g: np.ndarray, y: np.ndarray) -> np.ndarray:
    return _mul_a(g, _sub_a(_arr(1.0), _mul_a(y, y)))


def _scaled(fn: Callable) -> Callable:
    """add/sub with torch's `alpha`."""

    def f(a: Any, b: Any, *, alpha: Any = 1) -> np.ndarray:
        return fn(_arr(a), _mul_a(_arr(b), _arr(alpha)) if alpha != 1 else _arr(b))

    return f


def _eye(n: int, m: int | None = None, **_: Any) -> np.ndarray:
    out = _fill((n, n if m is None else m), 0.0)
    for i in range(min(out.shape)):
        out[i, i] = 1.0
    return out


def _like(value: float) -> Callable:
    def f(a: np.ndarray, *, dtype: Any = None, **_: Any) -> np.ndarray:
        code = _dtype_code(dtype, _arr_dtype(a))
        return _fill(a.shape, _to(value, code))

    return f


def _new_full(value: float | None = None) -> Callable:
    def f(a: np.ndarray, size: Sequence[int], fill: Any = None, *, dtype: Any = None, **_: Any):  # type: ignore[no-untyped-def]
        v = fill if value is None else value
        return _fill(size, _to(v, _dtype_code(dtype, _arr_dtype(a))))

    return f


def _full(size: Sequence[int], fill: Any, *, dtype: Any = None, **_: Any) -> np.ndarray:
    return _fill(size, _to(fill, _dtype_code(dtype, _dtype(fill))))


def _to_copy(a: np.ndarray, *, dtype: Any = None, **_: Any) -> np.ndarray:
    if dtype is None:
        return a.copy()
    code = _dtype_code(dtype)
    return _lift(lambda s: _to(s, code), 1)(a)


def _view(a: np.ndarray, shape: Sequence[int]) -> np.ndarray:
    return a.reshape(tuple(shape)).copy()


def _squeeze(a: np.ndarray, dim: Any = None) -> np.ndarray:
    if dim is None:
        return np.squeeze(a)
    dims = [dim] if isinstance(dim, int) else list(dim)
    dims = [d % a.ndim for d in dims if a.ndim and a.shape[d % a.ndim] == 1]
    return np.squeeze(a, axis=tuple(dims)) if dims else a


def _unsqueeze(a: np.ndarray, dim: int) -> np.ndarray:
    return np.expand_dims(a, dim % (a.ndim + 1))


def _sum(
    a: np.ndarray, dims: Any = None, keepdim: bool = False, *, dtype: Any = None
) -> np.ndarray:
    out = _reduce(_add, a, dims, keepdim)
    return _to_copy(out, dtype=dtype) if dtype is not None else out


def _all(a: np.ndarray, dim: Any = None, keepdim: bool = False) -> np.ndarray:
    return _reduce(_and, _lift(lambda s: _to(s, "b"), 1)(a), dim, keepdim)


def _any(a: np.ndarray, dim: Any = None, keepdim: bool = False) -> np.ndarray:
    return _reduce(_or, _lift(lambda s: _to(s, "b"), 1)(a), dim, keepdim)


def _amax(a: np.ndarray, dim: Any = None, keepdim: bool = False) -> np.ndarray:
    return _reduce(_maximum, a, dim, keepdim)


def _amin(a: np.ndarray, dim: Any = None, keepdim: bool = False) -> np.ndarray:
    return _reduce(_minimum, a, dim, keepdim)


def _max_dim(a: np.ndarray, dim: int, keepdim: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """torch.max(a, dim): values (NaN-propagating) and the index of the first maximum."""
    values = _reduce(_maximum, a, [dim], keepdim)
    moved = np.moveaxis(a, dim % a.ndim, -1)
    index = np.empty(moved.shape[:-1], dtype=object)
    for idx in np.ndindex(*moved.shape[:-1]):
        best, at = moved[idx][0], 0
        for j, v in enumerate(moved[idx][1:], start=1):
            take = _compare(">")(v, best)
            best, at = _where(take, v, best), _where(take, j, at)
        index[idx] = at
    if keepdim:
        index = np.expand_dims(index, dim % a.ndim)
    return values, index


def _diag_embed(a: np.ndarray, offset: int, d1: int, d2: int) -> np.ndarray:
    if offset != 0 or (d1 % (a.ndim + 1), d2 % (a.ndim + 1)) != (a.ndim - 1, a.ndim):
        raise NativeUnavailable("diag_embed beyond the main diagonal of the last two axes")
    n = a.shape[-1]
    out = _fill((*a.shape, n), 0.0)
    for i in range(n):
        _put(out, (..., i, i), a[..., i])
    return out


def _matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Matrix products (mm, mv, bmm, dot) as sums of scalar products."""
    va, vb = a.ndim == 1, b.ndim == 1
    A = a[None, :] if va else a
    B = b[:, None] if vb else b
    prod = _mul_a(A[..., :, :, None], B[..., None, :, :])  # (..., i, k, j)
    out = _reduce(_add, prod, [prod.ndim - 2], False)
    if vb:
        out = out[..., 0]
    if va:
        out = out[..., 0, :] if not vb else out[..., 0]
    return _arr(out)


def _binary_scalar(fn: Callable) -> Callable:
    return lambda a, b: fn(_arr(a), _arr(b))


_OPS: dict[str, Callable[..., Any]] = {
    "aten.add.Tensor": _scaled(_add_a),
    "aten.add.Scalar": _scaled(_add_a),
    "aten.sub.Tensor": _scaled(_sub_a),
    "aten.sub.Scalar": _scaled(_sub_a),
    "aten.rsub.Scalar": lambda a, b, alpha=1: _sub_a(_arr(b), _mul_a(_arr(a), _arr(alpha))),
    "aten.rsub.Tensor": lambda a, b, alpha=1: _sub_a(_arr(b), _mul_a(_arr(a), _arr(alpha))),
    "aten.mul.Tensor": _binary_scalar(_mul_a),
    "aten.mul.Scalar": _binary_scalar(_mul_a),
    "aten.div.Tensor": _binary_scalar(_div_a),
    "aten.div.Scalar": _binary_scalar(_div_a),
    "aten.neg.default": _lift(_neg, 1),
    "aten.abs.default": _lift(_unary("fabs"), 1),
    "aten.exp.default": _lift(_unary("exp"), 1),
    "aten.log.default": _lift(_unary("log"), 1),
    "aten.sqrt.default": _lift(_unary("sqrt"), 1),
    "aten.rsqrt.default": lambda a: _div_a(_arr(1.0), _lift(_unary("sqrt"), 1)(a)),
    "aten.reciprocal.default": lambda a: _div_a(_arr(1.0), a),
    "aten.tanh.default": _lift(_unary("tanh"), 1),
    "aten.sin.default": _lift(_unary("sin"), 1),
    "aten.cos.default": _lift(_unary("cos"), 1),
    "aten.expm1.default": _lift(_unary("expm1"), 1),
    "aten.log1p.default": _lift(_unary("log1p"), 1),
    "aten.sigmoid.default": lambda a: _div_a(
        _arr(1.0), _add_a(_arr(1.0), _lift(_unary("exp"), 1)(_lift(_neg, 1)(a)))
    ),
    "aten.sign.default": _lift(_sign, 1),
    "aten.sgn.default": _lift(_sign, 1),
    "aten.pow.Tensor_Scalar": lambda a, b: _lift(_pow, 2)(a, _arr(b)),
    "aten.pow.Tensor_Tensor": _lift(_pow, 2),
    "aten.square.default": lambda a: _mul_a(a, a),
    "aten.tanh_backward.default": _tanh_backward,
    "aten._softmax.default": _softmax,
    "aten._softmax_backward_data.default": _softmax_backward,
    "aten.maximum.default": _lift(_maximum, 2),
    "aten.minimum.default": _lift(_minimum, 2),
    "aten.mm.default": _matmul,
    "aten.mv.default": _matmul,
    "aten.bmm.default": _matmul,
    "aten.dot.default": _matmul,
    "aten.addmm.default": lambda c, a, b, beta=1, alpha=1: _add_a(
        _mul_a(c, _arr(beta)), _mul_a(_matmul(a, b), _arr(alpha))
    ),
    "aten.clamp.default": lambda a, lo=None, hi=None: (
        _lift(_minimum, 2)(_lift(_maximum, 2)(a, _arr(lo)) if lo is not None else a, _arr(hi))
        if hi is not None
        else (_lift(_maximum, 2)(a, _arr(lo)) if lo is not None else a)
    ),
    "aten.argmax.default": lambda a, dim=None, keepdim=False: _max_dim(
        a.reshape(-1) if dim is None else a, 0 if dim is None else dim, keepdim and dim is not None
    )[1],
    "aten.flip.default": lambda a, dims: np.flip(a, [d % a.ndim for d in dims]).copy(),
    "aten.diag_embed.default": lambda a, offset=0, d1=-2, d2=-1: _diag_embed(a, offset, d1, d2),
    "aten.clamp_min.default": lambda a, m: _lift(_maximum, 2)(a, _arr(m)),
    "aten.clamp_max.default": lambda a, m: _lift(_minimum, 2)(a, _arr(m)),
    "aten.where.self": _where_a,
    "aten.where.ScalarOther": lambda c, a, b: _where_a(c, a, _arr(b)),
    "aten.where.ScalarSelf": lambda c, a, b: _where_a(c, _arr(a), b),
    "aten.lt.Tensor": _lift(_compare("<"), 2),
    "aten.le.Tensor": _lift(_compare("<="), 2),
    "aten.gt.Tensor": _lift(_compare(">"), 2),
    "aten.ge.Tensor": _lift(_compare(">="), 2),
    "aten.eq.Tensor": _lift(_compare("=="), 2),
    "aten.ne.Tensor": _lift(_compare("!="), 2),
    "aten.lt.Scalar": _binary_scalar(_lift(_compare("<"), 2)),
    "aten.le.Scalar": _binary_scalar(_lift(_compare("<="), 2)),
    "aten.gt.Scalar": _binary_scalar(_lift(_compare(">"), 2)),
    "aten.ge.Scalar": _binary_scalar(_lift(_compare(">="), 2)),
    "aten.eq.Scalar": _binary_scalar(_lift(_compare("=="), 2)),
    "aten.ne.Scalar": _binary_scalar(_lift(_compare("!="), 2)),
    "aten.bitwise_and.Tensor": _lift(_and, 2),
    "aten.logical_and.default": _lift(_and, 2),
    "aten.bitwise_or.Tensor": _lift(_or, 2),
    "aten.logical_or.default": _lift(_or, 2),
    "aten.bitwise_not.default": _lift(_not, 1),
    "aten.logical_not.default": _lift(_not, 1),
    "aten.isnan.default": lambda a: _lift(_compare("!="), 2)(a, a),
    "aten.all.default": _all,
    "aten.all.dim": _all,
    "aten.all.dims": _all,
    "aten.any.default": _any,
    "aten.any.dim": _any,
    "aten.any.dims": _any,
    "aten.max.default": _amax,
    "aten.max.dim": _max_dim,
    "<built-in function getitem>": operator.getitem,
    "aten.min.default": _amin,
    "aten.amax.default": _amax,
    "aten.amin.default": _amin,
    "aten.sum.default": _sum,
    "aten.sum.dim_IntList": _sum,
    "aten.select.int": lambda a, dim, i: (
        np.take(a, i, axis=dim).copy() if a.ndim > 1 else _arr(a[i])
    ),
    "aten.slice.Tensor": _slice,
    "aten.slice_backward.default": _slice_backward,
    "aten.select_backward.default": _select_backward,
    "aten.unsqueeze.default": _unsqueeze,
    "aten.squeeze.dim": _squeeze,
    "aten.squeeze.dims": _squeeze,
    "aten.squeeze.default": _squeeze,
    "aten.permute.default": lambda a, dims: np.transpose(a, [d % a.ndim for d in dims]).copy(),
    "aten.t.default": lambda a: a.T.copy(),
    "aten.transpose.int": lambda a, d0, d1: np.swapaxes(a, d0, d1).copy(),
    "aten.expand.default": _expand,
    "aten.view.default": _view,
    "aten.reshape.default": _view,
    "aten._unsafe_view.default": _view,
    "aten.clone.default": lambda a, **_: a.copy(),
    "aten.alias.default": lambda a: a,
    "aten.lift_fresh_copy.default": lambda a: a.copy(),
    "aten.detach.default": lambda a: a,
    "aten._to_copy.default": _to_copy,
    "aten.cat.default": lambda xs, dim=0: np.concatenate(
        [x for x in xs if x.size or x.ndim > 1], axis=dim
    ),
    "aten.stack.default": lambda xs, dim=0: np.stack(xs, axis=dim),
    "aten.diagonal.default": lambda a, offset=0, d1=0, d2=1: np.diagonal(a, offset, d1, d2).copy(),
    "aten.repeat.default": lambda a, reps: np.tile(a, reps),
    "aten.constant_pad_nd.default": _pad,
    "aten.eye.m": _eye,
    "aten.eye.default": _eye,
    "aten.new_zeros.default": _new_full(0.0),
    "aten.new_ones.default": _new_full(1.0),
    "aten.new_full.default": _new_full(),
    "aten.new_empty.default": _new_full(0.0),
    "aten.zeros_like.default": _like(0.0),
    "aten.ones_like.default": _like(1.0),
    "aten.full_like.default": lambda a, v, **kw: _like(v)(a, **kw),
    "aten.full.default": _full,
    "aten.zeros.default": lambda size, **kw: _full(size, 0.0, **kw),
    "aten.ones.default": lambda size, **kw: _full(size, 1.0, **kw),
    "aten.scalar_tensor.default": lambda v, **kw: _full((), v, **kw),
}


def _evaluate(gm: torch.fx.GraphModule, inputs: list[np.ndarray]) -> list[np.ndarray]:
    """Run the traced graph on symbol arrays; returns the flattened outputs as arrays."""
    env: dict[str, Any] = {}
    it = iter(inputs)

    def load(a: Any) -> Any:
        return torch.fx.node.map_arg(a, lambda n: env[n.name])

    out: Any = None
    for node in gm.graph.nodes:
        if node.op == "placeholder":
            env[node.name] = next(it)
        elif node.op == "call_function":
            fn = _OPS.get(str(node.target))
            if fn is None:
                raise NativeUnavailable(f"operation {node.target} has no native translation")
            result = fn(*load(node.args), **load(node.kwargs))
            for r in result if isinstance(result, (list, tuple)) else [result]:
                if isinstance(r, np.ndarray) and any(isinstance(v, np.ndarray) for v in r.flat):
                    raise NativeUnavailable(f"translating {node.target} nested an array")
            env[node.name] = _arr(result) if not isinstance(result, (list, tuple)) else result
        elif node.op == "get_attr":  # a tensor constant captured by the trace
            value = getattr(gm, node.target)
            if not isinstance(value, Tensor):
                raise NativeUnavailable(f"graph attribute {node.target}")
            code = _dtype_code(value.dtype)
            arr = np.empty(value.numel(), dtype=object)
            for j, v in enumerate(value.detach().flatten().tolist()):
                arr[j] = _to(v, code)
            env[node.name] = arr.reshape(tuple(value.shape))
        elif node.op == "output":
            out = load(node.args[0])
        else:
            raise NativeUnavailable(f"graph node kind {node.op}")
    return [_arr(o) for o in torch.utils._pytree.tree_leaves(out)]


# ---------------------------------------------------------------------------------------------
# C emission
# ---------------------------------------------------------------------------------------------


def _literal(a: Scalar, dtype: str) -> str:
    if dtype == "d":
        v = float(a)
        if math.isnan(v):
            return "NAN"
        if math.isinf(v):
            return "INFINITY" if v > 0 else "(-INFINITY)"
        return repr(v)
    return str(int(a)) + ("LL" if dtype == "i" else "")


_INFIX = {"add": "+", "sub": "-", "mul": "*", "div": "/", "<": "<", "<=": "<=", ">": ">",
          ">=": ">=", "==": "==", "!=": "!=", "&&": "&&", "||": "||"}  # fmt: skip


_CT = {torch.float64: ("d", "double"), torch.int64: ("i", "int64_t"), torch.bool: ("b", "uint8_t")}


def _spec(t: Tensor) -> tuple[str, str]:
    if t.dtype not in _CT:
        raise NativeUnavailable(f"tensor dtype {t.dtype}")
    return _CT[t.dtype]


def _symbols(
    graph: _Graph, t: Tensor, name: str, code: str, fixed: dict[int, float] | None = None
) -> np.ndarray:
    """An object array of leaf symbols for tensor `t`, leaf j standing for ``name[j]``; the
    entries in `fixed` are the constants given there instead."""
    arr = np.empty(t.numel(), dtype=object)
    for j in range(t.numel()):
        arr[j] = (
            _to(fixed[j], code) if fixed and j in fixed else graph.node("leaf", (name, j), code)
        )
    return arr.reshape(tuple(t.shape))


# The largest step the generated code serves: gcc's time grows faster than linearly with the
# function's length (tanh(10), n = 24: 26 k statements, 10 s; tanh(30), n = 64: 107 k, over 2 min
# even at -O1). Larger steps take the Inductor scan, whose products call BLAS.
_MAX_STATEMENTS = 32_000

# Members per SIMD vector in an ensemble's code (four doubles: one 256-bit register).
_LANES = 4


def _source(
    fn: Callable,
    carry: Sequence[Tensor],
    xs: Sequence[Tensor],
    consts: Sequence[Tensor],
    member_consts: Sequence[bool],
    fixed: Sequence[dict[int, float]] = (),
    *,
    members: bool = False,
) -> tuple[str, list[tuple[int, ...]], list[torch.dtype], int]:
    """C source of the chunk loop; also the per-sample shapes and dtypes of the outputs and the
    members per vector (1: scalar code).

    Tensors arrive per member (batched ones with their member axis at size 1). `fixed[i]`
    maps flat entries of const i to the values they are compiled in as (`_structure`). With
    `members` and no per-sample outputs, the code runs `_LANES` members at once in SIMD
    vectors (`_vector_program`); otherwise one member at a time (`_scalar_program`)."""
    from torch.fx.experimental.proxy_tensor import make_fx

    n_c, n_x = len(carry), len(xs)

    def flat(*args: Tensor):  # type: ignore[no-untyped-def]
        new, outs = fn(*args)
        return (*new, *outs)

    args = [*carry, *xs, *consts]
    try:
        with warnings.catch_warnings():  # tracing touches module reprs; not the user's business
            warnings.simplefilter("ignore")
            gm = make_fx(flat)(*args)
    except Exception as exc:  # noqa: BLE001 - whatever stops tracing stops this path
        raise NativeUnavailable(f"tracing failed: {exc}") from exc
    graph = _Graph()
    names = [f"c{i}" for i in range(n_c)] + [f"x{i}" for i in range(n_x)]
    names += [f"k{i}" for i in range(len(consts))]
    fixed_of = [None] * (n_c + n_x) + list(fixed or [None] * len(consts))
    inputs = [_symbols(graph, t, nm, _spec(t)[0], fx)
              for t, nm, fx in zip(args, names, fixed_of, strict=True)]  # fmt: skip
    results = _evaluate(gm, inputs)
    if len(results) < n_c:
        raise NativeUnavailable("the step returned fewer values than it carries")
    outputs: list[tuple[tuple[str, int], Scalar, str]] = []
    for i, (r, c) in enumerate(zip(results[:n_c], carry, strict=True)):
        if tuple(r.shape) != tuple(c.shape):
            raise NativeUnavailable("carry changes shape")
        code = _spec(c)[0]
        outputs += [((f"n{i}", j), v, code) for j, v in enumerate(r.flat)]
    out_shapes, out_dtypes = [], []
    for i, r in enumerate(results[n_c:]):
        code = _arr_dtype(r) if r.size else "d"
        dtype = {"d": torch.float64, "i": torch.int64, "b": torch.bool}[code]
        out_shapes.append(tuple(r.shape))
        out_dtypes.append(dtype)
        outputs += [((f"o{i}", j), v, code) for j, v in enumerate(r.flat)]
    order = _needed(graph, outputs)
    if len(order) > _MAX_STATEMENTS:
        raise NativeUnavailable(
            f"the step is {len(order)} scalar operations, above the {_MAX_STATEMENTS} the "
            "generated code serves"
        )
    io = _IO(carry, xs, consts, member_consts, out_shapes, out_dtypes)
    if members and not out_shapes:
        return _vector_program(graph, order, outputs, io), out_shapes, out_dtypes, _LANES
    return _scalar_program(graph, order, outputs, io), out_shapes, out_dtypes, 1


class _IO:
    """The chunk function's arguments, as the emitters need them."""

    def __init__(self, carry, xs, consts, member_consts, out_shapes, out_dtypes):  # type: ignore[no-untyped-def]
        self.carry = [(_spec(c), c.numel()) for c in carry]
        self.xs = [(_spec(x), x.numel()) for x in xs]
        self.consts = [
            (_spec(k), k.numel(), bool(b)) for k, b in zip(consts, member_consts, strict=True)
        ]
        self.outs = [
            (_CT[d], max(int(np.prod(s)), 1)) for s, d in zip(out_shapes, out_dtypes, strict=True)
        ]

    def pointers(self) -> list[str]:
        """Declarations of the argument pointers ``p[...]`` in `make_native_chunk`'s order."""
        decl, slot = [], 0
        groups = [("c", self.carry, False), ("xs", self.xs, True), ("valid", [(("b", "uint8_t"), 0)], True),
                  ("k", [(s, n) for s, n, _ in self.consts], True), ("o", self.outs, False)]  # fmt: skip
        for prefix, items, const in groups:
            for i, ((_, ctype), _n) in enumerate(items):
                name = prefix if prefix == "valid" else f"{prefix}{i}_base"
                decl.append(f"  {'const ' if const else ''}{ctype} *{name} = ({ctype} *)p[{slot}];")
                slot += 1
        return decl


def _needed(graph: _Graph, outputs: list[tuple[Any, Scalar, str]]) -> list[int]:
    """Ids of the nodes the outputs depend on, in topological (creation) order."""
    need: set[int] = set()
    stack = [v.id for _, v, _ in outputs if isinstance(v, _Sym)]
    while stack:
        i = stack.pop()
        if i in need:
            continue
        need.add(i)
        stack.extend(a.id for a in graph.nodes[i][1] if isinstance(a, _Sym))
    return sorted(need)


_HEADER = ["#include <math.h>", "#include <stdint.h>", ""]
_SIGNATURE = "void torchfric_chunk(int64_t m0, int64_t m1, int64_t K, int64_t C, void **p) {"
_COMPARE = ("<", "<=", ">", ">=", "==", "!=")


def _scalar_expr(graph: _Graph, i: int) -> str:
    """C expression of node `i` in scalar code (``v<id>`` names the other nodes)."""
    op, args, dt = graph.nodes[i]

    def ref(a: Scalar, dtype: str) -> str:
        return (
            f"v{a.id}"
            if isinstance(a, _Sym)
            else _literal(a, _dtype(a) if dtype == "any" else dtype)
        )

    if op == "leaf":
        return f"{args[0]}[{args[1]}]"
    if op in _INFIX:
        t = "any" if op in _COMPARE else dt
        return f"{ref(args[0], t)} {_INFIX[op]} {ref(args[1], t)}"
    if op == "neg":
        return f"-{ref(args[0], dt)}"
    if op == "!":
        return f"!{ref(args[0], dt)}"
    if op == "?:":
        return f"{ref(args[0], 'b')} ? {ref(args[1], dt)} : {ref(args[2], dt)}"
    if op == "cast":
        a = ref(args[0], "any")
        return f"({a}) != 0" if dt == "b" else f"({_C_TYPE[dt]})({a})"
    if op in ("max", "min"):
        a, b = ref(args[0], dt), ref(args[1], dt)
        return f"({a} != {a} || {a} {'>' if op == 'max' else '<'} {b}) ? {a} : {b}"
    if op == "sign":
        a = ref(args[0], dt)
        return f"({_C_TYPE[dt]})(({a} > 0) - ({a} < 0))"
    if op == "pow":
        return f"pow({ref(args[0], 'd')}, {ref(args[1], 'd')})"
    if op in _MATH:
        return f"{op}({ref(args[0], 'd')})"
    raise NativeUnavailable(f"no C form for {op}")  # pragma: no cover - every op has a case


def _scalar_program(graph: _Graph, order: list[int], outputs: list, io: _IO) -> str:
    """One member at a time: the step as scalar statements inside the loop over samples."""
    lines = [*_HEADER, _SIGNATURE, *io.pointers(), "  for (int64_t m = m0; m < m1; ++m) {"]
    for i, ((_, ctype), size) in enumerate(io.carry):
        lines += [
            f"    {ctype} *c{i} = c{i}_base + m * {size};",
            f"    {ctype} n{i}[{max(size, 1)}];",
        ]
    for i, ((_, ctype), size, batched) in enumerate(io.consts):
        lines.append(f"    const {ctype} *k{i} = k{i}_base{f' + m * {size}' if batched else ''};")
    for i, ((_, ctype), size) in enumerate(io.outs):
        lines.append(f"    {ctype} *o{i} = o{i}_base + m * {size};")
    lines.append("    for (int64_t t = 0; t < C; ++t) {")
    for i, ((_, ctype), size) in enumerate(io.xs):
        lines.append(f"      const {ctype} *x{i} = xs{i}_base + t * {size};")
    for i in order:
        lines.append(f"      const {_C_TYPE[graph.nodes[i][2]]} v{i} = {_scalar_expr(graph, i)};")
    for (name, j), value, dt in outputs:
        size = io.outs[int(name[1:])][1] if name[0] == "o" else 0
        target = f"{name}[t * K * {size} + {j}]" if name[0] == "o" else f"{name}[{j}]"
        if isinstance(value, _Sym):
            src = f"v{value.id}" if value.dtype == dt else f"({_C_TYPE[dt]})v{value.id}"
        else:
            src = _literal(value, dt)
        lines.append(f"      {target} = {src};")
    lines.append("      if (valid[t]) {")
    for i, (_, size) in enumerate(io.carry):
        lines.append(f"        for (int j = 0; j < {size}; ++j) c{i}[j] = n{i}[j];")
    lines += ["      }", "    }", "  }", "}", ""]
    return "\n".join(lines)


def _vector_prelude(w: int) -> list[str]:
    """Types and helpers of the SIMD code: `vd` (w doubles), `vi` (w int64: integers, and
    booleans as masks of all ones / zeros), broadcasts, selects and lane-wise maths."""
    cs = ", ".join(["c"] * w)
    lines = [
        f"typedef double vd __attribute__((vector_size({8 * w})));",
        f"typedef int64_t vi __attribute__((vector_size({8 * w})));",
        f"static inline vd bd(double c) {{ vd r = {{{cs}}}; return r; }}",
        f"static inline vi bi(int64_t c) {{ vi r = {{{cs}}}; return r; }}",
        "static inline vd seld(vi c, vd a, vd b) { return (vd)(((vi)a & c) | ((vi)b & ~c)); }",
        "static inline vi seli(vi c, vi a, vi b) { return (a & c) | (b & ~c); }",
        "static inline vd i2d(vi a) { return __builtin_convertvector(a, vd); }",
        "static inline vi d2i(vd a) { return __builtin_convertvector(a, vi); }",
        f"static inline vd v_pow(vd a, vd b) {{ vd r; for (int l = 0; l < {w}; ++l) r[l] = pow(a[l], b[l]); return r; }}",
    ]  # fmt: skip
    for f in _MATH:
        lines.append(f"static inline vd v_{f}(vd a) {{ vd r; for (int l = 0; l < {w}; ++l) "
                     f"r[l] = {f}(a[l]); return r; }}")  # fmt: skip
    return lines


def _vector_expr(graph: _Graph, i: int, leaf: Callable[[str, int], str]) -> str:
    """C expression of node `i` in the SIMD code (every value a `vd` or `vi` vector)."""
    op, args, dt = graph.nodes[i]

    def ref(a: Scalar, dtype: str) -> str:
        """`a` as a vector of `dtype`'s kind ('d' → vd, 'i'/'b' → vi)."""
        if not isinstance(a, _Sym):
            if dtype == "b":
                return "bi(-1)" if a else "bi(0)"
            return f"bd({_literal(a, 'd')})" if dtype == "d" else f"bi({_literal(a, 'i')})"
        v = f"v{a.id}"
        if a.dtype == dtype or {a.dtype, dtype} <= {"i", "b"} and dtype != "b" and a.dtype != "b":
            return v
        return _vector_cast(v, a.dtype, dtype)

    if op == "leaf":
        return leaf(*args)
    if op in _COMPARE:
        t = _promote(*args)
        t = "i" if t == "b" else t
        return f"(vi)({ref(args[0], t)} {_INFIX[op]} {ref(args[1], t)})"
    if op in ("&&", "||"):
        return f"{ref(args[0], 'b')} {'&' if op == '&&' else '|'} {ref(args[1], 'b')}"
    if op in _INFIX:
        return f"{ref(args[0], dt)} {_INFIX[op]} {ref(args[1], dt)}"
    if op == "neg":
        return f"-{ref(args[0], dt)}"
    if op == "!":
        return f"~{ref(args[0], 'b')}"
    if op == "?:":
        sel = "seld" if dt == "d" else "seli"
        return f"{sel}({ref(args[0], 'b')}, {ref(args[1], dt)}, {ref(args[2], dt)})"
    if op == "cast":
        return _vector_cast(f"v{args[0].id}", args[0].dtype, dt)
    if op in ("max", "min"):
        a, b = ref(args[0], dt), ref(args[1], dt)
        sel = "seld" if dt == "d" else "seli"
        return f"{sel}((vi)({a} != {a}) | (vi)({a} {'>' if op == 'max' else '<'} {b}), {a}, {b})"
    if op == "sign":
        a, z = ref(args[0], dt), "bd(0.0)" if dt == "d" else "bi(0)"
        s = f"(((vi)({a} > {z}) & bi(1)) - ((vi)({a} < {z}) & bi(1)))"
        return f"i2d{s}" if dt == "d" else s
    if op == "pow":
        return f"v_pow({ref(args[0], 'd')}, {ref(args[1], 'd')})"
    if op in _MATH:
        return f"v_{op}({ref(args[0], 'd')})"
    raise NativeUnavailable(f"no C form for {op}")  # pragma: no cover - every op has a case


def _vector_cast(v: str, src: str, dst: str) -> str:
    """Vector `v` of kind `src` as kind `dst` (booleans are all-ones / zero masks)."""
    if src == dst:
        return v
    if dst == "b":
        return f"(vi)({v} != {'bd(0.0)' if src == 'd' else 'bi(0)'})"
    if src == "b":
        return f"({v} & bi(1))" if dst == "i" else f"i2d({v} & bi(1))"
    return f"i2d({v})" if dst == "d" else f"d2i({v})"


def _vector_program(graph: _Graph, order: list[int], outputs: list, io: _IO) -> str:
    """`_LANES` members at once: each carry and member constant is loaded into vectors (lane
    l = member m + l; a missing last member repeats its neighbour and is not stored), the
    samples run on those vectors, and the carry is stored back at the end of the chunk."""
    w = _LANES
    vt = {"d": "vd", "i": "vi", "b": "vi"}
    lines = [*_HEADER, *_vector_prelude(w), "", _SIGNATURE, *io.pointers()]
    lines.append(f"  for (int64_t m = m0; m < m1; m += {w}) {{")
    lines.append(f"    int64_t mem[{w}];")
    lines.append(f"    for (int l = 0; l < {w}; ++l) mem[l] = m + l < m1 ? m + l : m1 - 1;")

    def load(local: str, base: str, code: str, size: int) -> None:
        lines.append(f"    {vt[code]} {local}[{max(size, 1)}];")
        val = f"{base}[mem[l] * {size} + j]"
        val = f"({val} ? -1 : 0)" if code == "b" else val
        lines.append(
            f"    for (int j = 0; j < {size}; ++j) for (int l = 0; l < {w}; ++l) {local}[j][l] = {val};"
        )

    for i, ((code, _), size) in enumerate(io.carry):
        load(f"C{i}", f"c{i}_base", code, size)
    for i, ((code, _), size, batched) in enumerate(io.consts):
        if batched:
            load(f"K{i}", f"k{i}_base", code, size)
        else:
            lines.append(f"    const {io.consts[i][0][1]} *k{i} = k{i}_base;")

    def leaf(name: str, j: int) -> str:
        kind, idx = name[0], int(name[1:])
        if kind == "c":
            return f"C{idx}[{j}]"
        if kind == "k" and io.consts[idx][2]:
            return f"K{idx}[{j}]"
        code = (io.xs[idx] if kind == "x" else io.consts[idx])[0][0]
        return f"bd({name}[{j}])" if code == "d" else f"bi({name}[{j}])"

    lines.append("    for (int64_t t = 0; t < C; ++t) {")
    for i, ((_, ctype), size) in enumerate(io.xs):
        lines.append(f"      const {ctype} *x{i} = xs{i}_base + t * {size};")
    for i, ((code, _), size) in enumerate(io.carry):
        lines.append(f"      {vt[code]} N{i}[{max(size, 1)}];")
    for i in order:
        lines.append(f"      const {vt[graph.nodes[i][2]]} v{i} = {_vector_expr(graph, i, leaf)};")
    for (name, j), value, dt in outputs:
        if isinstance(value, _Sym):
            src = _vector_cast(f"v{value.id}", value.dtype, dt)
        elif dt == "b":
            src = "bi(-1)" if value else "bi(0)"
        else:
            src = f"bd({_literal(value, 'd')})" if dt == "d" else f"bi({_literal(value, 'i')})"
        lines.append(f"      N{name[1:]}[{j}] = {src};")
    lines.append("      if (valid[t]) {")
    for i, (_, size) in enumerate(io.carry):
        lines.append(f"        for (int j = 0; j < {size}; ++j) C{i}[j] = N{i}[j];")
    lines += ["      }", "    }"]
    for i, ((code, _), size) in enumerate(io.carry):
        val = f"C{i}[j][l] & 1" if code == "b" else f"C{i}[j][l]"
        lines.append(f"    for (int l = 0; l < {w} && m + l < m1; ++l) for (int j = 0; j < {size}; ++j) "
                     f"c{i}_base[(m + l) * {size} + j] = {val};")  # fmt: skip
    lines += ["  }", "}", ""]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Compilation and loading
# ---------------------------------------------------------------------------------------------


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
_FLAGS = ["-O2", "-march=native", "-fno-fast-math", "-ffp-contract=off", "-fPIC", "-shared"]
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
    """Compile `source` once (cached on disk by hash) and load it."""
    cc = compiler()
    if cc is None:
        raise NativeUnavailable("no C compiler found (set CC)")
    ident = " ".join([*_FLAGS, cc, sys.platform, _cpu()])
    key = hashlib.sha256((source + ident).encode()).hexdigest()[:24]
    with _LOCK:
        if key in _LOADED:
            return _LOADED[key]
        folder = cache_dir()
        lib = folder / f"step_{key}.so"
        if not lib.exists():
            try:
                folder.mkdir(parents=True, exist_ok=True)
                with tempfile.TemporaryDirectory(dir=folder) as tmp:
                    src = Path(tmp) / "step.c"
                    src.write_text(source)
                    out = Path(tmp) / "step.so"
                    run = subprocess.run([cc, *_FLAGS, str(src), "-o", str(out), "-lm"],
                                         capture_output=True, text=True)  # fmt: skip
                    if run.returncode != 0:
                        raise NativeUnavailable(f"C compiler failed: {run.stderr.strip()[:300]}")
                    os.replace(out, lib)  # atomic: other processes see all of it or nothing
            except OSError as exc:
                raise NativeUnavailable(f"cannot build in {folder}: {exc}") from exc
        handle = ctypes.CDLL(str(lib))
        handle.torchfric_chunk.argtypes = [*[ctypes.c_int64] * 4, ctypes.POINTER(ctypes.c_void_p)]
        handle.torchfric_chunk.restype = None
        _LOADED[key] = handle
        return handle


def _structure(k: Tensor, batched: bool) -> dict[int, float]:
    """The entries of const `k` that are exactly 0 or 1 (for every member when `batched`):
    compiled in as constants, so the products they take part in fold away (H = [I 0] and the
    paper's Q = diag(0, q, 0, …) are almost all zeros and ones). They are part of the compiled
    code's key: a const with another pattern gets code of its own."""
    if k.dtype != torch.float64 or k.numel() > 4096:
        return {}
    flat = k.detach().reshape(k.shape[0], -1) if batched else k.detach().reshape(1, -1)
    out: dict[int, float] = {}
    for value in (0.0, 1.0):
        same = (flat == value).all(0)
        out.update({int(j): value for j in same.nonzero().flatten().tolist()})
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
    independently, split across the cores (`_threads`). Per-sample outputs then
    have shape ``(C, K, ...)``, as the scan of the batched function gives them. Raises `NativeUnavailable` (before touching anything) when the
    function cannot be translated.
    """
    built: dict[tuple, tuple[ctypes.CDLL, list, list, int]] = {}
    failed: dict[tuple, NativeUnavailable] = {}

    def chunk(carry, xs, valid, consts):  # type: ignore[no-untyped-def]
        carry, xs, consts = tuple(carry), tuple(xs), tuple(consts)
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
