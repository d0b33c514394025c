"""What to do with the parameter covariance P_θθ between passes, measured (issue 9). Prints a table.

    python benchmarks/p_theta_policy.py              # about 5 min here
    python benchmarks/p_theta_policy.py --passes 4 --models tanh

The iterative off-line EKF (paper §4) re-filters the same data: after each pass the state part
of the belief is reset and θ carries over. What P_θθ does at that point decides whether the
passes converge. Policies compared, each from the pre-fit with the paper's tuning on the rig's
identification data (30 s, 1 kHz), no rollback (so that every policy shows what it does):

* `carry` (torchfric's policy): P_θθ at the end of the pass starts the next one. The filter
  then treats a re-run as more data, so P_θθ keeps shrinking and the steps get smaller.
* `reset`: P_θθ back to P0 at every pass (re-inflation: every pass is a first pass from the
  previous θ).
* `inflate ×10`: the carried P_θθ times 10 (a forgetting factor per pass).
* `floor`: the carried P_θθ with each variance raised to at least 1e-4 × its P0 value.

and two parameter scalings of P0 = diag(…, 1, …): `absolute` (the paper's P0 = 1 in
estimation coordinates: log units for M, b and the other positive parameters, raw units for the
rest) and `relative` (`estimator.p0_relative = true`: every raw entry's variance scaled by its
own size², so a slope of 30 and a weight of 0.05 move by the same fraction).

Reported after the last pass: inertia error, friction curve error against the rig's steady-state
curve over the excited range, validation FIT (open-loop, compiled rk4), trace P_θθ, and the
passes' innovation log-likelihoods (first → best → last).
"""

from __future__ import annotations

import argparse
import math
import pathlib
import time

import torch
from ekf_rig import friction_reference  # (this folder, run as a script)

from torchfric.app.config import Config
from torchfric.app.run import initial_model, load_data
from torchfric.data.rig import RigParameters
from torchfric.estimators.ekf import EKFState, FilterFailure, make_propagator, make_step, run_pass
from torchfric.estimators.metrics import friction_curve_error, score_simulation
from torchfric.estimators.passes import measurements

ROOT = pathlib.Path(__file__).resolve().parents[1]
F64 = torch.float64


def next_p_theta(policy: str, P_end: torch.Tensor, P0: torch.Tensor) -> torch.Tensor:
    if policy == "carry":
        return P_end
    if policy == "reset":
        return P0.clone()
    if policy == "inflate ×10":
        return 10.0 * P_end
    if policy == "floor":
        d = torch.diagonal(P_end)
        lift = (1e-4 * torch.diagonal(P0) - d).clamp_min(0.0)
        return P_end + torch.diag(lift)
    raise ValueError(policy)


def run(kind: str, policy: str, scaling: str, passes: int, cache: dict) -> dict:
    cfg = Config.load(
        ROOT / "experiments" / "configs" / f"arm_{kind}_ekf.toml",
        ["data.test=[]", "estimator.ensemble=0",
         f"estimator.p0_relative={str(scaling == 'relative').lower()}"],
    )
    if kind not in cache:
        train, val, _, _ = load_data(cfg)
        model, _ = initial_model(cfg, train)
        # One compiled step per model, reused by every policy: `identify_ekf` (which has no
        # hook between passes for P_θθ) would build and compile a new step on every call.
        step = make_step(make_propagator(model, 1), compile=True)
        cache[kind] = (train, val, model, step, model.get_theta().detach().clone())
    train, val, model, step, theta0 = cache[kind]  # (model is re-set below: θ0 = the pre-fit)
    tuning = cfg.estimator.ekf_tuning()
    k = model.num_parameters
    Q, P0_xx, H, R = tuning.matrices(k)
    theta = theta0.clone()
    P0 = tuning.initial_P_theta(model, theta)
    P_theta = P0.clone()
    lls, failed = [], ""
    t0 = time.perf_counter()
    for p in range(1, passes + 1):
        ll = 0.0
        try:
            for exp in train:
                y = measurements(exp, tuning.measure)
                P = torch.zeros(2 + k, 2 + k, dtype=F64)
                P[:2, :2] = P0_xx
                P[2:, 2:] = P_theta
                x = torch.cat([torch.stack([exp.q[0], exp.qdot[0]]).to(F64), theta])
                state, stats = run_pass(
                    EKFState(x, P), exp.u.to(F64), y, torch.tensor(exp.dt, dtype=F64),
                    Q, H, R, step, theta_bound=tuning.theta_bound,
                )  # fmt: skip
                ll += stats.loglik
                theta, P_theta = state.x[2:].clone(), state.P[2:, 2:].clone()
        except FilterFailure as fail:
            failed = f"diverged in pass {p} at sample {fail.sample}"
            break
        lls.append(ll)
        P_theta = next_p_theta(policy, P_theta, P0)
    seconds = time.perf_counter() - t0
    fitted = model.set_theta(theta)
    v, ref = friction_reference(train)
    with torch.no_grad():
        fric = 100 * float(friction_curve_error(fitted, v, ref))
        try:
            s = score_simulation(fitted, val[0], engine="compiled", substeps="auto")
            fq, fv = s.fit_q, s.fit_qdot
        except Exception:  # noqa: BLE001 - a model too stiff to simulate scores as failed
            fq = fv = math.nan
    return {
        "model": kind,
        "policy": policy,
        "scaling": scaling,
        "passes": len(lls),
        "failed": failed,
        "inertia_err_%": 100 * (float(fitted.inertia.detach()) / RigParameters().inertia - 1),
        "friction_err_%": fric,
        "fit_q": fq,
        "fit_qdot": fv,
        "trace_P_theta": float(torch.diagonal(P_theta).sum()),
        "loglik": (lls[0], max(lls), lls[-1]) if lls else (math.nan,) * 3,
        "seconds": seconds,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--models", nargs="+", default=["tanh", "polytopic"])
    p.add_argument("--policies", nargs="+", default=["carry", "reset", "inflate ×10", "floor"])
    p.add_argument("--scalings", nargs="+", default=["absolute", "relative"])
    p.add_argument("--passes", type=int, default=10)
    args = p.parse_args()
    torch.set_num_threads(1)
    cache: dict = {}
    rows = []
    for kind in args.models:
        for scaling in args.scalings:
            for policy in args.policies:
                r = run(kind, policy, scaling, args.passes, cache)
                rows.append(r)
                print(f"  {kind} / {scaling} / {policy}: {r['seconds']:.0f} s", flush=True)
    print()
    print(f"pre-fit start, paper tuning, {args.passes} passes, no rollback; rig data")
    head = (
        "| model | P0 scaling | P_θθ between passes | passes done | inertia error | "
        "friction curve error | validation FIT q / q̇ | trace P_θθ after | "
        "log-likelihood: pass 1 / best / last |"
    )
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for r in rows:
        a, b, c = r["loglik"]
        note = f" ({r['failed']})" if r["failed"] else ""
        print(
            f"| {r['model']} | {r['scaling']} | {r['policy']} | {r['passes']}{note} | "
            f"{r['inertia_err_%']:+.2f} % | {r['friction_err_%']:.1f} % | "
            f"{r['fit_q']:.1f} / {r['fit_qdot']:.1f} % | {r['trace_P_theta']:.3g} | "
            f"{a:,.0f} / {b:,.0f} / {c:,.0f} |"
        )


if __name__ == "__main__":
    main()
