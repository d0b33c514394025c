"""Long records: progress bars on a terminal, `check`'s estimates of time and memory, and
observers that keep nothing per sample. No test here times or measures memory: the 20-minute
record's peak is measured by benchmarks/long_record.py (docs/results.md)."""

from __future__ import annotations

import os
import pathlib
import re
import select
import subprocess
import sys
import time
from types import SimpleNamespace
from typing import Any

import pytest
from rig_configs import rig_config

from torchfric.app.commands.check import check_run
from torchfric.app.config import Config
from torchfric.app.run import config_model, estimate_run, load_data
from torchfric.app.run.autosize import auto_estimate, with_dynamic
from torchfric.app.run.monitors import ProgressLines, bar_size
from torchfric.resources import nominal_rate, run_peak_bytes, run_seconds

pty = pytest.importorskip("pty")  # POSIX only

RATE = re.compile(r"\d+(\.\d+)?k?sample/s")  # tqdm's rate with unit_scale: 41.2ksample/s
ETA = re.compile(r"<\d\d:\d\d")  # [00:01<00:04, ...]: elapsed < remaining


def _config(tmp: pathlib.Path) -> pathlib.Path:
    """A short single-filter run of the rig's identification record, nothing held out."""
    return rig_config(
        tmp, "short", data={"stop": 1500, "validation": None},
        estimator={"passes": 2, "tolerance": 0},
    )  # fmt: skip


def _read_all(fd: int, proc: subprocess.Popen[bytes], timeout: float) -> str:
    """Everything written to the pty's master `fd` until `proc` ends (or `timeout` s)."""
    out, end = b"", time.monotonic() + timeout
    while time.monotonic() < end:
        ready, _, _ = select.select([fd], [], [], 0.2)
        if ready:
            try:
                chunk = os.read(fd, 65536)
            except OSError:  # the slave side closed
                break
            out += chunk
        elif proc.poll() is not None:
            break
    return out.decode("utf-8", "replace")


def test_a_pty_without_a_size_still_gets_bars(monkeypatch: pytest.MonkeyPatch) -> None:
    # A pty that `script`, an IDE's console or `docker run -t` opens reports 0 × 0; tqdm then
    # drew nothing at all (0 columns: an empty bar; -1 rows: every bar hidden).
    monkeypatch.delenv("COLUMNS", raising=False)
    monkeypatch.delenv("LINES", raising=False)
    master, slave = pty.openpty()
    try:
        with os.fdopen(slave, "w", closefd=False) as stream:
            assert os.get_terminal_size(slave).columns == 0
            size = bar_size(stream)
            assert size is not None and min(size) > 0  # COLUMNS × LINES, else 80 × 24
    finally:
        os.close(master)
        os.close(slave)


def test_bars_within_a_pass_show_rate_and_eta_on_a_pty() -> None:
    master, slave = pty.openpty()
    stream = os.fdopen(slave, "w", closefd=True)
    try:
        cfg: Any = SimpleNamespace(estimator=SimpleNamespace(passes=3))
        scores: Any = SimpleNamespace(fits={})
        lines = ProgressLines(cfg, lambda _msg: None, scores, model=None, bars=stream)  # type: ignore[arg-type]
        total = 1_200_000
        for done in range(1000, 40_001, 1000):  # one report per chunk of 1000 samples
            lines.on_progress(1, done, total)
            time.sleep(0.01)
        stream.flush()
        ready, _, _ = select.select([master], [], [], 2.0)
        text = os.read(master, 65536).decode("utf-8", "replace") if ready else ""
        lines.close()
    finally:
        stream.close()
        os.close(master)
    assert "pass 1" in text
    assert RATE.search(text), text
    assert ETA.search(text), text


def test_train_under_a_pty_shows_progress_bars(tmp_path: pathlib.Path) -> None:
    cfg = _config(tmp_path)
    master, slave = pty.openpty()  # 0 × 0: as `script -qec "torchfric train ..." /dev/null`
    env = {**os.environ, "COLUMNS": "", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "torchfric", "train", str(cfg)],
        stdin=slave, stdout=slave, stderr=slave, env=env, cwd=tmp_path,
    )  # fmt: skip
    os.close(slave)
    try:
        text = _read_all(master, proc, timeout=300)
        assert proc.wait(timeout=60) == 0, text
    finally:
        os.close(master)
    assert re.search(r"pass 1: +\d+%\|", text), text  # the samples of pass 1, as a bar
    assert "sample/s" in text and "passes:" in text, text


def test_check_prints_estimated_time_and_memory(tmp_path: pathlib.Path) -> None:
    cfg = Config.load(str(_config(tmp_path)))
    text = check_run(cfg, timed=True)
    time_line = next(line for line in text.splitlines() if line.startswith("time"))
    memory_line = next(line for line in text.splitlines() if line.startswith("memory"))
    assert re.search(r"about \d", time_line) and "filter steps/s" in time_line, time_line
    assert re.search(r"about [\d.]+ [KMG]iB at peak", memory_line), memory_line


def test_peak_estimate_grows_with_the_record_not_with_the_passes() -> None:
    short = run_peak_bytes(samples=10_000, longest=10_000, n_theta=8, members=9)
    long = run_peak_bytes(samples=1_200_000, longest=1_200_000, n_theta=8, members=9)
    assert short < long < 1.5 * 2**30  # the bound for the default model


def _sizes(obj: Any, depth: int = 0) -> list[int]:
    """The lengths of the lists, dicts and sets held by `obj`'s attributes (two levels)."""
    out: list[int] = []
    for value in vars(obj).values() if hasattr(obj, "__dict__") else ():
        if isinstance(value, list | dict | set | tuple):
            out.append(len(value))
        elif depth < 1 and hasattr(value, "__dict__"):
            out += _sizes(value, depth + 1)
    return out


def test_progress_keeps_no_per_sample_history(monkeypatch: pytest.MonkeyPatch) -> None:
    # 1.2 M samples reported per chunk of 1000, three passes: nothing an observer holds grows
    # with the reports (a bar, lines or a list of rates per report would).
    cfg: Any = SimpleNamespace(estimator=SimpleNamespace(passes=3))
    scores: Any = SimpleNamespace(fits={})
    said: list[str] = []
    with open(os.devnull, "w") as sink:
        for bars in (None, sink):
            lines = ProgressLines(cfg, said.append, scores, model=None, bars=bars)  # type: ignore[arg-type]
            for p in (1, 2, 3):
                for done in range(1000, 1_200_001, 1000):
                    lines.on_progress(p, done, 1_200_000)
                assert max(_sizes(lines), default=0) < 100
            lines.close()
    assert len(said) == 3 * 1200  # the \r lines go out, none is kept by the observer


@pytest.mark.parametrize("records", [1, 4])
def test_auto_estimate_is_both_classes_on_what_they_are_compared_on_then_one(
    tmp_path: pathlib.Path, records: int
) -> None:
    """`model.dynamic = "auto"`: check's range runs from the static model after two passes to
    the LuGre model after every pass, each after both classes' ensembles over the samples
    `choose_dynamic` identifies them on: the first 70 % of a 30 k-sample record, the 70,000
    samples of `comparison_heads`' excerpts beyond 100,000 in all. At the nominal rate (not
    timed) both filters run at one rate, so the range is closed form."""
    cfg = Config.load(str(rig_config(
        tmp_path, "auto", data={"train": ["rig:identification"] * records, "validation": None},
        model={"dynamic": "auto"}, estimator={"ensemble": 1},
    )))  # fmt: skip
    train, *_ = load_data(cfg)
    lugre_cfg = with_dynamic(cfg, "lugre")
    lugre = estimate_run(lugre_cfg, train, config_model(lugre_cfg, train))
    est = auto_estimate(cfg, train, lugre, timed=False)
    samples, members, passes = sum(e.n for e in train), lugre.members, cfg.estimator.passes
    compared = 70_000 if records == 4 else round(0.7 * samples)
    rate = nominal_rate(members)
    both = 2 * members * compared / rate  # one pass of each class
    low, _ = run_seconds(samples=samples, passes=passes, members=members, rate=rate)
    assert est.compared == compared and est.static_rate == est.rate == rate
    assert est.seconds == pytest.approx((low + 2 * both, lugre.seconds[1] + passes * both))
    assert samples * members * passes / rate < est.seconds[1]  # every pass of the kept class
