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
from concurrent.futures import ThreadPoolExecutor

import torch
from torch import Tensor

from ..accel import Step, iter_chunks, rk4_chunk, structure_key
from ..data import Experiment
from ..errors import TorchfricError
from ..models.arm import ArmModel
from ..models.simulate import auto_substeps, simulate
from .ekf import (
    EKFState,
    FilterFailure,
    fixed_theta_chunks,
    healthy,
    make_fixed_theta_step,
    update,
)
from .metrics import fit_percent_batch
from .passes import measurements, state_belief
from .settings import EKFTuning

__all__ = [
    "simulate_members",
    "select_by_fit",
    "window_errors",
    "filtered_states",
]

# Windows simulated in one batch by `window_errors`, always this many (the last batch repeats its
# last window). The batch runs through the member program (`rk4_members_chunk`), traced for one
# window, so its size no longer shapes the generated code; until 2026-12-08 the batch was traced
# whole, 64 copies of the step in one C function (LuGre: 11 s of gcc on a machine's first auto
# run; all 1800 windows of a 5-minute record at once had been past the code's size ceiling).
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
    `engine` as in `simulate`: when every member needs the same count they run as one batch;
    otherwise odeint batches the members that share a count and "compiled" runs each member
    alone, in the shape of a single simulation (generated code that every model structure has
    anyway), the first alone and the others on a thread per core when the generated code ran
    (its calls free the GIL; an Inductor or eager fallback stays on one thread). The same RK4
    steps either way (the compiled engine equals odeint to 1e-12, tested), and each member's
    rows are the same bits alone or in a batch. Until 2026-11-28 "compiled" ran the whole
    batch once per count and kept each count's own rows: the nine LuGre members of a
    20-minute record needed 5 counts (7 … 40 sub-steps), so 1,089 member sub-steps a sample
    did the work of 142, 234 s of that run's 464 (now 52 s) and its peak memory, 1.59 GiB,
    five batches' results of the record's length.
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
    if engine == "compiled":
        from ..accel.native import thread_count  # (imported where the generated code runs)

        alone = [j for j in range(K) if need[j] <= max_substeps]

        def one(j: int) -> None:
            with torch.no_grad():  # (grad mode is per thread: a worker starts with it on)
                out[:, j] = simulate(model, exp.t, u, x0, theta=thetas[j], substeps=need[j],
                                     engine=engine)  # fmt: skip

        if not alone:
            return out
        one(alone[0])  # the first builds (or loads) the step's generated code, alone
        rest, threads = alone[1:], thread_count(len(alone) - 1)
        if threads > 1 and getattr(rk4_chunk(model), "path", None) == "native":  # frees the GIL
            with ThreadPoolExecutor(threads) as pool:
                list(pool.map(one, rest))
        else:
            for j in rest:
                one(j)
        return out
    for steps in sorted(set(need)):
        if steps > max_substeps:
            continue
        idx = [j for j in range(K) if need[j] == steps]
        B = len(idx)
        out[:, idx] = simulate(
            model, exp.t, u[:, None].expand(-1, B), x0.expand(B, 2), theta=thetas[idx],
            substeps=steps, engine=engine,
        )  # fmt: skip
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
    firsts = list(range(start, exp.n - window, window))
    if not firsts:
        raise TorchfricError(
            f"experiment {exp.name!r}: no window of {window} samples after sample {start}"
        )
    kw = {"q_scale": q_scale, "r_scale": r_scale, "samples": firsts[-1] + 1}
    starts = filtered_states(model, theta, exp, tuning, **kw)[firsts]
    u = exp.u.to(f64)
    idx = torch.tensor(firsts)[None, :] + torch.arange(window + 1)[:, None]  # (window+1, W)
    t = exp.t.to(f64)[: window + 1] - exp.t[0]
    q = exp.q.to(f64)
    out = []
    for b in range(0, len(firsts), WINDOW_BATCH):  # each window is its own simulation
        take = torch.arange(b, b + WINDOW_BATCH).clamp(max=len(firsts) - 1)  # last: repeated
        cols = idx[:, take]
        sim = simulate(model, t, u[cols], starts[take], theta=theta.to(f64), engine="compiled")
        err = sim[1:, :, 0] - q[cols[1:]]
        out.append((err * err).mean(dim=0)[: len(firsts) - b])
    return torch.cat(out)


@torch.no_grad()
def filtered_states(
    model: ArmModel,
    theta: Tensor,
    exp: Experiment,
    tuning: EKFTuning,
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    samples: int | None = None,
) -> Tensor:
    """`(n, s)` the filtered states ``x̂(t|t)`` of the first `samples` (all by default) of `exp`
    (q, q̇ and a dynamic model's z) by the filter with θ held at `theta`
    (`make_fixed_theta_step`, `tuning`'s Q and R times `q_scale` and `r_scale`): one pass, the
    states the per-sample outputs of the generated step, as the prediction-error stage's
    innovations are. The augmented filter with ``P_θθ = 0`` and no process noise on θ gives the
    same states bit for bit (tested).

    Raises:
        FilterFailure: the filter failed (the first bad sample; the belief at the start of the
            call that met it).
    """
    f64 = torch.float64
    k, s = model.num_parameters, model.state_size
    Q, P0_xx, H, R = tuning.fixed_theta_matrices(k, s)
    Q, R = (Q * q_scale)[None], (R * r_scale)[None]
    n_all = exp.n if samples is None else samples
    u, y = exp.u.to(f64)[:n_all], measurements(exp, tuning.measure)[:n_all]
    x, P = state_belief(exp, 1, P0_xx)
    first, inn = update(EKFState(x[0], P[0]), y[0], H, R[0])
    if not bool(healthy(first, inn, torch.tensor(math.inf, dtype=f64), s)):
        raise FilterFailure(0, "the first measurement update failed", EKFState(x[0], P[0]))
    x, P = first.x[None], first.P[None]
    out = torch.empty(n_all, s, dtype=f64)
    out[0] = x[0]
    step = _state_step(model, tuning)
    consts = (torch.tensor(exp.dt, dtype=f64), theta[None].to(f64), Q, H, R,
              torch.tensor(math.inf, dtype=f64))  # fmt: skip
    if step.chunk is not None:
        for i, n, xs, valid in iter_chunks((u[:-1], y[1:]), step.size):
            before = EKFState(x[0], P[0])
            (x, P), (xt, ok) = step.chunk((x, P), xs, valid, consts)
            if not bool(ok[:n].all()):
                bad = int((~ok[:n].reshape(n, -1).all(1)).nonzero()[0, 0])
                raise FilterFailure(1 + i + bad, "the fixed-θ filter became unhealthy", before)
            out[1 + i : 1 + i + n] = xt[:n, 0]
    else:
        for j in range(1, n_all):
            before = EKFState(x[0], P[0])
            x, P, xt, ok = step(x, P, u[j - 1], y[j], *consts)
            if not bool(ok.all()):
                raise FilterFailure(j, "the fixed-θ filter became unhealthy", before)
            out[j] = xt[0]
    return out


def _state_step(model: ArmModel, tuning: EKFTuning) -> Step:
    """The fixed-θ step (`make_fixed_theta_step`) with the new states as per-sample outputs,
    made once per model (`_STATE_STEPS`)."""
    key = (structure_key(model), tuning.substeps, tuning.compile)
    if key not in _STATE_STEPS:
        batched = make_fixed_theta_step(model, tuning.substeps)

        def fn(x, P, u, y, *consts):  # type: ignore[no-untyped-def]
            x1, P1, _e, _nis, _ll, ok = batched(x, P, u, y, *consts)
            return x1, P1, x1.clone(), ok

        step = fixed_theta_chunks(fn, batched, carry=2, name="fixed-θ states",
                                  compile=tuning.compile)  # fmt: skip
        _STATE_STEPS.clear()
        _STATE_STEPS[key] = step
    return _STATE_STEPS[key]


_STATE_STEPS: dict = {}
