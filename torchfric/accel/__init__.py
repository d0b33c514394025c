"""Compiled execution: the one place where torchfric compiles or generates code.

Estimators describe one sample's work as a plain function of tensors; this package runs it
fast, with the same arithmetic, and falls back to the plain function wherever it cannot:

- `chunks`: the chunk compiler (`make_chunk`: generated C, else an Inductor scan, else a
  Python loop over `CHUNK` samples per call), `compile_with_fallback`, `compile_step` /
  `Step`, and the helpers that feed sequences through chunks (`iter_chunks`, `run_chunks`).
- `simulation`: the "compiled" engine of `torchfric.models.simulate.simulate`, registered with
  `torchfric.models.simulate.register_engine` when this package is imported.
- `native`: the generated-C backend of `make_chunk` and its on-disk cache.

Only the estimators use this package; models and data never import it.
"""

from . import simulation  # registers simulate's "compiled" engine
from .chunks import (
    CHUNK,
    Step,
    chunk_options,
    compile_step,
    compile_with_fallback,
    fused_matmul,
    iter_chunks,
    make_chunk,
    pad_rows,
    product_name,
    run_chunks,
    step_key,
    structure_key,
)
from .simulation import compiled_engine, rk4_chunk

__all__ = [
    "CHUNK",
    "Step",
    "chunk_options",
    "compile_step",
    "compile_with_fallback",
    "compiled_engine",
    "fused_matmul",
    "iter_chunks",
    "make_chunk",
    "pad_rows",
    "product_name",
    "rk4_chunk",
    "run_chunks",
    "simulation",
    "step_key",
    "structure_key",
]
