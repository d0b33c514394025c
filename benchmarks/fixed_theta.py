"""The prediction-error stage's fixed-θ filters (issue 34): the filter on the states alone
(`make_fixed_theta_step`, what `torchfric.estimators.covariance` runs) against the augmented
step with P_θθ = 0 (what it ran before), the same data and θ, measured in one run. Prints one
table: K filters, filter-steps/s of each, and the largest difference of their innovations
and variances (0: the same numbers bit for bit).

    python benchmarks/fixed_theta.py              # about a minute on 2 cores
    python benchmarks/fixed_theta.py --members 1 8 64 --repeat 7

The data are the rig's 30 s identification record (29,999 filtered samples), the model the
committed quick-start checkpoint (tanh(3), k = 8), q measured alone (the stage's form), and the
K parameter vectors that checkpoint's θ with a 1e-4 random offset each. Times are the best of
`--repeat` calls after one warm-up call (the generated C built and cached first).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import pathlib

import torch
from releases import best

from torchfric.accel import CHUNK, compile_step, iter_chunks, step_key
from torchfric.app.artifacts import load_checkpoint
from torchfric.app.config import Config
from torchfric.app.run import load_data
from torchfric.environment import torch_settings
from torchfric.estimators.covariance import FIXED_CHUNK, innovations
from torchfric.estimators.ensemble import make_batched_step
from torchfric.estimators.passes import initial_belief, measured_data

ROOT = pathlib.Path(__file__).resolve().parents[1]


def augmented_innovations(model, experiments, tuning, thetas, step):  # type: ignore[no-untyped-def]
    """e and S of each θ's filter by the augmented step with P_θθ = 0 and no process noise on θ
    (the prediction-error stage before the states-only step), chunks of `CHUNK` samples."""
    K, k = thetas.shape
    Q, P0_xx, H, R = tuning.matrices(k, model.state_size)
    Q = Q.clone()
    Q[model.state_size :, model.state_size :] = 0.0
    Qk, Rk = Q.expand(K, *Q.shape).contiguous(), R.expand(K, *R.shape).contiguous()
    bound = torch.tensor(1e300, dtype=torch.float64)
    out = []
    for exp, u, y in measured_data(list(experiments), tuning.measure):
        x, P = initial_belief(exp, thetas, torch.zeros(K, k, k, dtype=torch.float64), P0_xx)
        e_t, S_t = torch.empty(exp.n - 1, K), torch.empty(exp.n - 1, K)
        consts = (torch.tensor(exp.dt, dtype=torch.float64), Qk, H, Rk, bound)
        for i, n, xs, valid in iter_chunks((u[:-1], y[1:]), step.size):
            (x, P), (e, nis, ll, _) = step.chunk((x, P), xs, valid, consts)
            e_t[i : i + n] = e[:n, :, 0]
            S_t[i : i + n] = (-2.0 * ll[:n] - nis[:n] - math.log(2.0 * math.pi)).exp()
        out.append((e_t, S_t))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--members", type=int, nargs="+", default=[1, 8, 17, 64])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    with torch_settings():
        cfg = Config.load(ROOT / "experiments" / "configs" / "arm_tanh_ekf.toml")
        train, *_ = load_data(cfg)
        model = load_checkpoint(ROOT / "checkpoints" / "arm_tanh_ekf.pt")
        tuning = cfg.estimator.ekf_tuning().resolved(train)
        tuning = dataclasses.replace(tuning, measure="position", r=(tuning.r[0],))
        batched = make_batched_step(model, tuning.substeps)
        aug = compile_step(batched, carry=2, members=True, size=CHUNK,
                           member_consts=(False, True, False, True, False),
                           key=step_key("fixed-θ batch", batched.key))  # fmt: skip
        samples = sum(e.n - 1 for e in train)
        theta = model.get_theta()
        g = torch.Generator().manual_seed(0)
        print(f"rig identification record, {samples:,} samples; tanh(3), k = {theta.numel()}; "
              f"best of {args.repeat}")  # fmt: skip
        print("| K filters | augmented step, P_θθ = 0, chunks of 1000 | states only, chunks of "
              f"{FIXED_CHUNK} | speed-up | max abs. difference e, S |")  # fmt: skip
        print("|---|---|---|---|---|")
        for K in args.members:
            thetas = theta + 1e-4 * torch.randn(K, theta.numel(), generator=g, dtype=torch.float64)
            t_old, old = best(lambda th=thetas: augmented_innovations(model, train, tuning, th, aug),
                              args.repeat)  # fmt: skip
            t_new, new = best(lambda th=thetas: innovations(model, train, tuning, th), args.repeat)
            diff = max(
                max(float((eo - en[1:]).abs().max()), float((so - sn[1:]).abs().max()))
                for (eo, so), (en, sn) in zip(old, new, strict=True)  # type: ignore[arg-type]
            )
            rate_old, rate_new = K * samples / t_old, K * samples / t_new
            print(f"| {K} | {rate_old / 1e6:.2f} M/s | {rate_new / 1e6:.2f} M/s | "
                  f"{t_old / t_new:.2f}× | {diff:.1e} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
