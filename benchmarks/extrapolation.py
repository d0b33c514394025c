"""Friction curves beyond the identified range: tanh(3) and polytopic(3) on the rig (issue 23).

    python benchmarks/extrapolation.py              # tanh(3) and polytopic(3), as shipped
    python benchmarks/extrapolation.py --paper      # also polytopic(3) as it was before
    python benchmarks/extrapolation.py --ablation   # and each of the two changes alone
    python benchmarks/extrapolation.py --seed 0 1 2 # several realisations of the records

The nominal LuGre rig (`torchfric.data.rig`) is excited up to 15 rad/s for identification and
12.75 rad/s for validation (the shipped records' ratio), and up to 24 rad/s for the
extrapolation record, all generated here in a temporary folder. Each model is identified by
`torchfric.fit` with the single-filter configs `experiments/configs/arm_{tanh,polytopic}_ekf.toml`
(train on the 15 rad/s record, keep the pass that validates best), and then scored against the
truth:

- curve %: RMS of (identified friction − the rig's steady-state curve) relative to the true
  curve's peak, over |v| <= 24 rad/s, and over the sliding range 1.2 <= |v| <= 24 rad/s (the
  5 % stick band left out, as in `benchmarks/ekf_rig.py`);
- FIT q / q̇ on the 24 rad/s record, simulated open loop from its first sample;
- the inertia's error against the rig's.

The goal (issue 23): both models within 10 % RMS of the true curve over ±24 rad/s and FIT on q
>= 90 % on the 24 rad/s record. ``--paper`` adds the polytopic model as it was before: the
paper's Gaussian validity functions (``extrapolation="gaussian"``, registered for that run only)
with the paper's P0 = 1 (``estimator.p0_theta``; the shipped config now uses 0.1), to show what
the change does; ``--ablation`` adds each change alone (the affine continuation with P0 = 1,
the Gaussians with P0 = 0.1). Nothing is written outside the temporary folder.
"""

from __future__ import annotations

import argparse
import contextlib
import pathlib
import sys
import tempfile
from collections.abc import Iterator

import numpy as np
import torch

import torchfric
from torchfric.data.rig import RigParameters, excitation, simulate_rig
from torchfric.estimators.metrics import friction_curve_error, score_simulation
from torchfric.models import friction as friction_module
from torchfric.models.friction import PolytopicFriction

ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "experiments" / "configs"

IDENT_PEAK, VALID_PEAK, EXTRA_PEAK = 15.0, 12.75, 24.0
# (excitation kind, duration [s], design peak [rad/s], disturbance stream): streams of their own,
# apart from the shipped records' (10-14).
RECORDS = {
    "ident15": ("identification", 30.0, IDENT_PEAK, 31),
    "valid15": ("validation", 20.0, VALID_PEAK, 32),
    "extra24": ("extrapolation", 20.0, EXTRA_PEAK, 33),
}


def write_records(folder: pathlib.Path, seed: int) -> dict[str, tuple[pathlib.Path, float]]:
    """The three records as ``t,u,q`` CSVs in `folder`: {name: (path, measured peak |q̇|)}."""
    truth = RigParameters()
    out = {}
    for name, (kind, duration, peak, stream) in RECORDS.items():
        u = excitation(kind, duration=duration, dt=truth.dt, seed=seed, peak_velocity=peak)
        rec = simulate_rig(truth, u, seed=(seed, stream))
        exp = torchfric.make_experiment(rec["t"], rec["u"], rec["q"], name=name)
        path = folder / f"{name}.csv"
        torchfric.save_csv(path, exp, include_qdot=False)
        out[name] = (path, float(np.abs(rec["qdot_true"]).max()))
    return out


class _PaperPolytopic(PolytopicFriction):
    """The polytopic model with the paper's Gaussian validity functions (``--paper`` only)."""

    def __init__(self, n: int = 3, **kwargs) -> None:  # type: ignore[no-untyped-def]
        kwargs.setdefault("extrapolation", "gaussian")
        super().__init__(n, **kwargs)


@contextlib.contextmanager
def paper_polytopic() -> Iterator[None]:
    """``model.friction = "polytopic"`` builds the paper's construction while this is open."""
    registry = friction_module.FRICTIONS
    saved = registry["polytopic"]
    registry["polytopic"] = _PaperPolytopic
    try:
        yield
    finally:
        registry["polytopic"] = saved


def identify(
    config: str, records: dict, run_dir: pathlib.Path, overrides: dict
) -> torchfric.TrainResult:
    data = {
        "train": [str(records["ident15"][0])],
        "validation": [str(records["valid15"][0])],
        "test": [str(records["extra24"][0])],
        "velocity": "highpass",
    }
    return torchfric.fit(CONFIGS / config, data=data, out=run_dir, quiet=True, **overrides)


def score(model: torchfric.ArmModel, extra: torchfric.Experiment) -> dict[str, float]:
    truth = RigParameters()
    v = torch.linspace(-EXTRA_PEAK, EXTRA_PEAK, 4801, dtype=torch.float64)
    ref = torch.as_tensor(truth.steady_state_friction(v.numpy()))
    sliding = v.abs() >= 0.05 * EXTRA_PEAK
    sim = score_simulation(model, extra)
    with torch.no_grad():
        return {
            "curve_all": 100.0 * friction_curve_error(model, v, ref),
            "curve_sliding": 100.0
            * float(
                (model.friction_torque(v[sliding]) - ref[sliding]).pow(2).mean().sqrt()
                / ref.abs().max()
            ),
            "fit_q": sim.fit_q,
            "fit_qdot": sim.fit_qdot,
            "inertia": 100.0 * (float(model.inertia) / truth.inertia - 1.0),
        }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--seed",
        type=int,
        nargs="+",
        default=[0],
        help="seeds of the records, one realisation each (default 0)",
    )
    parser.add_argument(
        "--paper",
        action="store_true",
        help="also identify polytopic(3) as before: the paper's Gaussians and P0 = 1",
    )
    parser.add_argument(
        "--ablation",
        action="store_true",
        help="--paper, and each of the two changes alone (the construction; P0 = 0.1)",
    )
    args = parser.parse_args(argv)
    runs = [
        ("tanh(3)", "arm_tanh_ekf.toml", {}, contextlib.nullcontext),
        ("polytopic(3)", "arm_polytopic_ekf.toml", {}, contextlib.nullcontext),
    ]
    poly, paper_p0 = "arm_polytopic_ekf.toml", {"estimator.p0_theta": 1.0}
    if args.paper or args.ablation:
        runs.append(("polytopic(3) before", poly, paper_p0, paper_polytopic))
    if args.ablation:
        runs.append(("affine, P0 1", poly, paper_p0, contextlib.nullcontext))
        runs.append(("Gaussians, P0 0.1", poly, {}, paper_polytopic))
    rows = []
    for seed in args.seed:
        with tempfile.TemporaryDirectory(prefix="torchfric-extrapolation-") as tmp:
            folder = pathlib.Path(tmp)
            records = write_records(folder, seed)
            peaks = ", ".join(f"{k} {p:.1f}" for k, (_, p) in records.items())
            print(f"records (seed {seed}), measured peak |q̇| [rad/s]: {peaks}", flush=True)
            extra = torchfric.load_experiment(records["extra24"][0]).with_velocity("highpass")
            for label, config, overrides, context in runs:
                with context():
                    result = identify(config, records, folder / f"run{len(rows)}", overrides)
                row = {"seed": seed, "model": label, **score(result.model, extra)}
                # The run's own test score is the same simulation: a check of this script.
                row["run_fit_q"] = result.metrics["test"]["extra24"]["fit_q"]
                row["val_fit_q"] = result.metrics["validation"]["valid15"]["fit_q"]
                rows.append(row)
    head = (
        f"{'seed':>4s} {'model':20s} {'curve % ±24':>11s} {'curve % 1.2-24':>14s} "
        f"{'FIT q / q̇ 24 rad/s':>19s} {'inertia':>8s} {'val FIT q':>9s}  goal"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        goal = "met" if r["curve_all"] <= 10.0 and r["fit_q"] >= 90.0 else "missed"
        print(
            f"{r['seed']:4d} {r['model']:20s} {r['curve_all']:11.2f} {r['curve_sliding']:14.2f} "
            f"{r['fit_q']:10.2f} / {r['fit_qdot']:6.2f} {r['inertia']:+7.2f}% "
            f"{r['val_fit_q']:9.2f}  {goal}"
        )
    if args.paper or args.ablation:
        print(
            "polytopic(3) before: the paper's Gaussian validity functions and P0 = 1, "
            "as shipped before issue 23"
        )
    mismatch = [r["model"] for r in rows if abs(r["fit_q"] - r["run_fit_q"]) > 1e-6]
    if mismatch:
        print(f"note: the run's own test FIT differs for {', '.join(mismatch)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
