"""A user's linear carriage with sharp stiction, simulated independently of torchfric: what the
default run reports there, and how far the true model class would reach (issue 31).

    python benchmarks/carriage.py                       # seeds 1 2 3, no disturbance, Coulomb
    python benchmarks/carriage.py --static 6 --disturbance 0.3 --seeds 11 12 13 14

The machine (a belt-driven carriage as a user would simulate it): mass 2.5 kg, c_m 12 N/A,
viscous 8 N s/m, Coulomb 4 N (``--static``: a Gaussian Stribeck dip to that level at
0.02 m/s), ``tanh(v / 1e-4 m/s)`` for the sign, a 1 µm encoder, a PD position loop on three
sines (|u| <= 3 A) and an optional 15-Hz band-limited load disturbance (``--disturbance``, std
in N). Its records stick and slip. Each seed writes a 30-s identification and a 20-s
validation record the way lab software does (semicolons, decimal commas, time in ms, counts);
``torchfric init --c-m 12 --counts-per-m 1e6`` and ``torchfric train`` run with every default.

Printed per seed: M and b with their ± σ and (estimate − truth)/σ, the validation FIT, and the
FIT the true law reaches when its sign function is drawn by one tanh neuron of slope W1 (the
model class's own ceiling as a function of the steepest neuron; truth W1 = 1e4).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import subprocess
import sys
import tempfile

import numpy as np
import torch

import torchfric

M, CM, B, FC, VS, EPS, CPM = 2.5, 12.0, 8.0, 4.0, 0.02, 1e-4, 1_000_000
FS_DEFAULT, DIST_DEFAULT = 6.0, 0.3  # the carriage `benchmarks/tracking.py` tracks [N]


def friction(v: float, fs: float, fc: float = FC) -> float:
    """The carriage's friction force [N] at velocity v [m/s]: b v and the Stribeck law."""
    return (fc + (fs - fc) * math.exp(-((v / VS) ** 2))) * math.tanh(v / EPS) + B * v


def simulate(seconds: float, seed: int, fs: float, disturbance: float, dt: float = 1e-3,
             sub: int = 10, change: tuple[float, float] | None = None,
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(t, u, encoder counts, true velocity): RK4 with `sub` steps per sample, the PD loop at
    the samples; `change` = (time, factor): Fc and Fs times factor from that time on."""
    rng = np.random.default_rng(seed)
    n = round(seconds / dt)
    t = np.arange(n) * dt
    ph = rng.uniform(0, 2 * np.pi, 3)
    ref = (0.04 * np.sin(2 * np.pi * 0.3 * t + ph[0]) + 0.015 * np.sin(2 * np.pi * 0.9 * t + ph[1])
           + 0.005 * np.sin(2 * np.pi * 2.1 * t + ph[2]))  # fmt: skip
    spectrum = np.fft.rfft(rng.standard_normal(n))
    spectrum[np.fft.rfftfreq(n, dt) > 15.0] = 0.0
    dist = np.fft.irfft(spectrum, n)
    dist = disturbance * dist / dist.std()
    q = v = 0.0
    Q, U, V, h = np.empty(n), np.empty(n), np.empty(n), dt / sub
    for k in range(n):
        u = min(3.0, max(-3.0, 40.0 * (ref[k] - q) - 1.5 * v))
        Q[k], U[k], V[k] = q, u, v
        force = CM * u + dist[k]
        gain = change[1] if change is not None and t[k] >= change[0] else 1.0

        def acc(w: float, force: float = force, gain: float = gain) -> float:
            return (force - friction(w, gain * fs, gain * FC)) / M

        for _ in range(sub):
            a1 = acc(v)
            v2 = v + 0.5 * h * a1
            a2 = acc(v2)
            v3 = v + 0.5 * h * a2
            a3 = acc(v3)
            v4 = v + h * a3
            a4 = acc(v4)
            q += h / 6 * (v + 2 * v2 + 2 * v3 + v4)
            v += h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
    return t, U, np.round(Q * CPM).astype(np.int64), V


def write(path: pathlib.Path, t: np.ndarray, u: np.ndarray, counts: np.ndarray, *_: object) -> None:
    """The record as lab software writes it (semicolons, decimal commas, ms, counts)."""
    with open(path, "w", newline="\r\n", encoding="utf-8") as f:
        f.write("Zeit [ms];Strom [A];Position [counts]\n")
        for tk, uk, ck in zip(t, u, counts, strict=True):
            f.write(f"{tk * 1000:.1f}".replace(".", ",") + ";" + f"{uk:.6f}".replace(".", ",")
                    + f";{ck}\n")  # fmt: skip


def ceiling(t: np.ndarray, u: np.ndarray, counts: np.ndarray, _v: np.ndarray, fs: float,
            ) -> dict[float, float]:  # fmt: skip
    """Validation FIT of the true machine drawn by torchfric's model class (one tanh neuron of
    slope W1 and height Fc, b, M, c_m true; Coulomb machines only: the Stribeck dip is not in
    one neuron), simulated with the default sub-step rule."""
    if fs != FC:
        return {}
    q = torch.tensor(counts / CPM)
    out = {}
    for w1 in (1e3, 3e3, 1e4, 3e4):
        model = torchfric.ArmModel(torchfric.OddTanhFriction(1, w1=[w1], w2=[FC]), inertia=M,
                                   viscous=B, c_m=CM)  # fmt: skip
        x = torchfric.simulate(model, torch.tensor(t), torch.tensor(u), torch.zeros(2),
                               max_substeps=256, engine="compiled").detach()  # fmt: skip
        out[w1] = float(torchfric.fit_percent(q, x[:, 0]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--static", type=float, default=FC, help="Fs [N] (4: Coulomb only)")
    ap.add_argument("--disturbance", type=float, default=0.0, help="load disturbance std [N]")
    ap.add_argument("--out", type=pathlib.Path, default=None)
    args = ap.parse_args()
    torch.set_default_dtype(torch.float64)
    root = args.out or pathlib.Path(tempfile.mkdtemp(prefix="carriage-"))
    root.mkdir(parents=True, exist_ok=True)
    cli = [sys.executable, "-m", "torchfric"]
    print(f"carriage: M {M} kg, b {B} N s/m, Fc {FC} N, Fs {args.static} N, 1 µm encoder, "
          f"disturbance {args.disturbance} N; runs in {root}")  # fmt: skip
    print("| seed | M ± σ | z_M | b ± σ | z_b | kept pass | validation FIT q | "
          "true law, FIT q at W1 = 1e3 / 3e3 / 1e4 / 3e4 |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        d = root / f"seed{seed}"
        d.mkdir(exist_ok=True)
        write(d / "ident.csv", *simulate(30.0, seed, args.static, args.disturbance))
        val = simulate(20.0, seed + 100, args.static, args.disturbance)
        write(d / "val.csv", *val)
        subprocess.run([*cli, "init", "ident.csv", "--c-m", "12", "--counts-per-m", "1e6",
                        "--force"], cwd=d, check=True, capture_output=True)  # fmt: skip
        res = subprocess.run([*cli, "train", "ident.toml", "--set", 'data.validation=["val.csv"]',
                              "--set", "model.dynamic=none",  # the static model's bias, as measured
                              "--json", "--quiet"], cwd=d, check=True, capture_output=True,
                             text=True)  # fmt: skip
        r = json.loads(res.stdout)
        p = r["parameters"]
        (m, sm), (b, sb) = ((p[k]["value"], p[k]["std"]) for k in ("inertia", "viscous"))
        fit = next(iter(r["validation"].values()))["fit_q"]
        top = ceiling(*val, args.static)
        tops = " / ".join(f"{top[w]:.3f}" for w in sorted(top)) if top else "—"
        print(f"| {seed} | {m:.5g} ± {sm:.2g} | {(m - M) / sm:+.1f} | {b:.5g} ± {sb:.2g} | "
              f"{(b - B) / sb:+.1f} | {r['best_pass']} ({r['stopped']}) | {fit:.2f} | {tops} |",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
