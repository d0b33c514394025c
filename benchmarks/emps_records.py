"""Are EMPS's two records the same machine? (issue 36, part 2: what a rule can reach)

    python benchmarks/emps_records.py            # both tables, about 15 s
    python benchmarks/emps_records.py --json out.json

The benchmark identifies on ``DATA_EMPS.mat`` and tests on ``DATA_EMPS_PULSES.mat``: the same
reference trajectory, with force pulses added in the test. A selection rule that reads the
identification record alone can only pick a model that is right on that record; this script
measures how far that record's machine is from the test record's, in two ways.

1. **Steady forces, without a model.** Where the axis cruises (the trapezoidal profile's
   constant-speed legs: |q̈| < 0.05 m/s² after the benchmark's own filtering — 4th-order
   Butterworth at 100 Hz run forwards and backwards, central differences, as the published
   IDIM-LS recipe does) the drive force ``gtau·vir`` equals the friction at that speed. Printed
   per speed band and file, and per 6.2-s cycle of the profile, so that a change between the
   records can be told from the spread within one; for the test record also with its force
   pulse off and on.
2. **How much of the test error a 1 % change of the drive explains.** Each committed EMPS
   checkpoint is scored by the benchmark's protocol (initial state from the first 20 samples,
   RMSE of q over the rest, mm) on both files with its drive gain c_m divided by 1 + k. The
   test file is read here only to measure; no config or rule reads it.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io

from torchfric import load_checkpoint, load_experiment
from torchfric.data.velocity import zero_phase_acceleration, zero_phase_derivative
from torchfric.estimators.metrics import score_benchmark

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "emps"
FILES = {"identification": "DATA_EMPS.mat", "test": "DATA_EMPS_PULSES.mat"}
BANDS = [(-0.14, -0.12), (-0.10, -0.08), (-0.06, -0.03), (0.03, 0.06), (0.08, 0.10), (0.12, 0.14)]
CYCLE = 6.2  # s, one period of the reference trajectory (four in each record)
STEADY = 0.05  # m/s², |q̈| below this counts as cruising
CHECKPOINTS = [
    "emps_lugre_asym_oe",
    "emps_lugre_asym_ekf_oe",
    "emps_tanh_asym_oe",
    "emps_tanh_oe",
    "emps_tanh_ekf_oe",
    "emps_defaults",
]
GAINS = [0.0, 0.005, 0.01, 0.015, 0.02, 0.03]


def cruising(path: Path) -> dict[str, np.ndarray]:
    """Speed, acceleration, drive force and time of one record; the cruising samples marked."""
    mat = scipy.io.loadmat(path)
    q = mat["qm"].ravel()
    dt = float(mat["t"].ravel()[1] - mat["t"].ravel()[0])
    v = zero_phase_derivative(q, dt, cutoff_hz=100.0).numpy()
    acc = zero_phase_acceleration(q, dt, cutoff_hz=100.0).numpy()
    force = float(mat["gtau"].ravel()[0]) * mat["vir"].ravel()
    t = np.arange(q.size) * dt
    rec = {"v": v, "force": force, "t": t, "steady": np.abs(acc) < STEADY}
    if "pulses_N" in mat:  # the test record's force pulses, {0, 5}
        rec["pulse"] = mat["pulses_N"].ravel() > 0
    return rec


def steady_forces(rec: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """Mean drive force per speed band over the whole record and per cycle."""
    rows = []
    n_cycles = math.ceil(rec["t"][-1] / CYCLE)
    for lo, hi in BANDS:
        band = rec["steady"] & (rec["v"] > lo) & (rec["v"] < hi)
        cycles = []
        for c in range(n_cycles):
            sel = band & (rec["t"] >= c * CYCLE) & (rec["t"] < (c + 1) * CYCLE)
            if sel.sum() > 50:
                cycles.append(float(rec["force"][sel].mean()))
        split = {}
        if "pulse" in rec:  # the cruise force with the test's pulse off and on
            split = {
                "pulse_off": float(rec["force"][band & ~rec["pulse"]].mean()),
                "pulse_on": float(rec["force"][band & rec["pulse"]].mean()),
            }
        rows.append({
            **split,
            "band": [lo, hi],
            "v": float(rec["v"][band].mean()),
            "force": float(rec["force"][band].mean()),
            "samples": int(band.sum()),
            "cycles": cycles,
        })  # fmt: skip
    return rows


def gain_scan(names: list[str]) -> dict[str, list[dict[str, float]]]:
    """Benchmark scores on both files with each checkpoint's c_m divided by 1 + k."""
    records = {
        key: load_experiment(DATA / name, columns={"u": "vir", "q": "qm"})
        for key, name in FILES.items()
    }
    out: dict[str, list[dict[str, float]]] = {}
    for name in names:
        path = ROOT / "checkpoints" / f"{name}.pt"
        if not path.exists():
            continue
        base = load_checkpoint(path)
        rows = []
        for k in GAINS:
            model = copy.deepcopy(base)
            model.c_m_fixed.fill_(float(base.c_m) / (1.0 + k))
            row = {"k": k}
            for key, rec in records.items():
                row[key] = 1000.0 * score_benchmark(model, rec, n_init=20, engine="compiled").rms_q
            rows.append(row)
        out[name] = rows
    return out


def print_forces(forces: dict[str, list[dict[str, Any]]]) -> None:
    print("Drive force gtau·vir [N] while cruising (|q̈| < 0.05 m/s²), per speed band (samples):")
    print()
    print(
        "| speed band [m/s] | mean speed | identification record | test record | test − identification | per cycle, identification | per cycle, test | test, pulse off / on |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for ident, test in zip(forces["identification"], forces["test"], strict=True):
        lo, hi = ident["band"]
        diff = test["force"] - ident["force"]
        rel = 100.0 * diff / abs(ident["force"])
        cyc_i = ", ".join(f"{f:+.2f}" for f in ident["cycles"])
        cyc_t = ", ".join(f"{f:+.2f}" for f in test["cycles"])
        print(
            f"| {lo:+.2f} … {hi:+.2f} | {ident['v']:+.4f} | {ident['force']:+.2f} ({ident['samples']}) | "
            f"{test['force']:+.2f} ({test['samples']}) | "
            f"{diff:+.2f} ({rel:+.1f} % of its size) | {cyc_i} | {cyc_t} | "
            f"{test.get('pulse_off', math.nan):+.2f} / {test.get('pulse_on', math.nan):+.2f} |"
        )
    print()


def print_gains(scan: dict[str, list[dict[str, float]]]) -> None:
    print("Benchmark RMSE [mm], test / identification file, with c_m divided by 1 + k:")
    print()
    print("| checkpoint | " + " | ".join(f"k = {100 * k:g} %" for k in GAINS) + " |")
    print("|---|" + "---|" * len(GAINS))
    for name, rows in scan.items():
        cells = " | ".join(f"{r['test']:.2f} / {r['identification']:.2f}" for r in rows)
        print(f"| `{name}` | {cells} |")
    print()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, help="also write the numbers here")
    ap.add_argument("--no-models", action="store_true", help="the model-free table only")
    args = ap.parse_args(argv)
    forces = {key: steady_forces(cruising(DATA / name)) for key, name in FILES.items()}
    print_forces(forces)
    scan = {} if args.no_models else gain_scan(CHECKPOINTS)
    if scan:
        print_gains(scan)
    if args.json:
        args.json.write_text(json.dumps({"forces": forces, "gain_scan": scan}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
