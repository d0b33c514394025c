"""ATen operations on arrays of symbols: what `make_fx`'s graph of the step becomes.

`_OPS` maps each ATen overload that the filter's steps use (and the common ones around them) to
the same operation on numpy object arrays of `torchfric.accel.native.scalar` symbols; `_evaluate` runs
a traced graph through it. An overload outside the table raises `NativeUnavailable` naming it.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .scalar import (
    NativeUnavailable,
    _add,
    _and,
    _arr,
    _compare,
    _div,
    _dtype,
    _fill,
    _lift,
    _maximum,
    _minimum,
    _mul,
    _neg,
    _not,
    _or,
    _pow,
    _promote,
    _reduce,
    _sign,
    _sub,
    _to,
    _unary,
    _where,
)

# Nothing public: `_OPS` and `_evaluate` serve `emit` inside this package.
__all__: list[str] = []

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
    if dtype == torch.float64:
        return "d"  # (float32 would need its own rounding: the torch paths serve it)
    raise NativeUnavailable(f"dtype {dtype}")


def _arr_dtype(a: np.ndarray) -> str:
    return _promote(*a.flat) if a.size else "d"


def _select(a: np.ndarray, dim: int, i: int) -> np.ndarray:
    return np.take(a, i, axis=dim).copy() if a.ndim > 1 else _arr(a[i])


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
    "aten.masked_fill.Scalar": lambda a, mask, v: _where_a(mask, _arr(v), a),
    "aten.masked_fill.Tensor": lambda a, mask, v: _where_a(mask, v, a),
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
    "aten.unbind.int": lambda a, dim=0: [_select(a, dim, i) for i in range(a.shape[dim])],
    "aten.select.int": _select,
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
