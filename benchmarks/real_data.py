"""torchfric on real measured data (issue 7): EMPS, HSM150 and the unbalanced disc. Prints a table.

    python benchmarks/real_data.py                         # train every config below, then score
    python benchmarks/real_data.py --update-checkpoints    # ... and copy them over checkpoints/
    python benchmarks/real_data.py emps                    # one data set (emps | hsm150 | disc)
    python benchmarks/real_data.py --from-checkpoints      # score the committed checkpoints only
    python benchmarks/real_data.py --from-checkpoints --json

The data sets are read from ``../shared/data`` (each has a SOURCE.md with provenance, units and
the published numbers quoted here). Scoring, per data set:

- EMPS: the benchmark protocol (Champneys et al. 2024 / nonlinear_benchmarks): open-loop
  simulation of the test file ``DATA_EMPS_PULSES.mat`` from ``u = vir``; the first 20 samples
  of ``qm`` set the initial state (`torchfric.estimators.metrics.score_benchmark`); the score is
  ``1000·RMSE(qm[20:], ŷ[20:])`` in mm. The same protocol on the identification file is shown
  for reference, and the published physical model (IDIM-LS) is scored the same way.
- HSM150: open-loop simulation of each repeat-3 test file from rest; RMSE of the angle [rad] and
  of the velocity against the file's measured velocity column [rad/s], and the steady-state
  speeds (means over t ∈ [8, 10) and [18, 20) s) simulated vs measured.
- Unbalanced disc: the held-out tail (samples 28,000 … 34,999, never used in training); the
  first 5 samples set the state, samples from 50 on are scored (the course's 50-sample
  initialisation), RMSE in rad. The physical model shipped with the data set is scored the
  same way, as shipped and with u one sample late. A run with ``data.input_delay`` is scored
  with the same delay (the same samples of q are scored either way).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time
from typing import Any

import torch

from torchfric import ArmModel, load_checkpoint, load_experiment
from torchfric.app.artifacts.checkpoint import read_checkpoint
from torchfric.app.config import Config
from torchfric.estimators.metrics import rms, score_benchmark, score_simulation
from torchfric.models.friction import CoulombFriction

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
CONFIGS = ROOT / "experiments" / "configs"

RUNS: dict[str, list[str]] = {
    "emps": [
        "emps_tanh_ekf",
        "emps_tanh_oe",
        "emps_tanh_ekf_oe",
        "emps_tanh_asym_oe",
        "emps_lugre_asym_oe",
        "emps_lugre_asym_ekf",
        "emps_lugre_asym_ekf_oe",
        "emps_defaults",
    ],
    "hsm150": ["hsm150_tanh_oe", "hsm150_tanh_asym_oe", "hsm150_defaults"],
    "disc": ["disc_tanh_ekf", "disc_tanh_oe", "disc_defaults"],
}

EMPS_COLUMNS = {"u": "vir", "q": "qm"}
EMPS_PUBLISHED = {  # Janot, Gautier, Brunot 2019, IDIM-LS, symmetric friction (SOURCE.md)
    "inertia": 95.1089,
    "viscous": 203.5034,
    "coulomb": 20.3935,
    "offset": -3.1648,
    "c_m": 35.1507,
}
EMPS_RESULTS_MM = {  # test RMSE in mm (SOURCE.md)
    "LTI state space (Champneys et al. 2024)": 5.53,
    "polynomial NARX (Champneys et al. 2024)": 5.17,
    "LSTM (Champneys et al. 2024)": 74.1,
    "dynoNet (Forgione & Piga 2021, best published)": 2.64,
}
HSM_COLUMNS = {"t": "data:0", "q": "data:2", "qdot": "data:3", "u": "data:4"}
HSM_CONDITIONS = ("neg_0.04", "neg_0.045", "pos_0.06", "pos_0.065")
DISC = {
    "file": "training-val-test-data.npz",
    "dt": 0.025,
    "test_start": 28000,
    "n_init": 5,
    "skip": 50,
}
DISC_PUBLISHED = {  # hidden test set, simulation RMSE in rad (gym-unbalanced-disk README)
    "lower bound": 0.0195,
    "good NN model": 0.0271,
    "linear model": 0.255,
}
DISC_SHIPPED = {"omega0": 11.3398, "gamma": 1.33283, "fc": 6.06273, "ku": 28.1362}


# -------------------------------------------------------------------------------------- helpers
def _params(model: ArmModel) -> dict[str, float]:
    return model.physical_parameters()


def _meta(path: pathlib.Path) -> dict[str, Any]:
    m = read_checkpoint(path).get("metrics", {})
    return {
        "estimator": m.get("estimator"),
        "init": m.get("init"),
        "passes": m.get("passes"),
        "epochs": m.get("epochs"),
        "best_epoch": m.get("best_epoch"),
        "seconds": m.get("seconds"),
    }


def _friction_at(model: ArmModel, v: list[float]) -> list[float]:
    with torch.no_grad():
        return [float(x) for x in model.friction_torque(torch.tensor(v, dtype=torch.float64))]


# -------------------------------------------------------------------------------------- EMPS
def emps_published_model() -> ArmModel:
    """The IDIM-LS model; sign(q̇) as tanh(q̇/1e-3 m/s) (SOURCE.md: changes the score < 0.15 mm)."""
    p = EMPS_PUBLISHED
    return ArmModel(
        CoulombFriction(fc=p["coulomb"], eps=1e-3),
        inertia=p["inertia"],
        viscous=p["viscous"],
        c_m=p["c_m"],
        offset=p["offset"],
    )


EMPS_V = [-0.1, -0.05, -0.01, 0.01, 0.05, 0.1]  # m/s, inside the excited range (|q̇| <= 0.13)


def emps_score(model: ArmModel) -> dict[str, Any]:
    folder = DATA / "emps"
    test = load_experiment(folder / "DATA_EMPS_PULSES.mat", columns=EMPS_COLUMNS)
    train = load_experiment(folder / "DATA_EMPS.mat", columns=EMPS_COLUMNS)
    p = _params(model)
    return {
        "test_rmse_mm": 1000 * score_benchmark(model, test, n_init=20, engine="compiled").rms_q,
        "train_rmse_mm": 1000 * score_benchmark(model, train, n_init=20, engine="compiled").rms_q,
        "inertia": p["inertia"],
        "viscous": p.get("viscous", float("nan")),
        "offset": p.get("offset", 0.0),
        "asymmetric": p.get("asymmetric", float("nan")),
        "friction_N": dict(zip(map(str, EMPS_V), _friction_at(model, EMPS_V), strict=True)),
    }


# -------------------------------------------------------------------------------------- HSM150
def hsm_test_files() -> list[pathlib.Path]:
    return [DATA / "hsm150_two_motor" / f"idf_{c}_3.mat" for c in HSM_CONDITIONS]


def hsm_score(model: ArmModel) -> dict[str, Any]:
    per_file = {}
    for path in hsm_test_files():
        exp = load_experiment(path, columns=HSM_COLUMNS)  # qdot = the rig's measured velocity
        s = score_simulation(model, exp)
        v_sim, v_meas = s.states[:, 1], exp.qdot
        steady = {}
        for label, (a, b) in {"phase1": (8000, 10000), "phase2": (18000, 20000)}.items():
            steady[label] = {
                "measured": float(v_meas[a:b].mean()),
                "simulated": float(v_sim[a:b].mean()),
            }
        per_file[path.stem] = {
            "rmse_q_rad": s.rms_q,
            "rmse_qdot_rad_s": rms(v_meas, v_sim),
            "steady_rad_s": steady,
        }
    p = _params(model)
    return {
        "rmse_q_rad": math.sqrt(sum(f["rmse_q_rad"] ** 2 for f in per_file.values()) / 4),
        "rmse_qdot_rad_s": math.sqrt(sum(f["rmse_qdot_rad_s"] ** 2 for f in per_file.values()) / 4),
        "files": per_file,
        "inertia": p["inertia"],
        "viscous": p.get("viscous", float("nan")),
        "offset": p.get("offset", 0.0),
        "friction_Nm": dict(
            zip(
                map(str, [-240.0, -160.0, 140.0, 300.0]),
                _friction_at(model, [-240.0, -160.0, 140.0, 300.0]),
                strict=True,
            )
        ),
    }


# -------------------------------------------------------------------------------------- disc
def disc_shipped_model() -> ArmModel:
    """The repo's physical model, per volt; its tanh(θ̇/0.001) widened to tanh(θ̇/0.01) so that
    RK4 at 40 Hz needs 8 rather than ~80 sub-steps."""
    s = DISC_SHIPPED
    return ArmModel(
        CoulombFriction(fc=s["fc"] / s["ku"], eps=0.01),
        inertia=1.0 / s["ku"],
        viscous=s["gamma"] / s["ku"],
        gravity=s["omega0"] ** 2 / s["ku"],
        c_m=1.0,
    )


def disc_score(model: ArmModel, input_delay: int = 0) -> dict[str, Any]:
    """`input_delay`: the model's u acts that many samples late (the run's data.input_delay); the
    tail then starts that many samples earlier in u, so the same samples of q are scored."""
    path = DATA / "unbalanced_disk" / DISC["file"]
    tail = load_experiment(
        path, columns={"q": "th"}, time_step=DISC["dt"], start=DISC["test_start"] - input_delay
    ).delay_input(input_delay)
    s = score_benchmark(model, tail, n_init=DISC["n_init"], skip=DISC["skip"], engine="compiled")
    p = _params(model)
    return {
        "test_rmse_rad": s.rms_q,
        "test_samples": tail.n - DISC["skip"],
        "input_delay": input_delay,
        "inertia": p["inertia"],
        "viscous": p.get("viscous", float("nan")),
        "gravity": p.get("gravity", float("nan")),
        "omega0": math.sqrt(p.get("gravity", float("nan")) / p["inertia"]),
    }


SCORERS = {"emps": emps_score, "hsm150": hsm_score, "disc": disc_score}
REFERENCES = {"emps": emps_published_model, "disc": disc_shipped_model}


# -------------------------------------------------------------------------------------- driver
def train_all(sets: list[str], *, update: bool = False) -> dict[str, pathlib.Path]:
    """Train every run of `sets` into a fresh run directory; {name: its checkpoint}.

    With `update`, each final checkpoint is also copied over the committed
    ``checkpoints/NAME.pt`` (the explicit ``--checkpoint`` step).
    """
    from torchfric.app.run import train

    out = {}
    for key in sets:
        for name in RUNS[key]:
            cfg = Config.load(CONFIGS / f"{name}.toml")
            sys.stderr.write(f"== training {name}\n")
            target = ROOT / "checkpoints" / f"{name}.pt" if update else None
            out[name] = train(cfg, checkpoint=target).checkpoint
    return out


def score_all(sets: list[str], paths: dict[str, pathlib.Path] | None = None) -> dict[str, Any]:
    """Score each run's checkpoint: `paths[name]`, else the committed checkpoints/NAME.pt."""
    out: dict[str, Any] = {}
    for key in sets:
        rows: dict[str, Any] = {}
        if key in REFERENCES:
            t0 = time.perf_counter()
            rows["published physical model"] = SCORERS[key](REFERENCES[key]())
            rows["published physical model"]["score_seconds"] = time.perf_counter() - t0
            if key == "disc":  # SOURCE.md: the shipped model fits better with u one sample late
                rows["published, u 1 sample late"] = disc_score(disc_shipped_model(), 1)
        for name in RUNS[key]:
            path = (paths or {}).get(name, ROOT / "checkpoints" / f"{name}.pt")
            if not path.is_file():
                rows[name] = {"missing": str(path)}
                continue
            t0 = time.perf_counter()
            model = load_checkpoint(path)
            delay = Config.load(CONFIGS / f"{name}.toml").data.input_delay
            scored = SCORERS[key](model, delay) if delay else SCORERS[key](model)
            rows[name] = {**_meta(path), **scored}
            rows[name]["score_seconds"] = time.perf_counter() - t0
        out[key] = rows
    return out


def _fmt(x: Any, spec: str) -> str:
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def print_table(results: dict[str, Any]) -> None:
    if "emps" in results:
        print("EMPS (test: DATA_EMPS_PULSES.mat, 1000·RMSE(qm[20:], ŷ[20:]) in mm)")
        print(
            f"{'model':<46}{'test mm':>9}{'train mm':>10}{'M kg':>9}{'b N·s/m':>10}"
            f"{'offset N':>10}{'a N·s/m':>9}  friction N at q̇ = "
            + ", ".join(f"{v:+g}" for v in EMPS_V)
        )
        for name, r in results["emps"].items():
            if "missing" in r:
                print(f"{name:<46}  (no checkpoint: {r['missing']})")
                continue
            fr = ", ".join(f"{x:+.1f}" for x in r["friction_N"].values())
            print(
                f"{name:<46}{r['test_rmse_mm']:>9.2f}{r['train_rmse_mm']:>10.2f}"
                f"{r['inertia']:>9.2f}{_fmt(r['viscous'], '.1f'):>10}{r['offset']:>10.2f}"
                f"{_fmt(r['asymmetric'], '.1f'):>9}  {fr}"
            )
        for name, mm in EMPS_RESULTS_MM.items():
            print(f"{name:<46}{mm:>9.2f}   (published)")
        print()
    if "hsm150" in results:
        print("HSM150 (test: repeat 3 of each condition, open loop from rest)")
        print(
            f"{'model':<20}{'RMSE q rad':>11}{'RMSE q̇ rad/s':>14}{'J kg·m²':>11}{'b':>11}"
            f"{'offset N·m':>12}  steady speeds sim/meas [rad/s]"
        )
        for name, r in results["hsm150"].items():
            if "missing" in r:
                print(f"{name:<20}  (no checkpoint: {r['missing']})")
                continue
            steady = "; ".join(
                f"{f.split('_', 1)[1][:-2]}: "
                + " ".join(
                    f"{s['simulated']:.0f}/{s['measured']:.0f}" for s in d["steady_rad_s"].values()
                )
                for f, d in r["files"].items()
            )
            print(
                f"{name:<20}{r['rmse_q_rad']:>11.1f}{r['rmse_qdot_rad_s']:>14.2f}"
                f"{r['inertia']:>11.3g}{_fmt(r['viscous'], '.3g'):>11}{r['offset']:>12.4f}  {steady}"
            )
        print()
    if "disc" in results:
        print("Unbalanced disc (held-out tail, samples 28000…34999, RMSE in rad)")
        print(f"{'model':<28}{'RMSE rad':>10}{'M':>10}{'b':>10}{'g_c':>8}{'ω0 rad/s':>10}")
        for name, r in results["disc"].items():
            if "missing" in r:
                print(f"{name:<28}  (no checkpoint: {r['missing']})")
                continue
            print(
                f"{name:<28}{r['test_rmse_rad']:>10.4f}{r['inertia']:>10.4g}"
                f"{_fmt(r['viscous'], '.4g'):>10}{r['gravity']:>8.3f}{r['omega0']:>10.3f}"
            )
        for name, v in DISC_PUBLISHED.items():
            print(f"{name + ' (hidden test set)':<28}{v:>10.4f}   (published)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sets", nargs="*", help=f"data sets: {', '.join(RUNS)} (default: all)")
    parser.add_argument("--from-checkpoints", action="store_true", help="score checkpoints only")
    parser.add_argument(
        "--update-checkpoints",
        action="store_true",
        help="copy each new run's checkpoint over the committed checkpoints/NAME.pt",
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of tables")
    args = parser.parse_args(argv)
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)
    if not DATA.is_dir():
        print(f"real data sets not found at {DATA}; they live beside the project", file=sys.stderr)
        return 2
    sets = list(args.sets) or list(RUNS)
    unknown = [s for s in sets if s not in RUNS]
    if unknown:
        parser.error(f"unknown data set(s) {unknown}; choose from {', '.join(RUNS)}")
    paths = None if args.from_checkpoints else train_all(sets, update=args.update_checkpoints)
    results = score_all(sets, paths)
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print_table(results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
