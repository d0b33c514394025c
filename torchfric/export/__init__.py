"""The identified model where simulation and control engineers work: an FMI 2.0 FMU
(`export_fmu`) and dependency-free C99 sources (`export_c`), written from the same torch code
that `torchfric.simulate` runs (`program`: the model's functions traced into C).

A layer of its own: it imports models and accel's C emitter; only app imports it.
"""

from __future__ import annotations

from .csource import export_c
from .fmu import FMUInfo, export_fmu, model_identifier

__all__ = ["FMUInfo", "export_c", "export_fmu", "model_identifier"]
