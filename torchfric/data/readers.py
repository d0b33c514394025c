"""Reading and writing records: `load_experiment` (.csv, .npz, .mat) and `save_csv`.

Only this module touches data files. Each format has a reader that returns the file's named
arrays (`_READERS`); `_select` picks our columns (t, u, q, qdot) from them, and
`load_experiment` checks the file (`torchfric.data.guards`) before reading and the record
(`validate_experiment`) after.
"""

from __future__ import annotations

import math
import os
import pathlib
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ..errors import MissingColumn, TorchfricError
from .convert import _check_step, _one_line
from .experiment import Experiment, _check_shapes, _validate
from .guards import _check_memory, _check_regular_file
from .lab import counter_time, nice_period, read_text_table, split_segments, wrap_jumps
from .units import COLUMN_NAMES, POSITION_UNITS, TIME_UNITS, position_factor, split_unit

__all__ = [
    "FILE_TYPES",
    "TEXT_TYPES",
    "load_experiment",
    "load_segments",
    "read_columns",
    "save_csv",
]

PathLike = str | os.PathLike[str]


# --------------------------------------------------------------------------- files
def _read_csv(path: pathlib.Path) -> dict[str, np.ndarray]:
    """A header line of names, then rows of numbers (`torchfric.data.lab.read_text_table`:
    delimiter and decimal separator sniffed; '#' starts a comment)."""
    return read_text_table(path)[0]


def _read_npz(path: pathlib.Path) -> dict[str, np.ndarray]:
    """The named arrays of a numpy ``.npz`` archive (no pickles)."""
    fix = "save it with numpy.savez(path, t=..., u=..., q=...)"
    try:
        with path.open("rb") as f:
            magic = f.read(6)
    except OSError as exc:
        raise TorchfricError(f"{path}: cannot read the file ({_one_line(exc)})") from None
    if not magic.startswith((b"PK", b"\x93NUMPY")):  # a zip archive, or a single .npy
        raise TorchfricError(
            f"{path}: cannot read as .npz: it is no numpy archive (no zip signature at the start); "
            f"{fix}"
        )
    try:
        archive = np.load(path, allow_pickle=False)
        if not isinstance(archive, np.lib.npyio.NpzFile):
            raise TorchfricError(f"{path}: holds one unnamed array, not named arrays; {fix}")
        with archive:
            return {key: np.asarray(archive[key]) for key in archive.files}
    except TorchfricError:
        raise
    except Exception as exc:  # a damaged archive can fail anywhere inside numpy / zipfile
        raise TorchfricError(f"{path}: cannot read as .npz ({_one_line(exc)}); {fix}") from None


def _read_mat(path: pathlib.Path) -> dict[str, np.ndarray]:
    """The named arrays of a MATLAB v4-v7 ``.mat`` file (without its ``__header__`` entries)."""
    try:
        import scipy.io  # on use: only MAT files need it

        raw = scipy.io.loadmat(path)
    except NotImplementedError:
        raise TorchfricError(
            f"{path}: MATLAB v7.3 (HDF5) files are not supported; re-save with save(..., '-v7')"
        ) from None
    except Exception as exc:  # a damaged file can fail anywhere inside loadmat (IndexError, ...)
        raise TorchfricError(
            f"{path}: cannot read as a MATLAB file ({_one_line(exc)}); expected a v4-v7 .mat"
        ) from None
    return {key: np.asarray(val) for key, val in raw.items() if not key.startswith("__")}


TEXT_TYPES: tuple[str, ...] = (".csv", ".txt", ".tsv", ".dat")
"""Suffixes of text tables (`read_text_table`: the separator and the decimal mark sniffed), as
loggers name them: a LabVIEW or oscilloscope export is often a tab-separated .txt or .dat."""
_READERS: dict[str, Callable[[pathlib.Path], dict[str, np.ndarray]]] = {
    **dict.fromkeys(TEXT_TYPES, _read_csv),
    ".npz": _read_npz,
    ".mat": _read_mat,
}
FILE_TYPES: tuple[str, ...] = tuple(_READERS)
"""The file suffixes `load_experiment` reads (compared in lower case)."""


def _available(table: Mapping[str, np.ndarray]) -> str:
    """The file's arrays for messages (``"none"`` when there are none), with the shape of each
    that has columns to choose from (``name:k``); a CSV's columns are plain names."""
    shown = [f"{k} {tuple(np.shape(v))}" if np.ndim(v) > 1 else k for k, v in table.items()]
    return ", ".join(shown) or "none"


def _has(table: Mapping[str, np.ndarray], spec: str) -> bool:
    """Whether `spec` ("name" or "name:k") names an array of `table`."""
    base, sep, idx = spec.rpartition(":")
    return spec in table or bool(
        sep and base in table and idx.strip().isascii() and idx.strip().isdigit()
    )


def _select(
    table: Mapping[str, np.ndarray], spec: str, ours: str, path: pathlib.Path
) -> np.ndarray:
    """The 1-D column `spec` ("name" or "name:k" for column k of a 2-D array) for `ours`."""
    index: int | None = None
    if spec in table:
        arr = table[spec]
    else:
        base, sep, idx = spec.rpartition(":")
        if not (sep and base in table and idx.strip().isascii() and idx.strip().isdigit()):
            raise MissingColumn(
                f"{path}: no column {spec!r} (for {ours}); the file has: {_available(table)}; "
                f'map it in data.columns, e.g. data.columns.{ours} = "<name>" '
                f"(columns={{{ours!r}: '<name>'}} in Python)",
                role=ours,
            )
        arr, index = table[base], int(idx)
    arr = np.asarray(arr)
    if arr.dtype.kind not in "biuf":
        raise TorchfricError(
            f"{path}: column {spec!r} (for {ours}) has dtype {arr.dtype}; expected real numbers"
        )
    if index is None:
        if arr.ndim == 2 and 1 in arr.shape:
            arr = arr.reshape(-1)  # MATLAB-style (N, 1) or (1, N)
        if arr.ndim != 1:
            hint = f"; select one column with '{spec}:k'" if arr.ndim == 2 else ""
            raise TorchfricError(
                f"{path}: {spec!r} (for {ours}) has shape {arr.shape}; expected N samples{hint}"
            )
    else:
        if arr.ndim != 2 or not index < arr.shape[1]:
            raise TorchfricError(
                f"{path}: {spec!r} (for {ours}) selects column {index} of an array of shape "
                f"{arr.shape}; 'name:k' needs a 2-D array with k < its number of columns"
            )
        arr = arr[:, index]
    return arr.astype(np.float64, copy=False)  # the Experiment copies it into a tensor


# --------------------------------------------------------------------------- loading
def _column_mapping(columns: Mapping[str, str] | None) -> dict[str, str]:
    """Our names (t, u, q, qdot) → names in the file: themselves, updated by `columns`."""
    mapping = dict(zip(COLUMN_NAMES, COLUMN_NAMES, strict=True))
    if columns is not None:
        if not isinstance(columns, Mapping):
            raise TorchfricError(f"columns = {columns!r}; expected a mapping such as {{'q': 'qm'}}")
        unknown = sorted(str(k) for k in columns if k not in COLUMN_NAMES)
        if unknown:
            raise TorchfricError(
                f"unknown key(s) {unknown} in columns; allowed keys are t, u, q, qdot (our names), "
                "each mapped to a name in the file"
            )
        for key, val in columns.items():
            if not isinstance(val, str) or not val:
                raise TorchfricError(f"columns[{key!r}] = {val!r}; expected a column name string")
        mapping.update(columns)
    return mapping


def _read_table(p: pathlib.Path) -> tuple[dict[str, np.ndarray], Callable[[int], str]]:
    """The named arrays of file `p`, read by its suffix's reader after the guards, and how
    messages name row k: its line in a CSV (1-based, the header counted), else its index."""
    if p.suffix.lower() not in _READERS:
        raise TorchfricError(
            f"{p}: unsupported file type {p.suffix!r}; expected one of {sorted(_READERS)}"
        )
    size = _check_regular_file(p)  # before anything is opened: a FIFO would block
    if size == 0:
        raise TorchfricError(
            f"{p}: the file is empty (0 bytes); give a file holding the record (t, u, q columns)"
        )
    _check_memory(p, size)
    if p.suffix.lower() in TEXT_TYPES:
        table, _, lines = read_text_table(p)
        return table, lines.where
    return _READERS[p.suffix.lower()](p), lambda k: f"index {k}"


def read_columns(path: PathLike) -> dict[str, np.ndarray]:
    """Every named array of a .csv, .npz or .mat file, as `load_experiment` reads it, before
    any column is chosen (a CSV's header names → its columns). For ``torchfric init``, which
    maps a file's columns to ours."""
    return _read_table(pathlib.Path(path))[0]


def _select_columns(
    table: Mapping[str, np.ndarray], mapping: Mapping[str, str], explicit: set[str], p: pathlib.Path
) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """(columns, their labels in messages): u and q always, t and qdot when present or asked."""
    cols: dict[str, np.ndarray] = {}
    labels: dict[str, str] = {}
    for key in COLUMN_NAMES:
        if key in ("u", "q") or key in explicit or _has(table, mapping[key]):
            cols[key] = _select(table, mapping[key], key, p)
            labels[key] = f"column {key} ({mapping[key]!r})"
    return cols, labels


def _sample_range(
    cols: dict[str, np.ndarray], p: pathlib.Path, start: int, stop: int | None
) -> dict[str, np.ndarray]:
    """The samples ``start ≤ k < stop`` of every column (of one length), after checking."""
    n = next(iter(cols.values())).shape[0]
    end = n if stop is None else stop
    ok = all(isinstance(i, int) and not isinstance(i, bool) for i in (start, end))
    if not ok or not 0 <= start < end <= n:
        raise TorchfricError(
            f"{p}: start={start!r}, stop={stop!r} is not a sample range of this file with {n} "
            f"samples; expected integers 0 <= start < stop <= {n} (data.start, data.stop in a "
            "run config)"
        )
    return {key: arr[start:end] for key, arr in cols.items()}


def _check_units(
    names: Mapping[str, str], p: pathlib.Path, time_unit: str, position_unit: str | None
) -> None:
    """Refuse a unit that a column's header states (``Zeit [ms]``) when another is given."""
    if time_unit not in TIME_UNITS:
        raise TorchfricError(f"time_unit = {time_unit!r}; expected one of {list(TIME_UNITS)}")
    given = {"t": ("time_unit", time_unit), "q": ("position_unit", position_unit)}
    for key, (setting, unit) in given.items():
        _, said, explicit = split_unit(names.get(key, ""))
        if explicit and unit is not None and said != unit:
            raise TorchfricError(
                f"{p}: the column {names[key]!r} is in {said} (its header says so) but "
                f'data.{setting} = "{unit}"; set data.{setting} = "{said}" ({setting}= in '
                "Python)"
            )


def _scaled_q(
    q: np.ndarray, unit: str | None, counts_per_rev: float | None, counts_per_m: float | None
) -> np.ndarray:
    if unit is None:
        return q
    try:
        return q * position_factor(unit, counts_per_rev, counts_per_m)
    except (KeyError, ValueError):
        raise TorchfricError(
            f"position_unit = {unit!r}: expected one of {list(POSITION_UNITS)}; counts need "
            "counts_per_rev (a rotary axis) or counts_per_m (a linear one)"
        ) from None


def _unwrap(
    q: np.ndarray, spans: list[tuple[int, int]], where: Callable[[int], str],
    period: float | None, p: pathlib.Path,
) -> np.ndarray:  # fmt: skip
    """q with each segment unwrapped at `period`; a wrap without a period is refused; an
    infinite period leaves q as it is (for a caller that looks at the wrap itself)."""
    if period == math.inf:
        return q
    jumps = [j + a for a, b in spans for j in wrap_jumps(q[a:b]).tolist()]
    if period is None:
        if jumps:
            k = jumps[0]
            guess = nice_period(q[np.isfinite(q)])
            raise TorchfricError(
                f"{p}: q wraps: it jumps from {q[k - 1]:.6g} to {q[k]:.6g} at {where(k)} "
                f"({len(jumps)} such jump(s) of about a period, {guess:g}): a single-turn "
                f"encoder's count or an angle that wraps; set data.wrap_period = {guess:g} "
                "(in data.position_unit) to unwrap it, or log the unwrapped position"
            )
        return q
    out = q.copy()
    for a, b in spans:
        out[a:b] = np.unwrap(q[a:b], period=period)
    return out


def _experiments(
    cols: Mapping[str, np.ndarray], spans: list[tuple[int, int]], labels: Mapping[str, str],
    p: pathlib.Path, name: str | None, rtol: float, start: int,
) -> list[Experiment]:  # fmt: skip
    """One checked `Experiment` per span of rows: ``name`` alone, or ``name#1``, ``name#2``."""
    stem = p.stem if name is None else name
    exps = []
    for i, (a, b) in enumerate(spans):
        part = {key: arr[a:b] for key, arr in cols.items()}
        _validate(part, where=str(p), labels=labels, rtol=rtol, min_samples=10, offset=start + a)
        label = stem if len(spans) == 1 else f"{stem}#{i + 1}"
        # the constructor copies each column into a tensor once
        exps.append(Experiment(**part, name=label))  # type: ignore[arg-type]
    return exps


def _check_time_step(exp: Experiment, time_step: float, rtol: float, p: pathlib.Path) -> None:
    step = float(np.median(np.diff(exp.t.numpy())))
    if abs(step - time_step) > rtol * time_step:
        raise TorchfricError(
            f"{p}: the time column has step {step:.9g} s but time_step = {time_step:.9g} s; "
            "drop time_step (data.time_step in a run config) or correct it"
        )


def load_segments(
    path: PathLike,
    *,
    columns: Mapping[str, str] | None = None,
    name: str | None = None,
    time_step: float | None = None,
    rtol: float = 1e-3,
    start: int = 0,
    stop: int | None = None,
    time_unit: str = "s",
    position_unit: str | None = None,
    counts_per_rev: float | None = None,
    counts_per_m: float | None = None,
    wrap_period: float | None = None,
) -> tuple[list[Experiment], list[str]]:
    """Load one record as its segments (`torchfric.data.lab.split_segments`), with notes of
    what was left out; rows are named by their line in a CSV (the header counted).

    Args: as `load_experiment`, and
        time_unit: unit of the file's t (`TIME_UNITS`); a header that states another
            (``Zeit [ms]``) is refused.
        position_unit: unit of q (`POSITION_UNITS`), converted to SI (rad or m), with
            `counts_per_rev` or `counts_per_m` for counts; None keeps q as in the file.
        wrap_period: q wraps at this period (in the file's unit): each segment is unwrapped.
            None: a q that wraps (`torchfric.data.lab.wrap_jumps`) is refused; ``math.inf``:
            q is kept as it is, wrapped or not.

    Segments are named ``name#1``, ``name#2``, … (just `name` when there is one).
    """
    p = pathlib.Path(path)
    mapping = _column_mapping(columns)
    table, where = _read_table(p)
    cols, labels = _select_columns(table, mapping, set(columns or {}), p)
    if time_step is not None:
        time_step = _check_step(time_step, "time_step")
    t_in_file = "t" in cols
    _check_units(mapping if t_in_file else {"q": mapping["q"]}, p, time_unit, position_unit)
    if not t_in_file:
        if time_step is None:
            raise MissingColumn(
                f"{p}: no time column {mapping['t']!r} (the file has: {_available(table)}); "
                "add a t column or give time_step, the sample period in s "
                "(data.time_step in a run config)",
                role="t",
            )
        counted = counter_time(table, time_step)  # dropped samples stay a gap
        cols = {"t": counted[0] if counted else np.arange(cols["q"].shape[0]) * time_step} | cols
        labels["t"] = counted[1] if counted else f"t = arange(N)*{time_step:g}"
    else:
        cols["t"] = cols["t"] * TIME_UNITS[time_unit]
    _check_shapes(cols, labels, str(p))
    cols = _sample_range(cols, p, start, stop)
    shifted = (lambda k: where(k + start)) if start else where
    found = split_segments(cols, labels, shifted, rtol=rtol, file=str(p))
    q = _unwrap(cols["q"], found.spans, shifted, wrap_period, p)
    cols["q"] = _scaled_q(q, position_unit, counts_per_rev, counts_per_m)
    if "qdot" in cols:
        cols["qdot"] = _scaled_q(cols["qdot"], position_unit, counts_per_rev, counts_per_m)
    exps = _experiments(cols, found.spans, labels, p, name, rtol, start)
    if time_step is not None and t_in_file:
        _check_time_step(exps[0], time_step, rtol, p)
    notes = []
    if found.notes:
        kept = sum(b - a for a, b in found.spans)
        names = ", ".join(e.name for e in exps[:3]) + (" …" if len(exps) > 3 else "")
        notes.append(
            f"{p.name}: {'; '.join(found.notes)}: read as {len(exps)} segment(s) of {kept} "
            f"samples in all ({names}), each starting its own state, θ shared"
        )
    return exps, notes


def load_experiment(
    path: PathLike,
    *,
    columns: Mapping[str, str] | None = None,
    name: str | None = None,
    time_step: float | None = None,
    rtol: float = 1e-3,
    start: int = 0,
    stop: int | None = None,
    **units: Any,
) -> Experiment:
    """Load and validate one record from a .csv, .npz or .mat file.

    Args:
        path: CSV with a header line (columns t, u, q, optional qdot; extra columns ignored;
            lines starting with '#' skipped; comma, semicolon, tab or space separated, decimal
            point or comma), or an .npz (`numpy.load`) / .mat (`scipy.io.loadmat`) file of
            named arrays; `(N, 1)` and `(1, N)` arrays are flattened.
        columns: our names (t, u, q, qdot) → names in the file, e.g. ``{"u": "vir", "q": "qm"}``.
            ``"name:k"`` selects column k of a 2-D array, e.g. ``{"q": "data:2"}``.
            Unmapped names are looked up as themselves; qdot is loaded when present.
        name: label of the experiment (default: the file name without suffix).
        time_step: sample period in s; builds ``t = arange(N)·time_step`` when the file has no
            time column. If the file has one, its step must agree within `rtol`.
        rtol: relative tolerance of the uniform-sampling check.
        start, stop: keep samples ``start ≤ k < stop`` of the file (``t`` not shifted).
        units: `load_segments`' time_unit, position_unit, counts_per_rev, counts_per_m and
            wrap_period.

    A record with missing or empty values is refused here (naming the first, by its line in
    a CSV); `load_segments` reads it as segments.
    """
    exps, notes = load_segments(
        path, columns=columns, name=name, time_step=time_step, rtol=rtol, start=start,
        stop=stop, **units,
    )  # fmt: skip
    if notes:
        raise TorchfricError(
            f"{path}: {notes[0].split(': ', 1)[1].split(': read as')[0]}; one record must be "
            "whole: fill or cut them (torchfric check and train read such a record as segments; "
            "load_segments in Python)"
        )
    return exps[0]


_SAVE_ROWS = 65_536  # rows formatted at a time by `save_csv`


def save_csv(path: PathLike, experiment: Experiment, *, include_qdot: bool = True) -> None:
    """Write header ``t,u,q[,qdot]`` and rows in ``%.17g`` (reloads bit-exactly).

    ``qdot`` is written when `include_qdot` is true and the experiment has one. A negative zero
    is written ``-0.0``: as ``-0`` a column of them reads as integers, and comes back as +0.
    """
    arrays = experiment.to_numpy()
    names = ["t", "u", "q"] + (["qdot"] if include_qdot and "qdot" in arrays else [])
    data = np.column_stack([arrays[key] for key in names])
    try:
        with open(path, "w", encoding="utf-8", newline="\n") as f:
            f.write(",".join(names) + "\n")
            for start in range(0, len(data), _SAVE_ROWS):  # a block at a time: bounded memory
                block = data[start : start + _SAVE_ROWS]
                text = np.char.mod("%.17g", block).astype(object)
                text[(block == 0) & np.signbit(block)] = "-0.0"
                f.writelines(",".join(row) + "\n" for row in text)
    except OSError as exc:
        raise TorchfricError(f"{path}: cannot write the file ({_one_line(exc)})") from None
