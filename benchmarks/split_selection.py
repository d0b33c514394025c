"""Does a time split of the identification record choose the ensemble's member better? A table.

    python benchmarks/split_selection.py                          # 8 axes, seeds 1 2 3
    python benchmarks/split_selection.py --machines belt-fast --seeds 1 2 --jobs 2

Issue 36, part 2: a rule that uses the identification data only and predicts the error on
data the model has not seen. The ensemble's members differ in start and tuning (Q and R
factors); which one a run keeps is the choice measured here, on each axis of
`benchmarks/model_class.py` (a user's path: ``torchfric init IDENT.csv --c-m C_M``):

1. **Whole record.** ``train`` with ``estimator.select = "identification"`` and three records
   beside it that choose nothing and are only scored member by member (ensemble.json): the
   validation record, and a *test* record neither rule reads (another seed's validation-like
   record). Each member's FIT on the identification record, the validation record and the test.
2. **Time split.** The same config on the first 70 % of the identification record, its last
   30 % given as the validation record (``select = "validation"``), the friction class fixed to
   run 1's: each member's open-loop FIT on the held-out end, from a model that never saw it.

Picks compared by the test FIT on q of run 1's member of that index (the same start and tuning
of the grid): by the time split (best held-out FIT, identification data only), by the whole
identification record (the ``"identification"`` rule), by validation (the default rule), and the
best member on the test (the oracle). Spearman's ρ over the members between each score and the
test FIT. Members that diverged or were rolled back in either run count with what they scored.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from model_class import AXES, CLI, _train, run_machines  # noqa: E402  (a sibling)

from torchfric.data.axis import axis_record, write_csv  # noqa: E402

HEAD = 0.7  # the share of the identification record the split run trains on
RULES = ("split", "ident", "valid", "oracle")


def _run(folder: Path, cfg: str, label: str, sets: list[str]) -> dict[str, Any]:
    """`model_class._train`'s run, with its ensemble.json's members."""
    metrics, checkpoint, _ = _train(folder, Path(cfg), sets, label)
    members = json.loads((checkpoint.parent / "ensemble.json").read_text())["members"]
    return {"metrics": metrics, "members": members}


def _fits(members: list[dict], record: str) -> np.ndarray:
    """Each member's FIT on q of `record` (NaN where it has none)."""
    return np.array([m.get("fits", {}).get(record, {}).get("fit_q", np.nan) for m in members])


def _rank(x: np.ndarray) -> np.ndarray:
    return np.argsort(np.argsort(x)).astype(float)


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3:
        return float("nan")
    return float(np.corrcoef(_rank(a[ok]), _rank(b[ok]))[0, 1])


def one(out: Path, machine: str, seed: int) -> dict[str, Any]:
    axis = AXES[machine]
    folder = out / f"{machine}_{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    ident = axis_record(axis, seed=seed, duration=30.0, kind="identification")
    cut = round(HEAD * len(ident["t"]))
    records = {
        "ident.csv": ident,
        "valid.csv": axis_record(axis, seed=seed, duration=30.0, kind="validation"),
        "test.csv": axis_record(axis, seed=seed + 1000, kind="validation"),
        "head.csv": {k: v[:cut] for k, v in ident.items()},
        "tail.csv": {k: v[cut:] for k, v in ident.items()},
    }
    for name, rec in records.items():
        write_csv(folder / name, {k: rec[k] for k in ("t", "u", "q")})
    subprocess.run([*CLI, "init", "ident.csv", "--c-m", repr(axis.c_m), "--out", "cfg.toml"],
                   cwd=folder, check=True, capture_output=True)  # fmt: skip
    whole = _run(folder, "cfg.toml", "whole", [
        'data.validation=["valid.csv", "test.csv"]', 'data.test=[]',
        "estimator.select=identification"])  # fmt: skip
    chosen = (whole["metrics"].get("dynamics") or {}).get("chosen", "none")
    split = _run(folder, "cfg.toml", "split", [
        'data.train=["head.csv"]', 'data.validation=["tail.csv"]', 'data.test=[]',
        "estimator.select=validation", f"model.dynamic={chosen}"])  # fmt: skip
    test = _fits(whole["members"], "test")
    scores = {
        "split": _fits(split["members"], "tail"),
        "ident": _fits(whole["members"], "ident"),
        "valid": _fits(whole["members"], "valid"),
        "oracle": test,
    }
    row: dict[str, Any] = {"machine": machine, "seed": seed, "class": chosen,
                           "members": len(test)}  # fmt: skip
    for rule, s in scores.items():
        pick = int(np.nanargmax(s)) if np.isfinite(s).any() else -1
        row[rule] = {"member": pick, "test_fit_q": float(test[pick]) if pick >= 0 else None,
                     "rho": _spearman(s, test)}  # fmt: skip
    print(f"{machine} seed {seed} done", file=sys.stderr, flush=True)
    return row


def print_table(rows: list[dict[str, Any]]) -> None:
    head = ("machine", "seed", "class", "member: split / ident. / valid. / best",
            "test FIT q: split", "ident.", "valid.", "best", "ρ with test: split", "ident.",
            "valid.")  # fmt: skip
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        picks = " / ".join(str(r[k]["member"]) for k in RULES)
        fits = " | ".join(f"{r[k]['test_fit_q']:.2f} %" for k in RULES)
        rhos = " | ".join(f"{r[k]['rho']:+.2f}" for k in RULES[:3])
        print(f"| {r['machine']} | {r['seed']} | {r['class']} | {picks} | {fits} | {rhos} |")
    for k in RULES:
        fit = np.array([r[k]["test_fit_q"] for r in rows], dtype=float)
        gap = np.array([r["oracle"]["test_fit_q"] for r in rows], dtype=float) - fit
        rho = np.array([r[k]["rho"] for r in rows], dtype=float)
        print(f"{k:>6}: median test FIT q {np.nanmedian(fit):.2f} %, mean {np.nanmean(fit):.2f} %, "
              f"median gap to the best member {np.nanmedian(gap):.2f} points (max "
              f"{np.nanmax(gap):.2f}), median ρ {np.nanmedian(rho):+.2f}")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    machines = ["stribeck", "lugre", "linear", "table", "belt", "belt-fast", "spindle", "carriage"]
    return run_machines(argv, __doc__, one, print_table, machines, list(AXES))


if __name__ == "__main__":
    raise SystemExit(main())
