"""A long record through ``torchfric train`` (issue: 20 min at 1 kHz). Prints one table: mode
(terminal: under a pseudo-terminal, the progress bars drawn; quiet: ``--quiet``), wall time,
peak resident memory (the child's maximum RSS, as ``/usr/bin/time -v`` reports it) and filter
steps per second end to end (the ensemble's member-samples filtered ÷ the wall time).

    python benchmarks/long_record.py                      # about 10 minutes on 2 cores
    python benchmarks/long_record.py --duration 120       # a 2-minute record, for a quick look
    python benchmarks/long_record.py --modes quiet --json after.json

The record is the user-style Stribeck axis (`torchfric.data.axis`, seed 1), written once as a
CSV (``t,u,q``, 32–47 MB for 20 minutes) into ``--cache`` and reused: simulating it takes about a
minute. The config is what ``torchfric init RECORD --c-m 1`` writes (the default model: tanh(3),
the 9-filter ensemble, up to 30 passes), the whole record identified, no validation record.
"""

from __future__ import annotations

import argparse
import json
import os
import pty
import re
import resource
import select
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLI = "import sys; from torchfric.app.cli import main; sys.exit(main())"


def record(cache: Path, duration: float) -> Path:
    """The axis record of `duration` s as a CSV in `cache` (made once)."""
    path = cache / f"axis_{duration:g}s.csv"
    if not path.exists():
        from torchfric.data.axis import STRIBECK_AXIS, axis_record, write_csv

        t0 = time.perf_counter()
        rec = axis_record(STRIBECK_AXIS, seed=1, duration=duration)
        part = path.with_suffix(".part")
        write_csv(part, rec)
        os.replace(part, path)
        print(f"made {path} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return path


def config(data: Path, folder: Path) -> Path:
    """The starter config ``torchfric init`` writes for `data` (c_m 1)."""
    out = folder / "long.toml"
    if not out.exists():
        subprocess.run(
            [sys.executable, "-c", CLI, "init", str(data), "--c-m", "1", "--out", str(out)],
            check=True, capture_output=True,
        )  # fmt: skip
    return out


def metrics_data(cfg: Path) -> Path:
    """The record `cfg` identifies from (its one ``data.train`` file)."""
    import tomllib

    path = Path(tomllib.loads(cfg.read_text())["data"]["train"][0])
    return path if path.is_absolute() else cfg.parent / path


def _drain(fd: int, proc: subprocess.Popen[bytes]) -> bytes:
    """What the child writes to the pty (read so that it never blocks), until it ends."""
    out = b""
    while True:
        ready, _, _ = select.select([fd], [], [], 0.5)
        if ready:
            try:
                chunk = os.read(fd, 1 << 16)
            except OSError:
                break
            if not chunk:
                break
            out += chunk
        elif proc.poll() is not None:
            break
    return out


def run(cfg: Path, mode: str, out: Path) -> dict[str, float]:
    """One ``torchfric train`` in a fresh process: wall time, the child's peak RSS, and the
    run's filter steps (from its ensemble.json or metrics.json)."""
    # the static class, as measured before init wrote model.dynamic = "auto" (which adds a
    # comparison of both classes on 70 % of the record, about 1.4 runs more)
    args = [sys.executable, "-c", CLI, "train", str(cfg), "--out", str(out),
            "--set", "model.dynamic=none"]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    if mode == "terminal":  # stdin, stdout and stderr on a pty: bars are drawn
        master, slave = pty.openpty()
        proc = subprocess.Popen(args, stdin=slave, stdout=slave, stderr=slave)
        os.close(slave)
        text = _drain(master, proc)
        os.close(master)
        code = proc.wait()
        # a bar drawn ("37%|███▋      |") with its rate and ETA within a pass; a pty without a
        # size used to get the numbers without the bar, or (under `script`) nothing at all
        shown = bool(re.search(rb"pass \d+: +\d+%\|.*?sample/s", text))
    else:
        done = subprocess.run([*args, "--quiet"], capture_output=True)
        code, shown, text = done.returncode, False, done.stderr
    wall = time.perf_counter() - t0
    if code != 0:
        raise SystemExit(f"train failed ({mode}):\n{text.decode(errors='replace')[-3000:]}")
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # KiB, the largest child's
    if peak <= before:
        print(
            f"  note: {mode}'s peak is at most an earlier child's ({before} KiB)", file=sys.stderr
        )
    metrics = json.loads((out / "metrics.json").read_text())
    ens = metrics.get("ensemble")  # member-samples filtered: the ensemble's count, else passes × N
    samples = sum(1 for _ in open(metrics_data(cfg))) - 1
    steps = ens["filter_steps_per_second"] * ens["seconds"] if ens else metrics["passes"] * samples
    return {
        "wall_s": wall,
        "peak_mib": peak / 1024,
        "filter_steps": steps,
        "steps_per_s": steps / wall,
        "bars_shown": shown,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=1200.0, help="record length in s")
    ap.add_argument("--modes", default="terminal,quiet", help="terminal, quiet or both")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "torchfric_long")
    ap.add_argument("--json", type=Path, help="write the table's numbers here")
    a = ap.parse_args()
    a.cache.mkdir(parents=True, exist_ok=True)
    data = record(a.cache, a.duration)
    cfg = config(data, a.cache)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mode in a.modes.split(","):
            # the peak RSS of RUSAGE_CHILDREN is the largest child's so far: the larger mode
            # first would hide the other's, so each mode runs in a child of its own
            child = [sys.executable, __file__, "--_one", mode, str(cfg), str(Path(tmp) / mode)]
            rows[mode] = json.loads(subprocess.run(child, check=True, capture_output=True,
                                                   text=True).stdout)  # fmt: skip
    n = sum(1 for _ in open(data)) - 1
    print(f"{n:,} samples ({a.duration:g} s at 1 kHz), {cfg.name} as torchfric init wrote it")
    print(f"{'mode':<10}{'wall time':>11}{'peak RSS':>11}{'filter steps/s':>16}  bars")
    for mode, r in rows.items():
        print(
            f"{mode:<10}{r['wall_s']:>9.0f} s{r['peak_mib']:>7.0f} MiB"
            f"{r['steps_per_s']:>16,.0f}  {'yes' if r['bars_shown'] else 'no'}"
        )
    if a.json:
        a.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--_one":
        print(json.dumps(run(Path(sys.argv[3]), sys.argv[2], Path(sys.argv[4]))))
    else:
        main()
