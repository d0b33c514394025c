"""Reading a user's record as `torchfric init` does: which of its columns are ours (t, u, q,
qdot), and whether its time and position units are what they seem.

- `parse_columns`: ``--column OURS=NAME`` flags (or a mapping) checked into a mapping; also used
  by ``evaluate`` and ``simulate``.
- `map_columns`: ours by name or a common alternative (`ALIASES`), without case and without a
  unit in brackets or after an underscore (``Time [s]``, ``pos_deg``); our own name wins, and
  for t, u and q a name with an alternative as one of its words (``motor_current``) comes
  last. Two
  candidates, or none for t, u or q, stop with the header and the line to write.
- `refuse_time_unit`, `refuse_milliseconds`: a time column in ms (by its name, or by a step of
  `MS_STEP` or more, or by the data check's evidence) is refused, not worked around.
- `position_unit_guess`: a unit in q's column name sets ``position_unit``; otherwise rad (or m),
  with a note when whole numbers only (encoder counts) or a speed above `FAST_SPEED` units/s
  suggest otherwise. `slow_cutoff`: a velocity cut-off for records too slow for 200 Hz.
"""

from __future__ import annotations

import math
import pathlib
import re
from collections.abc import Mapping, Sequence

import numpy as np

from ...data import DEFAULT_CUTOFF_HZ, Experiment, data_warnings
from ...data.units import COLUMN_NAMES, POSITION_UNITS, UNIT_ALIASES
from ...errors import TorchfricError, shorten
from ..config import toml_value

__all__ = [
    "ALIASES",
    "FAST_SPEED",
    "MS_STEP",
    "map_columns",
    "parse_columns",
    "position_unit_guess",
    "refuse_milliseconds",
    "refuse_time_unit",
    "rpm",
    "slow_cutoff",
]

ALIASES: dict[str, tuple[str, ...]] = {
    "t": ("t", "time", "times", "timestamp", "sec", "secs", "seconds"),
    "u": ("u", "input", "current", "i", "iq", "cmd", "command", "control", "torque", "tau",
          "force", "voltage", "volt", "pwm"),
    "q": ("q", "pos", "position", "theta", "th", "angle", "phi", "qm", "x", "encoder", "enc"),
    "qdot": ("qdot", "q_dot", "qd", "dq", "dqdt", "velocity", "vel", "speed", "omega",
             "thetadot", "theta_dot", "dtheta", "xdot", "x_dot"),
}  # fmt: skip
"""Names (lower case, unit removed) recognised for each of our columns; our own name first."""
FAST_SPEED = 100.0
"""A q that moves faster than this (99th percentile of |Δq|/dt, units/s) gets a unit note."""
MS_STEP = 0.5
"""A sample time of this many seconds or more (2 Hz or slower) is refused as milliseconds: a
1 kHz record in ms steps by 1.0, a 2 kHz one by 0.5, and friction transients need far faster
sampling than 2 Hz. Between 0.05 s and this, the data check's evidence decides."""
_MEANING = {"t": "time in s", "u": "input", "q": "position", "qdot": "velocity"}
_UNIT_IN_BRACKETS = re.compile(r"\s*[\[(]([^\])]*)[\])]\s*$")


# ------------------------------------------------------------------------------------ columns
def parse_columns(columns: Mapping[str, str] | Sequence[str]) -> dict[str, str]:
    """Our names → the file's from ``--column OURS=NAME`` strings (or a mapping), stripped; a
    one-line error for a string without ``=``, an OURS not among `COLUMN_NAMES`, or no NAME.
    ``torchfric init``, ``evaluate`` and ``simulate`` share it."""
    if not isinstance(columns, Mapping):
        bad = [s for s in columns if "=" not in s]
        if bad:
            raise TorchfricError(f"--column {bad[0]}: expected OURS=NAME, e.g. --column q=pos")
        columns = dict(s.split("=", 1) for s in columns)
    out = {k.strip(): v.strip() for k, v in columns.items()}
    for role, name in out.items():
        if role not in COLUMN_NAMES:
            raise TorchfricError(
                f"--column {role}={name}: {role!r} is not one of our columns; use "
                f"{', '.join(COLUMN_NAMES)}, e.g. --column q=encoder"
            )
        if not name:
            raise TorchfricError(
                f"--column {role}=: no column name; give the file's, e.g. --column {role}=pos"
            )
    return out


def _parse_name(name: str) -> tuple[str, str | None]:
    """(base name, unit) of a column name: ``"Time [s]"`` → ("time", "s"), ``"pos_deg"`` →
    ("pos", "deg"); the unit is None when the name gives none."""
    s, unit = name.strip().lower(), None
    m = _UNIT_IN_BRACKETS.search(s)
    if m:
        s, unit = s[: m.start()], UNIT_ALIASES.get(m.group(1).strip())
    s = re.sub(r"[\s.\-]+", "_", s).strip("_")
    base, sep, tail = s.rpartition("_")
    if unit is None and sep and base and tail in UNIT_ALIASES:
        s, unit = base, UNIT_ALIASES[tail]
    return s, unit


def map_columns(
    table: Mapping[str, np.ndarray], given: Mapping[str, str], path: pathlib.Path, timed: bool
) -> dict[str, str]:
    """Our names → the file's, from `given` (``--column``) and the names in `table`.

    `timed`: the sample time comes from ``--time-step``, so no t column is needed."""
    names = [k for k, v in table.items() if np.ndim(v) == 1 or 1 in np.shape(v)]
    header = ", ".join(table) or "nothing"
    mapping, unknown = dict(given), {}
    for role in COLUMN_NAMES:
        if role in mapping or (role == "t" and timed):
            continue
        free = [n for n in names if n not in mapping.values()]
        own = [n for n in free if _parse_name(n)[0] == role]
        found = own or [n for n in free if _parse_name(n)[0] in ALIASES[role]]
        if not found and role != "qdot":  # a word of the name: "motor_current", "force_cmd_N"
            found = [n for n in free if set(_parse_name(n)[0].split("_")) & set(ALIASES[role])]
        if len(found) == 1:
            mapping[role] = found[0]
        elif role != "qdot":  # qdot is optional (the velocity is rebuilt from q)
            unknown[role] = f"{' and '.join(found)} all look like it" if found else "none does"
    if unknown:
        which = "; ".join(f"{r} ({_MEANING[r]}): {why}" for r, why in unknown.items())
        fix = " ".join(f"--column {r}=NAME" for r in unknown)
        if unknown.get("t") == "none does":
            fix += " (or --time-step SECONDS for a file without a time column)"
        line = {k: mapping.get(k, "NAME") for k in COLUMN_NAMES if k in mapping or k in unknown}
        raise TorchfricError(
            f"{path}: cannot tell which column is {which}; the header is: {shorten(header)}; "
            f"rerun with {fix}, which writes under [data]: columns = {toml_value(line)}"
        )
    return mapping


# ------------------------------------------------------------------------------------ checks
def refuse_time_unit(mapping: Mapping[str, str], path: pathlib.Path) -> None:
    name = mapping.get("t")
    unit = _parse_name(name)[1] if name else None
    if unit in ("ms", "us"):
        raise TorchfricError(
            f"{path}: the time column {name!r} is in {unit}; torchfric reads t in seconds: "
            "convert it (t/1000 for ms), or leave it out and give --time-step SECONDS"
        )


def refuse_milliseconds(exp: Experiment, name: str | None, path: pathlib.Path) -> None:
    """Refuse a sample time that looks like milliseconds (`MS_STEP`, else the data check's
    evidence with the default velocity filter), where `_cutoff` would otherwise lower the
    filter's cut-off to fit it and so silence that check. `name`: the t column, or None for
    ``--time-step``."""
    dt = exp.dt
    if dt >= MS_STEP:
        why = f"a step of {MS_STEP:g} s or more, 2 Hz or slower, is no servo record's"
    else:
        found = [w for w in data_warnings(exp) if "looks like milliseconds" in w]
        if not found:
            return
        m = re.search(r"seconds column \((.*)\); convert", found[0])
        why = m[1] if m else found[0]
    rate = f"{dt:g} s ({1 / dt:.3g} Hz)"
    if name is None:
        raise TorchfricError(
            f"--time-step {dt:g}: a sample time of {rate} looks like milliseconds ({why}); "
            "give the sample time in seconds, e.g. --time-step 0.001 for 1 ms samples"
        )
    raise TorchfricError(
        f"{path}: the time column {name!r} steps by {rate}, which looks like milliseconds "
        f"({why}); torchfric reads t in seconds: convert the column to seconds (t/1000), or "
        "leave it out and give --time-step SECONDS"
    )


def position_unit_guess(
    name: str, q: np.ndarray, dt: float, config: str
) -> tuple[str, str, str, list[str]]:
    """(data.position_unit, the reason for the terminal and the config's comment, a hint for
    that comment, notes to show the user)."""
    unit = _parse_name(name)[1]
    if unit in POSITION_UNITS:
        return unit, f'from the column name "{name}"', "", []
    speed = float(np.quantile(np.abs(np.diff(q)), 0.99)) / dt
    if unit == "counts" or (np.all(q == np.round(q)) and np.unique(q).size >= 20):
        why = f'the name "{name}" says counts' if unit == "counts" else "q holds whole numbers only"
        note = (
            f"{why} ({q.min():.0f} … {q.max():.0f}): encoder counts? torchfric has no unit for "
            "counts; convert q to rad (× 2π / counts per turn) or to m before training, or "
            "every parameter comes out per count"
        )
    elif speed > FAST_SPEED:
        fast = f"q moves at up to {speed:.4g} units/s, {rpm(speed):,.0f} rpm if in rad"
        deg = f"{speed * POSITION_UNITS['deg']:.3g} rad/s"
        note = (
            f'{fast}: if q is in degrees, change the line position_unit = "rad" under [data] '
            f'in {config} to position_unit = "deg" ({deg}); in millimetres, to "mm"'
        )
        hint = (
            f"Up to {speed:.4g} units/s is {rpm(speed):,.0f} rpm in rad: if q is in "
            f'degrees, write position_unit = "deg" below ({deg}); in millimetres, "mm".'
        )
        return "rad", "taken as rad, but q moves fast for rad", hint, [note]
    else:
        return "rad", "nothing says otherwise; for a linear axis in m, the same numbers", "", []
    return "rad", "taken as rad, but see the note at the top", "", [note]


def slow_cutoff(dt: float) -> float | None:
    """A velocity cut-off when the default one is above 0.4 × Nyquist, else None."""
    nyquist = 0.5 / dt
    if DEFAULT_CUTOFF_HZ["highpass"] <= 0.4 * nyquist:
        return None
    return float(f"{0.4 * nyquist:.3g}")


def rpm(speed: float) -> float:
    """A speed in rad/s as revolutions per minute (the number that shows degrees read as rad)."""
    return speed * 30.0 / math.pi
