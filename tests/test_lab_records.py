"""Records as lab software and drives write them (issue: "read what labs write").

Each test writes one record of `torchfric.data.axis.STRIBECK_AXIS` (an independent simulator)
the way a lab would — semicolons and decimal commas, a German header with units, tabs, encoder
counts that wrap at 4096, rows missing and fields empty — and checks that it reads as the clean
CSV does, that ``init`` writes the config a user would have written, and that the identified
model is the clean CSV's within noise.
"""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

import torchfric
from torchfric.app.cli import main
from torchfric.app.config import Config
from torchfric.data import load_experiment, load_segments
from torchfric.data.axis import STRIBECK_AXIS, axis_record
from torchfric.data.units import split_unit
from torchfric.errors import TorchfricError

AXIS = STRIBECK_AXIS
DEG = 180.0 / math.pi
COUNTS = 4096 / (2 * math.pi)


@pytest.fixture(scope="module")
def record() -> dict[str, np.ndarray]:
    return axis_record(AXIS, seed=5, duration=3.0, kind="identification")


def _clean(path: pathlib.Path, r: dict[str, np.ndarray]) -> pathlib.Path:
    np.savetxt(path, np.column_stack([r["t"], r["u"], r["q"]]), delimiter=",", header="t,u,q",
               comments="", fmt=["%.6f", "%.10g", "%.12g"])  # fmt: skip
    return path


def _german(path: pathlib.Path, r: dict[str, np.ndarray], drop=(), empty=()) -> pathlib.Path:
    """``Zeit [ms];Strom [A];Winkel [deg]`` with decimal commas; rows `drop` left out, the
    current of rows `empty` left empty (row k is the file's line k + 2)."""
    lines = ["Zeit [ms];Strom [A];Winkel [deg]"]
    for k, (t, u, q) in enumerate(zip(r["t"], r["u"], r["q"], strict=True)):
        if k in drop:
            continue
        u_text = "" if k in empty else f"{u:.10g}"
        lines.append(f"{t * 1000:.3f};{u_text};{q * DEG:.10g}".replace(".", ","))
    path.write_text("\r\n".join(lines) + "\r\n", encoding="utf-8")
    return path


def _counts(path: pathlib.Path, r: dict[str, np.ndarray], *, wrap: bool) -> pathlib.Path:
    c = np.round(r["q"] * COUNTS)
    c = np.mod(c, 4096) if wrap else c
    np.savetxt(path, np.column_stack([r["t"], r["u"], c]), delimiter="\t",
               header="time\tcurrent\tencoder", comments="", fmt=["%.6f", "%.10g", "%d"])  # fmt: skip
    return path


# ------------------------------------------------------------------------------- reading
def test_header_units_and_names_in_other_languages() -> None:
    assert split_unit("Zeit [ms]") == ("zeit", "ms", True)
    assert split_unit("Winkel / °") == ("winkel", "deg", True)
    assert split_unit("Position in counts") == ("position", "counts", True)
    assert split_unit("Stellgröße (A)") == ("stellgrosse", None, False)
    assert split_unit("pos_deg") == ("pos", "deg", False)


@pytest.mark.parametrize("sep", [";", "\t", " "])
def test_dialects_read_as_the_clean_csv(tmp_path, record, sep) -> None:  # type: ignore[no-untyped-def]
    clean = load_experiment(_clean(tmp_path / "clean.csv", record))
    rows = [f"{t:.6f}{sep}{u:.10g}{sep}{q:.12g}" for t, u, q in
            zip(record["t"], record["u"], record["q"], strict=True)]  # fmt: skip
    text = "\n".join(rows)
    if sep != ",":
        text = text.replace(".", ",") if sep != " " else text
    path = tmp_path / "lab.csv"
    path.write_text(f"# logged by the drive\nt [s]{sep}u{sep}q\n\n{text}\n")
    lab = load_experiment(path, columns={"t": "t [s]"})
    for key in ("t", "u", "q"):
        np.testing.assert_array_equal(getattr(lab, key).numpy(), getattr(clean, key).numpy())


def test_decimal_commas_after_rows_of_integers_are_read_as_such(tmp_path, record) -> None:  # type: ignore[no-untyped-def]
    """A record that starts at rest (integers only in the first 50 rows the format is sniffed
    from) and writes decimal commas once it moves: the sniffer reads on to the first fraction."""
    rows = [f"{k};0;0" for k in range(300)]
    rows += [f"{k};{u:.10g};{q:.12g}".replace(".", ",") for k, u, q in
             zip(range(300, 300 + len(record["u"])), record["u"], record["q"], strict=True)]  # fmt: skip
    path = tmp_path / "rest.csv"
    path.write_text("Zeit [ms];u;q\n" + "\n".join(rows) + "\n")
    lab = load_experiment(path, columns={"t": "Zeit [ms]"}, time_unit="ms")
    np.testing.assert_allclose(lab.u.numpy()[300:], record["u"], rtol=1e-9, atol=0)  # 10 digits
    np.testing.assert_allclose(lab.q.numpy()[300:], record["q"], rtol=1e-11, atol=1e-12)


GERMAN_COLUMNS = {"t": "Zeit [ms]", "u": "Strom [A]", "q": "Winkel [deg]"}


def _read_alike(a: pathlib.Path, b: pathlib.Path, keys: tuple[str, ...]) -> tuple[list, list]:
    """`_german`'s columns of files `a` and `b` read as segments (ms, deg): the arrays `keys`
    of every segment equal bit for bit; each file's notes."""
    units = {"time_unit": "ms", "position_unit": "deg"}
    segs_a, notes_a = load_segments(a, columns=GERMAN_COLUMNS, **units)
    segs_b, notes_b = load_segments(b, columns=GERMAN_COLUMNS, **units)
    for x, y in zip(segs_a, segs_b, strict=True):
        for key in keys:
            np.testing.assert_array_equal(getattr(x, key).numpy(), getattr(y, key).numpy())
    return notes_a, notes_b


@pytest.mark.parametrize("suffix", [".txt", ".tsv", ".dat", ".TXT"])
def test_text_tables_named_as_loggers_name_them_read_as_the_csv(
    tmp_path, record, suffix, monkeypatch, capsys
) -> None:  # type: ignore[no-untyped-def]
    # A LabVIEW or oscilloscope export: tab-separated, units in the header, named .txt or .dat.
    clean = load_experiment(_clean(tmp_path / "clean.csv", record))
    rows = [f"{t:.6f}\t{u:.10g}\t{q:.12g}" for t, u, q in
            zip(record["t"], record["u"], record["q"] * DEG, strict=True)]  # fmt: skip
    path = tmp_path / f"log_ident{suffix}"
    path.write_text("Time [s]\tCurrent [A]\tAngle [deg]\n" + "\n".join(rows) + "\n")
    cols = {"t": "Time [s]", "u": "Current [A]", "q": "Angle [deg]"}
    lab = load_experiment(path, columns=cols, position_unit="deg")
    np.testing.assert_array_equal(lab.t.numpy(), clean.t.numpy())
    np.testing.assert_allclose(lab.q.numpy(), clean.q.numpy(), rtol=1e-11, atol=1e-12)
    monkeypatch.chdir(tmp_path)
    assert main(["init", path.name, "--c-m", "0.8", "--out", "log.toml"]) == 0
    out = capsys.readouterr().out
    assert f"{path.name} is tab-separated: read as such" in out
    d = Config.load(tmp_path / "log.toml").data
    assert d.columns == cols and d.position_unit == "deg"
    # a data file's name is refused as init's output and as a config
    assert main(["init", path.name, "--c-m", "0.8", "--out", f"x{suffix}"]) == 2
    assert "names a data file" in capsys.readouterr().err
    assert main(["check", path.name]) == 2
    assert "is a data file, not a config" in capsys.readouterr().err


def test_german_header_units_are_applied_or_refused(tmp_path, record) -> None:  # type: ignore[no-untyped-def]
    path = _german(tmp_path / "messung.csv", record)
    cols = {"t": "Zeit [ms]", "u": "Strom [A]", "q": "Winkel [deg]"}
    exp = load_experiment(path, columns=cols, time_unit="ms", position_unit="deg")
    np.testing.assert_allclose(exp.t.numpy(), record["t"], atol=1e-9)
    np.testing.assert_allclose(exp.q.numpy(), record["q"], atol=1e-9)
    with pytest.raises(TorchfricError, match=r"'Zeit \[ms\]' is in ms .* data\.time_unit = \"ms\""):
        load_experiment(path, columns=cols)
    with pytest.raises(TorchfricError, match=r"is in deg .*data\.position_unit = \"deg\""):
        load_experiment(path, columns=cols, time_unit="ms", position_unit="rad")


def test_gaps_and_empty_fields_become_segments_named_by_line(tmp_path, record) -> None:  # type: ignore[no-untyped-def]
    drop, empty = set(range(1200, 1210)), {600, 2400}
    path = _german(tmp_path / "gaps.csv", record, drop=drop, empty=empty)
    cols = {"t": "Zeit [ms]", "u": "Strom [A]", "q": "Winkel [deg]"}
    units = {"time_unit": "ms", "position_unit": "deg"}
    exps, notes = load_segments(path, columns=cols, **units)
    assert [e.name for e in exps] == ["gaps#1", "gaps#2", "gaps#3", "gaps#4"]
    assert [e.n for e in exps] == [600, 599, 1190, 599]
    (note,) = notes
    # the file's lines, 1-based with the header: row k is line k + 2 before the dropped rows
    assert "empty or NaN at line 602, line 2392" in note and "after line 1201 (10 samples)" in note
    with pytest.raises(TorchfricError, match=r"gaps\.csv: column u .* at line 602.*segments"):
        load_experiment(path, columns=cols, **units)
    jitter = _german(tmp_path / "odd.csv", dict(record, t=record["t"] + (record["t"] > 1) * 3e-4))
    with pytest.raises(TorchfricError, match=r"not uniform at line 1003 \(step 0\.0013"):
        load_segments(jitter, columns=cols, **units)


def test_a_row_of_units_under_the_names_joins_them(tmp_path, record, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    """A scope or PLC export writes its units in a row of their own: ``Zeit;Strom;Winkel``
    over ``[ms];[A];[deg]``. The row is joined to the names (``Zeit [ms]``), so it reads as the
    file with units in the header; rows and lines are counted below it; a row of numbers, or of
    words that are not short units, stays a data row (and is refused as before)."""
    german = _german(tmp_path / "one.csv", record, drop=set(range(1200, 1210)))
    head, *body = german.read_bytes().decode("utf-8").split("\r\n")
    two = tmp_path / "two.csv"
    two.write_text("\r\n".join(["Zeit;Strom;Winkel", "[ms];(A);deg", *body]), encoding="utf-8")
    notes_a, notes_b = _read_alike(german, two, ("q", "t"))
    assert "after line 1201 (10 samples)" in notes_a[0] and "after line 1202" in notes_b[0]
    monkeypatch.chdir(tmp_path)
    assert main(["init", "two.csv", "--c-m", "0.8"]) == 0
    assert Config.load(tmp_path / "two.toml").data.columns == GERMAN_COLUMNS
    capsys.readouterr()
    words = tmp_path / "words.csv"
    words.write_text("t;u;q\nzero;one point five;two\n0;1;2\n")
    with pytest.raises(TorchfricError, match=r"line 2: 'zero' in column 't' is not a number"):
        load_experiment(words)


def test_text_in_one_field_of_a_decimal_comma_file_is_named_by_its_line(tmp_path, record) -> None:  # type: ignore[no-untyped-def]
    """One field of text in a decimal-comma file (a unit typed into a cell, an error word from
    the logger) is the one the error names, with its line and the count of such fields; the
    good rows above it are not blamed."""
    german = _german(tmp_path / "plain.csv", record)
    lines = german.read_bytes().decode().split("\r\n")
    fields = lines[2000].split(";")
    lines[2000] = ";".join([fields[0], fields[1] + " V", fields[2]])  # line 2001
    lines[2500] = ";".join([*lines[2500].split(";")[:2], "Fehler"])  # line 2501
    bad = tmp_path / "text.csv"
    bad.write_bytes("\r\n".join(lines).encode())
    u_text = repr(fields[1] + " V")
    with pytest.raises(TorchfricError, match=rf"line 2001: {u_text} in column 'Strom \[A\]' "
                       r"is not a number \(1 in all; read as semicolon-separated, decimal comma\)"):  # fmt: skip
        load_experiment(bad)
    lines[2000] = ";".join(fields)
    bad.write_bytes("\r\n".join(lines).encode())
    with pytest.raises(TorchfricError, match=r"line 2501: 'Fehler' in column 'Winkel \[deg\]'"):
        load_experiment(bad)
    # a point among decimal commas is not read as a decimal point (1.234 may mean 1234)
    lines[2500] = ";".join([*lines[2500].split(";")[:2], "1.234"])
    bad.write_bytes("\r\n".join(lines).encode())
    with pytest.raises(TorchfricError, match=r"line 2501: '1\.234' in column 'Winkel \[deg\]'"):
        load_experiment(bad)


PREAMBLE = ["Name;X-Achse Trace", "Datei;C:\\TwinCAT\\Scope\\xachse.tcscopex",
            "Startzeit;28.11.2026 09:14:02", "Abtastrate;1 kHz", ""]  # fmt: skip


def test_a_scopes_preamble_above_the_header_is_skipped(tmp_path, record, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    """A scope export writes lines of its own above the column names (``Name;X-Achse Trace``,
    ``Abtastrate;1 kHz``, a blank line): they are skipped, the file reads as it does without
    them, line numbers still count them, and init says so; the input column's unit is named as
    c_m's. Lines above the first row of numbers with the rows' number of fields stay the header
    (a row of words under it is refused as before)."""
    german = _german(tmp_path / "plain.csv", record, drop=set(range(1200, 1210)))
    scope = tmp_path / "scope.csv"
    scope.write_bytes("\r\n".join(PREAMBLE).encode() + b"\r\n" + german.read_bytes())
    notes_a, notes_b = _read_alike(german, scope, ("q", "u", "t"))
    assert "after line 1201 (10 samples)" in notes_a[0] and "after line 1206" in notes_b[0]
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert main(["init", "scope.csv", "--c-m", "0.8"]) == 0
    out = capsys.readouterr().out
    assert "scope.csv: lines 1–5 above its header (line 6) are a preamble: skipped" in out
    assert "u is used as written, in A (column 'Strom [A]'): model.c_m is per A of u" in out
    assert Config.load(tmp_path / "scope.toml").data.columns == GERMAN_COLUMNS
    words = tmp_path / "words.csv"
    words.write_text("t;u;q\nzero;one;two\n0;1;2\n")
    with pytest.raises(TorchfricError, match=r"line 2: 'zero' in column 't' is not a number"):
        load_experiment(words)


def test_a_drives_german_names_for_the_actual_position_are_read_as_q(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Drive software names the measured position "Lageistwert" (or "Istlage"); a user walk's
    scope export stopped at "cannot tell which column is q"."""
    from torchfric.app.commands.columns import map_columns

    for name in ("Lageistwert [Inc]", "Istlage", "Positionsistwert (mm)",
                 "Gelenkwinkel [deg]", "Achsposition [mm]"):  # compounds: a robot's, an axis's
        table = {"Zeit [s]": np.zeros(3), "Stellgröße [V]": np.zeros(3), name: np.zeros(3)}
        assert map_columns(table, {}, tmp_path / "x.csv", False)["q"] == name
    # a robot controller's log (user walk): compound names for the input and the angle
    table = {"Zeit [ms]": np.zeros(3), "Motorstrom [A]": np.zeros(3), "Gelenkwinkel [deg]": np.zeros(3)}
    assert map_columns(table, {}, tmp_path / "x.csv", False) == {
        "t": "Zeit [ms]", "u": "Motorstrom [A]", "q": "Gelenkwinkel [deg]"}  # fmt: skip


def _stamped(path: pathlib.Path, r: dict[str, np.ndarray], stamp, sep: str = ",") -> pathlib.Path:  # type: ignore[no-untyped-def]
    """The record with its time column written by `stamp(datetime)` (a logger's clock times)."""
    import datetime

    start = datetime.datetime(2026, 11, 28, 23, 59, 58, 500_000)
    lines = [f"Timestamp{sep}u{sep}q"]
    for t, u, q in zip(r["t"], r["u"], r["q"], strict=True):
        when = start + datetime.timedelta(microseconds=round(t * 1e6))
        number = f"{u:.10g}{sep}{q:.12g}"
        lines.append(f"{stamp(when)}{sep}{number if sep == ',' else number.replace('.', ',')}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("kind", "stamp", "sep"),
    [
        ("date and time", lambda w: w.isoformat(sep=" ", timespec="milliseconds"), ","),
        ("date and time", lambda w: w.isoformat(timespec="microseconds") + "+01:00", ","),
        ("day.month.year and time",
         lambda w: w.strftime("%d.%m.%Y %H:%M:%S,") + f"{w.microsecond // 1000:03d}", ";"),
        ("time of day", lambda w: w.strftime("%H:%M:%S.%f"), ";"),  # passes midnight
    ],
)  # fmt: skip
def test_a_column_of_clock_times_reads_as_seconds_from_its_first_row(
    tmp_path, record, kind, stamp, sep, monkeypatch, capsys
) -> None:  # type: ignore[no-untyped-def]
    """Loggers write the time as a date and a clock time; read as seconds from the first row,
    to the nanosecond, it is the clean CSV's t (here across midnight), and init says so."""
    from torchfric.data.lab import CLOCK_FORMATS, sniff_format

    clean = load_experiment(_clean(tmp_path / "clean.csv", record))
    path = _stamped(tmp_path / "stamped.csv", record, stamp, sep)
    fmt = sniff_format(path)[0]
    assert fmt.clock == ("Timestamp",) and kind in CLOCK_FORMATS
    lab = load_experiment(path, columns={"t": "Timestamp"})
    np.testing.assert_allclose(lab.t.numpy(), clean.t.numpy(), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(lab.q.numpy(), clean.q.numpy())
    monkeypatch.chdir(tmp_path)
    assert main(["init", path.name, "--c-m", "0.8", "--out", "stamped.toml"]) == 0
    out = capsys.readouterr().out
    assert "column 'Timestamp' holds clock times: read as seconds from its first row" in out
    assert "t = 'Timestamp'" in out and "dt 0.001 s" in out


def test_a_loggers_names_for_its_clock_column_are_read_as_t(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """A logger heads its clock times "Datum/Zeit", "Date Time" or "Uhrzeit"; a user walk's
    record stopped at "cannot tell which column is t"."""
    from torchfric.app.commands.columns import map_columns

    for name in (
        "Datum/Zeit",
        "Date/Time",
        "Date Time",
        "DateTime",
        "Uhrzeit",
        "Datum und Uhrzeit",
    ):
        table = {
            name: np.zeros(3),
            "Drehmoment-Sollwert [Nm]": np.zeros(3),
            "Position [°]": np.zeros(3),
        }
        assert map_columns(table, {}, tmp_path / "x.csv", False)["t"] == name


def test_a_clock_time_in_another_format_is_named_by_line(tmp_path, record) -> None:  # type: ignore[no-untyped-def]
    path = _stamped(tmp_path / "mixed.csv", record, lambda w: w.strftime("%H:%M:%S.%f"))
    lines = path.read_text().splitlines()
    lines[10] = "yesterday," + lines[10].split(",", 1)[1]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(TorchfricError) as err:
        load_experiment(path, columns={"t": "Timestamp"})
    text = str(err.value)
    assert "line 11: 'yesterday' in column 'Timestamp' is not a clock time written as the " \
           "first row's ('23:59:58.500000'); write one format of clock time (1 in all; read as " \
           "comma-separated)" in text and "\n" not in text  # fmt: skip


# ------------------------------------------------------------------------------- init, check
def test_init_and_check_a_german_lab_file(tmp_path, record, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.chdir(tmp_path)
    _german(tmp_path / "messung.csv", record, drop=set(range(1200, 1210)), empty={600})
    assert main(["init", "messung.csv", "--c-m", "0.8"]) == 0
    out = capsys.readouterr().out
    assert "semicolon-separated, decimal comma" in out and "in 3 segments" in out
    d = Config.load(tmp_path / "messung.toml").data
    assert d.columns == {"t": "Zeit [ms]", "u": "Strom [A]", "q": "Winkel [deg]"}
    assert (d.time_unit, d.position_unit, d.wrap_period) == ("ms", "deg", None)
    assert main(["check", "messung.toml"]) == 0
    out = capsys.readouterr().out
    assert "messung.csv: 2974 samples in 3 segments" in out and "t in ms (converted to s)" in out


def test_wrapped_counts_are_refused_at_check_unless_unwrapped(
    tmp_path, record, monkeypatch, capsys
) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.chdir(tmp_path)
    _counts(tmp_path / "enc.csv", record, wrap=True)
    assert main(["init", "enc.csv", "--c-m", "0.8"]) == 0
    d = Config.load(tmp_path / "enc.toml").data
    assert (d.position_unit, d.counts_per_rev, d.wrap_period) == ("counts", 4096.0, 4096.0)
    assert "q wraps" in capsys.readouterr().out
    assert main(["check", "enc.toml", "--set", "data.wrap_period=4096"]) == 0
    capsys.readouterr()
    text = (tmp_path / "enc.toml").read_text().replace("\nwrap_period", "\n# wrap_period")
    (tmp_path / "enc.toml").write_text(text)
    assert main(["check", "enc.toml"]) == 2
    err = capsys.readouterr().err
    assert "q wraps: it jumps from" in err and "data.wrap_period = 4096" in err


def test_unwrapped_counts_need_their_resolution(tmp_path, record, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.chdir(tmp_path)
    _counts(tmp_path / "enc.csv", record, wrap=False)
    assert main(["init", "enc.csv", "--c-m", "0.8"]) == 2
    assert "--counts-per-rev N" in capsys.readouterr().err
    assert main(["init", "enc.csv", "--c-m", "0.8", "--counts-per-rev", "4096"]) == 0
    d = Config.load(tmp_path / "enc.toml").data
    assert (d.position_unit, d.counts_per_rev, d.wrap_period) == ("counts", 4096.0, None)
    with pytest.raises(TorchfricError, match=r'"counts" needs exactly one of data\.counts_per_rev'):
        Config.loads("", ["data.position_unit=counts"])


def _turns(path: pathlib.Path, r: dict[str, np.ndarray], header: str, wrap: bool = False) -> pathlib.Path:
    """A drive's log: time in ms, torque in % of rated, position in revolutions (tab)."""
    q = r["q"] / (2 * math.pi)
    q = np.mod(q, 1.0) if wrap else q
    rows = [f"{t * 1000:.3f}\t{u:.10g}\t{x:.12g}" for t, u, x in zip(r["t"], r["u"], q, strict=True)]
    path.write_text(f"Time [ms]\tTorque [%]\t{header}\n" + "\n".join(rows) + "\n")
    return path


def test_positions_in_revolutions_and_micrometres_are_read(tmp_path, record, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    """A servo drive logs q in revolutions, a linear scale in µm: both are units torchfric
    reads (before, "[rev]" was taken as rad: every parameter 2π off, silently)."""
    assert split_unit("Actual position [rev]") == ("actual_position", "rev", True)
    assert split_unit("Lageistwert [Umdr]")[1:] == ("rev", True)
    assert split_unit("Position in turns")[1:] == ("rev", True)
    assert split_unit("x [µm]")[1:] == ("um", True) and split_unit("x_um")[1:] == ("um", False)
    clean = load_experiment(_clean(tmp_path / "clean.csv", record))
    path = _turns(tmp_path / "drive_ident.csv", record, "Actual position [rev]")
    cols = {"t": "Time [ms]", "u": "Torque [%]", "q": "Actual position [rev]"}
    lab = load_experiment(path, columns=cols, time_unit="ms", position_unit="rev")
    np.testing.assert_allclose(lab.q.numpy(), clean.q.numpy(), rtol=1e-11, atol=1e-12)
    with pytest.raises(TorchfricError, match=r"is in rev \(its header says so\)"):
        load_experiment(path, columns=cols, time_unit="ms", position_unit="rad")
    monkeypatch.chdir(tmp_path)
    assert main(["init", path.name, "--c-m", "0.05"]) == 0
    assert 'position    rev (from the column name "Actual position [rev]")' in capsys.readouterr().out
    d = Config.load(tmp_path / "drive_ident.toml").data
    assert (d.position_unit, d.wrap_period, d.axis_unit) == ("rev", None, "rad")
    # a single-turn position, 0 … 1 rev, wraps at one revolution
    _turns(tmp_path / "single.csv", record, "Position [rev]", wrap=True)
    assert main(["init", "single.csv", "--c-m", "0.05"]) == 0
    assert Config.load(tmp_path / "single.toml").data.wrap_period == 1.0
    # micrometres: a linear axis, q in m
    rows = [f"{t:.6f},{u:.10g},{x * 1e6:.10g}" for t, u, x in zip(record["t"], record["u"], record["q"], strict=True)]
    (tmp_path / "scale.csv").write_text("t,u,Position [µm]\n" + "\n".join(rows) + "\n")
    capsys.readouterr()
    assert main(["init", "scale.csv", "--c-m", "5"]) == 0
    d = Config.load(tmp_path / "scale.toml").data
    assert (d.position_unit, d.axis_unit) == ("um", "m")
    scaled = load_experiment(tmp_path / "scale.csv", columns={"q": "Position [µm]"}, position_unit="um")
    np.testing.assert_allclose(scaled.q.numpy(), clean.q.numpy(), rtol=1e-9, atol=1e-12)


def test_a_unit_torchfric_does_not_read_is_refused_with_the_fix(tmp_path, record, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    """A header that states q's unit as one torchfric does not read stops init with one line
    (before: "position rad (nothing says otherwise)"); --position-unit names the unit."""
    monkeypatch.chdir(tmp_path)
    _turns(tmp_path / "inch.csv", record, "Position [inch]")
    assert main(["init", "inch.csv", "--c-m", "0.05"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and not (tmp_path / "inch.toml").exists()
    assert "the column 'Position [inch]' states its unit as \"inch\"" in err
    assert "rad, deg, rev, m, mm, um, counts" in err and "--position-unit" in err
    assert main(["init", "inch.csv", "--c-m", "0.05", "--position-unit", "mm"]) == 0
    assert "position    mm (--position-unit given)" in capsys.readouterr().out
    assert Config.load(tmp_path / "inch.toml").data.position_unit == "mm"
    # a known unit in the header and another on the command line: refused, nothing written
    _turns(tmp_path / "turns.csv", record, "Position [rev]")
    assert main(["init", "turns.csv", "--c-m", "0.05", "--position-unit", "rad"]) == 2
    err = capsys.readouterr().err.strip()
    assert "is in rev (its header says so) but --position-unit is rad" in err
    assert not (tmp_path / "turns.toml").exists()


def test_a_time_unit_torchfric_does_not_read_is_refused_unless_clock_times(tmp_path, record, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    """``Zeit [min]`` would make every rate 60× off if read as s: init refuses it in one line
    and --time-step reads the record without it; a clock column's bracket is not a unit."""
    monkeypatch.chdir(tmp_path)
    rows = [f"{t / 60:.12g};{u:.10g};{q:.12g}" for t, u, q in zip(record["t"], record["u"], record["q"], strict=True)]
    (tmp_path / "minutes.csv").write_text("Zeit [min];u;q\n" + "\n".join(rows) + "\n")
    assert main(["init", "minutes.csv", "--c-m", "0.8"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.count("minutes.csv") == 1
    assert "the time column 'Zeit [min]' states its unit as \"min\"" in err and "--time-step" in err
    assert main(["init", "minutes.csv", "--c-m", "0.8", "--time-step", "0.001"]) == 0
    d = Config.load(tmp_path / "minutes.toml").data
    assert d.time_step == 0.001 and "t" not in d.columns
    # a bracket that is not a unit stays a name; seconds spelled out are seconds
    rows = [f"{t:.6f};{u:.10g};{q:.12g}" for t, u, q in zip(record["t"], record["u"], record["q"], strict=True)]
    for header in ("Zeit (relativ)", "Time [seconds]"):
        (tmp_path / "rel.csv").write_text(f"{header};u;q\n" + "\n".join(rows) + "\n")
        assert main(["init", "rel.csv", "--c-m", "0.8", "--force"]) == 0
        d = Config.load(tmp_path / "rel.toml").data
        assert (d.columns["t"], d.time_unit) == (header, "s")
    # clock times under a header that names their format are read as seconds, as before
    start = np.datetime64("2026-11-28T09:15:00.000")
    stamps = [str(start + np.timedelta64(round(t * 1e6), "us"))[11:23] for t in record["t"]]
    rows = [f"{c},{u:.10g},{q:.12g}" for c, u, q in zip(stamps, record["u"], record["q"], strict=True)]
    (tmp_path / "clock.csv").write_text("Time [hh:mm:ss.fff],u,q\n" + "\n".join(rows) + "\n")
    capsys.readouterr()
    assert main(["init", "clock.csv", "--c-m", "0.8"]) == 0
    assert "holds clock times" in capsys.readouterr().out


# ------------------------------------------------------------------------------- the model
def _fit(cfg: pathlib.Path, **sets) -> dict[str, float]:  # type: ignore[no-untyped-def]
    result = torchfric.fit(str(cfg), out=str(cfg.parent / f"run_{cfg.stem}"), quiet=True,
                           **{"estimator.passes": 2, "estimator.ensemble": 0}, **sets)  # fmt: skip
    p = result.metrics["parameters"]
    return {k: p[k]["value"] for k in ("inertia", "viscous")}


def test_each_kind_of_file_identifies_the_clean_csvs_model(tmp_path, record) -> None:  # type: ignore[no-untyped-def]
    header = f"[model]\nc_m = {AXIS.c_m!r}\n"
    _clean(tmp_path / "clean.csv", record)
    (tmp_path / "clean.toml").write_text(f'[data]\ntrain = ["clean.csv"]\n{header}')
    _german(tmp_path / "de.csv", record, drop=set(range(1500, 1510)), empty={700, 2300})
    (tmp_path / "de.toml").write_text(
        '[data]\ntrain = ["de.csv"]\ntime_unit = "ms"\nposition_unit = "deg"\n'
        f'columns = {{ t = "Zeit [ms]", u = "Strom [A]", q = "Winkel [deg]" }}\n{header}'
    )
    _counts(tmp_path / "enc.csv", record, wrap=True)
    (tmp_path / "enc.toml").write_text(
        '[data]\ntrain = ["enc.csv"]\nposition_unit = "counts"\ncounts_per_rev = 4096\n'
        f'wrap_period = 4096\ncolumns = {{ t = "time", u = "current", q = "encoder" }}\n{header}'
    )
    clean = _fit(tmp_path / "clean.toml")
    for name in ("de", "enc"):
        got = _fit(tmp_path / f"{name}.toml")
        # within noise: the German file loses 3 % of its samples to the gap and the empty
        # fields, the counts file rounds q to 4096 per turn (the axis' encoder has 20000)
        for key, value in clean.items():
            assert got[key] == pytest.approx(value, rel=0.05), (name, key, got, clean)
