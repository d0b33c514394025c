"""The scalar expression graph that `torchfric.accel.native` traces the step into.

Every value of the traced computation is a `_Sym` node of a `_Graph` (or a Python constant);
operations intern their nodes, so equal sub-expressions are shared, and fold constants and the
exact identities x·0 = 0, x·1 = x, x + 0 = x. Operations on whole tensors are numpy object
arrays of these scalars (`_lift` turns a scalar operation into a broadcasting one).
"""

from __future__ import annotations

import functools
import math
import operator
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

__all__ = ["NativeUnavailable", "Scalar"]


class NativeUnavailable(RuntimeError):
    """The native path cannot serve this function (unsupported operation, no C compiler…)."""


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


def _extremum(op: str, pick: Callable[[Any, Any], Any]) -> Callable[[Scalar, Scalar], Scalar]:
    """Elementwise "max" or "min", NaN-propagating like torch.maximum / torch.minimum."""

    def f(a: Scalar, b: Scalar) -> Scalar:
        dt = _promote(a, b)
        a, b = _to(a, dt), _to(b, dt)
        if _const(a) and _const(b):
            return math.nan if math.isnan(a) or math.isnan(b) else pick(a, b)
        return _graph_of(a, b).node(op, (a, b), dt)

    return f


_maximum = _extremum("max", max)
_minimum = _extremum("min", min)


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
