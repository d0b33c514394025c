"""Plain C functions of a torch function, for code that runs without torch (`torchfric.export`).

`c_function` traces a function of a few small float64 tensors with the same tracer and scalar
graph as the filter's generated steps (`emit`), and writes it as one C99 function of pointers:
``static void NAME(const double *a, const double *b, …, double *out0, double *out1, …)``, each
argument's entries read as ``a[j]`` (flattened, row-major) and each output's written as
``outK[j]``. The arithmetic is the traced graph's, operation by operation, in IEEE double
precision; compiled without fast-math it agrees with the torch function to rounding (the
exported models' tests check 1e-12). Nothing but ``<math.h>`` is needed: the graph's integer
type is written ``long long``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from .aten import _evaluate
from .emit import _literal, _needed, _scalar_expr, _spec, _symbols
from .scalar import _C_TYPE, NativeUnavailable, _dtype, _Graph, _Sym

__all__ = ["c_function", "NativeUnavailable"]


def _ctype(code: str) -> str:
    return "long long" if code == "i" else _C_TYPE[code]


def c_function(
    name: str, fn: Callable[..., Tensor | tuple[Tensor, ...]], args: Sequence[tuple[str, Tensor]]
) -> str:
    """C source of ``static void name(args…, out0, out1, …)`` computing `fn` on the named
    float64 argument tensors (their values are only examples for the trace). A
    `NativeUnavailable` names an operation without a C form."""
    from torch.fx.experimental.proxy_tensor import make_fx

    examples = [t.detach().to(torch.float64) for _, t in args]

    def flat(*xs: Tensor) -> tuple[Tensor, ...]:
        out = fn(*xs)
        return tuple(out) if isinstance(out, (tuple, list)) else (out,)

    with warnings.catch_warnings():  # tracing touches module reprs; not the caller's business
        warnings.simplefilter("ignore")
        gm = make_fx(torch.func.functionalize(flat, remove="mutations"))(*examples)
    graph = _Graph()
    inputs = [
        _symbols(graph, t, nm, _spec(t)[0]) for (nm, _), t in zip(args, examples, strict=True)
    ]
    results = _evaluate(gm, inputs)
    outputs = [
        ((f"out{k}", j), v, "d") for k, r in enumerate(results) for j, v in enumerate(r.flat)
    ]
    order = _needed(graph, outputs)
    params = [f"const double *{nm}" for nm, _ in args]
    params += [f"double *out{k}" for k in range(len(results))]
    lines = [f"static void {name}({', '.join(params)}) {{"]
    for nm, _ in args:  # an argument the result does not read would warn under -Wextra
        lines.append(f"  (void){nm};")
    for i in order:
        expr = _scalar_expr(graph, i).replace("int64_t", "long long")
        lines.append(f"  const {_ctype(graph.nodes[i][2])} v{i} = {expr};")
    for (target, j), value, _ in outputs:
        if isinstance(value, _Sym):
            src = f"v{value.id}" if value.dtype == "d" else f"(double)v{value.id}"
        else:
            src = _literal(value, _dtype(value))
        lines.append(f"  {target}[{j}] = {src};")
    lines.append("}")
    return "\n".join(lines) + "\n"
