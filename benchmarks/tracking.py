"""On-line tracking and change detection on four machines of different scale (issues 24, 33):
detection delay, false alarms, the estimate after a change, throughput. Prints a table.

    python benchmarks/tracking.py                              # all four machines, seeds 0 1 2
    python benchmarks/tracking.py --machines rig --seeds 0 1 2 3 4 5
    python benchmarks/tracking.py --machines axis linear --cache /tmp/trk   # reuse models, records

Every row runs the real command, ``torchfric track CHECKPOINT REC.csv --out DIR`` with every
``[track]`` default, on one of four machines:

- ``rig``: the built-in rig, ``checkpoints/arm_tanh_ekf.pt`` (the paper's tanh(3) EKF). Change
  records from `torchfric.data.rig.changing_record`: 30 s of the identified rig, then 90 s of
  the rig "after maintenance" (no static friction). The two differ only at low speed, so the
  change becomes visible when the arm first runs slower than the Stribeck velocity (0.5 rad/s)
  after it: "after exciting motion" counts from there.
- ``axis``: the user-style rotary axis `torchfric.data.axis.STRIBECK_AXIS` (M 0.012 kg m², Fc
  0.05 N m, Fs 0.08 N m, 40 rad/s), and ``linear``: the EMPS-like `LINEAR_AXIS` (95 kg, Fc
  20 N, Fs 30 N, 1 µm encoder, 0.2 m/s), both with a 10 Hz coloured torque disturbance of
  2 % of Fc (as benchmarks/coverage.py). Identified as a user would: a 30 s identification
  record (seed 100), ``torchfric init IDENT.csv --c-m C_M`` and ``torchfric train`` with the
  defaults (cached in ``--cache``). Change records: `axis_record(..., change=(60, after))`,
  60 s of the nominal axis then 60 s with the whole Coulomb–Stribeck level ×1.4 (Fc and Fs
  both: a 40 % rise of the dry friction; the viscous b unchanged), one continuous run in its
  position loop (the state carried across; the loop does not know). A Coulomb change shows
  whenever the axis slides, so "after exciting motion" counts from the first sample at or
  after the change with |q̇| above a tenth of the Stribeck velocity (sliding: a resting axis
  creeps at ~1e-3 vs, and at rest no friction level shows).
- ``carriage``: the stick-slip linear carriage of `benchmarks/carriage.py` (2.5 kg, c_m 12,
  b 8 N s/m, Fc 4 N, Fs 6 N at 0.02 m/s, a 1 µm encoder, a 15-Hz load disturbance of 0.3 N),
  simulated outside torchfric and written as lab software writes it (semicolons, decimal
  commas, ms, counts); identified as a user would (``init --c-m 12 --counts-per-m 1e6``,
  ``train``); change records: 60 s, then Fc and Fs × 1.4. "After exciting motion" counts from
  the first sample after the change with |q̇| > vs/10 (it sticks for up to 2 s at a time).
- every machine: 10 minutes of unchanged data (another seed and excitation): false alarms.

Reported: the delay of the first detection after the change; false alarms (detections before
the change, or more than one after it); the final inertia against the truth and the final
steady-state curve's RMS error against the truth after the change (rig: over ±8 rad/s,
|q̇| > 0.05; axes: over ±v95 of the record, |q̇| > vs/10; in % of its peak; the starting model's
in brackets). Throughput: samples per second of the tracking loop (the command's own count).
The σ bands (issue 31): the share of track.csv's rows (one per 0.1 s) whose ±2σ holds the true
M and b, "before → after" the change (after: from 10 s after it), or over the unchanged record.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np
import torch

from torchfric import load_checkpoint
from torchfric.data.axis import (
    LINEAR_AXIS,
    STRIBECK_AXIS,
    AxisParameters,
    axis_record,
    true_friction,
)
from torchfric.data.rig import RigParameters, changing_record, excitation, simulate_rig
from torchfric.estimators.metrics import friction_curve_error

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import carriage  # noqa: E402  (benchmarks/carriage.py: the stick-slip carriage's simulator)

ROOT = pathlib.Path(__file__).resolve().parents[1]
CHECKPOINT = ROOT / "checkpoints" / "arm_tanh_ekf.pt"
CLI = [sys.executable, "-m", "torchfric"]
AXES = {"axis": STRIBECK_AXIS, "linear": LINEAR_AXIS}
IDENT_SEED, QUIET_SEED = 100, 7
BEFORE, AFTER = 60.0, 60.0  # the axes' change records [s]
RIG_TRUTH = (RigParameters().inertia, RigParameters().sigma2)  # M and b (the LuGre rig's σ2)


def write_csv(path: pathlib.Path, rec: dict) -> None:
    cols = np.column_stack([rec["t"], rec["u"], rec["q"]])
    np.savetxt(path, cols, delimiter=",", header="t,u,q", comments="", fmt="%.17g")


def track(
    checkpoint: pathlib.Path, csv: pathlib.Path, out: pathlib.Path
) -> tuple[dict, float, float]:
    """Run the command; (events, loop samples/s, wall seconds)."""
    start = time.perf_counter()
    cmd = [*CLI, "track", str(checkpoint), str(csv), "--out", str(out), "--quiet"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"torchfric track {csv.name} failed: {done.stderr.strip()[-500:]}")
    wall = time.perf_counter() - start
    rate = float(done.stdout.split("(")[1].split(" samples/s")[0].replace(",", ""))
    return json.loads((out / "events.json").read_text()), rate, wall


def bands(out: pathlib.Path, truth: tuple[float, float], change: float | None) -> str:
    """Share of track.csv's rows whose ±2σ band holds the true (M, b): before the change and
    from 10 s after it (the estimate re-converges in between), or over the whole record."""
    with open(out / "track.csv", encoding="utf-8") as f:
        names = f.readline().strip().split(",")
    table = np.loadtxt(out / "track.csv", delimiter=",", skiprows=1, ndmin=2)
    t = table[:, 0]
    inside = [np.abs(table[:, names.index(n)] - x) <= 2 * table[:, names.index(f"{n}_std")]
              for n, x in zip(("inertia", "viscous"), truth, strict=True)]  # fmt: skip
    spans = [t < change, t >= change + 10.0] if change is not None else [t >= t[0]]
    return " → ".join("/".join(f"{100 * ok[s].mean():.0f}" for ok in inside) for s in spans)


def disturbed(axis: AxisParameters) -> AxisParameters:
    return dataclasses.replace(
        axis, disturbance_std=0.02 * axis.coulomb, disturbance_bandwidth=10.0
    )


def changed(axis: AxisParameters) -> AxisParameters:
    """The axis with its dry friction (Fc and Fs) 40 % higher."""
    return dataclasses.replace(axis, coulomb=1.4 * axis.coulomb, static=1.4 * axis.static)


def cached(path: pathlib.Path, make: Any) -> dict:
    """An axis record from `path` (npz), else `make()` saved there."""
    if path.exists():
        with np.load(path) as f:
            return {k: f[k] for k in f.files}
    rec = make()
    np.savez(path, **rec)
    return rec


def identify(folder: pathlib.Path, axis: AxisParameters) -> pathlib.Path:
    """The user's path: ident.csv, ``torchfric init --c-m``, ``torchfric train`` (defaults)."""
    run = folder / "run"
    found = sorted(run.glob("*.pt")) if run.exists() else []
    if found:
        return found[0]
    folder.mkdir(parents=True, exist_ok=True)
    rec = cached(
        folder / "ident.npz",
        lambda: axis_record(axis, seed=IDENT_SEED, duration=30.0, kind="identification"),
    )
    write_csv(folder / "ident.csv", rec)
    for argv in (["init", "ident.csv", "--c-m", repr(axis.c_m), "--out", "cfg.toml", "--force"],
                 ["train", "cfg.toml", "--out", "run", "--quiet", "--overwrite",
                  "--set", "model.dynamic=none"]):  # fmt: skip
        done = subprocess.run([*CLI, *argv], cwd=folder, capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"torchfric {argv[0]} failed: {done.stderr.strip()[-500:]}")
    return sorted(run.glob("*.pt"))[0]


def rig_curve(model, truth: RigParameters) -> float:  # type: ignore[no-untyped-def]
    v = torch.linspace(-8.0, 8.0, 1601, dtype=torch.float64)
    v = v[v.abs() > 0.05]
    with torch.no_grad():
        return 100 * friction_curve_error(model, v, truth.steady_state_friction(v))


def axis_curve(model, truth: AxisParameters, v95: float) -> float:  # type: ignore[no-untyped-def]
    v = np.linspace(-v95, v95, 1601)
    v = v[np.abs(v) > truth.stribeck_velocity / 10]
    ref = torch.as_tensor(true_friction(truth, v))
    with torch.no_grad():
        return 100 * friction_curve_error(model, torch.as_tensor(v), ref)


def row(name: str, rec: dict, events: dict, final: Any, inertia: float, curve: float,
        start: float, rate: float, wall: float, visible: float | None,
        cover: str = "") -> dict:  # fmt: skip
    """One table row; a record with a change carries ``rec["change"]``."""
    changes = events["changes"]
    if "change" not in rec:
        return {"record": name, "samples": rec["t"].size, "delay": None, "visible": None,
                "changed": False,
                "false": len(changes), "inertia": 100 * (float(final.inertia.detach()) / inertia - 1),
                "curve": curve, "start": start, "rate": rate, "wall": wall,
                "cover": cover}  # fmt: skip
    change = float(rec["change"])
    after = [c for c in changes if c >= change]
    return {"record": name, "samples": rec["t"].size, "changed": True,
            "delay": (after[0] - change) if after else None,
            "visible": (after[0] - visible) if after and visible is not None else None,
            "false": len([c for c in changes if c < change]) + max(0, len(after) - 1),
            "inertia": 100 * (float(final.inertia.detach()) / inertia - 1),
            "curve": curve, "start": start, "rate": rate, "wall": wall,
            "cover": cover}  # fmt: skip


def rig_rows(d: pathlib.Path, seeds: list[int], minutes: float,
             checkpoint: pathlib.Path = CHECKPOINT) -> list[dict]:  # fmt: skip
    start = rig_curve(load_checkpoint(checkpoint), RigParameters().changed())
    rows = []
    for seed in seeds:
        rec = changing_record(30.0, 90.0, seed=seed)
        write_csv(d / f"rig_c{seed}.csv", rec)
        events, rate, wall = track(checkpoint, d / f"rig_c{seed}.csv", d / f"rig_c{seed}")
        change = float(rec["change"])
        slow = (rec["t"] >= change) & (np.abs(rec["qdot_true"]) < RigParameters().vs)
        final = load_checkpoint(d / f"rig_c{seed}" / "final.pt")
        rows.append(row(f"rig, change at 30 s, seed {seed}", rec, events, final,
                        RigParameters().inertia, rig_curve(final, RigParameters().changed()),
                        start, rate, wall, float(rec["t"][np.argmax(slow)]),
                        bands(d / f"rig_c{seed}", RIG_TRUTH, change)))  # fmt: skip
    p = RigParameters()
    n = int(minutes * 60 / p.dt)
    quiet = simulate_rig(p, excitation("validation", duration=n * p.dt, seed=QUIET_SEED),
                         seed=QUIET_SEED)  # fmt: skip
    write_csv(d / "rig_quiet.csv", quiet)
    events, rate, wall = track(checkpoint, d / "rig_quiet.csv", d / "rig_quiet")
    final = load_checkpoint(d / "rig_quiet" / "final.pt")
    rows.append(row(f"rig, unchanged, {minutes:g} min", quiet, events, final, p.inertia,
                    rig_curve(final, p), rig_curve(load_checkpoint(checkpoint), p), rate, wall,
                    None, bands(d / "rig_quiet", RIG_TRUTH, None)))  # fmt: skip
    return rows


def axis_rows(name: str, d: pathlib.Path, cache: pathlib.Path, seeds: list[int],
              minutes: float) -> list[dict]:  # fmt: skip
    axis = disturbed(AXES[name])
    later = changed(axis)
    ckpt = identify(cache / name, axis)
    truth = (axis.inertia, axis.viscous)
    model0 = load_checkpoint(ckpt)
    rows = []
    for seed in seeds:
        rec = cached(
            cache / name / f"change{seed}.npz",
            lambda s=seed: axis_record(
                axis, seed=s, duration=BEFORE + AFTER, kind="validation", change=(BEFORE, later)
            ),
        )
        write_csv(d / f"{name}_c{seed}.csv", rec)
        events, rate, wall = track(ckpt, d / f"{name}_c{seed}.csv", d / f"{name}_c{seed}")
        change = float(rec["change"])
        v95 = float(np.quantile(np.abs(rec["qdot_true"]), 0.95))
        sliding = (rec["t"] >= change) & (np.abs(rec["qdot_true"]) > 0.1 * axis.stribeck_velocity)
        final = load_checkpoint(d / f"{name}_c{seed}" / "final.pt")
        rows.append(row(f"{name}, change at {BEFORE:g} s, seed {seed}", rec, events, final,
                        axis.inertia, axis_curve(final, later, v95),
                        axis_curve(model0, later, v95), rate, wall,
                        float(rec["t"][np.argmax(sliding)]),
                        bands(d / f"{name}_c{seed}", truth, change)))  # fmt: skip
    quiet = cached(
        cache / name / f"quiet{minutes:g}.npz",
        lambda: axis_record(axis, seed=QUIET_SEED, duration=minutes * 60, kind="validation"),
    )
    write_csv(d / f"{name}_quiet.csv", quiet)
    events, rate, wall = track(ckpt, d / f"{name}_quiet.csv", d / f"{name}_quiet")
    final = load_checkpoint(d / f"{name}_quiet" / "final.pt")
    v95 = float(np.quantile(np.abs(quiet["qdot_true"]), 0.95))
    rows.append(row(f"{name}, unchanged, {minutes:g} min", quiet, events, final, axis.inertia,
                    axis_curve(final, axis, v95), axis_curve(model0, axis, v95), rate, wall,
                    None, bands(d / f"{name}_quiet", truth, None)))  # fmt: skip
    return rows


def carriage_curve(model, gain: float, v95: float) -> float:  # type: ignore[no-untyped-def]
    """The steady-state curve's RMS error against the carriage's (Fc, Fs × gain) over ±v95."""
    v = np.linspace(-v95, v95, 1601)
    v = v[np.abs(v) > carriage.VS / 10]
    fs = carriage.FS_DEFAULT * gain
    ref = torch.as_tensor([carriage.friction(x, fs, gain * carriage.FC) for x in v])
    with torch.no_grad():
        return 100 * friction_curve_error(model, torch.as_tensor(v), ref)


def carriage_rows(d: pathlib.Path, cache: pathlib.Path, seeds: list[int],
                  minutes: float) -> list[dict]:  # fmt: skip
    """The stick-slip carriage: a user's model from its lab-style record, then `track`."""
    folder = cache / "carriage"
    folder.mkdir(parents=True, exist_ok=True)
    fs, dist = carriage.FS_DEFAULT, carriage.DIST_DEFAULT

    def record(name: str, seconds: float, seed: int, change: tuple[float, float] | None) -> dict:
        path = folder / f"{name}.npz"
        if not path.exists():
            t, u, c, v = carriage.simulate(seconds, seed, fs, dist, change=change)
            np.savez(path, t=t, u=u, counts=c, v=v)
        with np.load(path) as f:
            rec = {k: f[k] for k in f.files}
        carriage.write(folder / f"{name}.csv", rec["t"], rec["u"], rec["counts"])
        return rec

    run = folder / "run"
    if not sorted(run.glob("*.pt")):
        record("ident", 30.0, IDENT_SEED, None)
        for argv in (["init", "ident.csv", "--c-m", "12", "--counts-per-m", "1e6", "--out",
                      "cfg.toml", "--force"],
                     ["train", "cfg.toml", "--out", "run", "--quiet", "--overwrite",
                      "--set", "model.dynamic=none"]):  # fmt: skip
            done = subprocess.run([*CLI, *argv], cwd=folder, capture_output=True, text=True)
            if done.returncode != 0:
                raise SystemExit(f"torchfric {argv[0]} failed: {done.stderr.strip()[-500:]}")
    ckpt = sorted(run.glob("*.pt"))[0]
    model0 = load_checkpoint(ckpt)
    rows = []
    for seed in seeds:
        rec = record(f"change{seed}", BEFORE + AFTER, 300 + seed, (BEFORE, 1.4))
        rec = {"t": rec["t"], "change": np.float64(BEFORE), "v": rec["v"]}
        events, rate, wall = track(ckpt, folder / f"change{seed}.csv", d / f"carriage_c{seed}")
        v95 = float(np.quantile(np.abs(rec["v"]), 0.95))
        sliding = (rec["t"] >= BEFORE) & (np.abs(rec["v"]) > 0.1 * carriage.VS)
        final = load_checkpoint(d / f"carriage_c{seed}" / "final.pt")
        rows.append(row(f"carriage, change at {BEFORE:g} s, seed {seed}", rec, events, final,
                        carriage.M, carriage_curve(final, 1.4, v95),
                        carriage_curve(model0, 1.4, v95), rate, wall,
                        float(rec["t"][np.argmax(sliding)]),
                        bands(d / f"carriage_c{seed}", (carriage.M, carriage.B), BEFORE)))  # fmt: skip
    quiet = record(f"quiet{minutes:g}", minutes * 60, QUIET_SEED, None)
    events, rate, wall = track(ckpt, folder / f"quiet{minutes:g}.csv", d / "carriage_quiet")
    final = load_checkpoint(d / "carriage_quiet" / "final.pt")
    v95 = float(np.quantile(np.abs(quiet["v"]), 0.95))
    rows.append(row(f"carriage, unchanged, {minutes:g} min", {"t": quiet["t"]}, events, final,
                    carriage.M, carriage_curve(final, 1.0, v95),
                    carriage_curve(model0, 1.0, v95), rate, wall, None,
                    bands(d / "carriage_quiet", (carriage.M, carriage.B), None)))  # fmt: skip
    return rows


MACHINES = ["rig", *AXES, "carriage"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", nargs="+", choices=MACHINES, default=MACHINES)
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2])
    ap.add_argument("--quiet-minutes", type=float, default=10.0)
    ap.add_argument("--cache", type=pathlib.Path, default=None,
                    help="folder for the axes' models and records, reused by later runs "
                    "(default: a fresh temporary folder)")  # fmt: skip
    ap.add_argument("--rig-checkpoint", type=pathlib.Path, default=CHECKPOINT,
                    help="the rig's model (default: the committed checkpoints/arm_tanh_ekf.pt; "
                    "a checkpoint of `torchfric train experiments/configs/arm_tanh_ekf.toml` "
                    "carries the run's two covariances)")  # fmt: skip
    ap.add_argument("--keep", type=pathlib.Path, default=None,
                    help="folder that keeps each record's CSV and its track output (track.csv, "
                    "track.png, final.pt) to look at (default: a temporary folder)")  # fmt: skip
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        d = args.keep or pathlib.Path(tmp)
        d.mkdir(parents=True, exist_ok=True)
        cache = args.cache or d / "cache"
        cache.mkdir(parents=True, exist_ok=True)
        for m in args.machines:
            if m == "rig":
                rows += rig_rows(d, args.seeds, args.quiet_minutes, args.rig_checkpoint)
            elif m == "carriage":
                rows += carriage_rows(d, cache, args.seeds, args.quiet_minutes)
            else:
                rows += axis_rows(m, d, cache, args.seeds, args.quiet_minutes)
    print("| record | samples | detection delay | after exciting motion | false alarms | "
          "final inertia | final curve (start) | loop samples/s | command | "
          "M / b in ±2σ, % of rows |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        delay = f"{r['delay']:.2f} s" if r["delay"] is not None else "–"
        visible = f"{r['visible']:+.2f} s" if r["visible"] is not None else "–"
        if r["changed"] and r["delay"] is None:
            delay = "missed"
        print(
            f"| {r['record']} | {r['samples']:,} | {delay} | {visible} | {r['false']} | "
            f"{r['inertia']:+.2f} % | {r['curve']:.2f} % ({r['start']:.2f} %) | "
            f"{r['rate']:,.0f} | {r['wall']:.1f} s | {r['cover']} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
