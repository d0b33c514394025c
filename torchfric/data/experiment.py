"""Measured experiments: checking, loading, saving and velocity reconstruction.

An `Experiment` is one uniformly sampled record of the input ``u`` (e.g. motor current) and the
encoder position ``q``, with an optional velocity ``qdot``. Every signal is a float64 tensor of
shape `(N,)`. `make_experiment` and `load_experiment` check the record (`validate_experiment`);
the plain constructor only converts and checks shapes.

Velocity reconstruction when ``qdot`` is not measured:

- `highpass_derivative` (causal, the paper's choice): the first-order high-pass differentiator
  ``H(s) = s·ωc/(s + ωc)``, ``ωc = 2π·cutoff_hz``, discretised with the bilinear (Tustin) map.
- `zero_phase_derivative` / `zero_phase_acceleration` (off-line): a Butterworth low-pass run
  forwards and backwards, then central differences.

Only `load_experiment` and `save_csv` touch files.
"""

from __future__ import annotations

import hashlib
import math
import os
import pathlib
import stat
import warnings
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import scipy.io
import scipy.signal
import torch
from torch import Tensor

from ..errors import TorchfricError, shorten
from ..resources import available_memory as _available_memory
from ..resources import format_bytes as _format_bytes
from ..resources import require_memory

__all__ = [
    "Experiment",
    "validate_experiment",
    "make_experiment",
    "load_experiment",
    "data_warnings",
    "save_csv",
    "highpass_derivative",
    "zero_phase_derivative",
    "zero_phase_acceleration",
    "reconstruct_velocity",
    "VELOCITY_METHODS",
    "DEFAULT_CUTOFF_HZ",
]

ArrayLike = Tensor | np.ndarray | Sequence[float]
PathLike = str | os.PathLike[str]

_COLUMNS = ("t", "u", "q", "qdot")


# --------------------------------------------------------------------------- conversion helpers


def _one_line(exc: BaseException) -> str:
    """The exception text on one line, at most `SHOW_LIMIT` characters (for wrapping errors)."""
    return shorten(" ".join(str(exc).split()) or type(exc).__name__)


def _as_numpy(x: ArrayLike, what: str) -> np.ndarray:
    """Convert a tensor / array / sequence of real numbers to a float64 numpy array."""
    if isinstance(x, Tensor):
        if x.is_complex():
            raise TorchfricError(f"{what} is a complex tensor; expected real numbers")
        return x.detach().to(device="cpu", dtype=torch.float64).numpy()
    try:
        arr = np.asarray(x)
    except (TypeError, ValueError) as exc:
        raise TorchfricError(f"{what} cannot be read as an array ({_one_line(exc)})") from None
    if arr.dtype.kind not in "biuf":
        raise TorchfricError(
            f"{what} has dtype {arr.dtype}; expected real numbers (a float tensor or array)"
        )
    return arr.astype(np.float64, copy=False)  # no copy of float64 data: callers only read it


def _as_tensor(arr: ArrayLike) -> Tensor:
    """A float64 CPU tensor that owns a copy of `arr`, in torch's own (64-byte aligned) memory.

    Not `torch.from_numpy`: numpy's buffers are only 16-byte aligned, at an address that
    changes from process to process, and the compiled EKF step rounds differently for
    differently aligned inputs. The filter amplifies one-ulp differences (a stick/slip event
    on one sample or the next), so the same run in two processes gave θ differing by 3e-6.
    """
    return torch.tensor(np.asarray(arr, dtype=np.float64), dtype=torch.float64)


def _check_step(dt: float, what: str) -> float:
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
        raise TorchfricError(f"{what} = {dt!r}; expected a positive finite sample period in s")
    return float(dt)


def _check_cutoff(cutoff_hz: float, dt: float, what: str) -> float:
    nyquist = 0.5 / dt
    if isinstance(cutoff_hz, bool) or not isinstance(cutoff_hz, (int, float)):
        raise TorchfricError(f"{what}: cutoff_hz = {cutoff_hz!r}; expected a number in Hz")
    if not (0.0 < cutoff_hz < nyquist):
        raise TorchfricError(
            f"{what}: cutoff_hz = {cutoff_hz!r} Hz is not in (0, Nyquist = {nyquist:g} Hz) for "
            f"dt = {dt:g} s; choose a cut-off below {nyquist:g} Hz"
        )
    return float(cutoff_hz)


def _signal(q: ArrayLike, what: str, min_len: int) -> np.ndarray:
    """`q` as a float64 array `(..., N)`, finite, with N >= min_len."""
    arr = _as_numpy(q, what)
    if arr.ndim == 0 or arr.shape[-1] < min_len:
        raise TorchfricError(
            f"{what} has shape {tuple(arr.shape)}; expected (..., N) with N >= {min_len} samples"
        )
    bad = np.flatnonzero(~np.isfinite(arr.reshape(-1)))
    if bad.size:
        k = int(bad[0]) % arr.shape[-1]
        raise TorchfricError(
            f"{what} has a non-finite value at sample {k}; remove or fill NaN/inf first"
        )
    return arr


# --------------------------------------------------------------------------- validation
def _check_shapes(cols: Mapping[str, np.ndarray], labels: Mapping[str, str], where: str) -> int:
    """Every column 1-D and of one length; returns that length."""
    for key, arr in cols.items():
        if arr.ndim != 1:
            raise TorchfricError(
                f"{where}: {labels[key]} has shape {tuple(arr.shape)}; expected a 1-D signal (N,) "
                "(flatten (N, 1) arrays first)"
            )
    lengths = {key: arr.shape[0] for key, arr in cols.items()}
    if len(set(lengths.values())) > 1:
        desc = ", ".join(f"{labels[k]}: {n}" for k, n in lengths.items())
        raise TorchfricError(
            f"{where}: columns have different lengths ({desc}); give all signals the same samples"
        )
    return next(iter(lengths.values()))


def _validate(
    cols: Mapping[str, np.ndarray],
    *,
    where: str,
    labels: Mapping[str, str],
    rtol: float,
    min_samples: int,
    offset: int = 0,
) -> None:
    """All checks of `validate_experiment`; indices in messages are shifted by `offset`."""
    if not (isinstance(rtol, (int, float)) and math.isfinite(rtol) and rtol > 0):
        raise TorchfricError(f"rtol = {rtol!r}; expected a positive relative tolerance")
    if isinstance(min_samples, bool) or not isinstance(min_samples, int) or min_samples < 2:
        raise TorchfricError(f"min_samples = {min_samples!r}; expected an integer >= 2")
    n = _check_shapes(cols, labels, where)
    if n < min_samples:
        raise TorchfricError(
            f"{where}: only {n} samples; at least {min_samples} are needed (use a longer record)"
        )
    for key, arr in cols.items():
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            k, value = int(bad[0]), float(arr[bad[0]])
            raise TorchfricError(
                f"{where}: {labels[key]} has a non-finite value {value!r} at index {k + offset} "
                f"({bad.size} in all); remove or fill these samples"
            )
    t = cols["t"]
    steps = np.diff(t)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise TorchfricError(
            f"{where}: time is not strictly increasing at index {k + offset} "
            f"(t = {float(t[k - 1])!r} then {float(t[k])!r}); sort the samples and drop duplicates"
        )
    median = float(np.median(steps))
    deviation = np.abs(steps - median)
    bad = np.flatnonzero(deviation > rtol * median)
    if bad.size:
        k = int(bad[0])
        raise TorchfricError(
            f"{where}: sampling is not uniform at index {k + 1 + offset} (step {steps[k]:.9g} s "
            f"vs median {median:.9g} s, relative tolerance {rtol:g}); resample the record, split "
            "it at the gap, or raise rtol"
        )


def validate_experiment(
    t: ArrayLike,
    u: ArrayLike,
    q: ArrayLike,
    qdot: ArrayLike | None = None,
    *,
    name: str,
    rtol: float = 1e-3,
    min_samples: int = 10,
) -> None:
    """Check one record; raise `TorchfricError` naming the column and first bad index.

    Checks: every signal 1-D with the same length `N >= min_samples`; all values finite;
    ``t`` strictly increasing; uniform sampling, ``max_k |Δt_k − median(Δt)| <= rtol·median(Δt)``.
    The default ``rtol = 1e-3`` accepts time-stamp jitter (EMPS: ±4e-8 s at 1 ms, i.e. 4e-5)
    and rejects a single missing sample (a step of 2·Δt).
    """
    cols = {"t": t, "u": u, "q": q} | ({} if qdot is None else {"qdot": qdot})
    arrays = {key: _as_numpy(val, f"{name}: column {key}") for key, val in cols.items()}
    labels = {key: f"column {key}" for key in arrays}
    _validate(arrays, where=name, labels=labels, rtol=rtol, min_samples=min_samples)


# --------------------------------------------------------------------------- the record
@dataclass(frozen=True, eq=False, repr=False)
class Experiment:
    """One uniformly sampled record.

    Attributes:
        t: `(N,)` time in s, strictly increasing, uniform step.
        u: `(N,)` input (e.g. motor current or voltage).
        q: `(N,)` position (rad or m).
        qdot: `(N,)` measured or reconstructed velocity, or None.
        name: label used in messages and reports.

    The constructor converts every signal to a float64 CPU tensor (a copy) and checks shapes
    only; use `make_experiment` or `load_experiment` for the full checks of
    `validate_experiment`.
    """

    t: Tensor
    u: Tensor
    q: Tensor
    qdot: Tensor | None = None
    name: str = "experiment"

    def __post_init__(self) -> None:
        cols = {key: getattr(self, key) for key in _COLUMNS if getattr(self, key) is not None}
        arrays = {key: _as_numpy(val, f"{self.name}: column {key}") for key, val in cols.items()}
        n = _check_shapes(arrays, {key: f"column {key}" for key in arrays}, self.name)
        if n < 2:
            raise TorchfricError(f"{self.name}: {n} samples; an experiment needs at least 2")
        for key, arr in arrays.items():
            object.__setattr__(self, key, _as_tensor(arr))

    @property
    def n(self) -> int:
        """Number of samples N."""
        return int(self.t.shape[0])

    @property
    def dt(self) -> float:
        """Mean sample step ``(t[N-1] − t[0]) / (N − 1)`` in s."""
        return float((self.t[-1] - self.t[0]) / (self.n - 1))

    @property
    def duration(self) -> float:
        """``t[N-1] − t[0]`` in s."""
        return float(self.t[-1] - self.t[0])

    def __repr__(self) -> str:
        has_qdot = "yes" if self.qdot is not None else "no"
        return f"Experiment(name={self.name!r}, n={self.n}, dt={self.dt:.6g}, qdot={has_qdot})"

    def with_velocity(
        self, method: str = "highpass", *, cutoff_hz: float | None = None
    ) -> Experiment:
        """A copy with ``qdot`` reconstructed from ``q`` (an existing ``qdot`` is replaced).

        `method` is "highpass" (causal) or "zero_phase" (off-line); `cutoff_hz=None` takes the
        method's default (`DEFAULT_CUTOFF_HZ`: 200 Hz and 50 Hz).
        """
        qdot = reconstruct_velocity(self.q, self.dt, method, cutoff_hz)
        return replace(self, qdot=qdot)

    def slice(self, start: int, stop: int | None = None) -> Experiment:
        """Samples ``start ≤ k < stop`` (``stop=None``: to the end); ``t`` is kept as is."""
        stop = self.n if stop is None else stop
        ok = all(isinstance(i, int) and not isinstance(i, bool) for i in (start, stop))
        if not ok or not (0 <= start and start + 2 <= stop <= self.n):
            raise TorchfricError(
                f"{self.name}: slice({start!r}, {stop!r}) is invalid for {self.n} samples; "
                f"expected integers 0 <= start, start + 2 <= stop <= {self.n}"
            )
        qdot = None if self.qdot is None else self.qdot[start:stop]
        return replace(
            self, t=self.t[start:stop], u=self.u[start:stop], q=self.q[start:stop], qdot=qdot
        )

    def delay_input(self, samples: int) -> Experiment:
        """A copy in which the input acts `samples` steps late: ``u_new[k] = u[k − samples]``.

        A transport delay of whole samples (e.g. one controller cycle between the logged command
        and the actuator). The first `samples` samples have no known input and are dropped, so
        the result has ``N − samples`` samples; ``t`` is kept as is. ``samples = 0`` is a copy.
        """
        ok = isinstance(samples, int) and not isinstance(samples, bool)
        if not ok or not 0 <= samples <= self.n - 2:
            raise TorchfricError(
                f"{self.name}: delay_input({samples!r}) is invalid for {self.n} samples; expected "
                f"an integer 0 <= samples <= {self.n - 2}"
            )
        if samples == 0:
            return replace(self)
        qdot = None if self.qdot is None else self.qdot[samples:]
        return replace(self, t=self.t[samples:], u=self.u[:-samples], q=self.q[samples:], qdot=qdot)

    def to_numpy(self) -> dict[str, np.ndarray]:
        """``{"t", "u", "q"[, "qdot"]}`` as float64 `(N,)` arrays (copies)."""
        return {
            key: getattr(self, key).numpy().copy()
            for key in _COLUMNS
            if getattr(self, key) is not None
        }

    def fingerprint(self) -> str:
        """SHA-256 hex digest of the little-endian float64 bytes of t, u, q (and qdot if set)."""
        digest = hashlib.sha256()
        for arr in self.to_numpy().values():
            digest.update(arr.astype("<f8").tobytes())
        return digest.hexdigest()


def make_experiment(
    t: ArrayLike,
    u: ArrayLike,
    q: ArrayLike,
    qdot: ArrayLike | None = None,
    *,
    name: str = "experiment",
    rtol: float = 1e-3,
) -> Experiment:
    """Validate (`validate_experiment`) and build an `Experiment` of float64 tensors."""
    validate_experiment(t, u, q, qdot, name=name, rtol=rtol)
    return Experiment(t=t, u=u, q=q, qdot=qdot, name=name)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- files
_HEAD_BYTES = 1 << 16  # the binary-data check looks at the first 64 KiB
_MAX_LINE = 1 << 20  # no header or comment line is longer than 1 MiB
_CSV_FIX = (
    "give a UTF-8 text file with a header line such as t,u,q and one row of numbers per sample"
)


def _not_utf8(path: pathlib.Path, exc: UnicodeDecodeError) -> TorchfricError:
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
    try:
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


def _available(table: Mapping[str, np.ndarray]) -> str:
    return ", ".join(f"{key} {tuple(np.shape(val))}" for key, val in table.items()) or "none"


def _has(table: Mapping[str, np.ndarray], spec: str) -> bool:
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
            raise TorchfricError(
                f"{path}: no column {spec!r} (for {ours}); the file has: {_available(table)}; "
                f"fix `columns`, e.g. columns={{{ours!r}: '<name>'}}"
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


# --------------------------------------------------------------------------- loading guards
_KINDS: tuple[tuple[Callable[[int], bool], str], ...] = (
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)

# Peak memory of `load_experiment` / bytes of the arrays the reader returns, measured with
# ru_maxrss in a fresh process on 19-50 MB files of 3 columns: CSV 2.06 (4.3 M rows "i,0,0") and
# 2.08 (0.8 M rows of %.17g), .npz 2.09, .mat 2.11. np.loadtxt's own peak is 1.07-1.23 × its
# result; the float64 tensors of the columns add 1 ×. Rounded up for the parser's temporaries.
_LOAD_MEMORY_RATIO = 2.5
# A CSV value takes at least 2 bytes (a digit and a separator) and becomes 8: at most 4 bytes of
# arrays per byte of file. Above that bound the first `_SAMPLE_BYTES` give the real row length.
_CSV_MAX_EXPANSION = 4
_SAMPLE_BYTES = 1 << 20
_MEMORY_FIX = (
    "shorten the file (data.start/data.stop apply only after loading) or split it into several "
    "files"
)


def _csv_array_bytes(p: pathlib.Path, size: int) -> int:
    """Bytes of the arrays a CSV of `size` bytes parses to, from the rows in its first MiB.

    Falls back to the bound ``_CSV_MAX_EXPANSION · size`` when the sample shows no data row.
    """
    bound = _CSV_MAX_EXPANSION * size
    try:
        with p.open("rb") as f:
            sample = f.read(_SAMPLE_BYTES)
    except OSError:
        return bound
    lines = sample.split(b"\n")
    if len(sample) < size:
        lines = lines[:-1]  # the last line of the sample may be cut
    rows = [s for s in lines if s.strip() and not s.lstrip().startswith(b"#")][1:]
    if not rows or b"\0" in sample:
        return bound
    row_bytes = sum(len(s) + 1 for s in rows) / len(rows)
    columns = max(s.count(b",") for s in rows) + 1
    return min(bound, int(size / row_bytes * columns * 8))


def _npz_array_bytes(p: pathlib.Path, size: int) -> int:
    """Uncompressed size of the archive's members (its central directory), else the file size."""
    try:
        with zipfile.ZipFile(p) as zf:
            return max(size, sum(info.file_size for info in zf.infolist()))
    except Exception:  # not a zip archive: the reader reports it
        return size


def _check_regular_file(p: pathlib.Path) -> int:
    """The size of `p` if it is a regular file (after links); else a one-line error.

    Only `os.stat`: a FIFO is never opened (that would block until a writer comes).
    """
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise TorchfricError(
            f"{p}: file not found (working directory {os.getcwd()}); check the path"
        ) from None
    except OSError as exc:
        raise TorchfricError(f"{p}: cannot access the file ({_one_line(exc)})") from None
    if stat.S_ISDIR(st.st_mode):
        raise TorchfricError(
            f"{p}: is a directory; give the path of a {p.suffix} file (a regular file)"
        )
    if not stat.S_ISREG(st.st_mode):
        kind = next((text for test, text in _KINDS if test(st.st_mode)), "not a regular file")
        raise TorchfricError(
            f"{p}: is {kind}, not a data file; give a regular file (save the data to a "
            f"{p.suffix} file first)"
        )
    return int(st.st_size)


def _check_memory(p: pathlib.Path, size: int) -> None:
    """Refuse up front a file whose load would need more memory than is available."""
    available = _available_memory()
    if available is None:
        return
    suffix = p.suffix.lower()
    if suffix == ".csv":
        if _CSV_MAX_EXPANSION * size * _LOAD_MEMORY_RATIO <= available:
            return  # fits even at the densest text: nothing to read
        array_bytes = _csv_array_bytes(p, size)
    elif suffix == ".npz":
        array_bytes = _npz_array_bytes(p, size)
    else:  # .mat: arrays as large as the file (a compressed v7 file expands further)
        array_bytes = size
    require_memory(
        int(array_bytes * _LOAD_MEMORY_RATIO),
        f"data file {p} is {_format_bytes(size)}: loading it",
        _MEMORY_FIX,
        available=available,
    )


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
    mapping = dict(zip(_COLUMNS, _COLUMNS, strict=True))
    if columns is not None:
        if not isinstance(columns, Mapping):
            raise TorchfricError(f"columns = {columns!r}; expected a mapping such as {{'q': 'qm'}}")
        unknown = sorted(str(k) for k in columns if k not in _COLUMNS)
        if unknown:
            raise TorchfricError(
                f"unknown key(s) {unknown} in columns; allowed keys are t, u, q, qdot (our names), "
                "each mapped to a name in the file"
            )
        for key, val in columns.items():
            if not isinstance(val, str) or not val:
                raise TorchfricError(f"columns[{key!r}] = {val!r}; expected a column name string")
        mapping.update(columns)
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
    table = _READERS[p.suffix.lower()](p)
    explicit = set(columns or {})

    cols: dict[str, np.ndarray] = {}
    labels: dict[str, str] = {}
    for key in _COLUMNS:
        if key in ("u", "q") or key in explicit or _has(table, mapping[key]):
            cols[key] = _select(table, mapping[key], key, p)
            labels[key] = f"column {key} ({mapping[key]!r})"
    if time_step is not None:
        time_step = _check_step(time_step, "time_step")
    t_in_file = "t" in cols
    if not t_in_file:
        if time_step is None:
            raise TorchfricError(
                f"{p}: no time column {mapping['t']!r} (the file has: {_available(table)}); "
                "add a t column or give time_step=<sample period in s>"
            )
        cols = {"t": np.arange(cols["q"].shape[0]) * time_step} | cols
        labels["t"] = f"t = arange(N)*{time_step:g}"
    n = _check_shapes(cols, labels, str(p))

    end = n if stop is None else stop
    ok = all(isinstance(i, int) and not isinstance(i, bool) for i in (start, end))
    if not ok or not 0 <= start < end <= n:
        raise TorchfricError(
            f"{p}: start={start!r}, stop={stop!r} is not a sample range of this file with {n} "
            f"samples; expected integers 0 <= start < stop <= {n}"
        )
    cols = {key: arr[start:end] for key, arr in cols.items()}
    _validate(cols, where=str(p), labels=labels, rtol=rtol, min_samples=10, offset=start)
    if time_step is not None and t_in_file:
        step = float(np.median(np.diff(cols["t"])))
        if abs(step - time_step) > rtol * time_step:
            raise TorchfricError(
                f"{p}: the time column has step {step:.9g} s but time_step = {time_step:.9g} s; "
                "drop time_step or correct it"
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


# --------------------------------------------------------------------------- velocity
def highpass_derivative(q: ArrayLike, dt: float, cutoff_hz: float = 200.0) -> Tensor:
    """Causal velocity from position by the high-pass differentiator ``H(s) = s·ωc/(s + ωc)``.

    Discretisation: bilinear (Tustin) ``s ← (2/dt)(1 − z⁻¹)/(1 + z⁻¹)`` *without* pre-warping.
    Its low-frequency gain is exactly that of ``s`` (a ramp gives its exact slope) and its
    response is ``H(jΩ)`` at ``Ω = (2/dt)·tan(ω·dt/2)``, i.e. the continuous filter to
    ``O((ω·dt)²)`` in the band where velocities are used. Pre-warping at ωc would instead scale
    every low-frequency velocity by ``(ωc·dt/2)/tan(ωc·dt/2)`` (0.865 for 200 Hz at 1 kHz), a
    bias that goes straight into viscous friction. The price: the −3 dB corner sits at
    ``atan(ωc·dt/2)/(π·dt)`` (178.6 Hz for 200 Hz at 1 kHz). Backward Euler would add half a
    sample of lag. With ``K = 2/dt``, ``p = (K − ωc)/(K + ωc)``, ``g = K·ωc/(K + ωc)``::

        v[k] = p·v[k−1] + g·(q[k] − q[k−1]),   v[0] = 0 (q[−1] = q[0]: at rest before k = 0)

    so a constant q gives exactly 0 from the first sample.

    Args:
        q: `(..., N)` position; filtered along the last axis.
        dt: sample period in s.
        cutoff_hz: ωc/2π; must be below the Nyquist frequency 1/(2·dt).

    Returns:
        `(..., N)` float64 velocity.
    """
    dt = _check_step(dt, "highpass_derivative: dt")
    wc = 2.0 * math.pi * _check_cutoff(cutoff_hz, dt, "highpass_derivative")
    qa = _signal(q, "highpass_derivative: q", 2)
    k = 2.0 / dt
    p = (k - wc) / (k + wc)
    g = k * wc / (k + wc)
    # Δq[k] = q[k] − q[k−1] with q[−1] = q[0]
    dq = np.diff(qa, axis=-1, prepend=qa[..., :1])
    # v[k] = p·v[k−1] + g·Δq[k], zero initial state
    v = scipy.signal.lfilter([g], [1.0, -p], dq, axis=-1)
    return _as_tensor(v)


def _zero_phase_lowpass(
    q: ArrayLike, dt: float, cutoff_hz: float, order: int, what: str
) -> np.ndarray:
    """Butterworth low-pass of order `order` run forwards and backwards (|H|², zero phase)."""
    dt = _check_step(dt, f"{what}: dt")
    cutoff_hz = _check_cutoff(cutoff_hz, dt, what)
    if isinstance(order, bool) or not isinstance(order, int) or not 1 <= order <= 12:
        raise TorchfricError(f"{what}: order = {order!r}; expected an integer from 1 to 12")
    qa = _signal(q, f"{what}: q", 3)
    sos = scipy.signal.butter(order, cutoff_hz, fs=1.0 / dt, output="sos")
    # pad by 3·order cut-off periods (the filter's transient has died out by then); odd
    # extension continues a ramp as a ramp, so the ends keep their velocity
    padlen = min(qa.shape[-1] - 1, math.ceil(3 * order / (cutoff_hz * dt)))
    return scipy.signal.sosfiltfilt(sos, qa, axis=-1, padtype="odd", padlen=padlen)


def zero_phase_derivative(
    q: ArrayLike, dt: float, cutoff_hz: float = 50.0, order: int = 4
) -> Tensor:
    """Off-line velocity: zero-phase Butterworth low-pass, then central differences.

    ``q_f = filtfilt(butter(order, cutoff_hz), q)`` (second-order sections, odd padding), then
    ``v[k] = (q_f[k+1] − q_f[k−1]) / (2·dt)`` (second-order one-sided at the ends, `np.gradient`).
    Non-causal: sample k uses the future, so use it for off-line pre-processing only. The odd
    pad flips the curvature at the ends: the first and last ≈ 3 cut-off periods
    (``3/(cutoff_hz·dt)`` samples, 60 at 50 Hz and 1 kHz) can be off by a few % of the velocity
    (drop them in fits, as the EMPS recipe drops 50); inside, the error is the sinc
    ``1 − (ω·dt)²/6`` of the central difference and the Butterworth roll-off ``|H_B(ω)|²``.

    Args:
        q: `(..., N)` position, N >= 3; processed along the last axis.
        dt: sample period in s.
        cutoff_hz: low-pass cut-off, below 1/(2·dt).
        order: Butterworth order (the forward-backward pass doubles it).

    Returns:
        `(..., N)` float64 velocity.
    """
    qf = _zero_phase_lowpass(q, dt, cutoff_hz, order, "zero_phase_derivative")
    v = np.gradient(qf, dt, axis=-1, edge_order=2)
    return _as_tensor(v)


def zero_phase_acceleration(
    q: ArrayLike, dt: float, cutoff_hz: float = 50.0, order: int = 4
) -> Tensor:
    """Off-line acceleration: central differences applied twice to the zero-phase filtered q.

    ``a = gradient(gradient(q_f, dt), dt)``, i.e. ``(q_f[k+2] − 2·q_f[k] + q_f[k−2]) / (2·dt)²``
    inside, the derivative of `zero_phase_derivative`'s output. `(..., N)` → `(..., N)`.
    The ends (≈ 3 cut-off periods) are unreliable, up to tens of % for a curved q: drop them.
    """
    qf = _zero_phase_lowpass(q, dt, cutoff_hz, order, "zero_phase_acceleration")
    v = np.gradient(qf, dt, axis=-1, edge_order=2)
    a = np.gradient(v, dt, axis=-1, edge_order=2)
    return _as_tensor(a)


VELOCITY_METHODS: dict[str, Callable[[ArrayLike, float, float], Tensor]] = {
    "highpass": highpass_derivative,
    "zero_phase": zero_phase_derivative,
}
DEFAULT_CUTOFF_HZ: dict[str, float] = {"highpass": 200.0, "zero_phase": 50.0}


def reconstruct_velocity(
    q: ArrayLike, dt: float, method: str = "highpass", cutoff_hz: float | None = None
) -> Tensor:
    """Velocity from position by `method` ("highpass" or "zero_phase"), `(..., N)` → `(..., N)`.

    `cutoff_hz=None` uses `DEFAULT_CUTOFF_HZ[method]` (200 Hz high-pass, 50 Hz zero-phase).
    """
    if method not in VELOCITY_METHODS:
        raise TorchfricError(
            f"unknown velocity method {method!r}; choose one of {sorted(VELOCITY_METHODS)}"
        )
    cutoff = DEFAULT_CUTOFF_HZ[method] if cutoff_hz is None else cutoff_hz
    return VELOCITY_METHODS[method](q, dt, cutoff)


# --------------------------------------------------------------------------- data warnings
# Saturation: u at its exact minimum or maximum in more than this fraction of the samples ...
_SATURATION_FRACTION = 0.01
# ... reached gradually: the median distance of the samples next to those runs from the limit is
# below this fraction of u's range (a clipped continuous signal: 0.002-0.005 for the rig's input
# clipped at ±60 % of its peak, 0.12 at ±80 %, where the rig's breakaway kicks jump onto the
# limit). A step / PRBS input jumps onto its levels from far away (the HSM150 torque steps: 1.0,
# the whole range) and is not flagged; neither is an input of fewer than
# `_SATURATION_MIN_LEVELS` distinct values (a few levels, by design).
_SATURATION_APPROACH = 0.25
_SATURATION_MIN_LEVELS = 20
# Time units: only sample times of at least this many seconds (<= 20 Hz) are suspected ...
_MS_MIN_STEP = 0.05
# ... when a measured qdot is this many times the finite difference of q (1000 for t in ms) ...
_MS_QDOT_RATIO = (300.0, 3000.0)
# ... or, without qdot, when the velocity filter's cut-off is above Nyquist and q is smooth on
# the scale of a sample: rms(Δ²q)/rms(Δq) ≈ ω·Δt (ω the motion's rms angular frequency) is below
# this. Measured: 0.003-0.063 on the 1 kHz records (rig 0.027-0.063, EMPS 0.005, HSM150 0.003),
# 0.28 on the 40 Hz unbalanced disc; a genuine ≤ 20 Hz servo record moving at ≥ 0.5 Hz exceeds it.
_MS_SMOOTHNESS = 0.15
# ... or that ratio, read as a frequency ω/2π = ratio/(2π·Δt), puts the motion below 0.02 Hz (a
# period over 50 s; servo test motions are faster). t in ms divides it by 1000: rig 0.0066 Hz,
# EMPS 0.0007, HSM150 0.0005, the disc (genuinely 40 Hz, ratio 0.28) 0.0018.
_MS_MOTION_HZ = 0.02


def _saturation_warnings(exp: Experiment) -> list[str]:
    u = exp.u.numpy()
    if u.size < 2 or not np.all(np.isfinite(u)):
        return []
    lo, hi = float(u.min()), float(u.max())
    span = hi - lo
    if not span > 0 or np.unique(u).size < _SATURATION_MIN_LEVELS:
        return []
    out = []
    for which, value in (("minimum", lo), ("maximum", hi)):
        at = u == value
        count = int(at.sum())
        if count <= _SATURATION_FRACTION * u.size:
            continue
        edge = np.flatnonzero(at[1:] != at[:-1])  # at[k] != at[k+1]
        outside = np.where(at[edge], u[edge + 1], u[edge])  # the neighbour off the limit
        approach = float(np.median(np.abs(outside - value))) / span
        if approach > _SATURATION_APPROACH:
            continue  # jumps onto the level: a step input, not a clip
        out.append(
            f"{exp.name}: the input u sits at its exact {which} {value:.6g} in "
            f"{count / u.size:.1%} of the samples ({count} of {u.size}), as a clipped or "
            "saturated signal does; remove the saturated segments or raise the amplifier's "
            "limit, because identification assumes the applied input equals the recorded one"
        )
    return out


def _time_unit_warning(exp: Experiment, velocity: str, cutoff_hz: float | None) -> str | None:
    dt = exp.dt
    if not (math.isfinite(dt) and dt >= _MS_MIN_STEP):
        return None
    q = exp.q.numpy()
    if not np.all(np.isfinite(q)) or q.size < 3:
        return None
    evidence = None
    if exp.qdot is not None:
        qdot = exp.qdot.numpy()
        fd = np.gradient(q, dt)
        if not np.all(np.isfinite(qdot)) or not np.any(fd) or not np.any(qdot):
            return None
        ratio = math.sqrt(float(np.mean(qdot**2)) / float(np.mean(fd**2)))
        if float(np.corrcoef(qdot, fd)[0, 1]) > 0.5 and (
            _MS_QDOT_RATIO[0] <= ratio <= _MS_QDOT_RATIO[1]
        ):
            evidence = f"the measured qdot is {ratio:.0f} times the finite difference of q"
    elif velocity in DEFAULT_CUTOFF_HZ:
        cutoff = DEFAULT_CUTOFF_HZ[velocity] if cutoff_hz is None else cutoff_hz
        nyquist = 0.5 / dt
        d1 = np.diff(q)
        if cutoff >= nyquist and np.any(d1):
            smooth = math.sqrt(float(np.mean(np.diff(d1) ** 2)) / float(np.mean(d1**2)))
            motion_hz = smooth / (2.0 * math.pi * dt)
            if smooth < _MS_SMOOTHNESS or motion_hz < _MS_MOTION_HZ:
                evidence = (
                    f"the {velocity} velocity cut-off {cutoff:g} Hz is above the Nyquist "
                    f"frequency {nyquist:g} Hz, and q moves as if sampled much faster: rms "
                    f"second/first difference {smooth:.3g}, a motion at {motion_hz:.2g} Hz"
                )
    if evidence is None:
        return None
    return (
        f"{exp.name}: sample time {dt:g} s ({1 / dt:g} Hz) looks like milliseconds in a seconds "
        f"column ({evidence}); convert the t column to seconds (t/1000)"
    )


def data_warnings(
    exp: Experiment, *, velocity: str = "highpass", velocity_cutoff_hz: float | None = None
) -> list[str]:
    """Plain one-sentence warnings about data that would almost certainly give a wrong model.

    Pure: reads `exp` only. Empty list when nothing is suspicious. Checks:

    - saturation: u sits at its exact minimum or maximum in more than 1 % of the samples and
      reaches that value gradually (the samples next to those runs lie, in the median, within
      25 % of u's range of it; u has at least 20 distinct values). Step and PRBS inputs, which
      jump onto their few levels, are not flagged.
    - time units: a sample time of at least 0.05 s (≤ 20 Hz) that contradicts the data: a
      measured ``qdot`` 300-3000 times the finite difference of q (t in ms makes it 1000), or,
      without ``qdot``, a velocity cut-off (`velocity`, `velocity_cutoff_hz`, as in
      `Experiment.with_velocity`) at or above the Nyquist frequency ``1/(2·dt)`` together with
      a position that moves as if sampled much faster: ``r = rms(Δ²q)/rms(Δq) < 0.15`` (q smooth
      on the scale of one sample) or ``r/(2π·dt) < 0.02 Hz`` (a motion slower than any servo
      test's).

    Args:
        exp: the record as loaded (before velocity reconstruction, so a measured qdot is seen).
        velocity: "highpass", "zero_phase" or "measured" (the config's ``data.velocity``).
        velocity_cutoff_hz: the reconstruction's cut-off; None = the method's default.
    """
    if not isinstance(exp, Experiment):
        raise TorchfricError(f"data_warnings: expected an Experiment, got {type(exp).__name__}")
    out = _saturation_warnings(exp)
    unit = _time_unit_warning(exp, velocity, velocity_cutoff_hz)
    if unit is not None:
        out.append(unit)
    return out
