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


class _Graph:
    """Interned scalar nodes ``(op, args, dtype)``; ids are in topological order."""

    def __init__(self) -> None:
        self.nodes: list[tuple[str, tuple, str]] = []
        self.index: dict[tuple, _Sym] = {}

    def node(self, op: str, args: tuple, dtype: str) -> _Sym:
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


def _slice_backward(g, sizes, dim, start, end, step):  # type: ignore[no-untyped-def]
    out = _fill(sizes, 0.0)
    idx = [slice(None)] * len(sizes)
    idx[dim] = slice(start, end, step)
    out[tuple(idx)] = g
    return out


def _select_backward(g, sizes, dim, index):  # type: ignore[no-untyped-def]
    out = _fill(sizes, 0.0)
    idx: list[Any] = [slice(None)] * len(sizes)
    idx[dim] = index
    out[tuple(idx)] = g
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
    out[tuple(slice(lo, lo + s) for s, (lo, _) in zip(a.shape, widths, strict=True))] = a
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
        out[..., i, i] = a[..., i]
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


def _emit_body(
    graph: _Graph, leaves: dict[int, str], outputs: list[tuple[str, Scalar, str]]
) -> list[str]:
    """Statements computing each output ``(target, value, dtype)``: the nodes they need, in order."""
    need: set[int] = set()
    stack = [v.id for _, v, _ in outputs if isinstance(v, _Sym)]
    while stack:
        i = stack.pop()
        if i in need:
            continue
        need.add(i)
        stack.extend(a.id for a in graph.nodes[i][1] if isinstance(a, _Sym))

    def ref(a: Scalar, dtype: str) -> str:
        return (
            f"v{a.id}"
            if isinstance(a, _Sym)
            else _literal(a, _dtype(a) if dtype == "any" else dtype)
        )

    lines: list[str] = []
    for i in sorted(need):
        op, args, dt = graph.nodes[i]
        if op == "leaf":
            expr = leaves[i]
        elif op in _INFIX:
            expr = f"{ref(args[0], dt if op not in ('<', '<=', '>', '>=', '==', '!=') else 'any')} {_INFIX[op]} {ref(args[1], dt if op not in ('<', '<=', '>', '>=', '==', '!=') else 'any')}"
        elif op == "neg":
            expr = f"-{ref(args[0], dt)}"
        elif op == "!":
            expr = f"!{ref(args[0], dt)}"
        elif op == "?:":
            expr = f"{ref(args[0], 'b')} ? {ref(args[1], dt)} : {ref(args[2], dt)}"
        elif op == "cast":
            expr = f"({_C_TYPE[dt]})({ref(args[0], 'any')})"
            if dt == "b":
                expr = f"({ref(args[0], 'any')}) != 0"
        elif op in ("max", "min"):
            a, b = ref(args[0], dt), ref(args[1], dt)
            cmp = ">" if op == "max" else "<"
            expr = f"({a} != {a} || {a} {cmp} {b}) ? {a} : {b}"
        elif op == "sign":
            a = ref(args[0], dt)
            expr = f"({_C_TYPE[dt]})(({a} > 0) - ({a} < 0))"
        elif op == "pow":
            expr = f"pow({ref(args[0], 'd')}, {ref(args[1], 'd')})"
        elif op in _MATH:
            expr = f"{op}({ref(args[0], 'd')})"
        else:  # pragma: no cover - every op above has a case
            raise NativeUnavailable(f"no C form for {op}")
        lines.append(f"const {_C_TYPE[dt]} v{i} = {expr};")
    for target, value, dt in outputs:
        lines.append(
            f"{target} = {ref(value, dt) if not isinstance(value, _Sym) or value.dtype == dt else f'({_C_TYPE[dt]})v{value.id}'};"
        )
    return lines


_CT = {torch.float64: ("d", "double"), torch.int64: ("i", "int64_t"), torch.bool: ("b", "uint8_t")}


def _spec(t: Tensor) -> tuple[str, str]:
    if t.dtype not in _CT:
        raise NativeUnavailable(f"tensor dtype {t.dtype}")
    return _CT[t.dtype]


def _symbols(
    graph: _Graph,
    leaves: dict[int, str],
    t: Tensor,
    name: str,
    code: str,
    fixed: dict[int, float] | None = None,
) -> np.ndarray:
    """An object array of leaf symbols for tensor `t`, leaf j reading ``name[j]``; the entries
    in `fixed` are the constants given there instead."""
    arr = np.empty(t.numel(), dtype=object)
    for j in range(t.numel()):
        if fixed and j in fixed:
            arr[j] = _to(fixed[j], code)
            continue
        sym = graph.node("leaf", (name, j), code)
        leaves[sym.id] = f"{name}[{j}]"
        arr[j] = sym
    return arr.reshape(tuple(t.shape))


def _source(
    fn: Callable,
    carry: Sequence[Tensor],
    xs: Sequence[Tensor],
    consts: Sequence[Tensor],
    member_consts: Sequence[bool],
    fixed: Sequence[dict[int, float]] = (),
) -> tuple[str, list[tuple[int, ...]], list[torch.dtype]]:
    """C source of the chunk loop; also the per-sample shapes and dtypes of the outputs.

    Tensors arrive per member (batched ones with their member axis at size 1). `fixed[i]`
    maps flat entries of const i to the values they are compiled in as (`_structure`)."""
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
    leaves: dict[int, str] = {}
    names = [f"c{i}" for i in range(n_c)] + [f"x{i}" for i in range(n_x)]
    names += [f"k{i}" for i in range(len(consts))]
    fixed_of = [None] * (n_c + n_x) + list(fixed or [None] * len(consts))
    inputs = [_symbols(graph, leaves, t, nm, _spec(t)[0], fx)
              for t, nm, fx in zip(args, names, fixed_of, strict=True)]  # fmt: skip
    results = _evaluate(gm, inputs)
    if len(results) < n_c:
        raise NativeUnavailable("the step returned fewer values than it carries")
    outputs: list[tuple[str, Scalar, str]] = []
    for i, (r, c) in enumerate(zip(results[:n_c], carry, strict=True)):
        if tuple(r.shape) != tuple(c.shape):
            raise NativeUnavailable("carry changes shape")
        code = _spec(c)[0]
        outputs += [(f"n{i}[{j}]", v, code) for j, v in enumerate(r.flat)]
    out_shapes, out_dtypes = [], []
    for i, r in enumerate(results[n_c:]):
        code = _arr_dtype(r) if r.size else "d"
        dtype = {"d": torch.float64, "i": torch.int64, "b": torch.bool}[code]
        out_shapes.append(tuple(r.shape))
        out_dtypes.append(dtype)
        outputs += [(f"o{i}[t * {r.size} + {j}]", v, code) for j, v in enumerate(r.flat)]

    body = _emit_body(graph, leaves, outputs)
    lines = ["#include <math.h>", "#include <stdint.h>", "",
             "void torchfric_chunk(int64_t m0, int64_t m1, int64_t C, void **p) {"]  # fmt: skip
    slot = 0
    decl: list[str] = []

    def pointer(name: str, ctype: str, const: bool) -> None:
        nonlocal slot
        decl.append(f"  {'const ' if const else ''}{ctype} *{name}_base = ({ctype} *)p[{slot}];")
        slot += 1

    for i, c in enumerate(carry):
        pointer(f"c{i}", _spec(c)[1], False)
    for i, x in enumerate(xs):
        pointer(f"xs{i}", _spec(x)[1], True)
    pointer("valid", "uint8_t", True)
    decl.append("  const uint8_t *valid = valid_base;")
    for i, k in enumerate(consts):
        pointer(f"k{i}", _spec(k)[1], True)
    for i, dt in enumerate(out_dtypes):
        pointer(f"o{i}", _CT[dt][1], False)
    lines += decl
    lines.append("  for (int64_t m = m0; m < m1; ++m) {")
    for i, c in enumerate(carry):
        ctype, size = _spec(c)[1], c.numel()
        lines.append(f"    {ctype} *c{i} = c{i}_base + m * {size};")
        lines.append(f"    {ctype} n{i}[{max(size, 1)}];")
    for i, k in enumerate(consts):
        off = f" + m * {k.numel()}" if member_consts[i] else ""
        lines.append(f"    const {_spec(k)[1]} *k{i} = k{i}_base{off};")
    for i, (r, dt) in enumerate(zip(out_shapes, out_dtypes, strict=True)):
        size = max(int(np.prod(r)), 1)
        lines.append(f"    {_CT[dt][1]} *o{i} = o{i}_base + m * C * {size};")
    lines.append("    for (int64_t t = 0; t < C; ++t) {")
    for i, x in enumerate(xs):
        lines.append(f"      const {_spec(x)[1]} *x{i} = xs{i}_base + t * {x.numel()};")
    lines += ["      " + s for s in body]
    lines.append("      if (valid[t]) {")
    for i, c in enumerate(carry):
        lines.append(f"        for (int j = 0; j < {c.numel()}; ++j) c{i}[j] = n{i}[j];")
    lines += ["      }", "    }", "  }", "}", ""]
    return "\n".join(lines), out_shapes, out_dtypes


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
        handle.torchfric_chunk.argtypes = [ctypes.c_int64, ctypes.c_int64, ctypes.c_int64,
                                           ctypes.POINTER(ctypes.c_void_p)]  # fmt: skip
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
    have shape ``(K, C, ...)``. Raises `NativeUnavailable` (before touching anything) when the
    function cannot be translated.
    """
    built: dict[tuple, tuple[ctypes.CDLL, list, list]] = {}

    def chunk(carry, xs, valid, consts):  # type: ignore[no-untyped-def]
        carry, xs, consts = tuple(carry), tuple(xs), tuple(consts)
        flags = tuple(member_consts) + (False,) * (len(consts) - len(member_consts))
        K = carry[0].shape[0] if members else 1
        C = valid.shape[0]
        fixed = [_structure(k, members and f) for k, f in zip(consts, flags, strict=True)]
        key = (tuple((t.shape, t.dtype) for t in (*carry, *xs, *consts)),
               tuple(tuple(sorted(f.items())) for f in fixed))  # fmt: skip
        if key not in built:
            one_c = [c[:1] if members else c for c in carry]
            one_k = [k[:1] if (members and f) else k for k, f in zip(consts, flags, strict=True)]
            src, shapes, dtypes = _source(
                fn, one_c, [x[0] for x in xs], one_k,
                flags if members else (False,) * len(consts), fixed,
            )  # fmt: skip
            built[key] = (_build(src), shapes, dtypes)
        lib, shapes, dtypes = built[key]
        new = [c.detach().clone().contiguous() for c in carry]
        ins = [x.detach().contiguous() for x in xs]
        ks = [k.detach().contiguous() for k in consts]
        v = valid.to(torch.uint8).contiguous()
        outs = [
            torch.empty((K, C, *s) if members else (C, *s), dtype=d)
            for s, d in zip(shapes, dtypes, strict=True)
        ]
        ptrs = (ctypes.c_void_p * (len(new) + len(ins) + 1 + len(ks) + len(outs)))(
            *[t.data_ptr() for t in (*new, *ins, v, *ks, *outs)]
        )
        threads = _threads(K)
        if threads == 1:
            lib.torchfric_chunk(0, K, C, ptrs)
        else:
            bounds = [K * i // threads for i in range(threads + 1)]
            workers = [threading.Thread(target=lib.torchfric_chunk, args=(a, b, C, ptrs))
                       for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]  # fmt: skip
            for w in workers:
                w.start()
            for w in workers:
                w.join()
        return tuple(new), tuple(outs)

    chunk.native = True  # type: ignore[attr-defined]
    return chunk
