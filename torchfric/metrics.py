"""Simulation-quality metrics: FIT and RMS of open-loop simulations against measurements."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .arm import ArmModel
from .data import Experiment
from .errors import TorchfricError
from .simulate import simulate

__all__ = ["fit_percent", "rms", "SimulationScore", "score_simulation", "friction_curve_error"]


def fit_percent(y: Tensor, y_hat: Tensor) -> float:
    """FIT % = 100 (1 − ‖y − ŷ‖ / ‖y − mean(y)‖); 100 is perfect, can be negative."""
    y = torch.as_tensor(y, dtype=torch.float64)
    y_hat = torch.as_tensor(y_hat, dtype=torch.float64)
    den = float((y - y.mean()).norm())
    if den == 0.0:
        raise TorchfricError("FIT is undefined for a constant signal (zero variance)")
    return 100.0 * (1.0 - float((y - y_hat).norm()) / den)


def rms(y: Tensor, y_hat: Tensor) -> float:
    """Root-mean-square error."""
    return float((torch.as_tensor(y) - torch.as_tensor(y_hat)).pow(2).mean().sqrt())


@dataclass
class SimulationScore:
    """Open-loop simulation of one experiment from its measured initial state."""

    name: str
    fit_q: float
    fit_qdot: float
    rms_q: float
    rms_qdot: float
    states: Tensor  # (N, 2) simulated [q, q̇]

    def to_dict(self) -> dict[str, float]:
        return {
            "fit_q": self.fit_q,
            "fit_qdot": self.fit_qdot,
            "rms_q": self.rms_q,
            "rms_qdot": self.rms_qdot,
        }


@torch.no_grad()
def score_simulation(
    model: ArmModel,
    experiment: Experiment,
    *,
    method: str = "rk4",
    substeps: int | str = "auto",
    skip: int = 0,
) -> SimulationScore:
    """Simulate `experiment` open loop from ``[q_0, q̇_0]`` and score q and q̇.

    q̇ is scored against the experiment's `qdot` (reconstructed or measured); `skip` leading
    samples are left out of the scores (a benchmark's state-initialisation window).
    """
    if experiment.qdot is None:
        raise TorchfricError(
            f"experiment {experiment.name!r} has no velocity to score against; reconstruct it first"
        )
    x0 = torch.stack([experiment.q[0], experiment.qdot[0]])
    states = simulate(model, experiment.t, experiment.u, x0, method=method, substeps=substeps)
    sl = slice(skip, None)
    q, v = experiment.q[sl], experiment.qdot[sl]
    return SimulationScore(
        name=experiment.name,
        fit_q=fit_percent(q, states[sl, 0]),
        fit_qdot=fit_percent(v, states[sl, 1]),
        rms_q=rms(q, states[sl, 0]),
        rms_qdot=rms(v, states[sl, 1]),
        states=states,
    )


@torch.no_grad()
def friction_curve_error(model: ArmModel, v: Tensor, reference: Tensor) -> float:
    """RMS of (identified total friction − reference) over `v`, relative to max |reference|."""
    err = model.friction_torque(v) - reference
    return float(err.pow(2).mean().sqrt() / reference.abs().max())
