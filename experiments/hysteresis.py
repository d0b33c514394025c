"""Pre-sliding hysteresis of the identified LuGre model beside the static fit (issue 23).

    python experiments/hysteresis.py              # from checkpoints/ -> experiments/figures/
    python experiments/hysteresis.py --out DIR    # write the figure elsewhere

Left: friction torque against displacement while the rig is driven by a slow sine whose
torque (0.9 Fs at its peak) stays below breakaway: the true rig (its own LuGre simulator, no
disturbance), the identified LuGre model (`checkpoints/arm_lugre_ekf.pt`) and the identified
static model (`checkpoints/arm_tanh_ekf.pt`, the paper's tanh(3) EKF). A LuGre system deflects
its bristles elastically and traces a closed hysteresis loop within a few encoder counts; a
static model has no stick at all, so it creeps at the velocity where its curve equals the
applied torque and drifts. Right: the steady-state friction curves, where the two models agree
with each other and with the truth. Every model is simulated from rest.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import pathlib

import numpy as np
import torch

from torchfric import ArmModel, load_checkpoint
from torchfric.data.rig import RigParameters, simulate_rig

ROOT = pathlib.Path(__file__).resolve().parents[1]
DT, SECONDS, FREQ = 1e-3, 4.0, 0.5  # two periods of a 0.5 Hz sine


def drive(p: RigParameters) -> np.ndarray:
    """The input current: 0.9 Fs of torque at its peak (below breakaway: the rig sticks)."""
    t = np.arange(int(SECONDS / DT)) * DT
    return 0.9 * p.Fs / p.c_m * np.sin(2 * math.pi * FREQ * t)


def friction_along(model: ArmModel, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Displacement q and friction torque along the model's own response to `u` from rest,
    stepped at 0.1 ms (a dynamic model: F = σ0 z + σ1 ż + b q̇ from its bristle state; a static
    one: its curve at q̇)."""
    theta = model.get_theta()
    fric, arm = model.split(theta)
    steps = 10
    h = DT / steps
    x = torch.zeros(model.state_size, dtype=torch.float64)
    qs, fs = [], []
    with torch.no_grad():
        for uk in torch.tensor(u):
            for _ in range(steps):
                if model.state_size == 2:
                    k1 = model.dynamics(x, uk, fric, arm)  # explicit midpoint (stiffness allows)
                    x = x + h * model.dynamics(x + 0.5 * h * k1, uk, fric, arm)
                else:
                    x = model.substep(x, uk, h, fric, arm)
            if model.state_size == 2:
                force = model.friction_torque(x[1:2], theta)[0]
            else:
                # the friction is what the field leaves of the motor torque: c_m u − M q̈
                acc = model.dynamics(x, uk, fric, arm)[1]
                force = arm["c_m"] * uk - arm["inertia"] * acc
            qs.append(float(x[0]))
            fs.append(float(force))
    return np.asarray(qs), np.asarray(fs)


def figure(out: pathlib.Path) -> pathlib.Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truth = dataclasses.replace(RigParameters(), disturbance_std=0.0)
    lugre = load_checkpoint(ROOT / "checkpoints" / "arm_lugre_ekf.pt")
    static = load_checkpoint(ROOT / "checkpoints" / "arm_tanh_ekf.pt")
    u = drive(truth)
    rig = simulate_rig(truth, u, seed=0)
    q_l, f_l = friction_along(lugre, u)
    q_s, f_s = friction_along(static, u)
    urad = 1e3  # plot in mrad
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax.plot(rig["q_true"] * urad, rig["friction"], "k", lw=2.2, label="rig (true LuGre)")
    ax.plot(q_l * urad, f_l, "C0--", lw=1.6, label="identified LuGre tanh(4)")
    drift = f"static tanh(3): creeps {abs(q_s).max() * urad:.0f} mrad (off the axes)"
    ax.plot(q_s * urad, f_s, "C3:", lw=1.4, label=drift)
    span = max(abs(rig["q_true"]).max(), abs(q_l).max()) * urad * 1.3
    ax.set_xlim(-span, span)
    ax.set_ylim(-1.15 * truth.Fs, 1.15 * truth.Fs)
    for k in range(-3, 4):
        ax.axvline(k * truth.quantum * urad, color="0.85", lw=0.6, zorder=0)
    ax.set_xlabel("displacement q [mrad] (grey: encoder counts)")
    ax.set_ylabel("friction torque [N m]")
    ax.set_title("pre-sliding: torque 0.9 Fs, 0.5 Hz, below breakaway")
    ax.legend(loc="upper left", fontsize=8)
    v = torch.linspace(-10, 10, 2001, dtype=torch.float64)
    with torch.no_grad():
        bx.plot(v, truth.steady_state_friction(v), "k", lw=2.2, label="rig (true)")
        bx.plot(v, lugre.friction_torque(v), "C0--", lw=1.6, label="LuGre tanh(4), steady state")
        bx.plot(v, static.friction_torque(v), "C3:", lw=1.4, label="static tanh(3)")
    bx.set_xlabel("velocity q̇ [rad/s]")
    bx.set_ylabel("friction torque [N m]")
    bx.set_title("steady-state friction curves")
    bx.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "fig6_lugre_hysteresis.png"
    fig.savefig(path, dpi=110, metadata={"Software": None})
    plt.close(fig)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "experiments" / "figures"))
    print(figure(pathlib.Path(parser.parse_args().out)))


if __name__ == "__main__":
    main()
