"""Records as lab software and drives write them: CSV text in any common dialect (`text`:
the delimiter and decimal separator sniffed, clock times read as seconds, rows named by
their line in the file), and
records with holes or wrapping positions (`segments`: gaps and NaN rows cut a record into
segments; wraps of a single-turn encoder found; a sample counter read as time).
`torchfric.data.readers` uses both."""

from .segments import (
    COUNTER_NAMES,
    MIN_SEGMENT,
    Segments,
    counter_time,
    nice_period,
    split_segments,
    wrap_jumps,
)
from .text import (
    CLOCK_FORMATS,
    CSV_FIX,
    MAX_LINE,
    RowLines,
    TextFormat,
    read_text_table,
    reading_notes,
    sniff_format,
)

__all__ = [
    "CLOCK_FORMATS",
    "COUNTER_NAMES",
    "CSV_FIX",
    "MAX_LINE",
    "MIN_SEGMENT",
    "RowLines",
    "Segments",
    "TextFormat",
    "counter_time",
    "nice_period",
    "read_text_table",
    "reading_notes",
    "sniff_format",
    "split_segments",
    "wrap_jumps",
]
