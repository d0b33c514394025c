"""Which records choose the kept model: ``estimator.select`` "identification" against "validation".

    python benchmarks/selection_rule.py                       # rig + 8 axes, seeds 1 2 3
    python benchmarks/selection_rule.py --machines belt-fast --seeds 1 2 3 4 --jobs 2

Every row is a user's path (`benchmarks/model_class.py`'s machines: the built-in rig's default
config with ``model.dynamic = "auto"``, or an independent axis simulator's 30-s identification
record given to ``torchfric init --c-m``, its validation record beside it), trained twice with
``torchfric train``: as ``init`` writes it (``estimator.select = "identification"``: the
identification records' open-loop FIT keeps the pass and the ensemble member, the validation
records choose nothing) and with ``--set estimator.select=validation`` (the validation records
choose, with the identification records, as every shipped config does). A third record that
neither rule reads judges both: for an axis a second validation-like record (another seed,
``data.test``), for the rig its extrapolation record. Columns per rule: the kept member,
validation FIT on q, test FIT on q, inertia error, b's error in its own σ (z), and for the
identification rule how far the best member's validation score lies above the kept one's
(``held_out`` in metrics.json; a warning beyond `torchfric.app.run.outcome.HELD_OUT_GAP`).
The validation rule's FIT is chosen on the record it is scored on; the identification rule's is
held out.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from model_class import AXES, _prepare, _train, _truth, run_machines  # noqa: E402  (a sibling)

from torchfric.data.axis import axis_record, write_csv  # noqa: E402
from torchfric.data.rig import RigParameters  # noqa: E402

RULES = ("identification", "validation")


def _viscous(machine: str) -> float:
    return RigParameters().sigma2 if machine == "rig" else AXES[machine].viscous


def _row(metrics: dict[str, Any], m_true: float, b_true: float) -> dict[str, Any]:
    b = metrics["parameters"]["viscous"]
    ens = metrics.get("ensemble") or {}
    held = metrics.get("held_out") or {}
    return {
        "member": ens.get("best"),
        "pass": metrics.get("best_pass"),
        "fit_q": next(iter(metrics["validation"].values()))["fit_q"],
        "test_fit_q": next(iter(metrics["test"].values()))["fit_q"],
        "m_err_pct": 100 * (metrics["inertia"] / m_true - 1),
        "b_z": (b["value"] - b_true) / b["std"] if b["std"] else None,
        "gap": held.get("best_score", 0.0) - held.get("score", 0.0) if held else None,
        "warned": any("chosen by the identification records" in w for w in metrics["warnings"]),
        "dynamic": (metrics.get("dynamics") or {}).get("chosen"),
    }


def one(out: Path, machine: str, seed: int) -> dict[str, Any]:
    folder = out / f"{machine}_{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    cfg, sets = _prepare(folder, machine, seed)
    m_true, _ = _truth(machine)
    assert m_true is not None
    if machine in AXES:  # a third record that neither rule reads: the judge of both
        test = folder / "test.csv"
        write_csv(test, axis_record(AXES[machine], seed=seed + 1000, kind="validation"))
        sets = [*sets, f'data.test=["{test.as_posix()}"]']
    row: dict[str, Any] = {"machine": machine, "seed": seed}
    for rule in RULES:
        metrics, _, secs = _train(folder, cfg, [*sets, f"estimator.select={rule}"], rule)
        row[rule] = _row(metrics, m_true, _viscous(machine)) | {"seconds": secs}
    print(f"{machine} seed {seed} done", file=sys.stderr, flush=True)
    return row


def _z(x: float | None) -> str:
    return "–" if x is None else f"{x:+.1f}"


def print_table(rows: list[dict[str, Any]]) -> None:
    head = ("machine", "seed", "class", "member kept (ident. / valid.)",
            "validation FIT q, ident. rule (held out)", "valid. rule (chosen on it)",
            "test FIT q, ident. / valid. rule",
            "M err ident. / valid.", "b z ident. / valid.", "best member's lead", "warned")  # fmt: skip
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        i, v = r["identification"], r["validation"]
        gap = "–" if i["gap"] is None else f"{i['gap']:.1f} points"
        print(
            f"| {r['machine']} | {r['seed']} | {i['dynamic']} | {i['member']} / {v['member']} | "
            f"{i['fit_q']:.2f} % | {v['fit_q']:.2f} % | "
            f"{i['test_fit_q']:.2f} / {v['test_fit_q']:.2f} % | {i['m_err_pct']:+.2f} / "
            f"{v['m_err_pct']:+.2f} % | {_z(i['b_z'])} / {_z(v['b_z'])} | {gap} | "
            f"{'yes' if i['warned'] else 'no'} |"
        )
    n = len(rows)
    for rule in RULES:
        same = sum(r[rule]["member"] == r["validation"]["member"] for r in rows)
        inside_b = sum(r[rule]["b_z"] is not None and abs(r[rule]["b_z"]) <= 2 for r in rows)
        fits = sorted(r[rule]["fit_q"] for r in rows)
        tests = sorted(r[rule]["test_fit_q"] for r in rows)
        print(
            f"{rule}: b inside ±2σ {inside_b}/{n}; validation FIT q median "
            f"{fits[n // 2]:.2f} %, worst {fits[0]:.2f} %; test FIT q median "
            f"{tests[n // 2]:.2f} %, worst {tests[0]:.2f} %; member as the validation rule's "
            f"{same}/{n}"
        )


def main(argv: list[str] | None = None) -> int:
    machines = ["rig", "stribeck", "lugre", "linear", "table", "belt", "belt-fast", "spindle",
                "carriage"]  # fmt: skip
    return run_machines(argv, __doc__, one, print_table, machines, ["rig", *AXES])


if __name__ == "__main__":
    raise SystemExit(main())
