"""The quick start against ``python -c "import torch"`` (issue 34, part 0), and against an
earlier release in the same run. Prints one table: each release's median wall time of
``torchfric train experiments/configs/arm_tanh_ekf.toml`` (a fresh process, warm compiled-code
cache, ``--quiet``, its own new run directory) and its ratio to the median ``import torch``.

    python benchmarks/quick_start.py                       # this tree, 5 runs (about a minute)
    python benchmarks/quick_start.py --before 81a0eb9      # and that commit, alternating

The earlier release is the commit's files (``git archive``) in a temporary folder, imported
through ``PYTHONPATH`` by the same Python; the runs alternate (this tree, the other, ``import
torch``) so that a busy moment of the machine falls on all three alike. Each release's first
run is a warm-up (it builds the release's compiled code into the cache) and is not counted.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from releases import checkout

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "experiments" / "configs" / "arm_tanh_ekf.toml"


def timed(cmd: list[str], tree: Path | None, cwd: Path) -> float:
    """Wall seconds of `cmd` (in a fresh process; `tree` first on its import path)."""
    env = None if tree is None else {**os.environ, "PYTHONPATH": str(tree)}
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=cwd, env=env, check=True, capture_output=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", help="an earlier commit to measure in the same run")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        trees: dict[str, Path] = {"this tree": ROOT}
        if args.before:
            trees[args.before] = checkout(args.before, work)
        runs = 0

        def quick(tree: Path) -> float:
            nonlocal runs
            runs += 1
            train = [sys.executable, "-m", "torchfric", "train", str(CONFIG), "--quiet",
                     "--out", str(work / f"run{runs}")]  # fmt: skip
            return timed(train, tree, work)

        for tree in trees.values():
            quick(tree)  # warm-up: the release's compiled code into the cache
        times: dict[str, list[float]] = {name: [] for name in [*trees, "import torch"]}
        for _ in range(args.repeat):
            for name, tree in trees.items():
                times[name].append(quick(tree))
            times["import torch"].append(timed([sys.executable, "-c", "import torch"], None, work))
    base = statistics.median(times["import torch"])
    print(f"quick start (`torchfric train {CONFIG.relative_to(ROOT)}`), medians of "
          f"{args.repeat}, this machine")  # fmt: skip
    print("| release | wall time | runs | × `import torch` (goal ≤ 1.6×) |")
    print("|---|---|---|---|")
    for name, ts in times.items():
        runs_text = " ".join(f"{t:.2f}" for t in ts)
        print(f"| {name} | {statistics.median(ts):.2f} s | {runs_text} | "
              f"{statistics.median(ts) / base:.2f}× |")  # fmt: skip


if __name__ == "__main__":
    main()
