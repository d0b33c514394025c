"""Simulation-quality metrics: FIT and RMS of open-loop simulations against measurements."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from ..data import Experiment
from ..errors import TorchfricError
from ..models.arm import ArmModel
from ..models.simulate import simulate

__all__ = [
    "fit_percent",
    "fit_percent_batch",
    "mean_fit",
    "rms",
    "SimulationScore",
    "score_simulation",
    "window_initial_state",
    "score_benchmark",
    "friction_curve_error",
]


def fit_percent(y: Tensor, y_hat: Tensor) -> float:
    """FIT % = 100 (1 − ‖y − ŷ‖ / ‖y − mean(y)‖); 100 is perfect, can be negative."""
    y = torch.as_tensor(y, dtype=torch.float64)
    y_hat = torch.as_tensor(y_hat, dtype=torch.float64)
    if float((y - y.mean()).norm()) == 0.0:
        raise TorchfricError("FIT is undefined for a constant signal (zero variance)")
    return float(fit_percent_batch(y.reshape(-1), y_hat.reshape(-1, 1))[0])


def fit_percent_batch(y: Tensor, y_hat: Tensor) -> Tensor:
    """FIT % of K simulations of one signal at once: `y (N,)`, `y_hat (N, K)` → `(K,)`.

    The formula of `fit_percent`, without its check: NaN where a simulation is NaN (a failed
    run), and ±inf or NaN for a constant `y`.
    """
    den = (y - y.mean()).norm()
    return 100.0 * (1.0 - (y[:, None] - y_hat).norm(dim=0) / den)


def mean_fit(fits: Mapping[str, Mapping[str, float]] | None) -> float | None:
    """The validation score: the mean over records of (FIT_q + FIT_q̇) / 2, or None when there
    are no scores. Both estimators keep the pass or epoch with the highest."""
    if not fits:
        return None
    vals = [0.5 * (v["fit_q"] + v["fit_qdot"]) for v in fits.values()]
    return sum(vals) / len(vals)


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
    engine: str = "odeint",
) -> SimulationScore:
    """Simulate `experiment` open loop from ``[q_0, q̇_0]`` and score q and q̇.

    q̇ is scored against the experiment's `qdot` (reconstructed or measured); `skip` leading
    samples are left out of the scores (a benchmark's state-initialisation window). `engine` as
    in `simulate`.
    """
    if experiment.qdot is None:
        raise TorchfricError(
            f"experiment {experiment.name!r} has no velocity to score against; reconstruct it first"
        )
    x0 = torch.stack([experiment.q[0], experiment.qdot[0]])
    states = simulate(
        model, experiment.t, experiment.u, x0, method=method, substeps=substeps, engine=engine
    )
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


def window_initial_state(q: Tensor, dt: float, n: int) -> Tensor:
    """``[q, q̇]`` at sample ``n − 1`` from the first `n` position samples alone.

    A least-squares quadratic ``q(t) ≈ c0 + c1 t + c2 t²`` through ``q[:n]`` (t relative to
    sample ``n − 1``), evaluated at sample ``n − 1``: ``[c0, c1]``. Needs ``n >= 3``. This is how a
    benchmark's state-initialisation window (EMPS: n = 20) is used; no velocity measurement and
    no later sample enters.
    """
    q = torch.as_tensor(q, dtype=torch.float64).reshape(-1)
    if isinstance(n, bool) or not isinstance(n, int) or n < 3 or n > q.numel():
        raise TorchfricError(
            f"initial-state window n = {n!r} is invalid for {q.numel()} samples; expected an "
            "integer 3 <= n <= N (a quadratic needs 3 points)"
        )
    t = (torch.arange(n, dtype=torch.float64) - (n - 1)) * dt
    A = torch.stack([torch.ones_like(t), t, t * t], dim=1)
    # "gelsd": the default "gelsy" reads an uninitialised pivot array (pytorch#71222), so its
    # result depends on the allocator's history
    coef = torch.linalg.lstsq(A, q[:n].unsqueeze(1), driver="gelsd").solution.squeeze(1)
    return coef[:2]


@torch.no_grad()
def score_benchmark(
    model: ArmModel,
    experiment: Experiment,
    *,
    n_init: int = 20,
    skip: int | None = None,
    method: str = "rk4",
    substeps: int | str = "auto",
    engine: str = "odeint",
) -> SimulationScore:
    """Score an open-loop simulation the way the nonlinear benchmarks do (EMPS: n_init = 20).

    The first `n_init` measured positions set the initial state (`window_initial_state`, at
    sample ``n_init − 1``); from there the model is simulated open loop from the input alone, and
    samples ``skip …`` are scored (default ``skip = n_init``; ``rms_q`` is the benchmark's RMSE).
    ``states`` `(N, 2)` repeats the initial state in rows ``< n_init − 1``. The q̇ scores are NaN
    when the experiment has no velocity. `engine` as in `simulate`: "compiled" gives odeint's
    rk4 steps to rounding, several hundred times faster on a 25 k-sample record.
    """
    skip = n_init if skip is None else skip
    k = n_init - 1
    x0 = window_initial_state(experiment.q, experiment.dt, n_init)
    if isinstance(skip, bool) or not isinstance(skip, int) or not n_init <= skip < experiment.n:
        raise TorchfricError(
            f"skip = {skip!r} is invalid for {experiment.n} samples; expected an integer with "
            f"n_init = {n_init} <= skip < N (the scored samples follow the initial-state window)"
        )
    sim = simulate(
        model,
        experiment.t[k:],
        experiment.u[k:],
        x0,
        method=method,
        substeps=substeps,
        engine=engine,
    )
    states = torch.cat([x0.expand(k, 2), sim])
    q = experiment.q[skip:]
    nan = float("nan")
    v = experiment.qdot[skip:] if experiment.qdot is not None else None
    return SimulationScore(
        name=experiment.name,
        fit_q=fit_percent(q, states[skip:, 0]),
        fit_qdot=nan if v is None else fit_percent(v, states[skip:, 1]),
        rms_q=rms(q, states[skip:, 0]),
        rms_qdot=nan if v is None else rms(v, states[skip:, 1]),
        states=states,
    )


@torch.no_grad()
def friction_curve_error(model: ArmModel, v: Tensor, reference: Tensor) -> float:
    """RMS of (identified total friction − reference) over `v`, relative to max |reference|."""
    err = model.friction_torque(v) - reference
    return float(err.pow(2).mean().sqrt() / reference.abs().max())
