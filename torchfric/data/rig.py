"""The synthetic rig: torchfric's own "true system" (Hensen et al. §2, §5; docs/results.md,
"Results on the synthetic rig").

A rotating arm without gravity, driven by a motor current ``u`` [A]::

    M v̇ = c_m u − F + τ_d(t),      q̇ = v,
    ż = v − σ0 |v| z / g(v),       g(v) = Fc + (Fs − Fc) exp(−(v/vs)²),
    F = σ0 z + σ1 ż + σ2 v                                   (LuGre friction)

so that, like the real arm, it shows pre-sliding (bristle deflection ``z``), hysteresis and a
Stribeck curve that the grey-box models ``M q̈ = c_m u − b q̇ − C(q̇)`` do not contain. The
steady-state friction curve is ``F_ss(v) = sign(v) g(v) + σ2 v``.

The rig lives in three modules: `torchfric.data.rig_model` (`RigParameters`, with the reasons
for each value, and `simulate_rig`, the LuGre integrator), `torchfric.data.excitation` (the
input currents) and this one, which names the experiments, runs them and writes their files.
All the public names of the three are importable from here.

Experiments (`EXPERIMENTS`, `rig_experiment`, `generate`): identification (30 s, peak ≈ 10 rad/s),
validation (20 s, another signal, peak within the identification range), extrapolation (20 s,
peak ≈ 1.6× identification), and the same identification/validation inputs applied to the system
"after maintenance" (`RigParameters.changed`: no static friction, Fs = Fc).
"""

from __future__ import annotations

import io
import json
import pathlib
import zipfile
from typing import Any

import numpy as np

from ..errors import TorchfricError
from ..files import atomic_write_bytes, atomic_write_text
from .excitation import _PEAK_VELOCITY, EXCITATIONS, excitation
from .rig_model import Integrator, RigParameters, _check_seed, simulate_rig

__all__ = [
    "RigParameters",
    "excitation",
    "simulate_rig",
    "EXPERIMENTS",
    "EXCITATIONS",
    "rig_experiment",
    "changing_record",
    "generate",
]

EXPERIMENTS: tuple[str, ...] = (
    "identification",
    "validation",
    "extrapolation",
    "changed_identification",
    "changed_validation",
)

# Per experiment: (excitation kind, duration [s], system "nominal" | "changed").
_EXPERIMENT_SPEC: dict[str, tuple[str, float, str]] = {
    "identification": ("identification", 30.0, "nominal"),
    "validation": ("validation", 20.0, "nominal"),
    "extrapolation": ("extrapolation", 20.0, "nominal"),
    "changed_identification": ("identification", 30.0, "changed"),
    "changed_validation": ("validation", 20.0, "changed"),
}
# Disturbance stream codes: independent of the excitation's streams for one seed.
_DISTURBANCE_CODE: dict[str, int] = {name: 10 + i for i, name in enumerate(EXPERIMENTS)}


# --------------------------------------------------------------------------------------------
# Named experiments and data files
# --------------------------------------------------------------------------------------------

_CACHE: dict[tuple[str, int], dict[str, np.ndarray]] = {}


def _check_name(name: str) -> tuple[str, float, str]:
    """The (excitation kind, duration, system) of experiment `name`; else a `TorchfricError`."""
    if name not in _EXPERIMENT_SPEC:
        raise TorchfricError(
            f"unknown rig experiment {name!r}; choose one of {', '.join(EXPERIMENTS)}"
        )
    return _EXPERIMENT_SPEC[name]


def _run_experiment(
    name: str, seed: int, integrate: Integrator | None = None
) -> dict[str, np.ndarray]:
    """Simulate experiment `name` for `seed` from scratch (`rig_experiment` memoises it)."""
    kind, duration, system = _check_name(name)
    nominal = RigParameters()
    params = nominal.changed() if system == "changed" else nominal
    u = excitation(kind, duration=duration, dt=nominal.dt, seed=seed, params=nominal)
    return simulate_rig(params, u, seed=(int(seed), _DISTURBANCE_CODE[name]), integrate=integrate)


def rig_experiment(
    name: str, *, seed: int = 0, integrate: Integrator | None = None
) -> dict[str, np.ndarray]:
    """One named experiment of `EXPERIMENTS` (see `simulate_rig` for the keys); deterministic.

    Results are memoised per ``(name, seed)``; the returned arrays are copies. `integrate` is
    `simulate_rig`'s (the same numbers whichever runs).
    """
    _check_name(name)
    key = (name, _check_seed(seed))
    if key not in _CACHE:
        _CACHE[key] = _run_experiment(name, int(seed), integrate)
    return {k: v.copy() for k, v in _CACHE[key].items()}


def changing_record(
    before: float,
    after: float,
    *,
    seed: int = 0,
    kind: str = "validation",
    integrate: Integrator | None = None,
) -> dict[str, np.ndarray]:
    """One continuous record in which the rig changes: `before` seconds of the nominal system,
    then `after` seconds of the system "after maintenance" (`RigParameters.changed`), the state
    ``(q, q̇, z)`` carried across the change (the machine is not stopped). The input is one
    `excitation` of `kind` over the whole record. Keys as `simulate_rig`'s, plus ``change``
    (the change's time, a 0-d array). For tracking (``torchfric track``) tests and benchmarks.
    """
    p = RigParameters()
    if not (before > 0 and after > 0):
        raise TorchfricError(f"changing_record needs before, after > 0 s, got {before}, {after}")
    u = excitation(kind, duration=before + after, dt=p.dt, seed=_check_seed(seed))
    n1 = int(round(before / p.dt))
    first = simulate_rig(p, u[: n1 + 1], seed=[seed, 11], integrate=integrate)
    x0 = (first["q_true"][-1], first["qdot_true"][-1], first["z"][-1])
    second = simulate_rig(p.changed(), u[n1:], seed=[seed, 12], x0=x0, integrate=integrate)
    out = {k: np.concatenate([first[k][:-1], second[k]]) for k in first if k != "t"}
    out["t"] = np.arange(u.size) * p.dt
    out["change"] = np.asarray(n1 * p.dt)
    return out


def _friction_table(params: RigParameters, v: np.ndarray) -> list[list[float]]:
    """Rows ``[v, F_ss(v)]`` of the steady-state friction curve, as plain floats for JSON."""
    return [[float(a), float(b)] for a, b in zip(v, params.steady_state_friction(v), strict=True)]


def _write_npz(path: pathlib.Path, arrays: dict[str, np.ndarray]) -> None:
    """An uncompressed ``.npz`` with fixed time stamps, so equal arrays give identical bytes."""
    whole = io.BytesIO()
    with zipfile.ZipFile(whole, "w", compression=zipfile.ZIP_STORED) as zf:
        for key in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arrays[key]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())
    atomic_write_bytes(path, whole.getvalue())


def _prepare_outdir(out: pathlib.Path, force: bool) -> None:
    """Create `out` for `generate`; refuse a file there, or the rig's files without `force`."""
    targets = [out / f"{n}.csv" for n in EXPERIMENTS] + [
        out / "truth.json",
        out / "truth_states.npz",
    ]
    existing = [p.name for p in targets if p.exists() or p.is_symlink()]
    if existing and not force:
        raise TorchfricError(
            f"{out} already holds {', '.join(existing[:4])}"
            + (f" and {len(existing) - 4} more" if len(existing) > 4 else "")
            + "; choose another folder, or pass --force to replace the rig's files there"
        )
    if out.exists() and not out.is_dir():
        raise TorchfricError(f"{out} is a file, not a folder; give a folder for the rig's data")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TorchfricError(
            f"cannot create output directory {str(out)!r}: {exc.strerror}"
        ) from exc


def generate(
    outdir: str | pathlib.Path,
    *,
    seed: int = 0,
    force: bool = False,
    integrate: Integrator | None = None,
) -> dict[str, pathlib.Path]:
    """Write every experiment as ``<outdir>/<name>.csv`` (``t,u,q``), plus ground truth.

    ``truth.json`` holds the nominal and changed `RigParameters`, per experiment its system,
    duration, seed and peak |q̇|, and the steady-state friction curve ``F_ss`` of both systems
    on a velocity grid; ``truth_states.npz`` holds ``<name>/<state>`` arrays (q_true,
    qdot_true, friction, z, disturbance). Creates ``outdir``; same seed → identical bytes.
    Returns ``{file stem: path}`` for every file written. Existing files are replaced only with
    `force` (otherwise nothing is written); each file is written atomically.
    """
    seed = _check_seed(seed)
    out = pathlib.Path(outdir)
    _prepare_outdir(out, force)
    nominal = RigParameters()
    changed = nominal.changed()
    paths: dict[str, pathlib.Path] = {}
    states: dict[str, np.ndarray] = {}
    per_experiment: dict[str, dict[str, Any]] = {}
    for name in EXPERIMENTS:
        data = rig_experiment(name, seed=seed, integrate=integrate)
        kind, duration, system = _EXPERIMENT_SPEC[name]
        path = out / f"{name}.csv"
        table = np.column_stack([data["t"], data["u"], data["q"]])
        rows = ("%.17g,%.17g,%.17g\n" * len(table)) % tuple(table.ravel().tolist())
        atomic_write_text(path, "t,u,q\n" + rows)
        paths[name] = path
        for key in ("q_true", "qdot_true", "friction", "z", "disturbance"):
            states[f"{name}/{key}"] = data[key]
        per_experiment[name] = {
            "system": system,
            "excitation": kind,
            "duration": duration,
            "samples": int(data["t"].size),
            "seed": int(seed),
            "disturbance_seed": [int(seed), _DISTURBANCE_CODE[name]],
            "design_peak_qdot": _PEAK_VELOCITY[kind],
            "peak_abs_qdot": float(np.max(np.abs(data["qdot_true"]))),
        }
    grid = np.round(np.linspace(-20.0, 20.0, 801), 10)
    truth = {
        "description": "torchfric synthetic rig: LuGre friction, Stribeck curve (torchfric.rig)",
        "seed": int(seed),
        "parameters": {"nominal": nominal.to_dict(), "changed": changed.to_dict()},
        "experiments": per_experiment,
        "steady_state_friction": {
            "columns": ["v", "F_ss"],
            "nominal": _friction_table(nominal, grid),
            "changed": _friction_table(changed, grid),
        },
    }
    path = out / "truth.json"
    atomic_write_text(path, json.dumps(truth, indent=1, sort_keys=True) + "\n")
    paths["truth"] = path
    path = out / "truth_states.npz"
    _write_npz(path, states)
    paths["truth_states"] = path
    return paths
