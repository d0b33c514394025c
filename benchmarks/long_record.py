"""A long record through ``torchfric train`` (issue: 20 min at 1 kHz). Prints one table: mode
(terminal: under a pseudo-terminal, the progress bars drawn; quiet: ``--quiet``), wall time,
peak resident memory (the child's maximum RSS, as ``/usr/bin/time -v`` reports it) and filter
steps per second end to end (the ensemble's member-samples filtered ÷ the wall time).

    python benchmarks/long_record.py                      # about 10 minutes on 2 cores
    python benchmarks/long_record.py --duration 120       # a 2-minute record, for a quick look
    python benchmarks/long_record.py --modes quiet --json after.json
    python benchmarks/long_record.py --modes quiet --dynamic auto --before 260a5ad --rounds 2
    python benchmarks/long_record.py --axis lugre-motor --seed 101 --validation --modes quiet \
        --dynamic auto --before 809092d

The record is the user-style Stribeck axis (`torchfric.data.axis`, seed 1; ``--seed``), or
with ``--axis lugre-motor`` a linear motor with LuGre friction (`AXES`), written once as a CSV
(``t,u,q``, 32–47 MB for 20 minutes) into ``--cache`` and reused: simulating it takes one to two
minutes. The config is what ``torchfric init RECORD --c-m C`` writes (C 1, or the motor's
35 N/A; the default model: tanh(3), the 9-filter ensemble, up to 30 passes), the whole record
identified, no validation record (``--validation``: a 30-s one, which keeps each member's
best-validating pass); ``--dynamic`` sets ``model.dynamic`` (``none`` by default,
the static class as measured before init wrote ``auto``; ``auto`` adds the comparison of both
classes). With ``--before REF`` the same runs of that commit (``git archive``, its torchfric
first on ``PYTHONPATH``) alternate with this tree's for ``--rounds`` rounds, and the table adds
the largest relative difference of the two releases' parameters (0 where the run computed the
same numbers).
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
from typing import Any

from releases import checkout

ROOT = Path(__file__).resolve().parents[1]

CLI = "import sys; from torchfric.app.cli import main; sys.exit(main())"


# --axis: the simulated machine and the c_m given to init. "stribeck" is
# `torchfric.data.axis.STRIBECK_AXIS`; "lugre-motor" the linear motor with LuGre friction of
# the user walk of 2026-11-28 (docs/results.md): 2.2 kg, 35 N/A, bristles of 10 counts of a
# 1-µm encoder, in SI units here.
AXES = {"stribeck": 1.0, "lugre-motor": 35.0}


def _axis(name: str):  # type: ignore[no-untyped-def]
    from torchfric.data.axis import STRIBECK_AXIS, AxisParameters

    if name == "stribeck":
        return STRIBECK_AXIS
    return AxisParameters(
        inertia=2.2, c_m=35.0, viscous=15.0, coulomb=4.0, static=6.0, stribeck_velocity=0.02,
        friction="lugre", sigma0=1.2e6, sigma1=2400.0, quantum=1e-6, dt=1e-3, max_speed=0.5,
        max_input=1.5, substeps=40,
    )  # fmt: skip


def record(
    cache: Path, duration: float, axis: str = "stribeck", seed: int = 1, validation: bool = False
) -> Path:
    """The `axis` record of `duration` s (noise and input of `seed`) as a CSV in `cache`
    (made once); with `validation`, named ``…_identification.csv`` beside a 30-s
    ``…_validation.csv`` of the same seed, which `torchfric init` then finds."""
    tag = "axis" if axis == "stribeck" else axis
    stem = f"{tag}_{duration:g}s{'' if seed == 1 else f'_seed{seed}'}"
    path = cache / (f"{stem}_identification.csv" if validation else f"{stem}.csv")
    records = [(path, duration, "identification")]
    if validation:
        records.append((cache / f"{stem}_validation.csv", 30.0, "validation"))
    for where, length, kind in records:
        if where.exists():
            continue
        from torchfric.data.axis import axis_record, write_csv

        t0 = time.perf_counter()
        rec = axis_record(_axis(axis), seed=seed, duration=length, kind=kind)
        part = where.with_suffix(".part")
        write_csv(part, rec)
        os.replace(part, where)
        print(f"made {where} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return path


def config(data: Path, folder: Path, c_m: float = 1.0) -> Path:
    """The starter config ``torchfric init`` writes for `data` (`c_m`)."""
    plain = re.fullmatch(r"axis_[\d.]+s", data.stem)  # the Stribeck record's config, as before
    out = folder / ("long.toml" if plain else f"{data.stem}.toml")
    if not out.exists():
        subprocess.run(
            [sys.executable, "-c", CLI, "init", str(data), "--c-m", f"{c_m:g}", "--out", str(out)],
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


def run(cfg: Path, mode: str, out: Path, dynamic: str) -> dict[str, Any]:
    """One ``torchfric train`` in a fresh process: wall time, the child's peak RSS, the run's
    filter steps (from its ensemble.json or metrics.json) and its parameters."""
    args = [sys.executable, "-c", CLI, "train", str(cfg), "--out", str(out),
            "--set", f"model.dynamic={dynamic}"]  # fmt: skip
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
        "parameters": {k: v["value"] for k, v in metrics["parameters"].items()},
        "comparison_s": (metrics.get("dynamics") or {}).get("seconds", 0.0),
        "ensemble_s": ens["seconds"] if ens else 0.0,
    }


def _rel(a: dict[str, float], b: dict[str, float]) -> float:
    """The largest relative difference between two runs' parameters."""
    return max(abs(a[k] - b[k]) / max(abs(a[k]), abs(b[k]), 1e-300) for k in a)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=1200.0, help="record length in s")
    ap.add_argument("--modes", default="terminal,quiet", help="terminal, quiet or both")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "torchfric_long")
    ap.add_argument("--json", type=Path, help="write the table's numbers here")
    ap.add_argument("--dynamic", default="none", help="model.dynamic: none, lugre or auto")
    ap.add_argument("--before", help="an earlier commit, measured alternately in the same run")
    ap.add_argument("--rounds", type=int, default=1, help="runs per release and mode")
    ap.add_argument("--axis", choices=sorted(AXES), default="stribeck", help="the machine")
    ap.add_argument("--seed", type=int, default=1, help="the record's noise and input")
    ap.add_argument("--validation", action="store_true", help="a 30-s validation record too")
    a = ap.parse_args()
    a.cache.mkdir(parents=True, exist_ok=True)
    data = record(a.cache, a.duration, a.axis, a.seed, a.validation)
    cfg = config(data, a.cache, AXES[a.axis])
    rows: dict[str, list[dict[str, Any]]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        trees = {"this tree": ROOT}
        if a.before:
            trees[a.before] = checkout(a.before, Path(tmp))
        for r in range(a.rounds):
            for mode in a.modes.split(","):
                for i, (name, tree) in enumerate(trees.items()):
                    # the peak RSS of RUSAGE_CHILDREN is the largest child's so far: each run
                    # goes in a child of its own, or a larger one would hide the next's
                    out = Path(tmp) / f"{mode}_{r}_{i}"
                    child = [sys.executable, __file__, "--_one", mode, str(cfg), str(out),
                             a.dynamic]  # fmt: skip
                    env = {**os.environ, "PYTHONPATH": str(tree)}
                    done = subprocess.run(child, capture_output=True, text=True, env=env)
                    if done.returncode:
                        raise SystemExit(
                            f"{name}, {mode}: {done.stdout[-2000:]}{done.stderr[-2000:]}"
                        )
                    rows.setdefault(f"{name}|{mode}", []).append(json.loads(done.stdout))
    n = sum(1 for _ in open(data)) - 1
    print(f"{n:,} samples ({a.duration:g} s at 1 kHz), {cfg.name} as torchfric init wrote it, "
          f"model.dynamic = {a.dynamic!r}")  # fmt: skip
    print("| release | mode | wall time (each run) | of it: class comparison | ensemble's passes "
          "| peak RSS | filter steps/s end to end | bars "
          "| max rel. difference of the parameters to this tree's |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for key, runs in rows.items():
        name, mode = key.split("|")
        mine = rows[f"this tree|{mode}"][0]["parameters"]
        walls, comp, ens = (
            " / ".join(f"{r[key]:.0f}" for r in runs)
            for key in ("wall_s", "comparison_s", "ensemble_s")
        )
        print(f"| {name} | {mode} | {walls} s | {comp} s | {ens} s "
              f"| {max(r['peak_mib'] for r in runs):.0f} MiB "
              f"| {max(r['steps_per_s'] for r in runs):,.0f} "
              f"| {'yes' if runs[0]['bars_shown'] else 'no'} "
              f"| {max(_rel(mine, r['parameters']) for r in runs):.1e} |")  # fmt: skip
    if a.json:
        a.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    if len(sys.argv) == 6 and sys.argv[1] == "--_one":
        print(json.dumps(run(Path(sys.argv[3]), sys.argv[2], Path(sys.argv[4]), sys.argv[5])))
    else:
        main()
