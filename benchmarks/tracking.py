"""On-line tracking on the synthetic rig (issue 24): detection delay, false alarms, the estimate
after a change, throughput. Prints a table.

    python benchmarks/tracking.py                 # 3 change records + 10 min unchanged (~1 min)
    python benchmarks/tracking.py --seeds 0 1 2 3 4 --quiet-minutes 30

Every row runs the real command, ``torchfric track checkpoints/arm_tanh_ekf.pt REC.csv --out
DIR`` (the paper's tanh(3) EKF checkpoint, default ``[track]`` settings), on records written by
`torchfric.data.rig.changing_record`:

- change: 30 s of the identified (nominal) rig, then 90 s of the rig "after maintenance" (no
  static friction), one continuous record (the state carried across the change). Reported: the
  detection delay after the change, and after the arm first runs slower than the Stribeck
  velocity (0.5 rad/s) once the change happened — the two systems differ only there, so a
  change made while the arm slides fast cannot show before; false alarms (detections before the change, or more than one after it), the
  final inertia against the truth and the final steady-state curve's RMS error against the
  new truth (over ±8 rad/s, |q̇| > 0.05, in % of its peak; the starting model's error in
  brackets);
- unchanged: the nominal rig for the given minutes: false alarms.

Throughput: samples per second of the tracking loop itself (filter, detector, rows; the
command's own count) and of the whole command (start-up, outputs), one core.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch

from torchfric import load_checkpoint
from torchfric.data.rig import RigParameters, changing_record, excitation, simulate_rig
from torchfric.estimators.metrics import friction_curve_error

ROOT = pathlib.Path(__file__).resolve().parents[1]
CHECKPOINT = ROOT / "checkpoints" / "arm_tanh_ekf.pt"


def write_csv(path: pathlib.Path, rec: dict) -> None:
    cols = np.column_stack([rec["t"], rec["u"], rec["q"]])
    np.savetxt(path, cols, delimiter=",", header="t,u,q", comments="", fmt="%.17g")


def track(csv: pathlib.Path, out: pathlib.Path) -> tuple[dict, float, float]:
    """Run the command; (events, loop samples/s, wall seconds)."""
    start = time.perf_counter()
    cmd = [sys.executable, "-m", "torchfric", "track", str(CHECKPOINT), str(csv), "--out",
           str(out), "--quiet"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - start
    rate = float(done.stdout.split("(")[1].split(" samples/s")[0].replace(",", ""))
    return json.loads((out / "events.json").read_text()), rate, wall


def curve_error(model, truth: RigParameters) -> float:  # type: ignore[no-untyped-def]
    v = torch.linspace(-8.0, 8.0, 1601, dtype=torch.float64)
    v = v[v.abs() > 0.05]
    with torch.no_grad():
        return 100 * friction_curve_error(model, v, truth.steady_state_friction(v))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2])
    ap.add_argument("--quiet-minutes", type=float, default=10.0)
    args = ap.parse_args(argv)
    start_err = curve_error(load_checkpoint(CHECKPOINT), RigParameters().changed())
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        d = pathlib.Path(tmp)
        for seed in args.seeds:
            rec = changing_record(30.0, 90.0, seed=seed)
            write_csv(d / f"c{seed}.csv", rec)
            events, rate, wall = track(d / f"c{seed}.csv", d / f"c{seed}")
            change = float(rec["change"])
            slow = (rec["t"] >= change) & (np.abs(rec["qdot_true"]) < RigParameters().vs)
            visible = float(rec["t"][np.argmax(slow)])
            after = [c for c in events["changes"] if c >= change]
            false = len([c for c in events["changes"] if c < change]) + max(0, len(after) - 1)
            final = load_checkpoint(d / f"c{seed}" / "final.pt")
            rows.append({
                "record": f"change at 30 s, seed {seed}", "samples": rec["t"].size,
                "delay": (after[0] - change) if after else None, "false": false,
                "visible": (after[0] - visible) if after else None,
                "inertia": 100 * (float(final.inertia.detach()) / RigParameters().inertia - 1),
                "curve": curve_error(final, RigParameters().changed()), "rate": rate, "wall": wall,
            })  # fmt: skip
        p = RigParameters()
        n = int(args.quiet_minutes * 60 / p.dt)
        u = excitation("validation", duration=n * p.dt, seed=7)
        quiet = simulate_rig(p, u, seed=7)
        write_csv(d / "quiet.csv", quiet)
        events, rate, wall = track(d / "quiet.csv", d / "quiet")
        final = load_checkpoint(d / "quiet" / "final.pt")
        rows.append({
            "record": f"unchanged, {args.quiet_minutes:g} min", "samples": n, "delay": None,
            "visible": None,
            "false": len(events["changes"]),
            "inertia": 100 * (float(final.inertia.detach()) / p.inertia - 1),
            "curve": curve_error(final, p), "rate": rate, "wall": wall,
        })  # fmt: skip
    print("| record | samples | detection delay | after the first slow motion | false alarms | "
          "final inertia | final curve (vs the truth after the change) | loop samples/s | "
          "command |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        delay = f"{r['delay']:.2f} s" if r["delay"] is not None else "–"
        visible = f"{r['visible']:+.2f} s" if r["visible"] is not None else "–"
        note = f" (start {start_err:.2f} %)" if r["delay"] is not None else ""
        print(
            f"| {r['record']} | {r['samples']:,} | {delay} | {visible} | {r['false']} | "
            f"{r['inertia']:+.2f} % | {r['curve']:.2f} %{note} | {r['rate']:,.0f} "
            f"({r['rate'] / 1000:.0f}× real time) | {r['wall']:.1f} s |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
