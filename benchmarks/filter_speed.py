"""The filter's speed in this tree and in an earlier release, measured in one run (issue 34,
part 2). Prints one table: filter-steps/s of each release and their ratio, for

- one augmented filter (`make_step` → `run_pass`, what `identify_ekf` runs), tanh(3) and LuGre;
- the ensemble's masked step (`make_masked_step`, chunks of 1000 samples, what
  `identify_ekf_ensemble` runs) at K = 9 (the default ensemble), 64 and 256 filters;
- the prediction-error stage's fixed-θ filters on the states alone
  (`torchfric.estimators.covariance.innovations`) at K = 1, 8 and 17 (2k + 1 for tanh(3)).

    python benchmarks/filter_speed.py                      # this tree (about 2 minutes)
    python benchmarks/filter_speed.py --before bb9d044     # and that commit (about 4 minutes)

The data are the rig's 30 s identification record, the models the committed checkpoints
`arm_tanh_ekf.pt` (tanh(3), k = 8) and `arm_lugre_ekf.pt`; the filters' parameter vectors the
checkpoint's θ with a random offset (1e-4 relative for the fixed-θ filters; ×/÷ 1.5 for the
ensemble's starts, as `random_thetas` draws them). Each release is measured by a fresh process
of this script importing that release's torchfric (``git archive`` into a temporary folder),
with a compiled-code cache of its own; every figure is the best of ``--repeat`` calls after a
warm-up call (the build is not timed), and the processes of the two releases alternate for
``--rounds`` rounds, keeping each figure's best, so that a busy moment of the machine falls on
both alike. The last column checks that the releases computed the same numbers: the largest
relative difference of the filters' end states (0 where the arithmetic is the same).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from releases import best, checkout

ROOT = Path(__file__).resolve().parents[1]


def measure(repeat: int) -> dict[str, tuple[float, list[float]]]:
    """{figure: (filter-steps/s, a few numbers of its result)} for the torchfric importable here."""
    import dataclasses

    import torch

    from torchfric.app.artifacts import load_checkpoint
    from torchfric.app.config import Config
    from torchfric.app.run import load_data
    from torchfric.environment import torch_settings
    from torchfric.estimators.covariance import innovations
    from torchfric.estimators.ekf import EKFState, make_propagator, make_step, run_pass
    from torchfric.estimators.ensemble import make_masked_step, random_thetas

    f64 = torch.float64
    out: dict[str, tuple[float, list[float]]] = {}
    with torch_settings():
        cfg = Config.load(ROOT / "experiments" / "configs" / "arm_tanh_ekf.toml")
        (exp, *_), *_ = load_data(cfg)
        u, y = exp.u.to(f64), torch.stack([exp.q, exp.qdot], -1).to(f64)
        dt, n = torch.tensor(exp.dt, dtype=f64), exp.n
        for label in ("tanh", "lugre"):
            model = load_checkpoint(ROOT / "checkpoints" / f"arm_{label}_ekf.pt")
            nx, k = model.state_size, model.num_parameters
            theta = model.get_theta()
            Q = torch.zeros(nx + k, nx + k, dtype=f64)
            Q[1, 1] = 1e-3
            H = torch.zeros(2, nx + k, dtype=f64)
            H[0, 0] = H[1, 1] = 1.0
            R = torch.diag(torch.tensor([1e-3, 1e-2], dtype=f64))
            x0 = torch.cat([y[0], torch.zeros(nx - 2, dtype=f64), theta])
            P0 = torch.zeros(nx + k, nx + k, dtype=f64)
            P0[nx:, nx:] = torch.eye(k, dtype=f64)
            step = make_step(make_propagator(model, 1), compile=True)
            start = EKFState(x0, P0)
            secs, (st, _) = best(
                lambda s=start, Q=Q, H=H, R=R, f=step: run_pass(s, u, y, dt, Q, H, R, f), repeat
            )
            out[f"one filter, {label}"] = ((n - 1) / secs, st.x.tolist())
            masked = make_masked_step(model, 1, compile=True)
            for K in (9, 64, 256) if label == "tanh" else (9,):
                th = random_thetas(model, theta, K, 1.5, torch.Generator().manual_seed(0))
                x = torch.cat([x0[:nx].expand(K, nx), th], 1)
                Qk, Rk = Q.expand(K, -1, -1).clone(), R.expand(K, -1, -1).clone()
                consts = (dt, Qk, H, Rk, torch.tensor(1e6, dtype=f64))
                C, index = masked.size, torch.arange(n)

                def ensemble(x=x, K=K, consts=consts, C=C, index=index, P0=P0, masked=masked):  # type: ignore[no-untyped-def]
                    carry = (x, P0.expand(K, -1, -1).clone(), torch.ones(K, dtype=torch.bool),
                             torch.full((K,), -1), torch.zeros(K, 2, dtype=f64),
                             torch.zeros(K, dtype=f64), torch.zeros(K, dtype=f64))  # fmt: skip
                    for j0 in range(1, n - C, C):
                        xs = (index[j0 : j0 + C], u[j0 - 1 : j0 - 1 + C], y[j0 : j0 + C])
                        valid = torch.ones(C, dtype=torch.bool)
                        carry = masked.chunk(carry, xs, valid, consts)[0]
                    return carry[0]

                secs, xe = best(ensemble, repeat)
                steps = K * len(range(1, n - C, C)) * C
                out[f"ensemble K = {K}, {label}"] = (steps / secs, xe[:, :4].flatten().tolist())
        model = load_checkpoint(ROOT / "checkpoints" / "arm_tanh_ekf.pt")
        tuning = cfg.estimator.ekf_tuning().resolved([exp])
        tuning = dataclasses.replace(tuning, measure="position", r=(tuning.r[0],))
        g = torch.Generator().manual_seed(0)
        for K in (1, 8, 17):
            th = model.get_theta() * (1 + 1e-4 * torch.randn(K, model.num_parameters, generator=g,
                                                             dtype=f64))  # fmt: skip
            secs, res = best(lambda th=th: innovations(model, [exp], tuning, th), repeat)
            e, S = res[0]
            out[f"fixed-θ filters K = {K}, tanh"] = (
                K * (n - 1) / secs,
                [float(e.sum()), float(S.sum())],
            )
    return out


def child(tree: Path, cache: Path, repeat: int) -> dict[str, tuple[float, list[float]]]:
    """`measure` in a fresh process that imports the torchfric of `tree`."""
    env = {**os.environ, "PYTHONPATH": str(tree), "TORCHFRIC_CACHE": str(cache)}
    run = subprocess.run([sys.executable, __file__, "--child", "--repeat", str(repeat)], env=env,
                         capture_output=True, text=True, check=True)  # fmt: skip
    return json.loads(run.stdout.strip().splitlines()[-1])


def _rel(a: list[float], b: list[float]) -> float:
    return max((abs(p - q) / max(abs(p), abs(q), 1e-300) for p, q in zip(a, b, strict=True)
                if math.isfinite(p) and math.isfinite(q)), default=0.0)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", help="an earlier commit to measure in the same run")
    ap.add_argument("--repeat", type=int, default=3, help="timed calls per figure and process")
    ap.add_argument("--rounds", type=int, default=2, help="processes per release, alternating")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure(args.repeat)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        trees = {"this tree": ROOT}
        if args.before:
            trees[args.before] = checkout(args.before, work)
        best: dict[str, dict[str, tuple[float, list[float]]]] = {name: {} for name in trees}
        for _ in range(args.rounds):
            for name, tree in trees.items():
                for fig, (rate, numbers) in child(
                    tree, work / f"cache-{len(name)}", args.repeat
                ).items():
                    if rate > best[name].get(fig, (0.0, []))[0]:
                        best[name][fig] = (rate, numbers)
    names = list(trees)
    print(f"filter-steps/s, the rig's identification record ({os.cpu_count()} cores), best of "
          f"{args.repeat} calls × {args.rounds} processes per release")  # fmt: skip
    head = " | ".join(names)
    extra = " | after / before | max rel. difference of the results |" if len(names) > 1 else " |"
    print(f"| filter | {head}{extra}")
    print("|---" * (len(names) + 1 + (2 if len(names) > 1 else 0)) + "|")
    for fig, (rate, numbers) in best[names[0]].items():
        cells = [f"{best[n][fig][0] / 1e6:.2f} M" if fig in best[n] else "–" for n in names]
        row = f"| {fig} | {' | '.join(cells)}"
        if len(names) > 1 and fig in best[names[1]]:
            other, theirs = best[names[1]][fig]
            row += f" | {rate / other:.2f}× | {_rel(numbers, theirs):.1e}"
        print(row + " |")


if __name__ == "__main__":
    main()
