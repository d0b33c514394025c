"""Does a run's ± σ hang on rounding? Its covariance stage redone at the kept θ and at θ
changed by 1e-12 relative.

    python benchmarks/sigma_rounding.py RUN_DIR [RUN_DIR ...]
    python benchmarks/sigma_rounding.py --coverage DIR      # every run of coverage.py --out DIR
    python benchmarks/sigma_rounding.py --coverage DIR --models tanh lugre --draws 4

A run directory is what ``torchfric train`` wrote (config.toml, metrics.json, the checkpoint);
its config is read from the run's parent folder (where coverage.py trains; use ``--cwd`` for
another). For each run the prediction-error stage that gives the reported σ
(`torchfric.app.run.confidence.attach_covariance`: noise model, polish, keep or reject,
sandwich plus offset) runs at the filter's kept θ (``filter_theta`` when the polish was kept)
and at `--draws` copies of it with every entry multiplied by ``1 + 1e-12·N(0, 1)`` (seeded).
A σ that is a smooth function of the data moves by about 1e-12 relative; the table gives, per
run, σ of M and of the slope (viscous, or a polytopic model's outer slope) at θ and the ratio
of the largest to the smallest over θ and the draws, the polish's accepted steps per draw, and
whether the polish was kept. The summary counts the runs whose σ of M or of the slope moved by
more than 1 %, per model. Post-hoc: nothing is trained, nothing in the run directories changes.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from coverage import slope_entry


def _restudy(run_dir: Path, draws: int, scale: float, cwd: Path | None) -> dict[str, Any]:
    """The covariance stage of `run_dir` at its kept θ and `draws` perturbations of it."""
    import torch

    from torchfric.app.artifacts.checkpoint import checkpoint_model, read_checkpoint
    from torchfric.app.config import Config
    from torchfric.app.run import confidence, load_data
    from torchfric.estimators.uncertainty import parameter_std

    checkpoint = next(iter(sorted(run_dir.glob("*.pt"))))
    ck = read_checkpoint(str(checkpoint))
    state0 = ck["estimator"]["state"]
    kept = torch.as_tensor(state0.get("filter_theta", state0["theta"]), dtype=torch.float64)
    P_filter = torch.as_tensor(state0.get("filter_P_theta", state0["P_theta"]))
    metrics = json.loads((run_dir / "metrics.json").read_text())
    os.chdir(cwd or run_dir.parent)
    cfg = Config.load(str(run_dir / "config.toml"))
    train, validation, *_ = load_data(cfg)
    slope = slope_entry(metrics["parameters"])
    gen = torch.Generator().manual_seed(5)
    rows = []
    for i in range(draws + 1):
        noise = scale * torch.randn(kept.shape, generator=gen, dtype=torch.float64) if i else 0.0
        theta = kept * (1 + noise)
        model = checkpoint_model(ck, str(checkpoint)).set_theta(theta)
        state = {"theta": theta.clone(), "P_theta": P_filter.clone()}
        extra = (
            {"tuning_scales": tuple(metrics["tuning_scales"])} if "tuning_scales" in metrics else {}
        )
        confidence.attach_covariance(cfg, model, train, state, extra, lambda _: None, validation)
        std = parameter_std(model.set_theta(state["theta"]), state["P_theta"], theta=state["theta"])
        polish = extra.get("polished") or extra.get("polish_rejected") or {}
        rows.append({"M": std["inertia"], "slope": std.get(slope[0]) if slope else None,
                     "steps": polish.get("steps", 0), "polished": "polished" in extra})  # fmt: skip
    return {"rows": rows, "slope": slope[0] if slope else None}


def _ratio(values: list[float | None]) -> float:
    vals = [v for v in values if v]
    return max(vals) / min(vals) if vals else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="*", type=Path, help="run directories")
    ap.add_argument("--coverage", type=Path, help="a coverage.py --out folder: all its runs")
    ap.add_argument("--models", nargs="*", default=[], help="with --coverage: only these models")
    ap.add_argument("--draws", type=int, default=2, help="perturbed copies of θ per run")
    ap.add_argument("--scale", type=float, default=1e-12, help="relative size of a perturbation")
    ap.add_argument("--cwd", type=Path, help="folder the runs' configs are read from")
    args = ap.parse_args()
    runs = [p.resolve() for p in args.runs]
    if args.coverage:
        found = sorted(glob.glob(str(args.coverage.resolve() / "seed*" / "run_*")))
        runs += [Path(r) for r in found
                 if not args.models or r.rsplit("run_", 1)[1] in args.models]  # fmt: skip
    if not runs:
        sys.exit("sigma_rounding: no run directories (give RUN_DIR… or --coverage DIR)")
    from torchfric.environment import torch_settings

    print(f"{'run':32s} {'σ M':>10s} {'ratio':>6s} {'σ slope':>10s} {'ratio':>6s}  polish steps")
    moved: dict[str, list[int]] = {}
    worst = 1.0
    t0 = time.perf_counter()
    with torch_settings():
        for run in runs:
            found = _restudy(run, args.draws, args.scale, args.cwd)
            rows = found["rows"]
            rM, rs = _ratio([r["M"] for r in rows]), _ratio([r["slope"] for r in rows])
            label = f"{run.parent.name}/{run.name}" if args.coverage else str(run)
            model = run.name.rsplit("run_", 1)[-1]
            tally = moved.setdefault(model, [0, 0])
            tally[0] += 1
            tally[1] += int(max(rM, rs if rs == rs else 1.0) > 1.01)
            worst = max(worst, rM, rs if rs == rs else 1.0)
            slope = rows[0]["slope"] or float("nan")
            kept = "kept" if rows[0]["polished"] else "rejected"
            print(f"{label:32s} {rows[0]['M']:10.3g} {rM:6.3f} {slope:10.3g} {rs:6.3f}  "
                  f"{kept} {[r['steps'] for r in rows]}", flush=True)  # fmt: skip
    print(
        f"\nσ of M or of the slope moved by more than 1 % over {args.draws} draws of "
        f"{args.scale:g} (the largest ratio {worst:.3f}; {time.perf_counter() - t0:.0f} s):"
    )
    for model, (n, k) in moved.items():
        print(f"  {model:12s} {k} of {n} runs")


if __name__ == "__main__":
    main()
