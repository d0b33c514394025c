"""Tests of torchfric.data's guards against files it cannot load (directories, pipes, devices,
files too large for memory, binary, empty or non-UTF-8 files) and of `data_warnings`, which flags
records that would almost certainly give a wrong model (clipped input, t in ms)."""

from __future__ import annotations

import os
import pathlib
import socket
import threading
import time

import numpy as np
import pytest
import scipy.io

import torchfric.data.checks as checks_module
import torchfric.data.guards as guards_module
import torchfric.data.readers as readers_module
from torchfric.data import Experiment, data_warnings, load_experiment, make_experiment
from torchfric.data.lab import MAX_LINE
from torchfric.data.rig import EXPERIMENTS, rig_experiment
from torchfric.errors import TorchfricError

GIB = 1 << 30
HSM150_COLUMNS = {"t": "data:0", "u": "data:4", "q": "data:2", "qdot": "data:3"}


def _one_line_error(path: pathlib.Path | str, match: str, **kwargs: object) -> str:
    """load_experiment(path) raises a one-line TorchfricError matching `match`; its text."""
    with pytest.raises(TorchfricError, match=match) as info:
        load_experiment(path, **kwargs)  # type: ignore[arg-type]
    text = str(info.value)
    assert "\n" not in text and len(text) < 400, text
    return text


def _write_csv(path: pathlib.Path, n: int = 50) -> pathlib.Path:
    t = np.arange(n) * 1e-3
    rows = "".join(f"{a:.17g},{np.sin(a):.17g},{np.cos(a):.17g}\n" for a in t)
    path.write_text("t,u,q\n" + rows)
    return path


# --------------------------------------------------------------------------- not a regular file
def test_directory_is_refused(tmp_path: pathlib.Path) -> None:
    (tmp_path / "run.csv").mkdir()
    text = _one_line_error(tmp_path / "run.csv", r"run\.csv: is a directory")
    assert "regular file" in text


def test_fifo_is_refused_without_opening_it(tmp_path: pathlib.Path) -> None:
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    outcome: list[BaseException | None] = []

    def load() -> None:
        try:
            load_experiment(fifo)
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            outcome.append(exc)
        else:
            outcome.append(None)

    worker = threading.Thread(target=load, daemon=True)
    worker.start()
    worker.join(timeout=10)
    if worker.is_alive():  # it opened the pipe and blocks: release it with a writer, then fail
        with open(fifo, "w"):
            pass
        worker.join(timeout=10)
        pytest.fail("load_experiment opened the FIFO (it blocked waiting for a writer)")
    (exc,) = outcome
    assert isinstance(exc, TorchfricError)
    text = str(exc)
    assert "pipe.csv: is a named pipe (FIFO)" in text and "give a regular file" in text
    assert "\n" not in text


@pytest.mark.parametrize("device", ["/dev/null", "/dev/zero"])
def test_character_devices_are_refused(tmp_path: pathlib.Path, device: str) -> None:
    if not os.path.exists(device):
        pytest.skip(f"{device} does not exist here")
    # /dev/zero would stream zeros forever if it were read; the link gives it a .csv name
    link = tmp_path / "device.csv"
    link.symlink_to(device)
    text = _one_line_error(link, r"device\.csv: is a character device")
    assert "give a regular file" in text
    # without a data suffix the type check speaks first, also in one line
    _one_line_error(device, r"unsupported file type ''")


def test_socket_is_refused(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "s.npz"
    if len(str(path)) > 100:  # AF_UNIX paths are limited to ~108 bytes
        pytest.skip("temporary path too long for a Unix socket")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.bind(str(path))
        text = _one_line_error(path, r"s\.npz: is a socket")
    assert "give a regular file" in text


def test_missing_file_still_names_the_working_directory(tmp_path: pathlib.Path) -> None:
    _one_line_error(tmp_path / "nope.npz", r"nope\.npz: file not found \(working directory")


# --------------------------------------------------------------------------- too large for memory
def _sparse(path: pathlib.Path, size: int) -> pathlib.Path:
    with open(path, "wb") as f:
        f.truncate(size)  # a hole: no disk space used, reads as NUL bytes
    return path


def test_sparse_20_gib_csv_is_refused_before_reading(
    tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = _sparse(tmp_path / "x.csv", 20 * GIB)
    monkeypatch.setattr(guards_module, "_available_memory", lambda: int(9.1 * GIB))

    def no_parse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the file was parsed before the memory check")

    monkeypatch.setattr(readers_module.np, "loadtxt", no_parse)
    monkeypatch.setattr(readers_module, "read_text_table", no_parse)
    start = time.perf_counter()
    text = _one_line_error(path, r"x\.csv is 20\.0 GiB: loading it needs about")
    assert time.perf_counter() - start < 2.0
    # no row of text in it: the bound of 4 bytes of float64 per byte of file, × the load ratio
    need = 20 * guards_module._CSV_MAX_EXPANSION * guards_module._LOAD_MEMORY_RATIO
    assert f"needs about {need:.0f} GiB of memory and 9.1 GiB is available" in text
    assert "data.start/data.stop apply only after loading" in text and "split it" in text


def test_sparse_20_gib_csv_with_the_real_available_memory(tmp_path: pathlib.Path) -> None:
    """Unpatched: refused for memory wherever < 200 GiB is free, else as binary; never read."""
    path = _sparse(tmp_path / "big.csv", 20 * GIB)
    start = time.perf_counter()
    _one_line_error(
        path,
        r"big\.csv (is 20\.0 GiB: loading it needs about .* GiB of memory and "
        r".* is available|: cannot read the file as CSV: it holds binary data)",
    )
    assert time.perf_counter() - start < 5.0


def test_csv_estimate_reads_the_row_length_from_the_first_rows(
    tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = _write_csv(tmp_path / "rows.csv", n=20_000)  # ≈ 60 bytes per row of 3 values
    size = path.stat().st_size
    arrays = guards_module._csv_array_bytes(path, size)
    assert arrays == pytest.approx(20_000 * 3 * 8, rel=0.05)
    assert arrays < guards_module._CSV_MAX_EXPANSION * size / 5  # far below the dense-text bound
    monkeypatch.setattr(guards_module, "_available_memory", lambda: 1 << 20)
    text = _one_line_error(path, r"rows\.csv is 1\.\d MiB: loading it needs about 1\.1 MiB")
    assert "1.0 MiB is available" in text
    monkeypatch.setattr(guards_module, "_available_memory", lambda: 2 << 20)
    assert load_experiment(path).n == 20_000  # enough: loads


def test_compressed_npz_is_judged_by_its_uncompressed_size(
    tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "z.npz"
    n = 400_000
    np.savez_compressed(path, t=np.arange(n) * 1e-3, u=np.zeros(n), q=np.zeros(n))
    assert path.stat().st_size < 1 << 20  # zeros compress to almost nothing
    monkeypatch.setattr(guards_module, "_available_memory", lambda: 8 << 20)
    _one_line_error(path, r"z\.npz is .*: loading it needs about 2[0-9]\.\d MiB of memory")


def test_available_memory_is_a_positive_byte_count() -> None:
    avail = guards_module._available_memory()
    if avail is None:
        pytest.skip("this platform reports no available memory")
    assert isinstance(avail, int) and avail > 0


# --------------------------------------------------------------------------- damaged contents
def test_garbage_binary_files(tmp_path: pathlib.Path) -> None:
    rng = np.random.default_rng(1)
    for suffix in (".csv", ".npz", ".mat"):
        path = tmp_path / f"junk{suffix}"
        path.write_bytes(rng.bytes(4096))
        _one_line_error(path, rf"junk\{suffix}: cannot read")
    path = tmp_path / "nul.csv"
    path.write_bytes(b"t,u,q\n" + b"\0" * 500)
    _one_line_error(path, r"nul\.csv: cannot read the file as CSV: it holds binary data")
    path = tmp_path / "junk.npz"
    path.write_bytes(b"not a zip archive at all" * 20)
    _one_line_error(path, r"junk\.npz: cannot read as \.npz: it is no numpy archive")


@pytest.mark.parametrize("suffix", [".csv", ".npz", ".mat"])
def test_empty_file(tmp_path: pathlib.Path, suffix: str) -> None:
    path = tmp_path / f"empty{suffix}"
    path.write_bytes(b"")
    _one_line_error(path, rf"empty\{suffix}: the file is empty \(0 bytes\)")


def test_header_only_and_blank_files(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "h.csv"
    for text in ("t,u,q\n", "t,u,q", "# comment\nt,u,q\n\n"):
        path.write_text(text)
        _one_line_error(path, r"h\.csv: no data rows below the header")
    path.write_text("\n\n   \n# only comments\n")
    _one_line_error(path, r"h\.csv: no header line")


def test_non_utf8_bytes(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "latin.csv"
    path.write_bytes("t,u,q\n0,1,2\n0.001,\xe9,2\n".encode("latin-1"))  # in the body
    _one_line_error(path, r"latin\.csv: cannot read the file: byte 0xe9 is not UTF-8 text.*UTF-8")
    path.write_bytes("t,\xb5,q\n0,1,2\n".encode("latin-1"))  # in the header
    _one_line_error(path, r"latin\.csv: cannot read the file: byte 0xb5 is not UTF-8 text")


def test_byte_order_mark_and_separators(tmp_path: pathlib.Path) -> None:
    good = _write_csv(tmp_path / "good.csv")
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + good.read_bytes())  # as Excel writes "CSV UTF-8"
    assert load_experiment(bom).fingerprint() == load_experiment(good).fingerprint()
    semi = tmp_path / "semi.csv"  # as lab software writes it: semicolons, decimal commas
    semi.write_text(good.read_text().replace(",", ";").replace(".", ","))
    assert load_experiment(semi).fingerprint() == load_experiment(good).fingerprint()


def test_bad_values_are_echoed_briefly(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "long.csv"
    path.write_text("t,u,q\n" + "x" * 100_000 + ",1,2\n")
    text = _one_line_error(path, r"long\.csv: line 2: 'x+… \(100000 characters\)' in column 't' is")
    assert text.count("x") < 210
    path.write_text("t," + "y" * 5000 + ",t\n0,1,2\n")
    text = _one_line_error(path, r"long\.csv: header .* has empty or repeated column names")
    assert text.count("y") < 210
    # a header line longer than 1 MiB (e.g. a text file without line breaks) is refused
    path.write_text("z" * (MAX_LINE + 10) + "\n")
    _one_line_error(path, r"long\.csv: line 1 is longer than 1024 KiB")


def test_loading_still_works_for_every_format(tmp_path: pathlib.Path) -> None:
    n = 200
    t = np.arange(n) * 1e-3
    u, q = np.sin(t), np.cos(t)
    np.savez(tmp_path / "a.npz", t=t, u=u, q=q)
    scipy.io.savemat(tmp_path / "a.mat", {"t": t, "u": u, "q": q})
    _write_csv(tmp_path / "a.csv", n)
    for suffix in (".npz", ".mat", ".csv"):
        exp = load_experiment(tmp_path / f"a{suffix}")
        assert exp.n == n
        np.testing.assert_allclose(exp.q.numpy(), q, rtol=0, atol=1e-15)


# --------------------------------------------------------------------------- data_warnings
def _rig(name: str = "identification") -> dict[str, np.ndarray]:
    return rig_experiment(name)


def _clipped(fraction: float) -> Experiment:
    a = _rig()
    limit = fraction * float(np.max(np.abs(a["u"])))
    return make_experiment(a["t"], np.clip(a["u"], -limit, limit), a["q"], name="clipped")


def test_data_warnings_is_exported_and_pure() -> None:
    assert "data_warnings" in checks_module.__all__
    exp = _clipped(0.6)
    before = exp.fingerprint()
    assert data_warnings(exp) == data_warnings(exp)
    assert exp.fingerprint() == before


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_rig_records_give_no_warning(name: str) -> None:
    a = _rig(name)
    exp = make_experiment(a["t"], a["u"], a["q"], name=name)
    for velocity in ("highpass", "zero_phase", "measured"):
        assert data_warnings(exp, velocity=velocity) == []


def test_input_clipped_at_60_percent_is_flagged_on_both_sides() -> None:
    warnings = data_warnings(_clipped(0.6))
    assert len(warnings) == 2
    low, high = warnings
    assert "u sits at its exact minimum -0.0492" in low and "u sits at its exact maximum" in high
    for text in warnings:
        assert "\n" not in text and "% of the samples" in text
        assert "remove the saturated segments or raise the amplifier's limit" in text
        assert "applied input equals the recorded one" in text
    fraction = float(high.split(" in ")[1].split("%")[0]) / 100
    u = _clipped(0.6).u.numpy()
    assert fraction == pytest.approx(np.mean(u == u.max()), abs=5e-4)


def test_input_clipped_mildly_or_stepped_is_not_flagged() -> None:
    # clipped at 95 % of its peak: only 0.04 % of the samples sit at the limits (< 1 %)
    assert data_warnings(_clipped(0.95)) == []
    # a PRBS input sits at its two levels all the time, by design
    n = 4000
    t = np.arange(n) * 1e-3
    rng = np.random.default_rng(0)
    prbs = np.repeat(rng.choice([-1.0, 1.0], n // 40), 40)
    exp = make_experiment(t, prbs, np.cumsum(prbs) * 1e-4, name="prbs")
    assert data_warnings(exp) == []
    # a noisy input that jumps onto one level held for 20 % of the record is a step, not a clip
    u = rng.normal(0.0, 0.1, n)
    u[1000:1800] = 2.0
    exp = make_experiment(t, u, np.cumsum(u) * 1e-4, name="step")
    assert data_warnings(exp) == []


def test_a_record_that_starts_and_ends_at_rest_is_not_a_clip() -> None:
    """A logger started before the test and stopped after it: u exactly 0 for the first and
    last 3 % of the samples of an input that never goes negative, then a ramp up. That rest is
    no clip (a user walk's validation segments drew the warning); the same input clipped at 0
    inside the record still is."""
    n = 10_000
    t = np.arange(n) * 1e-3
    rng = np.random.default_rng(1)
    phase = np.clip((np.arange(n) - 300) / (n - 600), 0.0, 1.0)
    u = np.sin(np.pi * phase) * (1.0 + 0.3 * np.sin(40 * np.pi * phase)) + 0.01 * rng.random(n)
    u[:300] = u[-300:] = 0.0  # rises from rest gradually, and falls back to it
    q = np.cumsum(u) * 1e-3
    assert data_warnings(make_experiment(t, u, q, name="rest")) == []
    # a unipolar amplifier clipping a command that dips below 0, inside the record
    clipped = np.maximum(np.sin(np.arange(n) * 0.004) + 0.3, 0.0) + 0.01 * rng.random(n)
    clipped[clipped < 0.01] = 0.0
    clipped[:300] = clipped[-300:] = 0.0
    (text,) = data_warnings(make_experiment(t, clipped, q, name="clip"))
    assert text.startswith("clip: the input u sits at its exact minimum 0 in ")


def test_rig_record_with_t_in_milliseconds_is_flagged() -> None:
    a = _rig()
    exp = make_experiment(a["t"] * 1000, a["u"], a["q"], name="ms")
    for velocity in ("highpass", "zero_phase"):
        (text,) = data_warnings(exp, velocity=velocity)
        assert text.startswith(
            "ms: sample time 1 s (1 Hz) looks like milliseconds in a seconds column"
        )
        assert text.endswith("convert the t column to seconds (t/1000)")
        assert "\n" not in text
    # a cut-off below Nyquist was chosen for this sample time: trust it
    assert data_warnings(exp, velocity_cutoff_hz=0.2) == []
    # a genuine record at 1 Hz moving at a servo's pace (0.5 rad/sample swings) is not flagged
    t = np.arange(300.0)
    q = np.sin(0.8 * t) + 0.3 * np.sin(2.1 * t)
    assert data_warnings(make_experiment(t, np.cos(t), q, name="slow")) == []


def test_measured_qdot_reveals_t_in_milliseconds() -> None:
    a = _rig()
    t, q = a["t"], a["q"]
    qdot = np.gradient(q, t)
    ok = make_experiment(t[::60], a["u"][::60], q[::60], qdot[::60], name="ok")
    assert ok.dt == pytest.approx(0.06)  # 17 Hz with a consistent velocity: no warning
    assert data_warnings(ok, velocity="measured") == []
    ms = make_experiment(t * 1000, a["u"], q, qdot, name="ms")
    (text,) = data_warnings(ms, velocity="measured")
    assert "the measured qdot is 1000 times the finite difference of q" in text
    # the evidence of qdot wins over the cut-off rule: a consistent qdot at 1 Hz is believed
    slow = make_experiment(t * 1000, a["u"], q, qdot / 1000, name="slow")
    assert data_warnings(slow) == []


# --------------------------------------------------------------------------- real data sets
def _real_records(shared: pathlib.Path) -> list[Experiment]:
    emps = [
        load_experiment(shared / "emps" / f, columns={"u": "vir", "q": "qm"})
        for f in ("DATA_EMPS.mat", "DATA_EMPS_PULSES.mat")
    ]
    hsm = [
        load_experiment(f, columns=HSM150_COLUMNS)
        for f in sorted((shared / "hsm150_two_motor").glob("idf_*.mat"))
    ]
    disc = load_experiment(
        shared / "unbalanced_disk" / "training-val-test-data.npz",
        columns={"q": "th"},
        time_step=0.025,
    )
    assert len(hsm) == 12
    return [*emps, *hsm, disc]


def test_real_data_gives_no_false_warning(shared_data: pathlib.Path) -> None:
    for exp in _real_records(shared_data):
        for velocity in ("highpass", "zero_phase", "measured"):
            assert data_warnings(exp, velocity=velocity) == [], exp.name
        # the HSM150 torque steps sit at their extreme values half of the time each
        if exp.name.startswith("idf_"):
            u = exp.u.numpy()
            assert np.mean(u == u.min()) == pytest.approx(0.5, abs=0.01)


def test_real_data_with_t_in_milliseconds_is_flagged(shared_data: pathlib.Path) -> None:
    for exp in _real_records(shared_data):
        ms = make_experiment(exp.t * 1000, exp.u, exp.q, exp.qdot, name=exp.name)
        texts = data_warnings(ms, velocity="measured" if exp.qdot is not None else "highpass")
        assert len(texts) == 1 and "looks like milliseconds in a seconds column" in texts[0]
        if exp.qdot is not None:  # HSM150: its velocity column is diff(q)/1 ms exactly
            assert "the measured qdot is 1000 times" in texts[0]


def test_a_record_cut_in_motion_starts_at_its_speed(tmp_path: pathlib.Path) -> None:
    """`data.start` inside a move (or a logger started mid-move): the identification starts
    from the record's speed, not from rest. The high-pass differentiator used to start at
    v = 0, and with the paper's P0 = 0 the EKF took that 0 as known (an EMPS-like axis cut at
    60 s, moving at 0.085 m/s, came out at 0.2 kg against 95)."""
    from torchfric.app.config import Config
    from torchfric.app.run import load_data
    from torchfric.data.axis import LINEAR_AXIS, axis_record, write_csv

    rec = axis_record(LINEAR_AXIS, seed=3, duration=4.0)
    start = int(np.argmax(np.abs(rec["qdot_true"]) > 0.5 * LINEAR_AXIS.max_speed))
    write_csv(tmp_path / "axis.csv", rec)
    cfg = Config.from_dict(
        {"data": {"train": [str(tmp_path / "axis.csv")], "start": start}, "model": {"c_m": 35.0}}
    )
    train = load_data(cfg)[0]
    true = rec["qdot_true"][start]
    assert abs(float(train[0].qdot[0]) - true) < 0.02 * abs(true)
