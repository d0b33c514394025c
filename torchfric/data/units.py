"""Units and column names of the data files: the one place they are defined.

- `COLUMN_NAMES`: the columns torchfric reads (t in s, the input u, the position q, and
  optionally the velocity qdot);
- `POSITION_UNITS`: the units ``data.position_unit`` accepts, each with its factor to SI (rad
  for a rotary axis, m for a linear one);
- `UNIT_ALIASES`: how lab software writes a unit in a column header (``[deg]``, ``(ms)``,
  ``[counts]``) → the unit's canonical name;
- `si_unit`, `force_unit`: the SI unit a position is converted to and the friction's unit.
"""

from __future__ import annotations

import math

__all__ = ["COLUMN_NAMES", "POSITION_UNITS", "UNIT_ALIASES", "force_unit", "si_unit"]

COLUMN_NAMES: tuple[str, ...] = ("t", "u", "q", "qdot")

POSITION_UNITS: dict[str, float] = {"rad": 1.0, "deg": math.pi / 180.0, "m": 1.0, "mm": 1e-3}
"""Unit of q in the data files → factor to SI (rad or m) that the runner multiplies q by."""

UNIT_ALIASES: dict[str, str] = {
    "deg": "deg", "degree": "deg", "degrees": "deg", "°": "deg", "rad": "rad",
    "radian": "rad", "radians": "rad", "m": "m", "meter": "m", "metre": "m",
    "meters": "m", "metres": "m", "mm": "mm", "counts": "counts", "count": "counts",
    "cnt": "counts", "cnts": "counts", "inc": "counts", "ticks": "counts",
    "s": "s", "sec": "s", "ms": "ms", "us": "us", "µs": "us",
}  # fmt: skip


def si_unit(unit: str) -> str:
    """The SI unit positions in `unit` are converted to: "m" (linear) or "rad" (rotary)."""
    return "m" if unit in ("m", "mm") else "rad"


def force_unit(unit: str) -> str:
    """The unit of the friction (and of c_m·u) on an axis whose positions are in `unit`."""
    return "N" if si_unit(unit) == "m" else "N m"
