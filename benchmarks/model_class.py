"""Static, LuGre and ``model.dynamic = "auto"`` on machines of known class (issue 36). A table.

    python benchmarks/model_class.py                                # every machine, 3 seeds each
    python benchmarks/model_class.py --machines stribeck --seeds 1 2 3 4 5 --jobs 2

Every row is a user's path: a machine's identification record (the built-in rig's, EMPS's, or one
written by an independent simulator, `torchfric.data.axis`, as a ``t,u,q`` CSV with ``torchfric
init IDENT.csv --c-m C_M``, which writes ``dynamic = "auto"``), trained twice with ``torchfric
train``: once as written (auto: the class it chooses, its t statistic, the windows' RMS errors
and LuGre's bristle travel through a reversal in position steps, read from ``metrics.json``'s
``dynamics``) and once with the other class fixed
(``--set model.dynamic=none`` or ``lugre``). Auto's trained model is the chosen class's fixed
run, bit for bit (`tests/test_model_class.py`), so the two runs give both classes' scores.

Machines: ``rig`` (the synthetic LuGre rig, `experiments/configs/arm_defaults.toml`, validated on
``rig:validation``), ``stribeck`` (`STRIBECK_AXIS`, static friction), ``lugre`` (`LUGRE_AXIS`,
LuGre bristles with a pre-sliding range of 0.4 encoder counts), ``linear`` (`LINEAR_AXIS`,
static, an EMPS-like linear axis), ``emps`` (the measured EMPS records,
`experiments/configs/emps_defaults.toml`; scored by the benchmark protocol on the test file),
and, not in the default list, two machines the rule was not tuned on: ``spindle`` (LuGre, bristles
travelling 6 counts of a 4096-count encoder) and ``carriage`` (static, sticking hard), and three
added with the rule in time: ``table`` (a heavy ball-screw table, static, a 0.5-µm scale),
``belt`` and ``belt-fast`` (LuGre belt axes whose bristles settle over 5 and 1.7 samples), and
``turntable`` (static, a 17-bit encoder: where the rule keeps LuGre on a static machine).
Columns per class: validation FIT on q (EMPS: test RMSE in mm), inertia error, steady-state
friction curve RMS error in % of the true curve's peak (over 5–95 % of the data's speeds, the
jump at zero left out), and the run's wall time.
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
import torch

from torchfric import load_checkpoint
from torchfric.data.axis import (
    LINEAR_AXIS,
    LUGRE_AXIS,
    STRIBECK_AXIS,
    AxisParameters,
    axis_record,
    true_friction,
    write_csv,
)
from torchfric.data.rig import RigParameters
from torchfric.estimators.metrics import friction_curve_error

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "torchfric"]
_COUNT = 2 * math.pi / 4096  # the spindle's 4096-count encoder
# Two machines the rule was not tuned on (a user's walk, docs/results.md): a LuGre spindle whose
# bristles travel 6 counts through a reversal, and a static carriage that sticks hard (Fs = 2 Fc).
SPINDLE_AXIS = AxisParameters(inertia=0.05, c_m=2.0, viscous=0.01, coulomb=0.3, static=0.45,
                              stribeck_velocity=0.5, friction="lugre", sigma0=0.45 / (3 * _COUNT),
                              sigma1=1.4 * math.sqrt(0.45 / (3 * _COUNT) * 0.05), quantum=_COUNT,
                              max_speed=20.0, substeps=40)  # fmt: skip
CARRIAGE_AXIS = AxisParameters(inertia=8.0, c_m=20.0, viscous=30.0, coulomb=6.0, static=12.0,
                               stribeck_velocity=0.005, quantum=1e-6, max_speed=0.3,
                               max_input=3.0)  # fmt: skip
# Three more, added with the rule in time (`torchfric.models.lugre.stick_rate`, 2026-11-28): a
# heavy ball-screw table with static friction and a 0.5-µm scale (a user walk's machine, where
# LuGre fits travelled 1–10 counts yet settled within a sample), and a LuGre belt axis whose
# bristles settle over 5 samples (belt) or 1.7 samples (belt-fast), 20 and 2.2 counts of travel.
TABLE_AXIS = AxisParameters(inertia=18.0, c_m=40.0, viscous=120.0, coulomb=15.0, static=24.0,
                            stribeck_velocity=0.004, quantum=0.5e-6, disturbance_std=0.3,
                            max_speed=0.15, max_input=1.5)  # fmt: skip


def _belt(rate_per_sample: float) -> AxisParameters:
    sigma0 = 6.0 * (rate_per_sample / 1e-3) ** 2  # √(σ0/M) × dt = rate_per_sample, M 6 kg
    return AxisParameters(inertia=6.0, c_m=25.0, viscous=40.0, coulomb=8.0, static=12.0,
                          stribeck_velocity=0.01, friction="lugre", sigma0=sigma0,
                          sigma1=1.6 * math.sqrt(6.0 * sigma0), quantum=5e-6, max_speed=0.5,
                          max_input=3.0, substeps=40)  # fmt: skip


# A static turntable with a 17-bit encoder, after a user walk's machine of 2026-11-28 (J 0.8,
# b 0.3, Coulomb 1.2 / stiction 1.6 N m, c_m 0.05 N m per %, 500 Hz), where auto kept LuGre on 4
# of 10 records. With the walk's Stribeck velocity, 0.05 rad/s, this simulator's records keep
# static on 6 of 6; at 0.3 rad/s (here) LuGre fits travel 4-15 counts and auto keeps 4 of 6.
TURNTABLE_AXIS = AxisParameters(inertia=0.8, c_m=0.05, viscous=0.3, coulomb=1.2, static=1.6,
                                stribeck_velocity=0.3, quantum=2 * math.pi / 131072, dt=2e-3,
                                max_speed=6.0, max_input=80.0)  # fmt: skip
AXES = {"stribeck": STRIBECK_AXIS, "lugre": LUGRE_AXIS, "linear": LINEAR_AXIS,
        "spindle": SPINDLE_AXIS, "carriage": CARRIAGE_AXIS, "table": TABLE_AXIS,
        "belt": _belt(0.2), "belt-fast": _belt(0.6), "turntable": TURNTABLE_AXIS}  # fmt: skip
CONFIGS = {
    "rig": ROOT / "experiments" / "configs" / "arm_defaults.toml",
    "emps": ROOT / "experiments" / "configs" / "emps_defaults.toml",
}
NAMES = {"none": "static", "lugre": "LuGre"}


def _prepare(folder: Path, machine: str, seed: int) -> tuple[Path, list[str]]:
    """The config a user would train (``init``'s for an axis) and the --set of its run."""
    if machine in CONFIGS:
        return CONFIGS[machine], ["model.dynamic=auto"]
    axis = AXES[machine]
    ident, valid, cfg = (folder / n for n in ("ident.csv", "valid.csv", "cfg.toml"))
    write_csv(ident, axis_record(axis, seed=seed, duration=30.0, kind="identification"))
    write_csv(valid, axis_record(axis, seed=seed, duration=30.0, kind="validation"))
    subprocess.run([*CLI, "init", ident.name, "--c-m", repr(axis.c_m), "--out", cfg.name],
                   cwd=folder, check=True, capture_output=True)  # fmt: skip
    return cfg, [f"data.validation={valid}"]


def _train(folder: Path, cfg: Path, sets: list[str], label: str) -> tuple[dict, Path, float]:
    out = folder / f"run_{label}"
    argv = [*CLI, "train", str(cfg), "--out", str(out), "--quiet"]
    for s in sets:
        argv += ["--set", s]
    t0 = time.perf_counter()
    done = subprocess.run(argv, cwd=folder, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{label}: {done.stderr.strip()[-400:]}")
    return json.loads((out / "metrics.json").read_text()), next(out.glob("*.pt")), seconds


def _truth(machine: str) -> tuple[float | None, Any]:
    """The true inertia and a function v ↦ true steady-state friction (None for EMPS)."""
    if machine == "rig":
        rig = RigParameters()
        return rig.inertia, lambda v: rig.steady_state_friction(torch.as_tensor(v)).numpy()
    if machine == "emps":
        return None, None
    axis: AxisParameters = AXES[machine]
    return axis.inertia, lambda v: true_friction(axis, np.asarray(v))


def _curve_error(checkpoint: Path, truth: Any, speeds: np.ndarray) -> float:
    v = torch.as_tensor(np.concatenate([-speeds[::-1], speeds]), dtype=torch.float64)
    true = torch.as_tensor(truth(v.numpy()), dtype=torch.float64)
    with torch.no_grad():
        return 100 * friction_curve_error(load_checkpoint(checkpoint), v, true)


def _score(machine: str, metrics: dict, checkpoint: Path, m_true: float | None, truth: Any,
           speeds: np.ndarray) -> dict[str, Any]:  # fmt: skip
    row: dict[str, Any] = {}
    if machine == "emps":
        sys.path.insert(0, str(ROOT / "benchmarks"))
        from real_data import emps_score  # the benchmark protocol, as in results.md

        row["test_rmse_mm"] = emps_score(load_checkpoint(checkpoint))["test_rmse_mm"]
    else:
        fits = next(iter(metrics["validation"].values()))
        row["fit_q"], row["fit_qdot"] = fits["fit_q"], fits["fit_qdot"]
        row["inertia_err_pct"] = 100 * (metrics["inertia"] / m_true - 1)
        row["curve_err_pct"] = _curve_error(checkpoint, truth, speeds)
    return row


def one(out: Path, machine: str, seed: int) -> dict[str, Any]:
    folder = out / f"{machine}_{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    cfg, sets = _prepare(folder, machine, seed)
    m_true, truth = _truth(machine)
    metrics, ckpt, secs = _train(folder, cfg, sets, "auto")
    dyn = metrics["dynamics"]
    chosen = dyn["chosen"]
    other = "lugre" if chosen == "none" else "none"
    speeds = _speeds(machine, seed)
    row: dict[str, Any] = {"machine": machine, "seed": seed, "chosen": chosen, "t": dyn["t"],
                           "gain": dyn["gain"], "auto_seconds": secs,
                           "travel_steps": dyn["bristle_travel"] / dyn["position_step"],
                           "per_sample": dyn["stick_rate"] * dyn["sample_time"],
                           "rmse": {r["dynamic"]: r["rmse_q"] for r in dyn["table"]}}  # fmt: skip
    row[chosen] = _score(machine, metrics, ckpt, m_true, truth, speeds) | {"seconds": None}
    metrics2, ckpt2, secs2 = _train(folder, cfg, [*sets, f"model.dynamic={other}"], other)
    row[other] = _score(machine, metrics2, ckpt2, m_true, truth, speeds) | {"seconds": secs2}
    print(f"{machine} seed {seed}: {NAMES[chosen]} (t {dyn['t']:+.1f})", file=sys.stderr,
          flush=True)  # fmt: skip
    return row


def _speeds(machine: str, seed: int) -> np.ndarray:
    """Where the curve is scored: 5–95 % of the identification record's true speeds for an axis,
    0.05–10 rad/s on the rig (as `benchmarks/dynamic_friction.py`)."""
    if machine == "rig":
        return np.linspace(0.05, 10.0, 50)
    if machine == "emps":
        return np.array([])
    rec = axis_record(AXES[machine], seed=seed, duration=30.0, kind="identification")
    return np.linspace(*np.quantile(np.abs(rec["qdot_true"]), [0.05, 0.95]), 50)


def print_table(rows: list[dict]) -> None:
    head = ("machine", "seed", "auto keeps", "t", "MSE gain", "bristle travel",
            "settling per sample", "static FIT q, q̇ / RMSE",
            "LuGre FIT q, q̇ / RMSE", "static M err", "LuGre M err", "static curve", "LuGre curve",
            "auto time", "other time")  # fmt: skip
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        s, d = r.get("none", {}), r.get("lugre", {})

        def fit(x: dict) -> str:
            if "test_rmse_mm" in x:
                return f"{x['test_rmse_mm']:.2f} mm"
            return f"{x['fit_q']:.2f}, {x['fit_qdot']:.2f} %"

        def pct(x: dict, k: str) -> str:
            return f"{x[k]:+.2f} %" if k in x else "–"

        other = s if r["chosen"] == "lugre" else d
        print(
            f"| {r['machine']} | {r['seed']} | {NAMES[r['chosen']]} | {r['t']:+.1f} | "
            f"{100 * r['gain']:+.1f} % | {r['travel_steps']:.2f} steps | {r['per_sample']:.2f} | "
            f"{fit(s)} | {fit(d)} | {pct(s, 'inertia_err_pct')} | "
            f"{pct(d, 'inertia_err_pct')} | {s.get('curve_err_pct', float('nan')):.2f} % | "
            f"{d.get('curve_err_pct', float('nan')):.2f} % | {r['auto_seconds']:.0f} s | "
            f"{other['seconds']:.0f} s |"
        )


def run_machines(argv: list[str] | None, doc: str, one: Any, table: Any, machines: list[str],
                 choices: list[str]) -> int:  # fmt: skip
    """The command line these benchmarks share: ``--machines`` (default `machines`),
    ``--seeds``, ``--jobs``, ``--out``, ``--json``; `one(out, machine, seed)` makes a row
    (`jobs` at a time; a seed for each axis, seed 0 for a config), `table(rows)` prints them."""
    p = argparse.ArgumentParser(description=doc.split("\n")[0])
    p.add_argument("--machines", nargs="+", default=machines, choices=choices)
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3])
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    out = a.out or Path(tempfile.mkdtemp(prefix=f"{Path(sys.argv[0]).stem}_"))
    jobs = [(m, s) for m in a.machines for s in (a.seeds if m in AXES else [0])]
    t0 = time.perf_counter()
    with ThreadPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(lambda job: one(out, *job), jobs))
    table(rows)
    print(f"\n{len(rows)} machines × seeds in {time.perf_counter() - t0:.0f} s; runs in {out}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_machines(argv, __doc__, one, print_table,
                        ["rig", "stribeck", "lugre", "linear", "emps"], ["rig", "emps", *AXES])  # fmt: skip


if __name__ == "__main__":
    raise SystemExit(main())
