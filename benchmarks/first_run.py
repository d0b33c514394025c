"""A user's first run on a new machine (issue 34): ``torchfric train`` of what ``torchfric init``
writes for a 60-s record (``model.dynamic = "auto"``: both friction classes identified and
compared), with an empty compiled-code cache (every generated filter and simulation step is
traced and built by the C compiler) and again with that cache filled. Prints one table.

    python benchmarks/first_run.py                        # this tree, 3 runs (about 4 minutes)
    python benchmarks/first_run.py --before 3ad6b21       # and that commit, alternating

The record is a 6.5-kg linear axis (42 N/V, b 28 N s/m, Coulomb 3 N, Stribeck peak 9 N at
13 mm/s, a 1-µm scale, 1 kHz) from `torchfric.data.axis`, written as ``t,u,q`` with a 30-s
validation record; ``init --c-m 42`` writes the config. Each cold run has a cache folder of its
own (``TORCHFRIC_CACHE``); the warm run follows it with the same folder. The earlier release is
the commit's files (``git archive``) imported through ``PYTHONPATH`` by the same Python; the
releases alternate so that a busy moment of the machine falls on both alike. The "comparison"
column is the class comparison's own time, read from the run's ``metrics.json``
(``dynamics.seconds``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from releases import checkout

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchfric.data.axis import AxisParameters, axis_record, write_csv  # noqa: E402

AXIS = AxisParameters(inertia=6.5, c_m=42.0, viscous=28.0, coulomb=3.0, static=9.0,
                      stribeck_velocity=0.013, quantum=1e-6, max_speed=0.3,
                      max_input=2.0)  # fmt: skip


def write_records(folder: Path, seed: int) -> Path:
    """The axis's identification (60 s) and validation (30 s) CSVs and ``init``'s config."""
    for kind, seconds in (("identification", 60.0), ("validation", 30.0)):
        write_csv(folder / f"{kind}.csv", axis_record(AXIS, seed=seed, duration=seconds, kind=kind))
    cfg = folder / "axis.toml"
    subprocess.run([sys.executable, "-m", "torchfric", "init", "identification.csv", "--c-m",
                    "42", "--out", cfg.name], cwd=folder, check=True, capture_output=True)  # fmt: skip
    return cfg


def train(cfg: Path, tree: Path, cache: Path, out: Path) -> tuple[float, float]:
    """Wall seconds of ``train`` (a fresh process, `tree` first on its import path, `cache` the
    compiled-code cache) and its class comparison's seconds."""
    env = {**os.environ, "PYTHONPATH": str(tree), "TORCHFRIC_CACHE": str(cache)}
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "torchfric", "train", str(cfg), "--quiet", "--out",
                    str(out)], cwd=cfg.parent, env=env, check=True, capture_output=True)  # fmt: skip
    wall = time.perf_counter() - t0
    metrics = json.loads((out / "metrics.json").read_text())
    return wall, float(metrics.get("dynamics", {}).get("seconds", float("nan")))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", help="an earlier commit to measure in the same run")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        cfg = write_records(work, args.seed)
        trees: dict[str, Path] = {"this tree": ROOT}
        if args.before:
            trees[args.before] = checkout(args.before, work)
        rows: dict[str, dict[str, list[float]]] = {
            name: {"cold": [], "cold_cmp": [], "warm": [], "warm_cmp": []} for name in trees
        }
        runs = 0
        for _ in range(args.repeat):
            for name, tree in trees.items():
                runs += 1
                cache = work / f"cache{runs}"
                cache.mkdir(mode=0o700)
                for kind in ("cold", "warm"):
                    wall, cmp = train(cfg, tree, cache, work / f"run{runs}-{kind}")
                    rows[name][kind].append(wall)
                    rows[name][f"{kind}_cmp"].append(cmp)
    med = statistics.median
    print(f"first run of `torchfric train` on init's config of a 60-s linear-axis record "
          f"(auto class), medians of {args.repeat}, this machine")  # fmt: skip
    print("| release | cold cache | of it the comparison | warm cache | of it the comparison "
          "| building the code (cold − warm) |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for name, r in rows.items():
        print(f"| {name} | {med(r['cold']):.1f} s | {med(r['cold_cmp']):.1f} s | "
              f"{med(r['warm']):.1f} s | {med(r['warm_cmp']):.1f} s | "
              f"{med(r['cold']) - med(r['warm']):.1f} s |")  # fmt: skip
    for name, r in rows.items():
        print(f"{name}: cold {' '.join(f'{t:.1f}' for t in r['cold'])}; "
              f"warm {' '.join(f'{t:.1f}' for t in r['warm'])}")  # fmt: skip


if __name__ == "__main__":
    main()
