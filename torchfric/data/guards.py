"""Guards run before a data file is opened: is it a regular file, and does its load fit in memory.

`load_experiment` calls `_check_regular_file` first (only `os.stat`: a FIFO is never opened)
and then `_check_memory`, which refuses up front a file whose load would need more memory than
is available, estimating the arrays from the file's size (and, for a CSV, its first rows).
"""

from __future__ import annotations

import os
import pathlib
import stat
import zipfile
from collections.abc import Callable

from ..errors import TorchfricError
from ..resources import available_memory as _available_memory
from ..resources import format_bytes as _format_bytes
from ..resources import require_memory
from .convert import _one_line

__all__: list[str] = []

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
    if suffix == ".npz":
        array_bytes = _npz_array_bytes(p, size)
    elif suffix == ".mat":  # arrays as large as the file (a compressed v7 file expands further)
        array_bytes = size
    else:  # a text table (.csv, .txt, .tsv, .dat: `readers.TEXT_TYPES`)
        if _CSV_MAX_EXPANSION * size * _LOAD_MEMORY_RATIO <= available:
            return  # fits even at the densest text: nothing to read
        array_bytes = _csv_array_bytes(p, size)
    require_memory(
        int(array_bytes * _LOAD_MEMORY_RATIO),
        f"data file {p} is {_format_bytes(size)}: loading it",
        _MEMORY_FIX,
        available=available,
    )
