"""Choosing by open-loop simulation: an ensemble's member, and the windows that score a class.

`select_by_fit`: every member that has a pass to show is simulated open loop (all members as one batch) on the
validation experiments and on the training experiments; its score is the mean FIT of q and q̇ on
the validation files and the mean FIT on the training files, weighted equally (the training
files alone when there is no validation). Only when no member simulates does the innovation
log-likelihood decide.

`window_errors`: short open-loop predictions started from a fixed-θ filter's estimates, the
score `torchfric.estimators.sizing.compare_dynamics` chooses static or LuGre friction by.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from ..data import Experiment
from ..errors import TorchfricError
from ..models.arm import ArmModel
from ..models.simulate import auto_substeps, simulate
from .ekf import EKFState, make_propagator, make_step, run_pass
from .metrics import fit_percent_batch
from .passes import initial_belief, measurements
from .settings import EKFTuning

__all__ = [
    "simulate_members",
    "select_by_fit",
    "window_errors",
]

# Windows simulated in one batch by `window_errors`, always this many (the last batch repeats its
# last window): one shape, so one generated simulation step serves every record (all 1800
# windows of a 5-minute record's end at once were a 28 s compile, past the generated code's
# size for LuGre, so an Inductor scan compiled anew in every process, and 280 MB kept).
WINDOW_BATCH = 64


@torch.no_grad()
def simulate_members(
    model: ArmModel,
    thetas: Tensor,
    exp: Experiment,
    *,
    max_substeps: int = 64,
    engine: str = "odeint",
) -> Tensor:
    """Open-loop simulations `(N, K, 2)` of `exp` from its measured initial state for K θ's.

    Each member is simulated with the RK4 sub-step count it needs (`auto_substeps`), so one
    stiff member does not make every other member's simulation slow. A member that would need
    more than `max_substeps` is not simulated: its rows are NaN (scored as a failed run).
    `engine` as in `simulate`: with "compiled" every sub-step count runs the whole batch of K
    (one compiled shape, so one compile per model structure) and keeps its own members' rows;
    odeint batches only the members that share a count. The same RK4 steps either way (the
    compiled engine equals odeint to 1e-12, tested).
    """
    if exp.qdot is None:
        raise TorchfricError(f"experiment {exp.name!r} has no velocity to score against")
    K = thetas.shape[0]
    need = [
        auto_substeps(model, exp.dt, theta=thetas[j], max_substeps=max_substeps + 1)
        for j in range(K)
    ]
    x0 = torch.stack([exp.q[0], exp.qdot[0]]).to(torch.float64)
    u = exp.u.to(torch.float64)
    if len(set(need)) == 1 and need[0] <= max_substeps:  # one batch: its result as it is
        return simulate(
            model, exp.t, u[:, None].expand(-1, K), x0.expand(K, 2), theta=thetas,
            substeps=need[0], engine=engine,
        )  # fmt: skip
    out = torch.full((exp.n, K, 2), float("nan"), dtype=torch.float64)
    for steps in sorted(set(need)):
        if steps > max_substeps:
            continue
        idx = [j for j in range(K) if need[j] == steps]
        run = list(range(K)) if engine == "compiled" else idx
        B = len(run)
        sim = simulate(
            model, exp.t, u[:, None].expand(-1, B), x0.expand(B, 2), theta=thetas[run],
            substeps=steps, engine=engine,
        )  # fmt: skip
        out[:, idx] = sim[:, [run.index(j) for j in idx]]
    return out


def select_by_fit(
    model: ArmModel,
    thetas: Tensor,
    alive: list[int],
    experiments: Sequence[Experiment],
    validation: Sequence[Experiment],
    loglik: Tensor,
    *,
    max_substeps: int = 64,
    engine: str = "odeint",
) -> tuple[Tensor, list[dict[str, dict[str, float]]], str]:
    """Score the members `alive` (indices into `thetas` `(K, k)`) for the selection.

    Returns the scores `(K,)` (−inf for members not scored or whose simulation failed), each
    member's ``{experiment: {"fit_q", "fit_qdot"}}`` and the rule used:
    "validation_and_train_fit", "train_fit" or "loglik" (no member simulates: the scores are
    the members' `loglik`).
    """
    # Selection by open-loop simulation of every record there is: the mean FIT (q and q̇) on
    # the validation files and the mean FIT on the training files, weighted equally (training
    # files alone when there is no validation). The EKF never fits open-loop simulations, so
    # the training files are a second check, not a fitted score; on the rig, validation alone
    # kept a polytopic member 3 % off in inertia for one user tuning in nine, both kept a
    # physical member for all nine (benchmarks/robustness.py, which shows each rule).
    # Not by the innovation likelihood: members differ in R and Q, and the likelihood prefers the
    # smallest R that the data allow, which on the rig is the member with the worst friction
    # curve. The likelihood only decides when no member simulates.
    f64 = torch.float64
    K = thetas.shape[0]
    scores = torch.full((K,), -math.inf, dtype=f64)
    fits: list[dict[str, dict[str, float]]] = [{} for _ in range(K)]
    idx = torch.tensor(alive)
    # (training files without a velocity, e.g. measure = "position", cannot be simulated from
    # their measured state and are left out)
    groups = [g for g in (list(validation), [e for e in experiments if e.qdot is not None]) if g]
    total = torch.zeros(len(alive), dtype=f64)
    for group in groups:
        group_fit = torch.zeros(len(alive), dtype=f64)
        for v in group:
            sim = simulate_members(model, thetas[idx], v, max_substeps=max_substeps, engine=engine)
            fq = fit_percent_batch(v.q.to(f64), sim[..., 0])
            fv = fit_percent_batch(v.qdot.to(f64), sim[..., 1])
            group_fit += 0.5 * (fq + fv) / len(group)
            for a, i in enumerate(alive):
                fits[i][v.name] = {"fit_q": float(fq[a]), "fit_qdot": float(fv[a])}
        total += group_fit / len(groups)
    if groups:
        scores[idx] = torch.nan_to_num(total, nan=-math.inf)
    selected_by = "validation_and_train_fit" if validation else "train_fit"
    if not bool(torch.isfinite(scores).any()):
        for i in alive:
            scores[i] = loglik[i]
        selected_by = "loglik"
    return scores, fits, selected_by


@torch.no_grad()
def window_errors(
    model: ArmModel,
    theta: Tensor,
    exp: Experiment,
    tuning: EKFTuning,
    start: int,
    window: int,
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
) -> Tensor:
    """`(W,)` mean squared position errors of open-loop simulations over the windows of `window`
    samples that tile `exp` from sample `start` on, each started from the filter's estimate.

    The filter (`tuning` resolved, its Q and R times `q_scale` and `r_scale`) runs over the
    whole record with θ held fixed at `theta` (no process noise on θ, ``P_θθ = 0``); at each
    window's first sample a its filtered state ``x̂(a|a)`` (q, q̇ and a dynamic model's bristle
    deflection z, from the measurements up to a only) starts a simulation of the next `window`
    samples under the recorded input, scored against the measured q of samples a+1 … a+window.
    The score is a k-step-ahead prediction error: causal, and free of the slow drift that
    makes a whole-record simulation of a position-loop record meaningless after seconds.
    """
    f64 = torch.float64
    k = model.num_parameters
    s = model.state_size
    Q, P0_xx, H, R = tuning.matrices(k, s)
    Q = Q * q_scale
    Q[s:, s:] = 0.0
    R = R * r_scale
    flow = make_propagator(model, tuning.substeps)
    step_fn = make_step(flow, compile=tuning.compile)  # the record up to the first window
    per_window = make_step(flow, compile=tuning.compile, chunk=window)  # one unpadded call each
    u = exp.u.to(f64)
    y = measurements(exp, tuning.measure)
    dt = torch.tensor(exp.dt, dtype=f64)
    x, P = initial_belief(exp, theta[None].to(f64), torch.zeros(1, k, k, dtype=f64), P0_xx)
    state, _ = run_pass(EKFState(x[0], P[0]), u[: start + 1], y[: start + 1], dt, Q, H, R,
                        step_fn, theta_bound=tuning.theta_bound)  # fmt: skip
    firsts = list(range(start, exp.n - window, window))
    if not firsts:
        raise TorchfricError(
            f"experiment {exp.name!r}: no window of {window} samples after sample {start}"
        )
    x0 = []
    for a in firsts:
        if a > start:
            state, _ = run_pass(state, u[a - window : a + 1], y[a - window : a + 1], dt, Q, H, R,
                                per_window, theta_bound=tuning.theta_bound, continuing=True)  # fmt: skip
        x0.append(state.x[:s])
    idx = torch.tensor(firsts)[None, :] + torch.arange(window + 1)[:, None]  # (window+1, W)
    t = exp.t.to(f64)[: window + 1] - exp.t[0]
    q, starts = exp.q.to(f64), torch.stack(x0)
    out = []
    for b in range(0, len(firsts), WINDOW_BATCH):  # each window is its own simulation
        take = torch.arange(b, b + WINDOW_BATCH).clamp(max=len(firsts) - 1)  # last: repeated
        cols = idx[:, take]
        sim = simulate(model, t, u[cols], starts[take], theta=theta.to(f64), engine="compiled")
        err = sim[1:, :, 0] - q[cols[1:]]
        out.append((err * err).mean(dim=0)[: len(firsts) - b])
    return torch.cat(out)
