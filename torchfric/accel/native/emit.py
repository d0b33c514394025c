"""C source of a chunk of steps: the traced step's scalar graph as straight-line code.

`_source` traces the per-sample function, evaluates it on symbols (`aten._evaluate`) and emits
one C function ``torchfric_chunk(m0, m1, K, C, p)`` that runs samples 0…C−1 of members m0…m1−1:
one member at a time in scalar code (`_scalar_program`), or, for ensembles, `_LANES` members per
SIMD vector (`_vector_program`, GCC vector types). The scalar
program also has a CUDA form (``target="cuda"``): the same statements in a kernel whose threads
are the members (`torchfric.accel.native.cuda`). A batch of simulations, each under its own
input, is a member program too: its per-member inputs are read lane by lane (``member_xs``).

Why this size: the two programs share the trace, the symbol graph and the argument layout, and
each emitter is one loop over the same graph; split apart they would restate the layout.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .aten import _arr_dtype, _evaluate
from .scalar import _C_TYPE, _MATH, NativeUnavailable, Scalar, _dtype, _Graph, _promote, _Sym, _to
from .tanh import SCALAR as _TANH
from .tanh import vector as _vector_tanh

# Nothing public: `_source` serves the package's `make_native_chunk`.
__all__: list[str] = []


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
    target: str = "c",
    member_xs: Sequence[bool] = (),
) -> tuple[str, list[tuple[int, ...]], list[torch.dtype], int]:
    """C source of the chunk loop; also the per-sample shapes and dtypes of the outputs and the
    members per vector (1: scalar code).

    Tensors arrive per member (batched ones with their member axis at size 1). `fixed[i]`
    maps flat entries of const i to the values they are compiled in as (`_structure`). With
    `members`, the code runs `_LANES` members at once in SIMD vectors (`_vector_program`);
    otherwise one member at a time (`_scalar_program`). With
    ``target="cuda"``, the scalar program as a CUDA kernel (one member per thread).
    `member_xs[i]` marks per-sample input i as one per member (``(C, K, ...)``, e.g. each
    window's own input in a batch of simulations): the SIMD program only."""
    from torch.fx.experimental.proxy_tensor import make_fx

    n_c, n_x = len(carry), len(xs)

    def flat(*args: Tensor):  # type: ignore[no-untyped-def]
        new, outs = fn(*args)
        return (*new, *outs)

    args = [*carry, *xs, *consts]
    try:
        with warnings.catch_warnings():  # tracing touches module reprs; not the user's business
            warnings.simplefilter("ignore")
            # functionalised: in-place operations (autograd's backward of maximum, say)
            # become their out-of-place forms, which the symbol arrays can evaluate
            gm = make_fx(torch.func.functionalize(flat, remove="mutations"))(*args)
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
    io = _IO(carry, xs, consts, member_consts, out_shapes, out_dtypes, member_xs)
    if any(io.member_xs) and (target == "cuda" or not members):
        raise NativeUnavailable("per-member inputs are served by the CPU's member program only")
    if target == "cuda":
        return _scalar_program(graph, order, outputs, io, cuda=True), out_shapes, out_dtypes, 1
    if members:
        return _vector_program(graph, order, outputs, io), out_shapes, out_dtypes, _LANES
    return _scalar_program(graph, order, outputs, io), out_shapes, out_dtypes, 1


class _IO:
    """The chunk function's arguments, as the emitters need them."""

    def __init__(self, carry, xs, consts, member_consts, out_shapes, out_dtypes, member_xs=()):  # type: ignore[no-untyped-def]
        self.carry = [(_spec(c), c.numel()) for c in carry]
        self.xs = [(_spec(x), x.numel()) for x in xs]
        self.member_xs = [bool(b) for b in member_xs] + [False] * (len(xs) - len(member_xs))
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


_HEADER = ["#include <math.h>", "#include <stdint.h>", "#include <string.h>", ""]
_SIGNATURE = "void torchfric_chunk(int64_t m0, int64_t m1, int64_t K, int64_t C, void **p) {"
_COMPARE = ("<", "<=", ">", ">=", "==", "!=")
# The CUDA form (NVRTC has no C library headers: its maths functions are built in): the same
# names, the member loop a grid-stride loop over the threads.
_CUDA_HEADER = [
    "typedef long long int64_t;",
    "typedef unsigned char uint8_t;",
    "#define INFINITY __longlong_as_double(0x7ff0000000000000LL)",
    "#define NAN __longlong_as_double(0x7ff8000000000000LL)",
    "",
]
_CUDA_SIGNATURE = (
    'extern "C" __global__ void torchfric_chunk(int m0_, int m1_, int K_, int C_, void **p) {\n'
    "  const int64_t m0 = m0_, m1 = m1_, K = K_, C = C_;"
)
_MEMBER_LOOP = "  for (int64_t m = m0; m < m1; ++m) {"
_CUDA_MEMBER_LOOP = (
    "  for (int64_t m = m0 + (int64_t)blockIdx.x * blockDim.x + threadIdx.x; m < m1;\n"
    "       m += (int64_t)gridDim.x * blockDim.x) {"
)


def _scalar_expr(graph: _Graph, i: int, own_tanh: bool = False) -> str:
    """C expression of node `i` in scalar code (``v<id>`` names the other nodes); `own_tanh`
    calls `torchfric.accel.native.tanh`'s ``tf_tanh`` instead of the C library's."""
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
        return f"{'tf_tanh' if own_tanh and op == 'tanh' else op}({ref(args[0], 'd')})"
    raise NativeUnavailable(f"no C form for {op}")  # pragma: no cover - every op has a case


def _scalar_program(
    graph: _Graph, order: list[int], outputs: list, io: _IO, *, cuda: bool = False
) -> str:
    """One member at a time: the step as scalar statements inside the loop over samples (with
    `cuda`, a kernel: one member per thread)."""
    head = [*_CUDA_HEADER, _CUDA_SIGNATURE] if cuda else [*_HEADER, _TANH, _SIGNATURE]
    lines = [*head, *io.pointers(), _CUDA_MEMBER_LOOP if cuda else _MEMBER_LOOP]
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
        lines.append(
            f"      const {_C_TYPE[graph.nodes[i][2]]} v{i} = {_scalar_expr(graph, i, not cuda)};"
        )
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
    lines.append(_vector_tanh(w))
    for f in (f for f in _MATH if f != "tanh"):
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
        if a.dtype == dtype:
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
    samples run on those vectors, each per-sample output is stored lane by lane, and the carry
    is stored back at the end of the chunk."""
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
        if kind == "x" and io.member_xs[idx]:
            return f"X{idx}[{j}]"
        code = (io.xs[idx] if kind == "x" else io.consts[idx])[0][0]
        return f"bd({name}[{j}])" if code == "d" else f"bi({name}[{j}])"

    lines.append("    for (int64_t t = 0; t < C; ++t) {")
    for i, ((code, ctype), size) in enumerate(io.xs):
        if not io.member_xs[i]:
            lines.append(f"      const {ctype} *x{i} = xs{i}_base + t * {size};")
            continue
        # one input per member, stored (C, K, ...): each lane reads its member's row
        val = f"xs{i}_base[(t * K + mem[l]) * {size} + j]"
        lines.append(f"      {vt[code]} X{i}[{max(size, 1)}];")
        lines.append(f"      for (int j = 0; j < {size}; ++j) for (int l = 0; l < {w}; ++l) "
                     f"X{i}[j][l] = {f'({val} ? -1 : 0)' if code == 'b' else val};")  # fmt: skip
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
        if name[0] == "o":  # a per-sample output: each real lane to its member's slot
            size = io.outs[int(name[1:])][1]
            cast = f"({io.outs[int(name[1:])][0][1]})"
            lane = "(o_v[l] & 1)" if dt == "b" else "o_v[l]"
            lines.append(
                f"      {{ const {vt[dt]} o_v = {src}; for (int l = 0; l < {w} && m + l < m1; ++l) "
                f"o{name[1:]}_base[(t * K + m + l) * {size} + {j}] = {cast}{lane}; }}"
            )
            continue
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
