"""Output error: backpropagation through the solver, the adjoint method and the compiled engine
(issues 5 and 8).

    python benchmarks/oe_adjoint.py                  # N = 1k, 4k, 16k, 30k samples (≈ 12 min)
    python benchmarks/oe_adjoint.py --samples 1000 4000 --json adjoint.json

For each horizon N (full-length simulation of the first N samples of the synthetic rig's
identification experiment, tanh(3) pre-fit, RK4 with one sub-step) and each gradient method, a
fresh Python process computes the output-error loss and its gradient once to warm up, then once
more timed. Reported: seconds for the loss + gradient, the peak resident memory of that process,
and its growth over the process's resident memory before any gradient (what the gradient itself
costs), plus the largest relative difference between the two methods' gradients.

Methods: "backprop" (torchdiffeq's rk4, autograd through every stage), "adjoint"
(`torchdiffeq.odeint_adjoint`) and "compiled" (`simulate(..., engine="compiled")`, what
`estimator.compile = true` uses for full-length output error: the same rk4 steps as a compiled
scan and the exact discrete gradient by a compiled reverse scan with the VJP of one step). The
warm-up call's time is reported too: for "compiled" it includes the one-time compile.

Backpropagation stores every solver stage for the backward pass: memory grows linearly with N.
The adjoint method (`torchdiffeq.odeint_adjoint`) integrates an augmented system backwards
instead: memory independent of N, at the price of a second integration (and an RK4-sized error in
the gradient, since the backward integration is not the discrete forward map's exact transpose).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

_CHILD = r"""
import json, resource, sys, time
import torch
torch.set_num_threads(1)
from torchfric.app.config import Config
from torchfric.estimators.shooting import full_loss as _full_loss, prepare as _prepare, scales as _scales
from torchfric.estimators.prefit import prefit
from torchfric.app.run import config_model, load_data

n, method = int(sys.argv[1]), sys.argv[2]
adjoint, engine = method == "adjoint", "compiled" if method == "compiled" else "odeint"
cfg = Config.loads('[data]\ntrain = ["rig:identification"]\nvalidation = []\n[model]\nc_m = 16.0\n')
exps = load_data(cfg)[0]
model = prefit(config_model(cfg, exps), exps).model
data = _prepare([exps[0].slice(0, n)], "identification")
scale, w = _scales(data), torch.tensor([1.0, 1.0], dtype=torch.float64)

def grad():
    theta = model.get_theta().requires_grad_(True)
    loss = _full_loss(model, data, theta, 1, scale, w, adjoint, engine)
    loss.backward()
    return theta.grad

def rss_mb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")

before = rss_mb()  # data and model in memory, no gradient yet
t0 = time.perf_counter()
grad()  # warm-up (first-call costs: the compile), same size as the timed call
first = time.perf_counter() - t0
t0 = time.perf_counter()
g = grad()
seconds = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"seconds": seconds, "first_seconds": first, "peak_mb": peak, "before_mb": before, "grad": g.tolist()}))
"""


def measure(n: int, method: str) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(n), method], capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, nargs="+", default=[1000, 4000, 16000, 30000])
    ap.add_argument("--json", help="also write the rows to this file")
    args = ap.parse_args()
    rows = []
    print("| samples N | method | loss + gradient [s] | first call [s] | peak RSS [MB] | growth over pre-call RSS [MB] | max rel. difference to backprop's gradient |")
    print("|---|---|---|---|---|---|---|")
    for n in args.samples:
        res = {m: measure(n, m) for m in ("backprop", "adjoint", "compiled")}
        gb = res["backprop"]["grad"]
        for m, r in res.items():
            diff = max(abs(a - b) / max(abs(b), 1e-12) for a, b in zip(r["grad"], gb, strict=True))
            growth = r["peak_mb"] - r["before_mb"]
            rows.append({"samples": n, "method": m,
                         **{k: r[k] for k in ("seconds", "first_seconds", "peak_mb")},
                         "growth_mb": growth, "grad_rel_diff": diff})  # fmt: skip
            print(f"| {n} | {m} | {r['seconds']:.2f} | {r['first_seconds']:.1f} | "
                  f"{r['peak_mb']:.0f} | {max(growth, 0):.0f} | {diff:.1e} |")  # fmt: skip
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
