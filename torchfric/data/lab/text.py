"""CSV text as lab software and drives write it: `read_text_table`.

The header line (the first that is neither blank nor a ``#`` comment, or the first after a scope's
preamble: `_head`) and up to `_SNIFF_ROWS` data lines decide the format: the delimiter is the first
of tab, ``;``, ``,`` and white space that splits the header and every sniffed line into the same
number (≥ 2) of fields; a row of units right under the names (``[ms];[V];[Inc]``) is joined to them
(``Zeit [ms]``, which `torchfric.data.units.split_unit` reads); the decimal separator is a comma
when the delimiter is not one and the first number with a fraction is written with a comma
(``1,25``); a column of clock times (`CLOCK_FORMATS`) is read as seconds from its first row. The
body is then read by pandas' C parser (`pandas.read_csv`, imported on use): quoted fields, a
byte-order mark, ``#`` comments, blank lines, empty fields and ``NaN`` (both read as NaN, which
`torchfric.data.lab.segments` drops) are its business.

A data row's place in the file is its line number (1-based, the header counted), found by
`RowLines`, which reads the file again only when a message needs one.
"""

from __future__ import annotations

import pathlib
import re
import warnings
from dataclasses import dataclass, field

import numpy as np

from ...errors import TorchfricError, shorten
from ..convert import _one_line
from ..guards import _MEMORY_FIX
from ..units import UNIT_ALIASES

__all__ = [
    "CLOCK_FORMATS",
    "CSV_FIX",
    "MAX_LINE",
    "RowLines",
    "TextFormat",
    "read_text_table",
    "reading_notes",
    "sniff_format",
]

_HEAD_BYTES = 1 << 16  # the binary-data check looks at the first 64 KiB
MAX_LINE = 1 << 20  # no header or comment line is longer than 1 MiB
_SNIFF_ROWS = 50
_PREAMBLE_LINES = 100  # lines above the header a scope or logger may write (`_head`)
CSV_FIX = (
    "give a UTF-8 text file with a header line such as t,u,q (or t;u;q) and one row of numbers "
    "per sample"
)
_DELIMITERS = {"\t": "tab", ";": "semicolon", ",": "comma", " ": "space"}
_COMMA_NUMBER = re.compile(r"^[+-]?\d*,\d+(?:[eE][+-]?\d+)?$")
_POINT_NUMBER = re.compile(r"^[+-]?\d*\.\d+(?:[eE][+-]?\d+)?$")
_FURTHER_LINES = 200_000  # how far `_comma_further` reads for a number with a fraction
# white space separates fields, but not a name from its unit: "Zeit [ms]" is one field
_SPACED_FIELD = re.compile(r"[^\s\[(]+(?:\s*[\[(][^\])]*[\])])?|[\[(][^\])]*[\])]")


@dataclass(frozen=True)
class TextFormat:
    """How a CSV's text was read: `delimiter` (tab, ``;``, ``,`` or ``" "`` for white space),
    `decimal` (``.`` or ``,``) and the header's line number (1-based)."""

    delimiter: str
    decimal: str
    header_line: int
    clock: tuple[str, ...] = ()  # columns of clock times (`CLOCK_FORMATS`), read as seconds
    preamble: int = 0  # lines above the header (neither blank nor #) skipped as a preamble

    def describe(self) -> str:
        """E.g. ``"semicolon-separated, decimal comma"``, for notes."""
        sep = _DELIMITERS[self.delimiter] + "-separated"
        return sep + (", decimal comma" if self.decimal == "," else "")


@dataclass
class RowLines:
    """Data row k (0-based, as read) → its line in the file (1-based, the header counted)."""

    path: pathlib.Path
    header_line: int
    _lines: np.ndarray | None = field(default=None, repr=False)

    def line(self, row: int) -> int:
        if self._lines is None:
            found = []
            with self.path.open(encoding="utf-8-sig", errors="replace") as f:
                for i, text in enumerate(f, start=1):
                    body = text.strip()
                    if i > self.header_line and body and not body.startswith("#"):
                        found.append(i)
            self._lines = np.asarray(found, dtype=np.int64)
        return int(self._lines[row]) if row < self._lines.size else self.header_line + row + 1

    def where(self, row: int) -> str:
        return f"line {self.line(row)}"


_BRACKETED = re.compile(r"[\[(]\s*([^\[\]()]+?)\s*[\])]\s*$")


def reading_notes(name: str, fmt: TextFormat | None, u_column: str) -> list[str]:
    """What `torchfric init` says about how the file `name` was read (`fmt`: None for a file
    that is not CSV text): its delimiter and decimal comma, a preamble skipped, clock columns,
    and the unit the input column's name gives, which is u's own (u is never converted)."""
    notes = []
    if fmt is not None:
        if fmt.delimiter != "," or fmt.decimal != ".":
            notes.append(f"{name} is {fmt.describe()}: read as such")
        if fmt.preamble:
            notes.append(f"{name}: lines 1–{fmt.header_line - 1} above its header (line "
                         f"{fmt.header_line}) are a preamble: skipped")  # fmt: skip
        notes += [f"column {c!r} holds clock times: read as seconds from its first row"
                  for c in fmt.clock]  # fmt: skip
    unit = _BRACKETED.search(u_column)
    if unit:
        notes.append(f"u is used as written, in {unit.group(1)} (column {u_column!r}): "
                     f"model.c_m is per {unit.group(1)} of u")  # fmt: skip
    return notes


def _not_utf8(path: pathlib.Path, exc: UnicodeDecodeError) -> TorchfricError:
    """The one-line error for a file that is not UTF-8 text, naming the first bad byte."""
    byte = exc.object[exc.start : exc.start + 1].hex() if exc.object else "?"
    return TorchfricError(
        f"{path}: cannot read the file: byte 0x{byte} is not UTF-8 text (a binary file, or text "
        "in another encoding such as Latin-1); re-save it as UTF-8 (plain ASCII numbers)"
    )


def _head(path: pathlib.Path) -> tuple[int, str, list[str], int, int]:
    """(index, text) of the header line, up to `_SNIFF_ROWS` data lines after it, the index of
    the first of them and how many lines above the header were skipped as a preamble.

    The header is the first line that is neither blank nor a comment, unless lines above the
    first row of numbers name fields in another number than those rows have — the preamble a
    scope or logger writes (``Name;Trace 1``, ``Abtastrate;1 kHz``): then it is the first of
    those lines whose fields, and those of every line after it, match the rows
    (`_header_after_preamble`)."""
    with path.open("rb") as f:
        head = f.read(_HEAD_BYTES)
    if not head:
        raise TorchfricError(f"{path}: the file is empty (0 bytes); {CSV_FIX}")
    nul = head.find(b"\0")
    if nul >= 0:
        raise TorchfricError(
            f"{path}: cannot read the file as CSV: it holds binary data (a NUL byte at offset "
            f"{nul}), not text; {CSV_FIX}"
        )
    lines: list[tuple[int, str]] = []  # (index, text) of the lines that are neither blank nor #
    numbers = 0  # lines from the first row of numbers on
    first_numbers: int | None = None  # that row's position in `lines`
    with path.open(encoding="utf-8-sig") as f:  # -sig: a byte-order mark is no part of a name
        for i, line in enumerate(iter(lambda: f.readline(MAX_LINE), "")):
            if len(line) >= MAX_LINE and not line.endswith("\n"):
                raise TorchfricError(
                    f"{path}: line {i + 1} is longer than {MAX_LINE // 1024} KiB; this is not a "
                    f"CSV with a header line; {CSV_FIX}"
                )
            body = line.strip()
            if not body or body.startswith("#"):
                continue
            lines.append((i, line.rstrip("\r\n")))
            if first_numbers is None and _numeric_line(body):
                first_numbers = len(lines) - 1
            numbers += first_numbers is not None
            if numbers > _SNIFF_ROWS or len(lines) > _SNIFF_ROWS + _PREAMBLE_LINES:
                break
    if not lines:
        raise TorchfricError(
            f"{path}: no header line; the first line must name columns, e.g. t,u,q"
        )
    at = _header_after_preamble(lines, first_numbers)
    (index, header), rows = lines[at], lines[at + 1 : at + 1 + _SNIFF_ROWS]
    first = rows[0][0] if rows else -1
    return index, header, [r.split("#")[0].strip() for _, r in rows], first, at


def _numeric_line(body: str) -> bool:
    """Whether a line is a row of numbers (or clock times) under some delimiter."""
    for delimiter in _DELIMITERS:
        fields = _split(body.split("#")[0], delimiter)
        if len(fields) >= 2 and all((_is_number(f) and f) or _clock_format(f) for f in fields):
            return True
    return False


def _header_after_preamble(lines: list[tuple[int, str]], first_numbers: int | None) -> int:
    """The position in `lines` of the header: 0, or past a preamble — the first line before the
    first row of numbers (at `first_numbers`, None: none) that splits, under some delimiter,
    into as many (≥ 2) fields as every line after it up to the sniffed rows."""
    if first_numbers is None or first_numbers < 2:
        return 0
    window = lines[: first_numbers + _SNIFF_ROWS]
    for k in range(first_numbers):
        for delimiter in _DELIMITERS:
            n = len(_split(window[k][1].split("#")[0], delimiter, header=True))
            if n >= 2 and all(
                len(_split(t.split("#")[0].strip(), delimiter)) == n for _, t in window[k + 1 :]
            ):
                return k
    return 0


def _split(line: str, delimiter: str, *, header: bool = False) -> list[str]:
    if delimiter == " ":
        found = _SPACED_FIELD.findall(line) if header else line.split()
        return [s.strip().strip("\"'") for s in found]
    fields = [s.strip().strip("\"'") for s in line.split(delimiter)]
    return fields[:-1] if len(fields) > 1 and not fields[-1] else fields  # a trailing delimiter


def _sniff(path: pathlib.Path, header: str, rows: list[str]) -> tuple[str, list[str]]:
    """(delimiter, column names): the first delimiter that splits the header and every sniffed
    row alike into two or more fields."""
    head = header.split("#")[0]
    for delimiter in _DELIMITERS:
        names = _split(head, delimiter, header=True)
        if len(names) >= 2 and all(len(_split(r, delimiter)) == len(names) for r in rows):
            return delimiter, names
    for delimiter in _DELIMITERS:  # the header alone: rows that differ fail below, by line
        names = _split(head, delimiter, header=True)
        if len(names) >= 2:
            return delimiter, names
    raise TorchfricError(
        f"{path}: the header {shorten(head.strip())!r} names one column; separate the column "
        "names (and the numbers of each row) by commas, semicolons, tabs or spaces, e.g. t;u;q"
    )


def sniff_format(path: pathlib.Path) -> tuple[TextFormat, list[str]]:
    """How the CSV text at `path` is written, and its column names (the header's fields)."""
    try:
        header_at, header, rows, first, preamble = _head(path)
    except UnicodeDecodeError as exc:
        raise _not_utf8(path, exc) from None
    except OSError as exc:
        raise TorchfricError(f"{path}: cannot read the file ({_one_line(exc)})") from None
    delimiter, names = _sniff(path, header, rows)
    try:
        [float(s.replace(",", ".")) for s in names]
    except ValueError:
        pass
    else:
        raise TorchfricError(
            f"{path}: the first line holds numbers, not column names; add a header such as t,u,q"
        )
    if len(set(names)) != len(names) or "" in names:
        raise TorchfricError(
            f"{path}: header {shorten(str(names))} has empty or repeated column names"
        )
    units = _units_row(rows[0], delimiter, len(names)) if rows else None
    if units is not None:  # a row of units under the names: "Zeit" over "[ms]" is "Zeit [ms]"
        names = [f"{n} [{u}]" if u else n for n, u in zip(names, units, strict=True)]
        rows, header_at = rows[1:], first
    fields = [f for r in rows for f in _split(r, delimiter)]
    comma = delimiter != "," and any(_COMMA_NUMBER.match(f) for f in fields)
    if delimiter != "," and not comma and not any(_POINT_NUMBER.match(f) for f in fields):
        comma = _comma_further(path, delimiter)  # the first rows: integers only (at rest)
    first = _split(rows[0], delimiter) if rows else []
    clock = tuple(n for n, f in zip(names, first, strict=False) if _clock_format(f))
    fmt = TextFormat(delimiter, "," if comma else ".", header_at + 1, clock, preamble)
    return fmt, names


# Clock times a logger writes in place of seconds, each with the substitution that makes it ISO
# 8601 for pandas: a date and a time ("2026-11-28 09:15:02.001", "T" too, a zone allowed), a
# European date ("28.11.2026 09:15:02,001") and a time of day alone ("09:15:02.001"); the
# fraction of a second after a point or a comma.
_FRACTION = r"(?:[.,]\d+)?"
CLOCK_FORMATS = {
    "date and time": (re.compile(rf"^(\d{{4}}-\d{{2}}-\d{{2}})[T ](\d{{1,2}}:\d{{2}}:\d{{2}}{_FRACTION})"
                                 r"(Z|[+-]\d{2}:?\d{2})?$"), r"\1T\2\3"),
    "day.month.year and time": (re.compile(rf"^(\d{{1,2}})\.(\d{{1,2}})\.(\d{{4}}) "
                                           rf"(\d{{1,2}}:\d{{2}}:\d{{2}}{_FRACTION})$"),
                                r"\3-\2-\1T\4"),
    "time of day": (re.compile(rf"^(\d{{1,2}}:\d{{2}}:\d{{2}}{_FRACTION})$"), r"1970-01-01T\1"),
}  # fmt: skip


def _clock_format(text: str) -> str | None:
    """The `CLOCK_FORMATS` name that `text` is written in, or None."""
    return next((k for k, (rx, _) in CLOCK_FORMATS.items() if rx.match(text.strip())), None)


def _comma_further(path: pathlib.Path, delimiter: str) -> bool:
    """Whether the first number with a fraction in the file's first `_FURTHER_LINES` lines
    (the sniffed ones held integers only, as a record that starts at rest does) is written
    with a decimal comma."""
    with path.open(encoding="utf-8-sig", errors="replace") as f:
        for i, line in enumerate(f):
            if i > _FURTHER_LINES:
                break
            for field in _split(line.split("#")[0], delimiter):
                if _COMMA_NUMBER.match(field):
                    return True
                if _POINT_NUMBER.match(field):
                    return False
    return False


_UNIT = re.compile(r"^[\[(]?\s*([^\d\s\[\]()][^\[\]()]{0,15}?)?\s*[\])]?$")


def _units_row(row: str, delimiter: str, columns: int) -> list[str] | None:
    """The units of a row that lab software (a scope export, a PLC logger) writes under the
    column names — ``[ms];[V];[Inc]``, ``s,V,counts`` — with their brackets taken off (an empty
    field: no unit); None when `row` is a data row: it has a number in it, a field that is not a
    short word, or neither a bracketed field nor a unit torchfric knows (`UNIT_ALIASES`)."""
    fields = _split(row, delimiter)
    if len(fields) != columns:
        return None
    units, known = [], False
    for f in fields:
        m = None if _is_number(f) else _UNIT.match(f)
        if m is None:
            return None
        units.append((m.group(1) or "").strip())
        known |= f[:1] in "[(" or units[-1].lower() in UNIT_ALIASES
    return units if known else None


def _is_number(text: str) -> bool:
    try:
        float(text.replace(",", "."))
    except ValueError:
        return text.lower() in ("nan", "")
    return True


def read_text_table(path: pathlib.Path) -> tuple[dict[str, np.ndarray], TextFormat, RowLines]:
    """The named columns of a CSV text file, how it was read, and its rows' line numbers."""
    fmt, names = sniff_format(path)
    data = _parse(path, names, fmt)
    if data.shape[0] == 0:
        raise TorchfricError(f"{path}: no data rows below the header; the file holds no samples")
    return {name: data[:, j] for j, name in enumerate(names)}, fmt, RowLines(path, fmt.header_line)


def _parse(path: pathlib.Path, names: list[str], fmt: TextFormat) -> np.ndarray:
    """The body as an `(N, len(names))` float array; empty fields and NaN are NaN."""
    import pandas as pd  # on use: --help and the app's faces never load it

    sep = r"\s+" if fmt.delimiter == " " else fmt.delimiter
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            frame = pd.read_csv(
                path, sep=sep, decimal=fmt.decimal, comment="#", header=None, names=names,
                usecols=range(len(names)), skiprows=fmt.header_line, index_col=False,
                skip_blank_lines=True, encoding="utf-8-sig", engine="c",
            )  # fmt: skip
    except UnicodeDecodeError as exc:
        raise _not_utf8(path, exc) from None
    except MemoryError:
        raise TorchfricError(
            f"{path}: not enough memory to parse the file; {_MEMORY_FIX}"
        ) from None
    except Exception as exc:  # pandas' ParserError names the file's line ("in line 9")
        raise TorchfricError(
            f"{path}: cannot parse the data ({_one_line(exc)}); expected {len(names)} "
            f"{fmt.describe()} numbers per row, as the header names"
        ) from None
    out = np.empty((len(frame), len(names)))
    for j, name in enumerate(names):
        col = frame[name]
        clock = name in fmt.clock
        if clock:
            values = _clock_seconds(col)
        else:
            values = _numbers(col, fmt.decimal)
        bad = np.flatnonzero(np.isnan(values) & col.notna().to_numpy())
        if bad.size:
            row = int(bad[0])
            line = RowLines(path, fmt.header_line).line(row)
            n, how = bad.size, fmt.describe()
            what = (
                f"is not a clock time written as the first row's ({col.iloc[0]!r}); write one "
                f"format of clock time ({n} in all; read as {how})"
                if clock
                else f"is not a number ({n} in all; read as {how}); write numbers only"
            )
            raise TorchfricError(
                f"{path}: line {line}: {shorten(str(col.iloc[row]))!r} in column {name!r} {what}"
            )
        out[:, j] = values
    return out


def _numbers(col, decimal: str) -> np.ndarray:  # type: ignore[no-untyped-def]
    """A column as floats, NaN where a field is not a number. One field of text leaves pandas'
    whole column as text, its decimal commas unread: they are read here, so that only the
    fields that are not numbers are NaN (and the error names the first of them, not the first
    row)."""
    import pandas as pd

    if not pd.api.types.is_numeric_dtype(col):  # text (object, or pandas' string dtype)
        text = col.astype("string").str.strip()
        if decimal != ".":  # a point where commas are decimal is not read as one (1.234: 1234?)
            text = text.where(~text.str.contains(".", regex=False).fillna(False))
            text = text.str.replace(decimal, ".", regex=False)
        col = text
    return pd.to_numeric(col, errors="coerce").to_numpy(np.float64, na_value=np.nan)


def _clock_seconds(col) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Seconds from the first row of a column of clock times (`CLOCK_FORMATS`, the first row's
    format), to the nanosecond; NaN where a row is empty or not in that format. A time of day
    that falls back by more than 12 hours has passed midnight: a day is added from there."""
    import pandas as pd

    text = col.astype("string").str.strip()
    rx, iso = CLOCK_FORMATS[_clock_format(str(text.iloc[0])) or "date and time"]
    iso_text = text.str.replace(rx, iso, regex=True).str.replace(",", ".", regex=False)
    ok = text.str.match(rx).fillna(False).to_numpy(bool)
    stamps = pd.to_datetime(iso_text.where(ok), format="ISO8601", errors="coerce", utc=True)
    when = stamps.to_numpy("datetime64[ns]")
    ns, good = when.astype(np.int64), ~np.isnat(when)
    if not good.any():
        return np.full(len(col), np.nan)
    if iso.startswith("1970"):  # a time of day: midnight passed where it falls back by > 12 h
        kept = ns[good]
        day = 86_400 * 10**9
        kept = kept + day * np.cumsum(np.r_[0, np.diff(kept) < -day // 2])
        ns = ns.copy()
        ns[good] = kept
    seconds = (ns - ns[np.flatnonzero(good)[0]]) / 1e9
    return np.where(good, seconds, np.nan)
