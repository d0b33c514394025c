"""Reading a user's record as `torchfric init` does: which of its columns are ours (t, u, q,
qdot), and whether its time and position units are what they seem.

- `parse_columns`: ``--column OURS=NAME`` flags (or a mapping) checked into a mapping; also used
  by ``evaluate`` and ``simulate``.
- `map_columns`: ours by name or a common alternative (`ALIASES`, English and the languages of
  lab software: German, French, Spanish, Italian), without case, accents and a unit
  (`torchfric.data.units.split_unit`: ``Time [s]``, ``t/ms``, ``pos_deg``); our own name wins,
  and for t, u and q a name with an alternative as one of its words (``motor_current``) or as
  its last part (``Gelenkwinkel``) comes last. Two candidates, or none for t, u or q, stop with
  the header and the line to write.
- `time_unit_of`: the unit in t's name; `refuse_milliseconds`: a step that looks like ms (a
  step of `MS_STEP` or more, or by the data check's evidence) is refused, not worked around.
- `position_unit_guess`: the unit of q (`PositionGuess`): from its name, encoder counts (with
  their resolution, given or from a wrap) and a wrap period; otherwise rad (or m), with a note
  when a speed above `FAST_SPEED` units/s suggests otherwise. `slow_cutoff`: a velocity
  cut-off for records too slow for 200 Hz.
- `parse_counts`: ``--counts-per-rev``/``--counts-per-m``; `parse_c_m`: ``--c-m``; the unit of
  q from ``--position-unit`` where its header names none, or one torchfric does not read
  (refused without it). Records beside the data named as its held-out ones: `pairs`.
- What the record needs beyond its units: `noisy_cutoff` (a coarse encoder's quieter velocity),
  `terms_found` (a constant force, an unbalanced arm's gravity), `split_record` (``--split``).

Why this size: everything init reads off a record before it writes a line of config, apart from
the config's text itself (`init`).
"""

from __future__ import annotations

import contextlib
import math
import pathlib
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ...data import DEFAULT_CUTOFF_HZ, Experiment, data_warnings
from ...data.lab import nice_period, wrap_jumps
from ...data.units import (
    COLUMN_NAMES,
    OTHER_TIME_UNITS,
    POSITION_UNITS,
    TIME_UNITS,
    split_unit,
    stated_unit,
)
from ...data.velocity import quieter_cutoff_hz, reconstruct_velocity
from ...errors import TorchfricError, shorten
from ..config import toml_value

__all__ = ["ALIASES", "parse_counts", "FAST_SPEED", "MS_STEP", "map_columns", "named_file",
           "noisy_cutoff", "terms_found", "parse_c_m", "parse_columns", "PositionGuess",
           "position_unit_guess", "refuse_milliseconds", "time_unit_of", "rpm", "slow_cutoff",
           "split_record"]  # fmt: skip

_MIN_PART = 100  # samples in each part of a --split

ALIASES: dict[str, tuple[str, ...]] = {
    "t": ("t", "time", "times", "timestamp", "sec", "secs", "seconds",
          "date", "datetime", "clock",  # a logger's clock times (`torchfric.data.lab`)
          "zeit", "zeitstempel", "zeitpunkt", "datum", "uhrzeit",
          "temps", "tiempo", "tempo"),
    "u": ("u", "input", "current", "i", "iq", "cmd", "command", "control", "torque", "tau",
          "force", "voltage", "volt", "pwm",
          "strom", "motorstrom", "sollstrom", "stellgrosse", "stellgroesse", "stellwert",
          "eingang", "spannung", "moment", "drehmoment", "sollmoment", "kraft",
          "courant", "couple", "commande", "tension", "corriente", "par", "entrada",
          "corrente", "coppia", "ingresso"),
    "q": ("q", "pos", "position", "theta", "th", "angle", "phi", "qm", "x", "encoder", "enc",
          "winkel", "drehwinkel", "lage", "weg", "istposition", "istwinkel", "geber",
          "lageistwert", "istlage", "positionsistwert",
          "posicion", "angulo", "posizione", "angolo"),
    "qdot": ("qdot", "q_dot", "qd", "dq", "dqdt", "velocity", "vel", "speed", "omega",
             "thetadot", "theta_dot", "dtheta", "xdot", "x_dot", "geschwindigkeit",
             "winkelgeschwindigkeit", "vitesse", "velocidad", "velocita"),
}  # fmt: skip
"""Names (lower case, unit removed) recognised for each of our columns; our own name first."""
FAST_SPEED = 100.0
"""A q that moves faster than this (99th percentile of |Δq|/dt, units/s) gets a unit note."""
MS_STEP = 0.5
"""A sample time of this many seconds or more (2 Hz or slower) is refused as milliseconds: a
1 kHz record in ms steps by 1.0, a 2 kHz one by 0.5, and friction transients need far faster
sampling than 2 Hz. Between 0.05 s and this, the data check's evidence decides."""
_MEANING = {"t": "time in s", "u": "input", "q": "position", "qdot": "velocity"}


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
    """(base name, unit) of a column name (`torchfric.data.units.split_unit`)."""
    base, unit, _ = split_unit(name)
    return base, unit


def _compound_of(base: str, aliases: Sequence[str]) -> bool:
    """`base` is a compound ending in an alias of five letters or more (``gelenkwinkel``)."""
    return any(base.endswith(a) and len(base) > len(a) for a in aliases if len(a) >= 5)


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
            # else a compound, head noun last: "Gelenkwinkel"
            found = found or [n for n in free if _compound_of(_parse_name(n)[0], ALIASES[role])]
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
@contextlib.contextmanager
def named_file(data: pathlib.Path) -> Iterator[None]:
    """A `TorchfricError` raised inside, with the file's path in front."""
    try:
        yield
    except TorchfricError as err:
        raise TorchfricError(f"{data}: {err}") from None


def time_unit_of(mapping: Mapping[str, str], clock: Sequence[str] = ()) -> str:
    """The unit of the t column by its name (``Zeit [ms]``, ``t_ms``), else s. A name that
    states a time unit torchfric does not read (``Zeit [min]``, `OTHER_TIME_UNITS`) is
    refused, unless the column holds clock times (`clock`: read as seconds whatever the header
    says); another bracket (``Zeit (relativ)``) is not a unit."""
    name = mapping.get("t")
    unit = _parse_name(name)[1] if name else None
    said = stated_unit(name) if name and name not in clock else None
    if said in OTHER_TIME_UNITS:
        raise TorchfricError(
            f'the time column {name!r} states its unit as "{said}", which torchfric does not '
            f"read (it reads {', '.join(TIME_UNITS)}); convert t to one of them, or give "
            "--time-step SECONDS, the sample time, and the column is not read"
        )
    return unit if unit in TIME_UNITS else "s"


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
        f'({why}); name the unit in the header ("{name} [ms]"), which init then reads as '
        'data.time_unit = "ms", or leave the column out and give --time-step SECONDS'
    )


@dataclass
class PositionGuess:
    """What init writes for q: ``position_unit`` (and counts per revolution or metre, the wrap
    period), the reason, a hint for the config's comment, and notes for the user."""

    unit: str
    why: str
    hint: str = ""
    notes: list[str] = field(default_factory=list)
    counts_per_rev: float | None = None
    counts_per_m: float | None = None
    wrap_period: float | None = None


def _wrap(parts: Sequence[np.ndarray], unit: str | None) -> tuple[float | None, str]:
    """(the period q wraps at, a note), or (None, "") when no segment of q wraps."""
    jumps = sum(wrap_jumps(part).size for part in parts)
    if not jumps:
        return None, ""
    q = np.concatenate(parts)
    known = {"deg": 360.0, "rad": 2 * math.pi, "rev": 1.0}
    period = known[unit] if unit in known else nice_period(q)
    return period, (
        f"q wraps ({jumps} jump(s) of about {period:g} between samples, "
        f"{q.min():.6g} … {q.max():.6g}): unwrapped at load, data.wrap_period = {period:g}"
    )


def _header_unit(name: str, given: str | None) -> str | None:
    """q's unit from its column name, or `given` (``--position-unit``). A name that states a
    unit torchfric does not read is refused without `given` (taking it as rad would scale
    every parameter wrongly), and one that states another known unit than `given` always."""
    unit = _parse_name(name)[1]
    said = stated_unit(name)
    if given is not None:
        if given not in POSITION_UNITS:
            raise TorchfricError(
                f"--position-unit {given}: expected one of {', '.join(POSITION_UNITS)}"
            )
        if unit is not None and said is not None and unit != given:
            raise TorchfricError(
                f"the column {name!r} is in {unit} (its header says so) but --position-unit "
                f"is {given}; leave --position-unit out, or give --position-unit {unit}"
            )
        return given
    if said is not None and unit is None:
        raise TorchfricError(
            f'the column {name!r} states its unit as "{said}", which torchfric does not read '
            f"(it reads {', '.join(POSITION_UNITS)}); convert q to one of them, or give "
            f"--position-unit UNIT with q's unit (e.g. --position-unit rad if '{said}' is not "
            "a unit)"
        )
    return unit


def position_unit_guess(
    name: str, parts: Sequence[np.ndarray], dt: float, config: str, *,
    counts_per_rev: float | None = None, counts_per_m: float | None = None,
    position_unit: str | None = None,
) -> PositionGuess:  # fmt: skip
    """What init writes for q (`PositionGuess`), from q's column name, its values (each
    segment's, in the file's unit), ``--counts-per-rev``/``--counts-per-m`` and
    ``--position-unit`` (`position_unit`, which wins over a name that states no unit or one
    torchfric does not read)."""
    unit = _header_unit(name, position_unit)
    q = np.concatenate(parts)
    counted = unit == "counts" or (np.all(q == np.round(q)) and np.unique(q).size >= 20)
    period, wrap_note = _wrap(parts, unit)
    named = unit in POSITION_UNITS and unit != "counts"  # the header names another unit
    if counts_per_rev or counts_per_m or (counted and not named):
        why = f'the name "{name}" says counts' if unit == "counts" else "q holds whole numbers only"
        per_rev = counts_per_rev if not counts_per_m else None
        if not (per_rev or counts_per_m):
            if period is None:
                raise TorchfricError(
                    f"{why} ({q.min():.0f} … {q.max():.0f}): encoder counts; rerun with "
                    "--counts-per-rev N (counts per revolution of a rotary axis) or "
                    "--counts-per-m N (per metre of a linear one), which init writes as "
                    'position_unit = "counts"; if q is not in counts, name its unit in the '
                    'header, e.g. "q [mm]"'
                )
            per_rev = period
            wrap_note += (
                f"; counts_per_rev = {period:g} is taken from the wrap: correct it if the "
                "encoder counts otherwise per revolution"
            )
        given = "--counts-per-rev" if counts_per_rev else "--counts-per-m" if counts_per_m else ""
        return PositionGuess(
            "counts", f"{why}; {f'{given} given' if given else 'per revolution from the wrap'}",
            notes=[wrap_note] if wrap_note else [], counts_per_rev=per_rev,
            counts_per_m=counts_per_m, wrap_period=period,
        )  # fmt: skip
    notes = [wrap_note] if wrap_note else []
    if unit in POSITION_UNITS:
        why = "--position-unit given" if position_unit else f'from the column name "{name}"'
        return PositionGuess(unit, why, notes=notes, wrap_period=period)
    steps = np.concatenate([np.abs(np.diff(part)) for part in parts])
    if period is not None:
        steps = steps[steps < 0.5 * period]
    speed = float(np.quantile(steps, 0.99)) / dt
    if speed > FAST_SPEED:
        fast = f"q moves at up to {speed:.4g} units/s, {rpm(speed):,.0f} rpm if in rad"
        deg = f"{speed * math.pi / 180.0:.3g} rad/s"
        notes.append(
            f'{fast}: if q is in degrees, change the line position_unit = "rad" under [data] '
            f'in {config} to position_unit = "deg" ({deg}); in millimetres, to "mm"'
        )
        hint = (
            f"Up to {speed:.4g} units/s is {rpm(speed):,.0f} rpm in rad: if q is in "
            f'degrees, write position_unit = "deg" below ({deg}); in millimetres, "mm".'
        )
        return PositionGuess("rad", "taken as rad, but q moves fast for rad", hint, notes,
                             wrap_period=period)  # fmt: skip
    why = "nothing says otherwise; for a linear axis in m, the same numbers"
    return PositionGuess("rad", why, notes=notes, wrap_period=period)


def parse_c_m(value: float | str | None) -> float:
    """The motor constant given on the command line (`--c-m`): required, positive."""
    if value is None:
        raise TorchfricError(
            "--c-m is required: the motor constant, torque (N·m) or force (N) per unit of the "
            "input u (e.g. the torque constant in N·m/A times the gear ratio); torchfric does "
            "not estimate it by default, because from u and q alone it cannot be told from the "
            "inertia and friction: e.g. torchfric init data.csv --c-m 0.5"
        )
    try:
        c_m = float(value)
    except ValueError:
        c_m = math.nan
    if not (math.isfinite(c_m) and c_m > 0):
        comma = isinstance(value, str) and re.fullmatch(r"\s*\d+,\d+\s*", value)
        raise TorchfricError(
            f"--c-m {value}: expected a positive number, the motor constant (torque or force "
            "per unit of u), e.g. --c-m 16"
            + (f" (with a decimal point: --c-m {value.strip().replace(',', '.')})" if comma else "")
        )
    return c_m


def slow_cutoff(dt: float) -> float | None:
    """A velocity cut-off when the default one is above 0.4 × Nyquist, else None."""
    nyquist = 0.5 / dt
    if DEFAULT_CUTOFF_HZ["highpass"] <= 0.4 * nyquist:
        return None
    return float(f"{0.4 * nyquist:.3g}")


def noisy_cutoff(
    q: np.ndarray, dt: float, cutoff: float, wrap: float | None
) -> tuple[float, float] | None:
    """``(noise share, quieter cut-off)`` when the high-pass velocity of the position `q` (in
    the file's units, unwrapped at `wrap`) at `cutoff` carries noise above
    `torchfric.data.velocity.NOISY_VELOCITY` of its own 95th-percentile speed
    (`quieter_cutoff_hz`: both are in the file's units, so their ratio is the SI one)."""
    qa = np.unwrap(q, period=wrap) if wrap else np.asarray(q, dtype=np.float64)
    speed = np.abs(reconstruct_velocity(qa, dt, "highpass", cutoff).numpy())
    return quieter_cutoff_hz(qa, dt, "highpass", cutoff, float(np.quantile(speed, 0.95)))


def terms_found(
    segments: Sequence[Experiment], c_m: float, position: PositionGuess
) -> dict[str, tuple[float | None, str]]:
    """``{term: (initial value or None, note)}`` for the white-box terms the records' inverse
    dynamics ask for (`torchfric.estimators.settings`, each taking at least `OFFSET_SHARE`
    of the residual): ``offset`` for a constant force, ``gravity`` for ``g sin(q − q0)`` on a
    rotary axis (its value g when the lowest point q0 is within `GRAVITY_PHASE` of 0, else None
    and a note to re-zero q), and ``input_delay`` (a [data] key) when u acting whole samples
    late removes `DELAY_SHARE` of it. q is unwrapped and scaled to SI from the file's unit."""
    from ...data import make_experiment
    from ...data.units import position_factor, si_unit
    from ...estimators.settings import DELAY_SHARE, input_delay_found
    from ..run import needed_terms

    wrap = position.wrap_period
    scale = position_factor(position.unit, position.counts_per_rev, position.counts_per_m)
    parts = []
    for e in segments:
        q = np.unwrap(e.q.numpy(), period=wrap) if wrap else e.q.numpy()
        parts.append(make_experiment(e.t, e.u, q * scale, name=e.name))
    found: dict[str, tuple[float | None, str]] = {}
    rotary = si_unit(position.unit, position.counts_per_m) == "rad"
    needed = needed_terms(parts, c_m, rotary)
    if "offset" in needed:
        force, share = needed["offset"]
        text = _OFFSET.format(force, share) if share is not None else _OFFSET_ARM.format(force)
        found["offset"] = (0.0, text)
    try:
        delay, share = input_delay_found(parts, c_m, rotary)
    except TorchfricError:  # never moves: the check that follows says so
        delay, share = 0, 0.0
    if delay and share >= DELAY_SHARE:
        found["input_delay"] = (float(delay), _DELAY.format(delay, share))
    if "gravity" in needed:
        g, q0, share, on = needed["gravity"]
        text = _GRAVITY.format(g, math.degrees(q0), share, _GRAVITY_ON if on else _REZERO)
        found["gravity"] = (float(f"{g:.3g}") if on else None, text)
    return found


_OFFSET = (
    "the record's inverse dynamics leave a constant force or torque of {0:.4g} (c_m·u fitted "
    "by inertia, viscous and Coulomb terms: a constant takes {1:.0%} of the residual), as "
    "gravity on a vertical axis, a cable's pull or an amplifier's offset leaves one: "
    "model.offset is on"
)
_OFFSET_ARM = (  # beside gravity: `needed_terms`
    "beside the unbalanced arm's torque below, the record's inverse dynamics leave a constant "
    "torque of {0:.4g} (c_m·u fitted by inertia, viscous and Coulomb terms and g·sin(q − q0)); "
    "an arm's log often carries one (a cable, a spring, friction that differs by direction), "
    "and without it the inertia and b take it up: model.offset is on")  # fmt: skip
_GRAVITY = (
    "the record's inverse dynamics carry a torque {0:.3g}·sin(q − q0) with its lowest point at "
    "q0 = {1:.0f}° (it takes {2:.0%} of the residual), as an unbalanced arm does: {3}"
)
_DELAY = (
    "the record's inverse dynamics fit best with u acting {0} sample(s) late (its residual "
    "{1:.0%} lower than without): data.input_delay = {0}"
)
_GRAVITY_ON = "model.gravity is on (g_c sin q, q = 0 hanging straight down)"
_REZERO = (
    "model.gravity (g_c sin q) takes q = 0 hanging straight down, so it stays off: re-zero q "
    "at the lowest point, then turn it on"
)


def split_record(
    exp: Experiment, fraction: float, folder: pathlib.Path, stem: str
) -> dict[pathlib.Path, Experiment]:
    """{new file: its part} for init's ``--split``: the first `fraction` and the rest."""
    k = round(fraction * exp.n)
    if min(k, exp.n - k) < _MIN_PART:
        raise TorchfricError(
            f"--split {fraction:g} leaves {min(k, exp.n - k)} samples in one part of "
            f"{exp.n}; each part needs at least {_MIN_PART}: choose a fraction nearer 0.5"
        )
    parts = {
        folder / f"{stem}_identification.csv": exp.slice(0, k),
        folder / f"{stem}_validation.csv": exp.slice(k),
    }
    for p in parts:
        if p.exists() or p.is_symlink():
            raise TorchfricError(
                f"--split would write {p}, which exists; init never replaces a data file: move "
                "it away, or write the config into another folder with --out"
            )
    return parts


def rpm(speed: float) -> float:
    """A speed in rad/s as revolutions per minute (the number that shows degrees read as rad)."""
    return speed * 30.0 / math.pi


def parse_counts(per_rev: float | str | None, per_m: float | str | None) -> dict[str, float | None]:
    """``--counts-per-rev`` and ``--counts-per-m``, checked: positive numbers, not both."""
    out: dict[str, float | None] = {}
    for key, value in (("counts_per_rev", per_rev), ("counts_per_m", per_m)):
        if value is None:
            continue
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        flag = "--" + key.replace("_", "-")
        if not (math.isfinite(number) and number > 0):
            raise TorchfricError(f"{flag} {value}: expected a positive number, e.g. {flag} 4096")
        out[key] = number
    if len(out) > 1:
        raise TorchfricError(
            "--counts-per-rev and --counts-per-m both given: an axis is rotary (per revolution) "
            "or linear (per metre); give one"
        )
    return out
