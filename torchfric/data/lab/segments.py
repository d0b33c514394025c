"""A record with holes as segments, and positions that wrap: `split_segments`, `wrap_jumps`.

- `split_segments`: rows with an empty or non-finite value are left out, and the record is
  cut wherever rows are left out or missing (a time step of 1.5 sample steps or more); each run
  of whole rows is a segment, identified with the others (each starts its own state, θ is
  shared). Where the record is cut, segments shorter than `MIN_SEGMENT` samples or `MIN_SEGMENT_S`
  seconds are dropped. A time step that goes back,
  or lies between one step and 1.5 (jitter beyond the tolerance), is an error: that is no gap.
- `wrap_jumps`: the samples where q jumps by about a whole period (a single-turn encoder's
  count at 4096 → 0, an angle at 360° → 0): at least half q's range in one step, at least
  `_JUMP_RATIO` times the largest other step, from one end of the range to within 10 % of the
  other, in a q that moves (20 values or more). `nice_period` proposes the period.
- `counter_time`: t of a file without a time column, from its sample counter where it has one
  (``Index``, ``Sample``, ``Nr`` …), so that samples its logger dropped stay a gap.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from ...errors import TorchfricError

__all__ = [
    "COUNTER_NAMES", "MIN_SEGMENT", "Segments", "counter_time", "nice_period", "split_segments",
    "wrap_jumps",
]  # fmt: skip

MIN_SEGMENT = 50
MIN_SEGMENT_S = 0.2
"""A segment is kept when it holds `MIN_SEGMENT` samples and `MIN_SEGMENT_S` seconds: a shorter
one is mostly the start transient of the velocity filter and of the state, and too short for
the pre-fit's zero-phase filter (3 periods of 50 Hz at each end)."""
_GAP = 1.5  # a step of this many sample steps or more is a gap (samples missing)
_JUMP_RATIO = 10.0
_MIN_VALUES = 20


@dataclass(frozen=True)
class Segments:
    """`spans`: (first, stop) row ranges of the segments kept; `notes`: what was left out."""

    spans: list[tuple[int, int]]
    notes: list[str]


def _ranges(rows: np.ndarray, where: Callable[[int], str]) -> str:
    """Rows as the file names them, runs joined: ``line 12, lines 40–49``."""
    runs: list[tuple[int, int]] = []
    for r in rows.tolist():
        if runs and r == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], r)
        else:
            runs.append((r, r))
    shown = [
        where(a) if a == b else f"{where(a)}–{where(b).split()[-1]}".replace("line ", "lines ", 1)
        for a, b in runs[:4]
    ]
    return ", ".join(shown) + (f" and {len(runs) - 4} more" if len(runs) > 4 else "")


def split_segments(
    cols: Mapping[str, np.ndarray], labels: Mapping[str, str], where: Callable[[int], str],
    *, rtol: float, file: str,
) -> Segments:  # fmt: skip
    """The segments of `cols` (t in s, u, q, ...; rows as read); `where(k)` names row k."""
    n = cols["t"].shape[0]
    ok = np.ones(n, dtype=bool)
    notes: list[str] = []
    for key, arr in cols.items():
        bad = ~np.isfinite(arr)
        if bad.any():
            what = "empty or NaN" if np.isnan(arr[bad]).all() else "not finite"
            notes.append(f"{labels[key]} {what} at {_ranges(np.flatnonzero(bad), where)}")
        ok &= ~bad
    rows = np.flatnonzero(ok)
    if rows.size < 2:
        raise TorchfricError(f"{file}: fewer than 2 rows hold a value in every column; no record")
    t = cols["t"][rows]
    steps = np.diff(t)
    back = np.flatnonzero(steps <= 0)
    if back.size:
        k = int(back[0])
        raise TorchfricError(
            f"{file}: time is not strictly increasing at {where(int(rows[k + 1]))} (t = "
            f"{float(t[k])!r} then {float(t[k + 1])!r}); sort the samples and drop duplicates"
        )
    adjacent = np.diff(rows) == 1
    dt = float(np.median(steps[adjacent] if adjacent.any() else steps))
    cut = (~adjacent) | (steps >= _GAP * dt)
    odd = np.flatnonzero(~cut & (np.abs(steps - dt) > rtol * dt))
    if odd.size:
        k = int(odd[0])
        raise TorchfricError(
            f"{file}: sampling is not uniform at {where(int(rows[k + 1]))} (step {steps[k]:.9g} s "
            f"vs median {dt:.9g} s, relative tolerance {rtol:g}): neither one sample step nor a "
            "gap of missing samples; resample the record"
        )
    missing = np.flatnonzero(adjacent & cut)
    if missing.size:
        gaps = [f"after {where(int(rows[k]))} ({round(steps[k] / dt) - 1} samples)"
                for k in missing[:4]]  # fmt: skip
        more = f" and {missing.size - 4} more" if missing.size > 4 else ""
        notes.append(f"t skips samples {', '.join(gaps)}{more}")
    bounds = np.concatenate([[0], np.flatnonzero(cut) + 1, [rows.size]])
    spans, short = [], []
    # a whole record keeps any length (the record's own checks apply); a cut one its long runs
    whole = bounds.size == 2 and rows.size == n
    least = 0 if whole else max(MIN_SEGMENT, math.ceil(MIN_SEGMENT_S / dt))
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if b - a >= least:
            spans.append((int(rows[a]), int(rows[b - 1]) + 1))
        else:
            short.append(f"{where(int(rows[a]))} ({b - a} rows)")
    if short:
        notes.append(
            f"segment(s) shorter than {least} samples ({MIN_SEGMENT_S:g} s) dropped: at {', '.join(short[:4])}"
            + (f" and {len(short) - 4} more" if len(short) > 4 else "")
        )
    if not spans:
        raise TorchfricError(
            f"{file}: no run of {least} whole samples ({MIN_SEGMENT_S:g} s) is left ({'; '.join(notes)}); fill "
            "the missing values or give a longer record"
        )
    return Segments(spans, notes)


def wrap_jumps(q: np.ndarray) -> np.ndarray:
    """Indices k where ``q[k] − q[k−1]`` is a wrap (about a whole period); empty if none."""
    none = np.zeros(0, dtype=np.int64)
    if q.size < 3 or np.unique(q).size < _MIN_VALUES:  # a step or a few levels: no motion
        return none
    d = np.abs(np.diff(q))
    lo, span = float(np.min(q)), float(np.max(q) - np.min(q))
    big = d >= 0.5 * span
    if not big.any() or big.all():
        return none
    rest = float(np.max(d[~big]))
    if rest == 0 or np.min(d[big]) < _JUMP_RATIO * rest:
        return none
    k = np.flatnonzero(big) + 1
    # a wrap goes from one end of q's range to the other
    ends = np.minimum(q[k - 1], q[k]) - lo, lo + span - np.maximum(q[k - 1], q[k])
    return k if np.all(np.maximum(*ends) <= 0.1 * span) else none


def nice_period(q: np.ndarray) -> float:
    """The period q most likely wraps at: 2π, 360, or the smallest power of 2 or round
    number (1, 2, 2.5, 5 × 10^k) at or above its range (a whole count above, for counts)."""
    span = float(np.max(q) - np.min(q))
    if np.all(q == np.round(q)):
        span += 1.0
    candidates = [2 * math.pi, 360.0]
    candidates += [2.0**k for k in range(1, 40)]
    candidates += [m * 10.0**k for k in range(-3, 12) for m in (1, 2, 2.5, 5)]
    fits = [c for c in candidates if span * (1 - 1e-9) <= c <= 1.05 * span]
    return min(fits) if fits else float(f"{span:.3g}")


COUNTER_NAMES = frozenset({
    "index", "idx", "sample", "samples", "sample no", "sample nr", "nr", "no", "count", "counter",
    "step", "frame", "zähler", "zaehler", "lfd nr", "lfd. nr", "messpunkt",
})  # fmt: skip
"""Header names (case and a unit in brackets aside) that `counter_time` reads as a sample
counter."""


def counter_time(
    table: Mapping[str, np.ndarray], time_step: float
) -> tuple[np.ndarray, str] | None:
    """``(t, label)`` of a file without a time column, from its sample counter: the first
    column named as in `COUNTER_NAMES` whose values are whole numbers that rise by 1 from row to
    row (more where the logger dropped samples), ``t = (counter − counter₀)·time_step``. With
    it the dropped samples stay a gap (`split_segments`), where ``arange(N)·time_step`` would
    join the rows on either side as if they were one step apart. None when there is no such
    column (a counter that ever steps back or does not mostly step by 1 is none)."""
    for name, col in table.items():
        base = re.sub(r"\s*[\[(].*$", "", name).strip().lower().rstrip(".:#").strip()
        if base not in COUNTER_NAMES or np.ndim(col) != 1 or np.size(col) < 2:
            continue
        c = np.asarray(col, dtype=np.float64)
        steps = np.diff(c)
        if not np.isfinite(c).all() or (c != np.round(c)).any() or (steps <= 0).any():
            continue
        if np.median(steps) == 1:
            return (c - c[0]) * time_step, f"t = ({name} − {c[0]:g})·{time_step:g}"
    return None
