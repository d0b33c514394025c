"""The run's figures (matplotlib, drawn off-screen): the friction curve and a simulated response.

Both return a matplotlib figure for TensorBoard's ``add_figure``; positions are in the SI unit
that `data.position_unit` converts to.
"""

from __future__ import annotations

from typing import Any

import torch

from ..data import Experiment
from ..estimators.metrics import SimulationScore
from ..models.arm import ArmModel

__all__ = ["friction_figure", "response_figure", "si_unit"]


def si_unit(unit: str) -> str:
    """The unit positions are converted to (data.position_unit → SI)."""
    return "m" if unit in ("m", "mm") else "rad"


def _pyplot() -> Any:
    """matplotlib's pyplot on the off-screen Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def friction_figure(model: ArmModel, v_max: float, title: str, unit: str = "rad") -> Any:
    """The model's friction torque (viscous, Coulomb-like and offset terms) over ±`v_max`."""
    plt = _pyplot()
    v = torch.linspace(-v_max, v_max, 801, dtype=torch.float64)
    with torch.no_grad():
        f = model.friction_torque(v)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(v.numpy(), f.numpy())
    force = "N" if unit in ("m", "mm") else "N m"
    ax.set_xlabel(f"velocity q̇ [{si_unit(unit)}/s]")
    ax.set_ylabel(f"friction b·q̇ + C(q̇) + offset [{force}]")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    # fixed margins: `tight_layout` measured every label and cost as much as the drawing
    fig.subplots_adjust(left=0.15, right=0.97, bottom=0.12, top=0.92)
    return fig


def response_figure(exp: Experiment, score: SimulationScore, unit: str = "rad") -> Any:
    """Measured against open-loop simulated q and q̇ of one record, titled with the FITs."""
    plt = _pyplot()
    t = exp.t.numpy()
    fig, ax = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    ax[0].plot(t, exp.q.numpy(), label="measured")
    ax[0].plot(t, score.states[:, 0].numpy(), "--", label="simulated")
    ax[0].set_ylabel(f"q [{si_unit(unit)}]")
    ax[0].legend(loc="best")
    ax[1].plot(t, exp.qdot.numpy(), label="reconstructed")
    ax[1].plot(t, score.states[:, 1].numpy(), "--", label="simulated")
    ax[1].set_ylabel(f"q̇ [{si_unit(unit)}/s]")
    ax[1].set_xlabel("t [s]")
    ax[0].set_title(f"{exp.name}: FIT q {score.fit_q:.1f} %, q̇ {score.fit_qdot:.1f} %")
    fig.subplots_adjust(left=0.1, right=0.98, bottom=0.1, top=0.93, hspace=0.08)
    return fig
