"""Reading and writing records: `load_experiment` (.csv, .npz, .mat) and `save_csv`.

Only this module touches data files. Each format has a reader that returns the file's named
arrays (`_READERS`); `_select` picks our columns (t, u, q, qdot) from them, and
`load_experiment` checks the file (`torchfric.data.guards`) before reading and the record
(`validate_experiment`) after.
"""

from __future__ import annotations

import os
import pathlib
import warnings
from collections.abc import Callable, Mapping

import numpy as np

from ..errors import MissingColumn, TorchfricError, shorten
from .convert import _check_step, _one_line
from .experiment import Experiment, _check_shapes, _validate
from .guards import _MEMORY_FIX, _check_memory, _check_regular_file
from .units import COLUMN_NAMES

__all__ = ["FILE_TYPES", "load_experiment", "read_columns", "save_csv"]

PathLike = str | os.PathLike[str]


# --------------------------------------------------------------------------- files
_HEAD_BYTES = 1 << 16  # the binary-data check looks at the first 64 KiB
_MAX_LINE = 1 << 20  # no header or comment line is longer than 1 MiB
_CSV_FIX = (
    "give a UTF-8 text file with a header line such as t,u,q and one row of numbers per sample"
)


def _not_utf8(path: pathlib.Path, exc: UnicodeDecodeError) -> TorchfricError:
    """The one-line error for a file that is not UTF-8 text, naming the first bad byte."""
    byte = exc.object[exc.start : exc.start + 1].hex() if exc.object else "?"
    return TorchfricError(
        f"{path}: cannot read the file: byte 0x{byte} is not UTF-8 text (a binary file, or text "
        "in another encoding such as Latin-1); re-save it as UTF-8 (plain ASCII numbers)"
    )


def _find_header(path: pathlib.Path) -> tuple[int, str] | None:
    """(index, text) of the first line that is neither blank nor a '#' comment, or None.

    Reads line by line up to that line only (the body is parsed by `np.loadtxt`); lines are
    split like `np.loadtxt` splits them (universal newlines), so the index is its `skiprows`.
    """
    with path.open(encoding="utf-8-sig") as f:  # -sig: a byte-order mark is no part of a name
        for i, line in enumerate(iter(lambda: f.readline(_MAX_LINE), "")):
            if len(line) >= _MAX_LINE and not line.endswith("\n"):
                raise TorchfricError(
                    f"{path}: line {i + 1} is longer than {_MAX_LINE // 1024} KiB; this is not a "
                    f"CSV with a header line; {_CSV_FIX}"
                )
            if line.strip() and not line.lstrip().startswith("#"):
                return i, line.rstrip("\r\n")
    return None


def _read_csv(path: pathlib.Path) -> dict[str, np.ndarray]:
    """Header line of names, then comma-separated numbers; '#' starts a comment."""
    try:
        with path.open("rb") as f:
            head = f.read(_HEAD_BYTES)
        if not head:
            raise TorchfricError(f"{path}: the file is empty (0 bytes); {_CSV_FIX}")
        nul = head.find(b"\0")
        if nul >= 0:
            raise TorchfricError(
                f"{path}: cannot read the file as CSV: it holds binary data (a NUL byte at "
                f"offset {nul}), not text; {_CSV_FIX}"
            )
        found = _find_header(path)
    except UnicodeDecodeError as exc:
        raise _not_utf8(path, exc) from None
    except OSError as exc:
        raise TorchfricError(f"{path}: cannot read the file ({_one_line(exc)})") from None
    if found is None:
        raise TorchfricError(
            f"{path}: no header line; the first line must name columns, e.g. t,u,q"
        )
    header_at, header = found
    names = [s.strip().strip("\"'") for s in header.split("#")[0].split(",")]
    try:
        [float(s) for s in names]
    except ValueError:
        pass
    else:
        raise TorchfricError(
            f"{path}: the first line holds numbers, not column names; add a header such as t,u,q"
        )
    if len(names) == 1 and (";" in names[0] or "\t" in names[0]):
        sep = "semicolon" if ";" in names[0] else "tab"
        raise TorchfricError(
            f"{path}: the header {shorten(names[0])!r} is {sep}-separated; torchfric reads "
            "comma-separated files, so replace the separators with commas (t,u,q)"
        )
    if len(set(names)) != len(names) or "" in names:
        raise TorchfricError(
            f"{path}: header {shorten(str(names))} has empty or repeated column names"
        )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numpy warns on an empty body; handled below
            data = np.loadtxt(
                path, delimiter=",", comments="#", skiprows=header_at + 1, ndmin=2, encoding="utf-8"
            )
    except UnicodeDecodeError as exc:  # a ValueError: before the generic parse error
        raise _not_utf8(path, exc) from None
    except ValueError as exc:
        raise TorchfricError(
            f"{path}: cannot parse the data ({_one_line(exc)}); expected {len(names)} "
            "comma-separated numbers per row"
        ) from None
    except MemoryError:
        raise TorchfricError(
            f"{path}: not enough memory to parse the file; {_MEMORY_FIX}"
        ) from None
    if data.size == 0:
        raise TorchfricError(f"{path}: no data rows below the header; the file holds no samples")
    if data.shape[1] != len(names):
        raise TorchfricError(
            f"{path}: {data.shape[1]} values per row but the header names {len(names)} columns"
        )
    return {name: data[:, j] for j, name in enumerate(names)}


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


_READERS: dict[str, Callable[[pathlib.Path], dict[str, np.ndarray]]] = {
    ".csv": _read_csv,
    ".npz": _read_npz,
    ".mat": _read_mat,
}
FILE_TYPES: tuple[str, ...] = tuple(_READERS)
"""The file suffixes `load_experiment` reads (compared in lower case)."""


def _available(table: Mapping[str, np.ndarray]) -> str:
    """The file's arrays and their shapes, for messages (``"none"`` when there are none)."""
    return ", ".join(f"{key} {tuple(np.shape(val))}" for key, val in table.items()) or "none"


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


def _read_table(p: pathlib.Path) -> dict[str, np.ndarray]:
    """The named arrays of file `p`, read by its suffix's reader after the guards."""
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
    return _READERS[p.suffix.lower()](p)


def read_columns(path: PathLike) -> dict[str, np.ndarray]:
    """Every named array of a .csv, .npz or .mat file, as `load_experiment` reads it, before
    any column is chosen (a CSV's header names → its columns). For ``torchfric init``, which
    maps a file's columns to ours."""
    return _read_table(pathlib.Path(path))


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
    cols: dict[str, np.ndarray],
    labels: Mapping[str, str],
    p: pathlib.Path,
    start: int,
    stop: int | None,
) -> dict[str, np.ndarray]:
    """The samples ``start ≤ k < stop`` of every column, after checking shapes and the range."""
    n = _check_shapes(cols, labels, str(p))
    end = n if stop is None else stop
    ok = all(isinstance(i, int) and not isinstance(i, bool) for i in (start, end))
    if not ok or not 0 <= start < end <= n:
        raise TorchfricError(
            f"{p}: start={start!r}, stop={stop!r} is not a sample range of this file with {n} "
            f"samples; expected integers 0 <= start < stop <= {n} (data.start, data.stop in a "
            "run config)"
        )
    return {key: arr[start:end] for key, arr in cols.items()}


def load_experiment(
    path: PathLike,
    *,
    columns: Mapping[str, str] | None = None,
    name: str | None = None,
    time_step: float | None = None,
    rtol: float = 1e-3,
    start: int = 0,
    stop: int | None = None,
) -> Experiment:
    """Load and validate one record from a .csv, .npz or .mat file.

    Args:
        path: CSV with a header line (columns t, u, q, optional qdot; extra columns ignored;
            lines starting with '#' skipped), or an .npz (`numpy.load`) / .mat
            (`scipy.io.loadmat`) file of named arrays; `(N, 1)` and `(1, N)` arrays are flattened.
        columns: our names (t, u, q, qdot) → names in the file, e.g. ``{"u": "vir", "q": "qm"}``.
            ``"name:k"`` selects column k of a 2-D array, e.g. ``{"q": "data:2"}``.
            Unmapped names are looked up as themselves; qdot is loaded when present.
        name: label of the experiment (default: the file name without suffix).
        time_step: sample period in s; builds ``t = arange(N)·time_step`` when the file has no
            time column. If the file has one, its step must agree within `rtol`.
        rtol: relative tolerance of the uniform-sampling check.
        start, stop: keep samples ``start ≤ k < stop`` of the file (``t`` not shifted).
    """
    p = pathlib.Path(path)
    mapping = _column_mapping(columns)
    table = _read_table(p)
    cols, labels = _select_columns(table, mapping, set(columns or {}), p)
    if time_step is not None:
        time_step = _check_step(time_step, "time_step")
    t_in_file = "t" in cols
    if not t_in_file:
        if time_step is None:
            raise MissingColumn(
                f"{p}: no time column {mapping['t']!r} (the file has: {_available(table)}); "
                "add a t column or give time_step, the sample period in s "
                "(data.time_step in a run config)",
                role="t",
            )
        cols = {"t": np.arange(cols["q"].shape[0]) * time_step} | cols
        labels["t"] = f"t = arange(N)*{time_step:g}"
    cols = _sample_range(cols, labels, p, start, stop)
    _validate(cols, where=str(p), labels=labels, rtol=rtol, min_samples=10, offset=start)
    if time_step is not None and t_in_file:
        step = float(np.median(np.diff(cols["t"])))
        if abs(step - time_step) > rtol * time_step:
            raise TorchfricError(
                f"{p}: the time column has step {step:.9g} s but time_step = {time_step:.9g} s; "
                "drop time_step (data.time_step in a run config) or correct it"
            )
    # the constructor copies each column into a tensor once (one copy, not two, at the peak)
    return Experiment(
        t=cols["t"],  # type: ignore[arg-type]
        u=cols["u"],  # type: ignore[arg-type]
        q=cols["q"],  # type: ignore[arg-type]
        qdot=cols.get("qdot"),  # type: ignore[arg-type]
        name=p.stem if name is None else name,
    )


def save_csv(path: PathLike, experiment: Experiment, *, include_qdot: bool = True) -> None:
    """Write header ``t,u,q[,qdot]`` and rows in ``%.17g`` (reloads bit-exactly).

    ``qdot`` is written when `include_qdot` is true and the experiment has one.
    """
    arrays = experiment.to_numpy()
    names = ["t", "u", "q"] + (["qdot"] if include_qdot and "qdot" in arrays else [])
    data = np.column_stack([arrays[key] for key in names])
    try:
        np.savetxt(path, data, fmt="%.17g", delimiter=",", header=",".join(names), comments="")
    except OSError as exc:
        raise TorchfricError(f"{path}: cannot write the file ({_one_line(exc)})") from None
