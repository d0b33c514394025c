"""Units and column names of the data files: the one place they are defined.

- `COLUMN_NAMES`: the columns torchfric reads (t, the input u, the position q, and optionally
  the velocity qdot);
- `TIME_UNITS`: the units ``data.time_unit`` accepts, each with its factor to s;
- `POSITION_UNITS`: the units ``data.position_unit`` accepts, each with its factor to SI (rad
  for a rotary axis, m for a linear one); ``"counts"`` has none of its own: `position_factor`
  takes it from the counts per revolution (or per metre);
- `UNIT_ALIASES`: how lab software writes a unit in a column header (``[deg]``, ``(ms)``,
  ``/ms``, ``in ms``, ``[Inkremente]``) → the unit's canonical name; `split_unit` reads it;
- `si_unit`, `force_unit`: the SI unit a position is converted to and the friction's unit.
"""

from __future__ import annotations

import math
import re
import unicodedata

__all__ = [
    "COLUMN_NAMES",
    "OTHER_TIME_UNITS",
    "POSITION_UNITS",
    "TIME_UNITS",
    "UNIT_ALIASES",
    "force_unit",
    "position_factor",
    "si_unit",
    "split_unit",
    "stated_unit",
]

COLUMN_NAMES: tuple[str, ...] = ("t", "u", "q", "qdot")

TIME_UNITS: dict[str, float] = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
"""Unit of t in the data files → factor to s that the loader multiplies t by."""

POSITION_UNITS: dict[str, float | None] = {
    "rad": 1.0, "deg": math.pi / 180.0, "rev": 2.0 * math.pi, "m": 1.0, "mm": 1e-3, "um": 1e-6,
    "counts": None,
}  # fmt: skip
"""Unit of q in the data files → factor to SI (rad or m) that the loader multiplies q by
(None for counts: 2π / counts per revolution, or 1 / counts per metre)."""

LINEAR_UNITS = ("m", "mm", "um")
"""The position units of a linear axis (the rest but counts are angles)."""

UNIT_ALIASES: dict[str, str] = {
    "deg": "deg", "degree": "deg", "degrees": "deg", "°": "deg", "grad": "deg", "rad": "rad",
    "radian": "rad", "radians": "rad", "rev": "rev", "revs": "rev", "revolution": "rev",
    "revolutions": "rev", "turn": "rev", "turns": "rev", "umdr": "rev", "umdrehung": "rev",
    "umdrehungen": "rev", "m": "m", "meter": "m", "metre": "m",
    "meters": "m", "metres": "m", "mm": "mm", "µm": "um", "um": "um", "micron": "um",
    "microns": "um", "counts": "counts", "count": "counts",
    "cnt": "counts", "cnts": "counts", "inc": "counts", "incr": "counts", "ticks": "counts",
    "increments": "counts", "inkremente": "counts", "inkr": "counts", "pulses": "counts",
    "impulse": "counts", "digits": "counts",
    "s": "s", "sec": "s", "secs": "s", "second": "s", "seconds": "s", "ms": "ms", "msec": "ms",
    "millisecond": "ms", "milliseconds": "ms", "us": "us", "µs": "us", "μs": "us", "usec": "us",
    "microsecond": "us", "microseconds": "us",
}  # fmt: skip

OTHER_TIME_UNITS = frozenset({
    "min", "mins", "minute", "minutes", "h", "hr", "hrs", "hour", "hours", "ns", "nsec",
    "nanosecond", "nanoseconds", "d", "day", "days",
})  # fmt: skip
"""Time units a header may state that torchfric does not convert: refused by name, where any
other bracket after a time column's name (``Zeit (relativ)``, ``Time (UTC)``) is not a unit."""

_EXPLICIT = re.compile(r"\s*(?:[\[(]([^\])]*)[\])]|/\s*(\S+)|\s+in\s+(\S+))\s*$")


def _plain(text: str) -> str:
    """Lower case without accents: ``Stellgröße`` → ``stellgrosse``, ``Posición`` →
    ``posicion`` (µ and ° are kept: they are units)."""
    text = text.strip().lower().replace("ß", "ss")
    decomposed = unicodedata.normalize("NFKD", text)
    return "".join(c for c in decomposed if not unicodedata.combining(c)).replace("μ", "µ")


def split_unit(name: str) -> tuple[str, str | None, bool]:
    """(base name, unit, whether the unit is explicit) of a column name: ``"Zeit [ms]"`` →
    ("zeit", "ms", True), ``"t/ms"`` and ``"Zeit in ms"`` likewise, ``"pos_deg"`` → ("pos",
    "deg", False); the unit is None when the name gives none (or one we do not know)."""
    s, unit, explicit = _plain(name), None, False
    m = _EXPLICIT.search(s)
    if m and m.start() > 0:
        s, unit = s[: m.start()], UNIT_ALIASES.get(next(g for g in m.groups() if g).strip())
        explicit = unit is not None
    s = re.sub(r"[\s.\-]+", "_", s).strip("_")
    base, sep, tail = s.rpartition("_")
    if unit is None and sep and base and tail in UNIT_ALIASES:
        s, unit = base, UNIT_ALIASES[tail]
    return s, unit, explicit


def stated_unit(name: str) -> str | None:
    """The unit a column name states explicitly (``"Position [rev]"`` → "rev", ``"t/ms"`` →
    "ms", ``"Weg in inch"`` → "inch"), as written (lower case), known to torchfric or not;
    None when the name states none."""
    s = _plain(name)
    m = _EXPLICIT.search(s)
    if not (m and m.start() > 0):
        return None
    return next(g for g in m.groups() if g).strip() or None


def position_factor(
    unit: str, counts_per_rev: float | None = None, counts_per_m: float | None = None
) -> float:
    """The factor from `unit` to SI: `POSITION_UNITS`, or for counts 2π/`counts_per_rev` (a
    rotary axis) or 1/`counts_per_m` (a linear one)."""
    factor = POSITION_UNITS[unit]
    if factor is not None:
        return factor
    if counts_per_rev:
        return 2.0 * math.pi / counts_per_rev
    if counts_per_m:
        return 1.0 / counts_per_m
    raise ValueError("position unit 'counts' needs counts_per_rev or counts_per_m")


def si_unit(unit: str, counts_per_m: float | None = None) -> str:
    """The SI unit positions in `unit` are converted to: "m" (linear) or "rad" (rotary);
    counts are metres with `counts_per_m`, else radians."""
    return "m" if unit in LINEAR_UNITS or (unit == "counts" and counts_per_m) else "rad"


def force_unit(unit: str, counts_per_m: float | None = None) -> str:
    """The unit of the friction (and of c_m·u) on an axis whose positions are in `unit`."""
    return "N" if si_unit(unit, counts_per_m) == "m" else "N m"
