"""Does a score on the identification record predict EMPS's test error? (issue 36, part 2)

    python benchmarks/emps_selection.py                      # 24 candidates, 2 jobs
    python benchmarks/emps_selection.py --candidates 30 --seed 1 --json out.json

The candidates are the space the shipped `emps_lugre_asym_oe` config was drawn from (results.md,
EMPS: σ0 1e5–3e6 N/m and σ1 10–3000 N·s/m log-uniform, size 3 or 4, 40/80/150 L-BFGS steps),
drawn with a seeded generator. Each is trained twice with ``torchfric train``:

- on the first 70 % of ``DATA_EMPS.mat`` (``data.stop``), then scored on the held-out 30 % by the
  benchmark's protocol (initial state from its first 20 samples, RMSE of q over the rest): the
  **held-out score**, blocked time-split validation on the identification record;
- on the whole ``DATA_EMPS.mat``, then scored on it (the **identification score**, what the
  30-trial sweep selected by) and on the test file ``DATA_EMPS_PULSES.mat`` (the **test RMSE**,
  which no rule reads).

Printed: every candidate, the Spearman rank correlation of each score with the test RMSE, and
the test RMSE of the candidate each rule picks beside the best candidate's.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from torchfric import load_checkpoint, load_experiment
from torchfric.estimators.metrics import score_benchmark

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "experiments" / "configs" / "emps_lugre_asym_oe.toml"
DATA = ROOT.parent / "shared" / "data" / "emps"
COLUMNS = {"u": "vir", "q": "qm"}
CLI = [sys.executable, "-m", "torchfric"]
HOLDOUT = 0.3


def candidates(n: int, seed: int) -> list[dict[str, Any]]:
    """`n` draws of the sweep's space (seeded)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        out.append({
            "id": i,
            "model.sigma0": float(10 ** rng.uniform(5, math.log10(3e6))),
            "model.sigma1": float(10 ** rng.uniform(1, math.log10(3000))),
            "model.size": int(rng.choice([3, 4])),
            "estimator.lbfgs_steps": int(rng.choice([40, 80, 150])),
        })  # fmt: skip
    return out


def _train(out: Path, sets: dict[str, Any]) -> Path:
    argv = [*CLI, "train", str(CONFIG), "--out", str(out), "--quiet"]
    for key, value in sets.items():
        argv += ["--set", f"{key}={value!r}" if isinstance(value, float) else f"{key}={value}"]
    done = subprocess.run(argv, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(done.stderr.strip()[-300:])
    return next(out.glob("*.pt"))


def one(folder: Path, cand: dict[str, Any], ident: Any, test: Any) -> dict[str, Any]:
    sets = {k: v for k, v in cand.items() if k != "id"}
    cut = ident.n - round(HOLDOUT * ident.n)
    row: dict[str, Any] = dict(cand)
    t0 = time.perf_counter()
    try:
        head = load_checkpoint(
            _train(folder / f"c{cand['id']:02d}_head", {**sets, "data.stop": cut})
        )
        full = load_checkpoint(_train(folder / f"c{cand['id']:02d}_full", sets))
    except RuntimeError as err:
        return row | {"error": str(err)}
    row["heldout_mm"] = (
        1000 * score_benchmark(head, ident.slice(cut), n_init=20, engine="compiled").rms_q
    )
    row["ident_mm"] = 1000 * score_benchmark(full, ident, n_init=20, engine="compiled").rms_q
    row["test_mm"] = 1000 * score_benchmark(full, test, n_init=20, engine="compiled").rms_q
    row["seconds"] = time.perf_counter() - t0
    print(f"candidate {cand['id']}: held-out {row['heldout_mm']:.2f} mm, test {row['test_mm']:.2f} mm",
          file=sys.stderr, flush=True)  # fmt: skip
    return row


def spearman(a: list[float], b: list[float]) -> float:
    ra, rb = (np.argsort(np.argsort(x)).astype(float) for x in (a, b))
    return float(np.corrcoef(ra, rb)[0, 1])


def report(rows: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [
        r
        for r in rows
        if "test_mm" in r
        and all(map(math.isfinite, (r["heldout_mm"], r["test_mm"], r["ident_mm"])))
    ]
    test = [r["test_mm"] for r in ok]
    best = min(ok, key=lambda r: r["test_mm"])
    summary: dict[str, Any] = {
        "candidates": len(rows),
        "scored": len(ok),
        "best_test_mm": best["test_mm"],
    }
    for rule in ("heldout_mm", "ident_mm"):
        pick = min(ok, key=lambda r: r[rule])
        summary[rule] = {"spearman": spearman([r[rule] for r in ok], test),
                         "pick": pick["id"], "pick_test_mm": pick["test_mm"]}  # fmt: skip
    return summary


def print_table(rows: list[dict[str, Any]], summary: dict[str, Any]) -> None:
    print(
        "| candidate | σ0 | σ1 | size | L-BFGS steps | held-out 30 % [mm] | identification [mm] | test [mm] |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in sorted(rows, key=lambda r: r.get("heldout_mm", math.inf)):
        if "error" in r:
            print(f"| {r['id']} | {r['model.sigma0']:.3g} | {r['model.sigma1']:.3g} | {r['model.size']} | "
                  f"{r['estimator.lbfgs_steps']} | failed: {r['error'][:60]} | | |")  # fmt: skip
            continue
        print(f"| {r['id']} | {r['model.sigma0']:.3g} | {r['model.sigma1']:.3g} | {r['model.size']} | "
              f"{r['estimator.lbfgs_steps']} | {r['heldout_mm']:.2f} | {r['ident_mm']:.2f} | "
              f"{r['test_mm']:.2f} |")  # fmt: skip
    print()
    for rule, name in (
        ("heldout_mm", "held-out 30 % (time split)"),
        ("ident_mm", "identification record"),
    ):
        s = summary[rule]
        print(
            f"{name}: Spearman ρ with the test RMSE {s['spearman']:+.2f}; picks candidate "
            f"{s['pick']}, test {s['pick_test_mm']:.2f} mm (best candidate {summary['best_test_mm']:.2f} mm)"
        )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--candidates", type=int, default=24)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    folder = a.out or Path(tempfile.mkdtemp(prefix="emps_selection_"))
    ident = load_experiment(DATA / "DATA_EMPS.mat", columns=COLUMNS)
    test = load_experiment(DATA / "DATA_EMPS_PULSES.mat", columns=COLUMNS)
    t0 = time.perf_counter()
    with ThreadPoolExecutor(a.jobs) as pool:
        rows = list(
            pool.map(lambda c: one(folder, c, ident, test), candidates(a.candidates, a.seed))
        )
    summary = report(rows)
    print_table(rows, summary)
    print(f"\n{len(rows)} candidates in {time.perf_counter() - t0:.0f} s; runs in {folder}")
    if a.json:
        a.json.write_text(json.dumps({"rows": rows, "summary": summary}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
