"""Sweep throughput (issue 24): trials per minute of ``torchfric sweep`` with ``--jobs 1`` and
``--jobs 2`` on the rig. Prints one table; every number is measured in this run.

    python benchmarks/sweep_speed.py                 # about 2 minutes on 2 cores
    python benchmarks/sweep_speed.py --trials 12 --passes 3

Each sweep is a fresh study in a temporary folder over the same small space
(``estimator.p0_theta`` log-uniform in [0.3, 3], ``model.size`` in {2, 3}) of a small config:
tanh friction, one filter (``estimator.ensemble = 0``), ``--passes`` passes over the rig's first
``--samples`` identification samples, validated on the rig's validation record. Pruning is off
(`optuna.pruners.NopPruner`) so that every trial runs its passes and the rows compare. The
compiled filter step is built once before the first sweep (a warm cache, as on a machine that
has run torchfric before). Columns: trials per minute over the trials alone (the sweep's own
clock, from the first trial's start to the last one's end, worker start-up included) and over
the whole call (config and study checks, writing trials.csv, best.toml and the figure), and the
median duration of one trial as Optuna recorded it.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

SPACE = """[space]
"estimator.p0_theta" = { low = 0.3, high = 3.0, log = true }
"model.size" = { choices = [2, 3] }
"""


def _sweep(folder: pathlib.Path, cfg: pathlib.Path, sets: list[str], trials: int, jobs: int):
    import optuna

    from torchfric.app.sweep.driver import run_sweep

    space = folder / "space.toml"
    space.write_text(SPACE, encoding="utf-8")
    t0 = time.perf_counter()
    result = run_sweep(
        cfg, space, trials, out=folder / f"jobs{jobs}", jobs=jobs, sets=sets,
        pruner=optuna.pruners.NopPruner(), say=lambda msg: None,
    )  # fmt: skip
    wall = time.perf_counter() - t0
    durations = [r["duration_s"] for r in result.rows if r["duration_s"] is not None]
    states = {r["state"] for r in result.rows}
    return result.added, result.seconds, wall, statistics.median(durations), states


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=8, help="trials per sweep (default 8)")
    ap.add_argument("--passes", type=int, default=2, help="filter passes per trial (default 2)")
    ap.add_argument("--samples", type=int, default=10000, help="identification samples")
    args = ap.parse_args()

    from rig_configs import rig_config

    from torchfric.app.run.launch import fit

    sets = [
        f"estimator.passes={args.passes}",
        "estimator.tolerance=0",
        f"data.stop={args.samples}",
    ]
    with tempfile.TemporaryDirectory(prefix="torchfric-sweep-speed-") as tmp:
        folder = pathlib.Path(tmp)
        cfg = rig_config(folder, name="sweep_speed", model={"size": 2})
        for size in (2, 3):  # build the compiled steps of both sizes once: a warm cache
            fit(
                cfg, out=folder / f"warm{size}", quiet=True, model={"size": size},
                estimator={"passes": 1}, data={"stop": args.samples},
            )  # fmt: skip
        rows = []
        for jobs in (1, 2):
            added, seconds, wall, median, states = _sweep(folder, cfg, sets, args.trials, jobs)
            rows.append((jobs, added, 60 * added / seconds, 60 * added / wall, median, states))
    print(
        f"sweep throughput on this machine ({os.cpu_count()} cores): {args.trials} trials of "
        f"{args.passes} passes over {args.samples} rig samples + validation, pruning off\n"
    )
    print(
        "| --jobs | trials | trials/min (trials) | trials/min (whole call) | median trial | states |"
    )
    print("|---:|---:|---:|---:|---:|---|")
    for jobs, added, per_min, per_min_wall, median, states in rows:
        print(
            f"| {jobs} | {added} | {per_min:.1f} | {per_min_wall:.1f} | {median:.2f} s | "
            f"{', '.join(sorted(states))} |"
        )


if __name__ == "__main__":
    main()
