"""The kept EKF θ against the prediction-error optimum, in σ of the truth, for finished runs.

    python benchmarks/coverage.py --models tanh-coulomb --seeds 0 2 4 7 --out /tmp/cov
    python benchmarks/pem_gap.py /tmp/cov/seed0*/run_tanh-coulomb --truth 0.012 0.004

For each run directory of `benchmarks/coverage.py` (or any run whose machine's inertia and
viscous coefficient are known): the filter's kept θ (``filter_theta`` when the run's polish
moved it), the run's covariance stage redone from there (noise model, then `pem_refine` up to
12 Gauss–Newton steps), and for both points M and b as (estimate − truth)/σ, the relative error
of M and the validation score. It shows whether a σ misses because the reported point is not
the criterion's optimum, or because the optimum itself is off.
"""

from __future__ import annotations

import argparse
import copy
import json
import pathlib

import torch

import torchfric
from torchfric.app.artifacts import read_checkpoint
from torchfric.app.config import Config
from torchfric.app.run import load_data, parameter_table
from torchfric.app.run.confidence import _position_only, _score
from torchfric.estimators.covariance import noise_model, pem_covariance, pem_refine


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=pathlib.Path)
    ap.add_argument("--truth", nargs=2, type=float, default=(0.012, 0.004), metavar=("M", "B"))
    args = ap.parse_args()
    torch.set_default_dtype(torch.float64)
    m_true, b_true = args.truth
    print(
        "run | steps | ℓ gain | score kept / optimum | z_M, z_b kept | z_M, z_b optimum | rel M kept / optimum"
    )
    for run in args.runs:
        cfg = Config.load(str(run / "config.toml"))
        train, val, _, _ = load_data(cfg)
        path = next(run.glob("*.pt"))
        state = read_checkpoint(path)["estimator"]["state"]
        theta = torch.as_tensor(state.get("filter_theta", state["theta"]))
        model = torchfric.load_checkpoint(path).set_theta(theta)
        q_scale, r_scale = json.loads((run / "metrics.json").read_text()).get(
            "tuning_scales", (1.0, 1.0)
        )
        tuning = _position_only(cfg.estimator.ekf_tuning().resolved(train))
        qs, rs = noise_model(model, train, tuning, theta, q_scale=q_scale, r_scale=r_scale)[0]
        at = pem_covariance(model, train, tuning, theta, q_scale=qs, r_scale=rs)
        best, pem, trace = pem_refine(model, train, tuning, theta, q_scale=qs, r_scale=rs,
                                      iterations=12, start=at)  # fmt: skip

        def z(th: torch.Tensor, cov: torch.Tensor, model=model) -> tuple[float, float, float]:  # type: ignore[no-untyped-def]
            table = parameter_table(copy.deepcopy(model).set_theta(th), cov)
            (m, sm), (b, sb) = (
                (table[k]["value"], table[k]["std"]) for k in ("inertia", "viscous")
            )
            return (m - m_true) / sm, (b - b_true) / sb, m / m_true - 1

        zk, zo = z(theta, at.cov), z(best, pem.cov)
        judged = val or train
        print(f"{run.parent.name}/{run.name} | {len(trace) - 1} | {trace[-1] - trace[0]:.1f} | "
              f"{_score(cfg, model, theta, judged):.3f} / {_score(cfg, model, best, judged):.3f} | "
              f"{zk[0]:+.2f}, {zk[1]:+.2f} | {zo[0]:+.2f}, {zo[1]:+.2f} | {zk[2]:+.2e} / {zo[2]:+.2e}",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
