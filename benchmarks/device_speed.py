"""Ensembles on the CPU and on a CUDA GPU (issue 34, part 3). Prints tables; every number is
measured in this run, on this machine.

    python benchmarks/device_speed.py                       # CPU rows; GPU rows where CUDA is seen
    python benchmarks/device_speed.py --members 9 100 1000 10000 --samples 30000 --json out.json

Sections:
1. The ensemble's masked step (`torchfric.estimators.ensemble.make_masked_step`, compiled
   chunks of 1000 samples, as `identify_ekf_ensemble` runs them) over the rig's identification
   record, tanh(3), for K filters: filter-steps/s on the CPU (generated C, four members per SIMD
   vector, members split across this machine's cores) and on the GPU (``device="cuda"``: the same
   generated step as a CUDA kernel, one member per thread, one launch per chunk), each with its
   first call (trace and build) apart; and how far the GPU's final beliefs are from the CPU's
   (max relative difference of θ and of P over all members).
2. `identify_ekf_ensemble` end to end for a big batch (``--e2e-members`` random starts, 1000 by
   default, ×/÷ 1.5 around the pre-fit), 2 passes, on the CPU and with ``device="cuda"``:
   seconds, filter-steps/s and the largest relative difference of the members' θ.

A run keeps batches under `torchfric.accel.native.cuda.MEMBERS_PER_CORE` members per CPU core on
the CPU, where they are faster; section 1 lifts that rule to measure every size on the GPU.

Without a CUDA device the GPU columns say so and nothing fails (``--device cuda`` in a run is
then refused with a one-line message; `torchfric.app.run.device_named`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ekf_speed import initial, rig_data, tuning  # noqa: E402

from torchfric import ArmModel, make_friction  # noqa: E402
from torchfric.accel.native import cuda  # noqa: E402
from torchfric.estimators.ensemble import (  # noqa: E402
    identify_ekf_ensemble,
    make_masked_step,
    random_thetas,
)
from torchfric.estimators.identify import EKFTuning  # noqa: E402
from torchfric.estimators.prefit import prefit  # noqa: E402

F64 = torch.float64


def start_model(exp) -> ArmModel:  # type: ignore[no-untyped-def]
    model = ArmModel(make_friction("tanh", 3), inertia=0.03, viscous=0.01, c_m=16.0)
    prefit(model, [exp])
    return model


def masked_pass(model: ArmModel, exp, K: int, n: int, device: torch.device | None):  # type: ignore[no-untyped-def]
    """(filter-steps/s, first-call s, final carry on the CPU, path) of `n` samples of the masked
    step for K members, chunk by chunk as `identify_ekf_ensemble` feeds it."""
    k = model.num_parameters
    Q, H, R = tuning(k)
    th = random_thetas(model, model.get_theta(), K, 1.5, torch.Generator().manual_seed(0))
    st = initial(model, exp)
    x = torch.cat([st.x[:2].expand(K, 2), th], 1)
    P = st.P.expand(K, -1, -1).clone()
    Qk, Rk = Q.expand(K, -1, -1).clone(), R.expand(K, -1, -1).clone()
    step = make_masked_step(model, 1, compile=True, device=device)
    carry = (x, P, torch.ones(K, dtype=torch.bool), torch.full((K,), -1),
             torch.zeros(K, 2, dtype=F64), torch.zeros(K, dtype=F64), torch.zeros(K, dtype=F64))  # fmt: skip
    u, y = exp.u.to(F64), torch.stack([exp.q, exp.qdot], -1).to(F64)
    dt, bound = torch.tensor(exp.dt, dtype=F64), torch.tensor(1e6, dtype=F64)
    C, index = step.size, torch.arange(exp.n)
    valid = torch.ones(C, dtype=torch.bool)

    def chunk(carry, j0):  # type: ignore[no-untyped-def]
        sl = slice(j0, j0 + C)
        xs = (index[sl], u[j0 - 1 : j0 - 1 + C], y[sl])
        return step.chunk(carry, xs, valid, (dt, Qk, H, Rk, bound))[0]

    rule, cuda.MEMBERS_PER_CORE = cuda.MEMBERS_PER_CORE, 0  # every size on the GPU here
    try:
        return _timed(chunk, carry, K, n, C) + (step.chunk.path,)
    finally:
        cuda.MEMBERS_PER_CORE = rule


def _timed(chunk, carry, K: int, n: int, C: int):  # type: ignore[no-untyped-def]
    t0 = time.perf_counter()
    first_carry = chunk(carry, 1)
    bool(first_carry[2].all())  # waits for the device
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for j0 in range(1, 1 + n, C):
        carry = chunk(carry, j0)
    bool(carry[2].all())
    seconds = time.perf_counter() - t0
    rate = K * len(range(1, 1 + n, C)) * C / seconds
    return rate, first, tuple(c.cpu() for c in carry)


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(((a - b).abs() / b.abs().clamp_min(1e-300)).max())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, nargs="+", default=[9, 100, 1000])
    ap.add_argument("--samples", type=int, default=30000, help="samples per pass (≤ the record)")
    ap.add_argument("--passes", type=int, default=2, help="passes of the end-to-end section")
    ap.add_argument("--e2e-members", type=int, default=1000, help="filters of that section")
    ap.add_argument(
        "--skip-cpu-above",
        type=int,
        default=10**9,
        help="no CPU row for ensembles larger than this (minutes on 2 cores)",
    )
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_default_dtype(F64)
    torch.set_num_threads(1)
    gpu = torch.device("cuda") if torch.cuda.is_available() else None
    exp = rig_data()
    n = min(args.samples, exp.n - 1001)
    model = start_model(exp)
    cores = len(os.sched_getaffinity(0))
    where = torch.cuda.get_device_name(0) if gpu else "no CUDA device"
    print(
        f"# tanh(3), k = {model.num_parameters}, {n} samples a pass; CPU: {cores} core(s); "
        f"GPU: {where}; torch {torch.__version__}\n"
    )
    rows = []
    print(
        "| K filters | CPU filter-steps/s (first call s) | GPU filter-steps/s (first call s) "
        "| GPU / CPU | max rel. diff θ, P (GPU vs CPU) |"
    )
    print("|---|---|---|---|---|")
    for K in args.members:
        row: dict = {"K": K}
        cpu = None
        if K <= args.skip_cpu_above:
            r, first, cpu, path = masked_pass(model, exp, K, n, None)
            row.update(cpu_rate=r, cpu_first=first, cpu_path=path)
        if gpu is not None:
            r, first, dev, path = masked_pass(model, exp, K, n, gpu)
            row.update(gpu_rate=r, gpu_first=first, gpu_path=path)
            if cpu is not None:
                row["diff_theta"] = rel(dev[0][:, 2:], cpu[0][:, 2:])
                row["diff_P"] = float((dev[1] - cpu[1]).abs().max() / cpu[1].abs().max())
        rows.append(row)
        c = (f"{row['cpu_rate'] / 1e6:.2f} M ({row['cpu_first']:.2f}, {row['cpu_path']})"
             if "cpu_rate" in row else "not run")  # fmt: skip
        g = (f"{row['gpu_rate'] / 1e6:.2f} M ({row['gpu_first']:.2f}, {row['gpu_path']})"
             if "gpu_rate" in row else "no CUDA device")  # fmt: skip
        ratio = (
            f"{row['gpu_rate'] / row['cpu_rate']:.2f}×"
            if "gpu_rate" in row and "cpu_rate" in row
            else ""
        )
        d = f"{row['diff_theta']:.1e}, {row['diff_P']:.1e}" if "diff_theta" in row else ""
        print(f"| {K} | {c} | {g} | {ratio} | {d} |", flush=True)
    print()
    end = {}
    m0 = start_model(exp)
    th = random_thetas(m0, m0.get_theta(), args.e2e_members, 1.5, torch.Generator().manual_seed(1))
    ones = torch.ones(args.e2e_members, dtype=F64)
    tune = EKFTuning(passes=args.passes, tolerance=0.0)
    for name, device in (("cpu", None), ("cuda", gpu)):
        if name == "cuda" and gpu is None:
            continue
        m = start_model(exp)
        t0 = time.perf_counter()
        res = identify_ekf_ensemble(m, exp, tune, members=(th, ones, ones), device=device)
        end[name] = {"seconds": time.perf_counter() - t0, "thetas": res.thetas,
                     "rate": res.summary()["filter_steps_per_second"]}  # fmt: skip
    print(
        f"identify_ekf_ensemble, {args.e2e_members} filters, {args.passes} passes over {exp.n} "
        "samples (with the selection's simulations, on the CPU):"
    )
    for name, r in end.items():
        print(f"  {name}: {r['seconds']:.2f} s, {r['rate'] / 1e6:.2f} M filter-steps/s")
    if "cuda" in end:
        print(
            f"  max relative difference of the members' θ, GPU vs CPU: "
            f"{rel(end['cuda']['thetas'], end['cpu']['thetas']):.1e}"
        )
    if args.json:
        out = {"rows": rows, "end_to_end": {k: {"seconds": v["seconds"], "rate": v["rate"]}
                                            for k, v in end.items()}}  # fmt: skip
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=2)


if __name__ == "__main__":
    main()
