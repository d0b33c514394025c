"""Does torchfric's ±2σ cover the truth? Coverage over seeds on an independent machine.

    python benchmarks/coverage.py                                   # 20 seeds × 3 models
    python benchmarks/coverage.py --seeds 0 1 2 --models tanh --jobs 2
    python benchmarks/coverage.py --set estimator.passes=20         # any --set, on every run
    python benchmarks/coverage.py --models tanh-coulomb tanh-openloop   # the two diagnostics

For every seed and model, as a user would: `torchfric.data.axis` (an independent simulator, not
the built-in rig and not torchfric's vector field) records an identification and a validation
run of a machine whose truth is known — the Stribeck preset (`STRIBECK_AXIS`) for the tanh and
polytopic models, the LuGre preset (`LUGRE_AXIS`) for the LuGre model — written as ``t,u,q`` CSV
files; ``torchfric init IDENT.csv --c-m C_M`` writes the config, ``torchfric train`` runs it
(``--set model.friction=…``, ``model.dynamic=lugre``, ``data.validation=VALID.csv``). Then:

- inertia M and viscous b (for "polytopic", which has no b, the outer local model's slope, the
  curve's slope at high speed, see `slope_entry`) from ``metrics.json`` against the truth;
- the friction curve's band: `friction_band(model, P_theta, v)` of the checkpoint (the band the
  report draws) at 0.1, 0.25, 0.5, 0.75, 0.9 × the 95th percentile of |q̇_true| of the
  identification record, against `true_friction`.

Two diagnostic machines separate the causes of a miss (not in the default run):

- ``tanh-coulomb``: the tanh model on a Coulomb axis (the Stribeck preset with Fs = Fc: one tanh
  neuron draws its curve exactly), so the curve class cannot bias M, b or the band;
- ``tanh-openloop``: the tanh model on the Stribeck axis, its recorded input replayed open loop
  with fresh disturbance and encoder noise (`simulate_axis`), so the input no longer carries the
  measurement's error as it does in the position loop;
- ``tanh-linear``: the tanh model on the EMPS-like linear axis (`LINEAR_AXIS`: 95 kg, a 1 µm
  encoder, Coulomb 20 N and Stribeck 30 N at 0.01 m/s): a machine whose encoder is so fine
  that the likeliest noise model has the filter follow it sample by sample.

A ±2σ interval of a Gaussian belief covers the truth 95.4 % of the time: that is the nominal
coverage; the issue's acceptance band is 85–99 % (each of M, b and the curve). The table also
gives the median |error|/σ (≈ 0.67 when σ is right), relative errors, convergence and passes.
Rows per run go to DIR/coverage.csv, the summary to DIR/coverage.json (DIR: --out, default a
fresh temporary folder). A run takes about a minute on one core (the default 9-filter ensemble).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np

from torchfric.data.axis import (
    LINEAR_AXIS,
    LUGRE_AXIS,
    STRIBECK_AXIS,
    AxisParameters,
    axis_record,
    simulate_axis,
    true_friction,
    write_csv,
)

MODELS = ("tanh", "polytopic", "lugre")
DIAGNOSTICS = ("tanh-coulomb", "tanh-openloop", "tanh-linear")
AXES: dict[str, tuple[str, AxisParameters]] = {  # model → (record name, machine)
    "tanh": ("stribeck", STRIBECK_AXIS),
    "polytopic": ("stribeck", STRIBECK_AXIS),
    "lugre": ("lugre", LUGRE_AXIS),
    "tanh-coulomb": ("coulomb", dataclasses.replace(STRIBECK_AXIS, static=STRIBECK_AXIS.coulomb)),
    "tanh-openloop": ("openloop", STRIBECK_AXIS),
    "tanh-linear": ("linear", LINEAR_AXIS),
}
SETS: dict[str, list[str]] = {
    "tanh": ["model.friction=tanh", "model.dynamic=none"],
    "polytopic": ["model.friction=polytopic", "model.dynamic=none"],
    "lugre": ["model.friction=tanh", "model.dynamic=lugre"],
    "tanh-coulomb": ["model.friction=tanh", "model.dynamic=none"],
    "tanh-openloop": ["model.friction=tanh", "model.dynamic=none"],
    "tanh-linear": ["model.friction=tanh", "model.dynamic=none"],
}
OPEN_LOOP_NOISE = 97  # the replay's noise seed is [seed, this, kind]: independent of the loop's
FRACTIONS = (0.1, 0.25, 0.5, 0.75, 0.9)  # of the 95th percentile of |q̇_true|
NOMINAL = 0.954
ACCEPT = (0.85, 0.99)
CLI = [sys.executable, "-m", "torchfric"]


def slope_entry(parameters: dict[str, Any]) -> tuple[str, dict[str, float]] | None:
    """(name, {value, std}) of the viscous term: "viscous", else the outer slope of a polytopic
    model (the highest-numbered ``a<i>`` / ``a[i]``), else None."""
    if "viscous" in parameters:
        return "viscous", parameters["viscous"]
    slopes = [(int(m.group(1)), k) for k in parameters if (m := re.fullmatch(r"a\[?(\d+)\]?", k))]
    if slopes:
        name = max(slopes)[1]
        return name, parameters[name]
    return None


def covariance(checkpoint: Path) -> Any:
    """θ's covariance in estimation coordinates, as the checkpoint stores it (None if absent)."""
    from torchfric.app.artifacts.checkpoint import read_checkpoint

    state = read_checkpoint(checkpoint).get("estimator", {}).get("state", {})
    return state.get("P_theta")


def curve_check(checkpoint: Path, axis: AxisParameters, speeds: np.ndarray) -> list[float]:
    """(mean − truth)/σ of the total friction at `speeds` (NaN where there is no band)."""
    import torch

    import torchfric
    from torchfric.estimators.uncertainty import friction_band

    P = covariance(checkpoint)
    if P is None:
        return [math.nan] * speeds.size
    model = torchfric.load_checkpoint(checkpoint)
    v = torch.as_tensor(speeds, dtype=torch.float64)
    mean, std = friction_band(model, torch.as_tensor(P, dtype=torch.float64), v)
    err = mean.detach().numpy() - true_friction(axis, speeds)
    return list(err / std.detach().numpy())


def make_records(folder: Path, seed: int, duration: float, name: str, axis: AxisParameters) -> dict:
    """Write NAME_ident.csv and NAME_valid.csv (once per seed) and the config from `init`."""
    ident, valid, cfg = (folder / f"{name}_{s}" for s in ("ident.csv", "valid.csv", "cfg.toml"))

    def record(kind: str) -> dict:
        rec = axis_record(axis, seed=seed, duration=duration, kind=kind)
        if name == "openloop":  # the same input, open loop, with noise the input never saw
            qm, qt, vt = simulate_axis(axis, rec["u"], seed=[seed, OPEN_LOOP_NOISE, len(kind)])
            rec = {**rec, "q": qm, "q_true": qt, "qdot_true": vt}
        return rec

    rec = record("identification")
    if not ident.exists():
        write_csv(ident, rec)
        write_csv(valid, record("validation"))
    if not cfg.exists():
        out = subprocess.run([*CLI, "init", ident.name, "--c-m", repr(axis.c_m), "--out", cfg.name],
                             cwd=folder, capture_output=True, text=True)  # fmt: skip
        if out.returncode != 0:  # fall back to the minimal config of docs/config.md
            print(f"init failed ({out.stderr.strip()[-300:]}); writing a minimal config",
                  file=sys.stderr)  # fmt: skip
            cfg.write_text(f'[data]\ntrain = ["{ident.name}"]\nvalidation = ["{valid.name}"]\n'
                           f'[model]\nc_m = {axis.c_m!r}\nfriction = "tanh"\n')  # fmt: skip
    v95 = float(np.quantile(np.abs(rec["qdot_true"]), 0.95))
    return {"cfg": cfg, "valid": valid, "speeds": np.array(FRACTIONS) * v95}


def one_run(folder: Path, seed: int, model: str, files: dict, sets: list[str], env: dict) -> dict:
    """Train one model on one seed's records; the row of coverage.csv."""
    name, axis = AXES[model]
    run_dir = folder / f"run_{model}"
    argv = [*CLI, "train", str(files["cfg"]), "--out", str(run_dir), "--quiet"]
    for s in [*SETS[model], f"data.validation={files['valid']}", *sets]:
        argv += ["--set", s]
    t0 = time.perf_counter()
    out = subprocess.run(argv, cwd=folder, capture_output=True, text=True, env=env)
    row: dict[str, Any] = {"seed": seed, "model": model, "axis": name,
                           "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
    if out.returncode != 0:
        row["error"] = (out.stderr.strip().splitlines() or ["?"])[-1][:300]
        return row
    metrics = json.loads((run_dir / "metrics.json").read_text())
    params = metrics["parameters"]
    row |= {"converged": metrics.get("converged"), "best_pass": metrics.get("best_pass"),
            "passes": metrics.get("passes"),
            "fit_q": next(iter(metrics.get("validation", {}).values()), {}).get("fit_q")}  # fmt: skip
    slope = slope_entry(params)
    truth = {"M": axis.inertia, "b": axis.viscous}
    for key, entry in (("M", ("inertia", params.get("inertia"))), ("b", slope)):
        if entry is None or entry[1] is None:
            continue
        value, std = entry[1]["value"], entry[1]["std"]
        err = value - truth[key]
        row |= {f"{key}_name": entry[0], f"{key}_true": truth[key], f"{key}_hat": value,
                f"{key}_std": std, f"{key}_relerr": err / truth[key],
                f"{key}_z": err / std if std > 0 else math.inf}  # fmt: skip
    checkpoint = next(run_dir.glob("*.pt"), None)
    if checkpoint is not None:
        for i, (v, z) in enumerate(zip(files["speeds"], curve_check(checkpoint, axis, files["speeds"]), strict=True)):  # fmt: skip
            row[f"v{i + 1}"], row[f"curve{i + 1}_z"] = float(v), float(z)
    return row


def seed_job(out: Path, seed: int, models: list[str], duration: float, sets: list[str],
             env: dict) -> list[dict]:  # fmt: skip
    folder = out / f"seed{seed:02d}"
    folder.mkdir(parents=True, exist_ok=True)
    rows, made = [], {}
    for model in models:
        name, axis = AXES[model]
        if name not in made:
            made[name] = make_records(folder, seed, duration, name, axis)
        try:
            row = one_run(folder, seed, model, made[name], sets, env)
        except Exception as exc:  # a changed file format: one bad row, not a lost benchmark
            row = {"seed": seed, "model": model, "axis": name, "seconds": 0.0,
                   "error": f"{type(exc).__name__}: {exc}"[:300]}  # fmt: skip
        print(f"seed {seed} {model}: {row.get('error') or 'ok'} ({row['seconds']} s)",
              file=sys.stderr, flush=True)  # fmt: skip
        rows.append(row)
    return rows


def summarise(rows: list[dict], model: str) -> dict[str, Any]:
    """The table's numbers for one model."""
    mine = [r for r in rows if r["model"] == model]
    ok = [r for r in mine if "error" not in r]
    out: dict[str, Any] = {"runs": len(mine), "failed": len(mine) - len(ok)}
    for key in ("M", "b"):
        z = [r[f"{key}_z"] for r in ok if f"{key}_z" in r]
        rel = [abs(r[f"{key}_relerr"]) for r in ok if f"{key}_relerr" in r]
        out[key] = {"n": len(z), "covered": sum(abs(x) <= 2 for x in z),
                    "median_abs_z": statistics.median(map(abs, z)) if z else None,
                    "median_relerr": statistics.median(rel) if rel else None,
                    "max_relerr": max(rel) if rel else None,
                    "names": sorted({r[f"{key}_name"] for r in ok if f"{key}_name" in r})}  # fmt: skip
    cz = [r[f"curve{i}_z"] for r in ok for i in range(1, 6) if not math.isnan(r.get(f"curve{i}_z", math.nan))]  # fmt: skip
    out["curve"] = {"n": len(cz), "covered": sum(abs(x) <= 2 for x in cz),
                    "median_abs_z": statistics.median(map(abs, cz)) if cz else None}  # fmt: skip
    out["converged"] = sum(bool(r.get("converged")) for r in ok)
    passes = [r["passes"] for r in ok if r.get("passes") is not None]
    out["median_passes"] = statistics.median(passes) if passes else None
    out["seconds"] = round(sum(r["seconds"] for r in mine), 1)
    return out


def _pct(k: int, n: int) -> str:
    return f"{k}/{n} ({100 * k / n:.0f} %)" if n else "n/a"


def _num(x: float | None, fmt: str) -> str:
    return "n/a" if x is None else format(x, fmt)


def _rel(x: float | None) -> str:
    return "" if x is None else f"{100 * x:.3g} %"


def print_table(summary: dict[str, dict], wall: float) -> None:
    print(f"±2σ coverage (nominal {100 * NOMINAL:.1f} %, accepted "
          f"{100 * ACCEPT[0]:.0f}–{100 * ACCEPT[1]:.0f} %); |err|/σ median ≈ 0.67 when σ is right")  # fmt: skip
    for model, s in summary.items():
        M, b, c = s["M"], s["b"], s["curve"]
        print(f"\n{model}: {s['runs']} runs, {s['failed']} failed, converged {s['converged']}, "
              f"median passes {_num(s['median_passes'], 'g')}, {s['seconds']} s of runs")  # fmt: skip
        print(f"  {'':<18}{'coverage':>16}{'median |err|/σ':>16}{'median rel err':>16}{'max rel err':>14}")  # fmt: skip
        for label, d in ((f"M ({', '.join(M['names']) or 'inertia'})", M),
                         (f"b ({', '.join(b['names']) or 'n/a'})", b), ("curve (5 speeds)", c)):  # fmt: skip
            print(f"  {label:<18}{_pct(d['covered'], d['n']):>16}{_num(d['median_abs_z'], '.3g'):>16}"
                  f"{_rel(d.get('median_relerr')):>16}{_rel(d.get('max_relerr')):>14}")  # fmt: skip
    print(f"\ntotal wall time {wall:.0f} s")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(20)))
    ap.add_argument("--models", nargs="+", choices=MODELS + DIAGNOSTICS, default=list(MODELS))
    ap.add_argument("--duration", type=float, default=30.0, help="seconds per record")
    ap.add_argument(
        "--out", type=Path, default=None, help="a new or empty folder (default: a fresh temp dir)"
    )
    ap.add_argument("--jobs", type=int, default=1, help="seeds run in parallel")
    ap.add_argument("--disturbance", type=float, default=0.02,
                    help="torque disturbance std as a fraction of the axis's Coulomb level, "
                    "low-passed at 10 Hz (the built-in rig's: 0.02); 0 = none")  # fmt: skip
    ap.add_argument("--bandwidth", type=float, default=10.0,
                    help="the disturbance's first-order low-pass [Hz]; 0 = white (held per "
                    "sample)")  # fmt: skip
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="extra `torchfric train --set` for every run (repeatable)")  # fmt: skip
    args = ap.parse_args(argv)
    for model, (name, axis) in AXES.items():
        AXES[model] = (name, dataclasses.replace(
            axis, disturbance_std=args.disturbance * axis.coulomb,
            disturbance_bandwidth=args.bandwidth))  # fmt: skip
    out = args.out or Path(tempfile.mkdtemp(prefix="torchfric-coverage-"))
    out.mkdir(parents=True, exist_ok=True)
    taken = [f"seed{s:02d}/run_{m}" for s in args.seeds for m in args.models
             if (out / f"seed{s:02d}" / f"run_{m}").exists()]  # fmt: skip
    if taken:  # train refuses a run directory that holds an earlier run
        raise SystemExit(f"{out} already holds {', '.join(taken[:3])}: give a new --out")
    env = dict(os.environ)
    if args.jobs > 1:  # share the cores instead of oversubscribing them
        threads = str(max(1, (os.cpu_count() or 1) // args.jobs))
        env.setdefault("OMP_NUM_THREADS", threads)
        env.setdefault("MKL_NUM_THREADS", threads)
    print(f"coverage: seeds {args.seeds}, models {args.models}, out {out}", file=sys.stderr)
    t0 = time.perf_counter()
    rows: list[dict] = []
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        jobs = [pool.submit(seed_job, out, s, args.models, args.duration, args.set, env)
                for s in args.seeds]  # fmt: skip
        for job in as_completed(jobs):
            rows.extend(job.result())
    wall = time.perf_counter() - t0
    rows.sort(key=lambda r: ((MODELS + DIAGNOSTICS).index(r["model"]), r["seed"]))
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(out / "coverage.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    summary = {m: summarise(rows, m) for m in args.models}
    (out / "coverage.json").write_text(json.dumps(
        {"command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
         "seeds": args.seeds, "duration": args.duration, "sets": args.set, "nominal": NOMINAL,
         "disturbance": args.disturbance, "bandwidth": args.bandwidth,
         "accept": ACCEPT, "fractions_of_p95_speed": FRACTIONS, "wall_seconds": round(wall, 1),
         "models": summary}, indent=2, default=str) + "\n")  # fmt: skip
    print_table(summary, wall)
    print(f"rows: {out / 'coverage.csv'}\nsummary: {out / 'coverage.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
