"""EKF on the synthetic rig: accuracy against the truth and filter speed. Prints a table.

    python benchmarks/ekf_rig.py                      # train both models (paper tuning), then score
    python benchmarks/ekf_rig.py --from-checkpoints   # score checkpoints/arm_{tanh,polytopic}_{ekf,oe,ekf_oe}.pt
    python benchmarks/ekf_rig.py --speed-only         # only the steps/s section

Reference rows: the truth itself (the rig without its disturbance, and the paper's model class with the
exact steady-state friction curve) simulated and scored like an identified model.

Accuracy targets (issue 3): inertia within 1 % of the truth, validation FIT >= 95 % on q and q̇,
friction curve within 5 % (RMS relative to peak) of the rig's steady-state curve over the excited
velocity range. Speed: filter steps per second for one filter, tanh(3), eager and compiled.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import time

import torch

from torchfric import ArmModel, EKFTuning, load_checkpoint, make_experiment, make_friction
from torchfric.app.config import Config
from torchfric.data.rig import RigParameters, rig_experiment, simulate_rig
from torchfric.estimators.ekf import (
    EKFState,
    make_propagator,
    make_step,
    measurement_matrix,
    run_pass,
)
from torchfric.estimators.metrics import fit_percent, friction_curve_error, score_simulation
from torchfric.models.friction import StribeckFriction

ROOT = pathlib.Path(__file__).resolve().parents[1]


def rig(name: str):  # type: ignore[no-untyped-def]
    d = rig_experiment(name)
    return make_experiment(d["t"], d["u"], d["q"], name=name).with_velocity("highpass")


def friction_reference(experiments) -> tuple[torch.Tensor, torch.Tensor]:  # type: ignore[no-untyped-def]
    """Velocities over the excited sliding range of `experiments` (5 % to 100 % of their peak
    |q̇|, both signs; the stick band is not a curve) and the rig's true steady-state friction
    there: what `friction_curve_error` compares an identified curve with."""
    v_peak = float(max(e.qdot.abs().max() for e in experiments))
    v = torch.linspace(-v_peak, v_peak, 801)
    v = v[v.abs() > 0.05 * v_peak]
    return v, torch.as_tensor(RigParameters().steady_state_friction(v.numpy()))


def accuracy(models: dict[str, tuple[ArmModel, dict]]) -> list[dict]:
    truth = RigParameters()
    ident, val, extra = rig("identification"), rig("validation"), rig("extrapolation")
    v, ref = friction_reference([ident])
    rows = []
    for name, (model, meta) in models.items():
        sv, se = score_simulation(model, val), score_simulation(model, extra)
        rows.append(
            {
                "model": name,
                "inertia": float(model.inertia.detach()),
                "inertia_err_%": 100 * (float(model.inertia.detach()) / truth.inertia - 1),
                "val_fit_q": sv.fit_q,
                "val_fit_qdot": sv.fit_qdot,
                "extra_fit_q": se.fit_q,
                "extra_fit_qdot": se.fit_qdot,
                "friction_err_%": 100 * friction_curve_error(model, v, ref),
                "passes": meta.get("passes") or meta.get("epochs"),
                "seconds": meta.get("seconds"),
            }
        )
    return rows


def ceiling(eps: float = 1e-3) -> list[dict]:
    """How well the *truth* simulates the validation and extrapolation experiments.

    - "LuGre rig, no disturbance": the rig itself (its own integrator, true parameters, true
      initial bristle state) without the random disturbance torque, which no deterministic model
      can reproduce: the ceiling for any model.
    - "true static curve": the grey-box model class of the paper, ``M q̈ = c_m u − b q̇ − C(q̇)``,
      with the true inertia, viscous coefficient and the rig's exact steady-state friction curve
      (Stribeck with a smooth sign of width `eps`, simulated and scored like an identified
      model): the ceiling for a model that has identified the static curve perfectly.
    """
    truth = RigParameters()
    static = ArmModel(
        StribeckFriction(fc=truth.Fc, fs=truth.Fs, vs=truth.vs, eps=eps),
        inertia=truth.inertia,
        viscous=truth.sigma2,
        c_m=truth.c_m,
    )
    quiet = dataclasses.replace(truth, disturbance_std=0.0)
    rows = []
    for name in ("validation", "extrapolation"):
        d, e = rig_experiment(name), rig(name)
        s = simulate_rig(quiet, d["u"], seed=0, x0=(d["q_true"][0], d["qdot_true"][0], d["z"][0]))
        fq = fit_percent(e.q, torch.as_tensor(s["q_true"]))
        fv = fit_percent(e.qdot, torch.as_tensor(s["qdot_true"]))
        rows.append(
            {
                "reference": "LuGre rig, no disturbance",
                "experiment": name,
                "fit_q": fq,
                "fit_qdot": fv,
            }
        )
        sc = score_simulation(static, e, engine="compiled")
        rows.append(
            {
                "reference": f"true static curve (eps {eps:g})",
                "experiment": name,
                "fit_q": sc.fit_q,
                "fit_qdot": sc.fit_qdot,
            }
        )
    return rows


def speed(samples: int = 3000) -> list[dict]:
    ident = rig("identification").slice(0, samples)
    rows = []
    for kind, size in (("tanh", 3), ("polytopic", 3)):
        model = ArmModel(
            make_friction(kind, size),
            inertia=0.03,
            viscous=0.01 if kind == "tanh" else None,
            c_m=16.0,
        )
        n = 2 + model.num_parameters
        tuning = EKFTuning()
        Q = torch.diag(torch.tensor([0.0, 1e-3] + [0.0] * (n - 2)))
        R = torch.diag(torch.tensor(tuning.r))
        H = measurement_matrix("both", n)
        y = torch.stack([ident.q, ident.qdot], -1)
        dt = torch.tensor(ident.dt)
        for compiled in (False, True):
            # The real code path of a pass (`run_pass`: compiled, it filters 1000-sample chunks
            # in one call), as `torchfric train` runs it; benchmarks/ekf_speed.py has more.
            fn = make_step(make_propagator(model, 1), compile=compiled)
            x = torch.cat([torch.stack([ident.q[0], ident.qdot[0]]), model.get_theta()])
            P = torch.diag(torch.tensor([0.0, 0.0] + [1.0] * (n - 2)))
            t0 = time.perf_counter()
            run_pass(EKFState(x, P), ident.u[:3], y[:3], dt, Q, H, R, fn)  # compile (if any)
            first = time.perf_counter() - t0
            t0 = time.perf_counter()
            run_pass(EKFState(x, P), ident.u[:samples], y[:samples], dt, Q, H, R, fn)
            el = time.perf_counter() - t0
            rows.append(
                {
                    "model": f"{kind}({size})",
                    "path": fn.chunk.path if compiled else "eager",  # compiled: native or inductor
                    "steps_per_s": (samples - 1) / el,
                    "us_per_step": 1e6 * el / (samples - 1),
                    "first_call_s": first,
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--from-checkpoints", action="store_true")
    ap.add_argument("--speed-only", action="store_true")
    ap.add_argument("--json", type=pathlib.Path, default=None, help="also write the tables as JSON")
    args = ap.parse_args()
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)
    out: dict[str, list[dict]] = {}
    if not args.speed_only:
        models = {}
        names = [f"arm_{k}_{m}" for k in ("tanh", "polytopic") for m in ("ekf", "oe", "ekf_oe")]
        names.insert(1, "arm_tanh_ekf_ensemble")
        for name in names if args.from_checkpoints else ["arm_tanh_ekf", "arm_polytopic_ekf"]:
            if args.from_checkpoints:
                ckpt = ROOT / "checkpoints" / f"{name}.pt"
                if not ckpt.exists():
                    continue  # score the reference checkpoints that have been produced
                raw = torch.load(ckpt, weights_only=True)
                models[name] = (load_checkpoint(ckpt), raw["metrics"])
            else:
                from torchfric.app.run import train

                cfg = Config.load(
                    ROOT / "experiments" / "configs" / f"{name}.toml", ["data.test=[]"]
                )
                res = train(cfg, run_dir=ROOT / "runs" / f"bench_{name}")
                models[name] = (res.model, res.metrics)
        out["ceiling"] = ceiling()
        print("The truth, simulated open loop and scored like an identified model:")
        print(f"{'reference':<34}{'experiment':<15}{'FIT q':>8}{'FIT q̇':>8}")
        for r in out["ceiling"]:
            print(
                f"{r['reference']:<34}{r['experiment']:<15}{r['fit_q']:>8.2f}{r['fit_qdot']:>8.2f}"
            )
        print()
        out["accuracy"] = accuracy(models)
        print(
            f"{'model':<20}{'M':>10}{'M err %':>9}{'val FIT q':>11}{'val FIT q̇':>11}"
            f"{'extr FIT q':>12}{'extr FIT q̇':>12}{'fric err %':>11}{'pass/ep':>8}{'time s':>8}"
        )
        for r in out["accuracy"]:
            print(
                f"{r['model']:<20}{r['inertia']:>10.5f}{r['inertia_err_%']:>9.2f}{r['val_fit_q']:>11.2f}"
                f"{r['val_fit_qdot']:>11.2f}{r['extra_fit_q']:>12.2f}{r['extra_fit_qdot']:>12.2f}"
                f"{r['friction_err_%']:>11.2f}{r['passes'] or 0:>8}{(r['seconds'] or 0):>8.0f}"
            )
        print()
    out["speed"] = speed()
    print(f"{'model':<16}{'path':<10}{'steps/s':>10}{'µs/step':>10}{'first call s':>14}")
    for r in out["speed"]:
        print(
            f"{r['model']:<16}{r['path']:<10}{r['steps_per_s']:>10.0f}{r['us_per_step']:>10.0f}{r['first_call_s']:>14.1f}"
        )
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
