"""How output error depends on the initial guess, alone and after the EKF (issue 5). Prints a table.

    python benchmarks/oe_starts.py                   # 10 starts, tanh(3) (about 15 min here)
    python benchmarks/oe_starts.py --starts 3 --lbfgs 10 --json starts.json

Starts: `--starts` initial guesses of the tanh(3) arm model drawn over the issue-9 box around the
configs' constant guesses (`experiments/configs/arm_tanh_ekf.toml` with ``model.init = "config"``:
M 0.03, b 0.01, default friction parameters), every parameter scaled by a log-uniform factor in
[1/3, 3] (`torchfric.estimators.ensemble.random_thetas`; start 0 is the guess itself). From each start:

- **OE alone**: output error on the rig's identification data (30 s at 1 kHz) at full length, by
  L-BFGS (`--lbfgs` iterations, strong-Wolfe line search) on the normalised q and q̇ simulation
  error, through the compiled engine (exact discrete gradient), RK4 sub-steps chosen from the
  start (`substeps = "auto"`). Full length, because that is the criterion that is scored; the
  windowed Adam of the `arm_tanh_oe` config needs a good start to keep windows and simulation
  consistent.
- **EKF, then OE**: the iterative EKF with the paper's tuning (10 passes, compiled) from the same
  start, then the same OE from the EKF's model.

Every result is simulated open loop on the validation and extrapolation experiments (neither
steers anything: no early stopping here) and compared with the truth: inertia and the friction
curve over the excited range (as `benchmarks/ekf_rig.py`). Times are wall-clock per run on this
machine, compiles included (the OE engine compiles once per process; every EKF compiles anew).
"""

from __future__ import annotations

import argparse
import copy
import json
import pathlib
import statistics
import time

import torch
from ekf_rig import friction_reference  # (this folder, run as a script)

from torchfric import EKFTuning, identify_ekf, identify_output_error
from torchfric.app.config import Config
from torchfric.app.run import initial_model, load_data
from torchfric.data.rig import RigParameters
from torchfric.errors import TorchfricError
from torchfric.estimators.ensemble import random_thetas
from torchfric.estimators.metrics import friction_curve_error, score_simulation
from torchfric.estimators.output_error import OETuning

ROOT = pathlib.Path(__file__).resolve().parents[1]


def score(model, val, extra, v, ref) -> dict:  # type: ignore[no-untyped-def]
    truth = RigParameters().inertia
    sv = score_simulation(model, val, engine="compiled")
    se = score_simulation(model, extra, engine="compiled")
    return {
        "inertia_err_%": 100 * (float(model.inertia.detach()) / truth - 1),
        "friction_err_%": 100 * friction_curve_error(model, v, ref),
        "val_fit_q": sv.fit_q,
        "val_fit_qdot": sv.fit_qdot,
        "extra_fit_q": se.fit_q,
        "extra_fit_qdot": se.fit_qdot,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--starts", type=int, default=10)
    p.add_argument("--lbfgs", type=int, default=30, help="L-BFGS iterations of each OE run")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=pathlib.Path)
    args = p.parse_args()
    torch.set_num_threads(1)
    cfg = Config.load(
        ROOT / "experiments" / "configs" / "arm_tanh_ekf.toml",
        ["model.init=config", 'data.test=["rig:extrapolation"]'],
    )
    train, vals, tests, _ = load_data(cfg)
    val, extra = vals[0], tests[0]
    guess, _ = initial_model(cfg, train)
    thetas = random_thetas(
        guess, guess.get_theta(), args.starts, 3.0, torch.Generator().manual_seed(args.seed)
    )
    v, ref = friction_reference(train)
    oe = OETuning(epochs=0, window=0, lbfgs_steps=args.lbfgs, substeps="auto", compile=True)
    ekf = EKFTuning(compile=True)
    rows = []
    for i, th in enumerate(thetas):
        start = copy.deepcopy(guess).set_theta(th)
        for method in ("oe", "ekf+oe"):
            t0 = time.perf_counter()
            row: dict = {"start": i, "method": method}
            try:
                model = start
                if method == "ekf+oe":
                    model = identify_ekf(start, train, ekf).model
                    row["ekf"] = score(model, val, extra, v, ref)
                    row["ekf_seconds"] = time.perf_counter() - t0
                model = identify_output_error(model, train, oe).model
                with torch.no_grad():
                    row.update(score(model, val, extra, v, ref))
                row["status"] = "ok"
            except TorchfricError as err:  # a diverged filter or an unsimulatable start
                row["status"] = f"failed: {err}"
            row["seconds"] = time.perf_counter() - t0
            rows.append(row)
            print(json.dumps(row), flush=True)
            if args.json:
                args.json.write_text(json.dumps(rows, indent=2))
    print()
    print(
        f"{args.starts} starts (×/÷ 3 box around the configs' constant guess), tanh(3), rig data; "
        f"OE = full-length L-BFGS ({args.lbfgs} iterations)"
    )
    head = (
        "| method | runs ok | inertia ≤ 1 % | inertia ≤ 1 % and curve ≤ 5 % | validation FIT q: min / median / max "
        "| validation FIT q̇: min / median / max | extrapolation FIT q: min / median / max | time per run: median |"
    )
    print(head)
    print("|" + "---|" * (head.count("|") - 1))

    def spread(xs: list[float]) -> str:
        return f"{min(xs):.1f} / {statistics.median(xs):.1f} / {max(xs):.1f} %" if xs else "–"

    first = [r["ekf"] | {"seconds": r["ekf_seconds"]} for r in rows if "ekf" in r]
    groups = [("EKF alone (the EKF+OE runs' first stage)", first)]
    groups += [
        (m, [r for r in rows if r["method"] == m and r["status"] == "ok"]) for m in ("oe", "ekf+oe")
    ]
    for name, ok in groups:
        n_all = args.starts
        print(
            f"| {name} | {len(ok)} / {n_all} | "
            f"{sum(abs(r['inertia_err_%']) <= 1 for r in ok)} | "
            f"{sum(abs(r['inertia_err_%']) <= 1 and r['friction_err_%'] <= 5 for r in ok)} | "
            f"{spread([r['val_fit_q'] for r in ok])} | {spread([r['val_fit_qdot'] for r in ok])} | "
            f"{spread([r['extra_fit_q'] for r in ok])} | "
            f"{statistics.median([r['seconds'] for r in ok]) if ok else float('nan'):.0f} s |"
        )


if __name__ == "__main__":
    main()
