"""Static against LuGre friction models on the synthetic rig (issue 23). Prints a table.

    python benchmarks/dynamic_friction.py               # every row (about 3 min on 2 cores)
    python benchmarks/dynamic_friction.py --json out.json

Every row is one ``torchfric train`` (through `torchfric.fit`) of
``experiments/configs/arm_lugre_ekf.toml`` with only the friction model changed: the same data,
pre-fit, default 9-tuning EKF ensemble (the member with the best validation FIT kept), 10 passes
and 2 integrator steps per sample. "changed" re-identifies the rig "after maintenance" (Fs = Fc)
the same way from its own pre-fit and scores its own validation record. The ceilings are the
true system's own open-loop FIT on the validation record: the rig's LuGre model with its true
parameters, and its true *static* curve (the best any static model can reach), both simulated
with torchfric's integrators.

Columns: validation FIT on q, extrapolation FIT on q (the 16 rad/s record), changed-system
validation FIT on q, inertia error, steady-state curve RMS error over ±10 rad/s in % of the true
curve's peak, σ0 and σ1 (true 1250 and 12), and the wall time of the training.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile
import time

import torch

import torchfric
from torchfric import ArmModel, make_friction, simulate
from torchfric.data.rig import RigParameters, rig_experiment
from torchfric.estimators.metrics import fit_percent, friction_curve_error

ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIG = ROOT / "experiments" / "configs" / "arm_lugre_ekf.toml"

# (label, [model] overrides)
ROWS: list[tuple[str, dict]] = [
    ("static tanh(3)", {"dynamic": "none", "size": 3}),
    ("static tanh(4)", {"dynamic": "none", "size": 4}),
    ("static polytopic(3)", {"dynamic": "none", "friction": "polytopic", "size": 3}),
    ("LuGre tanh(3)", {"size": 3}),
    ("LuGre tanh(4)", {"size": 4}),
    ("LuGre polytopic(3)", {"friction": "polytopic", "size": 3}),
]


def _fit_q(model: ArmModel, name: str) -> float:
    arr = rig_experiment(name, seed=0)
    t, u = torch.tensor(arr["t"]), torch.tensor(arr["u"])
    with torch.no_grad():
        x = simulate(model, t, u, torch.zeros(2, dtype=torch.float64), engine="compiled")
    return fit_percent(torch.tensor(arr["q"]), x[:, 0])


def ceilings() -> dict[str, float]:
    """The true system's open-loop FIT on the validation records (nominal and changed)."""
    out = {}
    for label, p in (("nominal", RigParameters()), ("changed", RigParameters().changed())):
        # the Stribeck module's tanh(v/ε) is sign(v) from the stick velocity 1e-6 on: g is the
        # rig's g to rounding (tests/test_lugre.py reproduces the rig with this model)
        fr = make_friction("stribeck", 1, fc=p.Fc, fs=p.Fs, vs=p.vs, eps=1e-8)
        lugre = ArmModel(fr, inertia=p.inertia, viscous=p.sigma2, c_m=p.c_m, dynamic="lugre",
                         sigma0=p.sigma0, sigma1=p.sigma1, stick_velocity=1e-6)  # fmt: skip
        record = "validation" if label == "nominal" else "changed_validation"
        out[f"lugre_{label}"] = _fit_q(lugre, record)
        out[f"static_{label}"] = _fit_q(lugre.static_twin(), record)
    return out


def curve_error(model: ArmModel, truth: RigParameters, v_max: float = 10.0) -> float:
    v = torch.linspace(-v_max, v_max, 2001, dtype=torch.float64)
    v = v[v.abs() > 0.05]  # the true curve jumps at 0; a continuous model cannot follow there
    with torch.no_grad():
        return 100 * friction_curve_error(model, v, truth.steady_state_friction(v))


def run_row(label: str, model_keys: dict, out: pathlib.Path) -> dict:
    row: dict = {"model": label}
    start = time.perf_counter()
    res = torchfric.fit(CONFIG, out=out / label.replace(" ", "_"), quiet=True, model=model_keys)
    row["seconds"] = time.perf_counter() - start
    truth = RigParameters()
    p = res.model.physical_parameters()
    row["fit_validation"] = res.metrics["validation"]["validation"]["fit_q"]
    row["fit_extrapolation"] = res.metrics["test"]["extrapolation"]["fit_q"]
    row["inertia_error_pct"] = 100 * (p["inertia"] / truth.inertia - 1)
    row["curve_error_pct"] = curve_error(res.model, truth)
    row["sigma0"], row["sigma1"] = (
        p.get(k, float("nan")) for k in ("lugre_sigma0", "lugre_sigma1")
    )
    changed = torchfric.fit(
        CONFIG, out=out / (label.replace(" ", "_") + "_changed"), quiet=True, model=model_keys,
        data={"train": ["rig:changed_identification"], "validation": ["rig:changed_validation"],
              "test": []},
    )  # fmt: skip
    row["fit_changed"] = changed.metrics["validation"]["changed_validation"]["fit_q"]
    row["curve_error_changed_pct"] = curve_error(changed.model, truth.changed())
    return row


def print_table(rows: list[dict], ceil: dict[str, float]) -> None:
    print(
        f"ceilings (validation FIT q): LuGre system {ceil['lugre_nominal']:.2f} %, true static "
        f"curve {ceil['static_nominal']:.2f} %; changed: {ceil['lugre_changed']:.2f} % / "
        f"{ceil['static_changed']:.2f} %"
    )
    head = ("model", "val FIT q", "extrap FIT q", "changed FIT q", "M err", "curve err",
            "changed curve", "σ0", "σ1", "time")  # fmt: skip
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print(
            f"| {r['model']} | {r['fit_validation']:.2f} % | {r['fit_extrapolation']:.2f} % | "
            f"{r['fit_changed']:.2f} % | {r['inertia_error_pct']:+.2f} % | "
            f"{r['curve_error_pct']:.2f} % | {r['curve_error_changed_pct']:.2f} % | "
            f"{r['sigma0']:.4g} | {r['sigma1']:.4g} | {r['seconds']:.1f} s |"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="also write the rows to this JSON file")
    parser.add_argument("--only", nargs="*", help="labels of the rows to run (default: all)")
    args = parser.parse_args(argv)
    ceil = ceilings()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, keys in ROWS:
            if args.only and label not in args.only:
                continue
            rows.append(run_row(label, keys, pathlib.Path(tmp)))
            print(f"  {label}: done in {rows[-1]['seconds']:.1f} s", file=sys.stderr)
    print_table(rows, ceil)
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps({"ceilings": ceil, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
