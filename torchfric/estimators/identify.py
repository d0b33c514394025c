"""Off-line iterative EKF identification (Hensen et al. §4–5).

Each pass filters every experiment in turn. At the start of each experiment the state part of
the belief is re-initialised (``x = [q_0, q̇_0]``, ``P_xx = P0_xx``, cross terms zero) while θ and
``P_θθ`` carry over from the previous experiment / pass. After a pass whose relative change of θ
is below `tolerance`, the passes stop early. The pass loop, rollback and convergence rules are
those of `torchfric.estimators.passes` (shared with the ensemble), for one member.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from ..data import Experiment
from ..errors import DivergenceError
from ..models.arm import ArmModel
from .ekf import EKFState, FilterFailure, PassStats, make_propagator, make_step, run_pass
from .observers import Callback, EKFCallback
from .passes import (
    EKFResult,
    Filtering,
    PassLedger,
    PassRecord,
    PassSums,
    initial_belief,
    measured_data,
    prepared,
    run_passes,
)
from .propagation import finer_steps
from .settings import EKFTuning

__all__ = ["EKFTuning", "PassRecord", "EKFResult", "EKFCallback", "identify_ekf"]


def identify_ekf(
    model: ArmModel,
    experiments: Experiment | Sequence[Experiment],
    tuning: EKFTuning | None = None,
    *,
    callback: Callback | None = None,
    start: tuple[Tensor, Tensor, list[PassRecord]] | None = None,
    progress_every: int = 2000,
) -> EKFResult:
    """Identify θ of `model` with the iterative off-line augmented-state EKF.

    Args:
        model: the arm; its current θ is the initial guess (not modified).
        experiments: one or more experiments with `qdot` when velocity is measured.
        tuning: `EKFTuning` (paper defaults).
        callback: a `Callback` (`EKFCallback`) for progress and per-pass hooks.
        start: resume from ``(θ, P_θθ, history)`` of completed passes.

    Returns:
        `EKFResult` with a fitted copy of the model, θ, P_θθ and per-pass `PassRecord`s.

    Raises:
        DivergenceError: naming pass, experiment, sample and reason; `.last_good` holds the
            result after the last completed pass (or the initial guess).
    """
    auto = tuning is not None and tuning.substeps == "auto"
    k = model.num_parameters
    exps, tuning = prepared(experiments, tuning or EKFTuning(), k, "identify_ekf", model)
    callback = callback or Callback()
    Q, P0_xx, H, R = tuning.matrices(model.num_parameters, model.state_size)
    data = measured_data(exps, tuning.measure)

    def make(n: int) -> Any:
        return make_step(make_propagator(model, n), compile=tuning.compile)

    total = sum(e.n for e, _, _ in data)
    f = Filtering(data, Q, P0_xx, H, R, make(tuning.substeps), tuning.theta_bound, callback,
                  progress_every, total, tuning.substeps)  # fmt: skip
    if start is not None:
        theta, P_theta, history = start[0], start[1], list(start[2])
    else:
        theta = model.get_theta()
        P_theta, history = tuning.initial_P_theta(model, theta), []
    ledger = PassLedger.from_history(model, tuning, theta, P_theta, history)

    def on_pass_end(p: int, records: list[PassRecord | None]) -> bool | None:
        return callback.on_pass_end(records[0], ledger.result(0))

    one_pass = finer_steps(lambda p: _filter_pass(p, ledger, f), f, ledger, exps, make, auto)
    run_passes(ledger, tuning.passes, one_pass, on_pass_end)
    return dataclasses.replace(ledger.result(0), substeps=f.substeps)


def _filter_pass(p: int, ledger: PassLedger, f: Filtering) -> PassSums:
    """Pass `p` over every experiment from the ledger's θ and ``P_θθ``.

    Raises:
        DivergenceError: when the filter fails; `.last_good` is the ledger's result before `p`.
    """
    theta, P_theta = ledger.theta, ledger.P_theta  # (1, k), (1, k, k)
    sum_e2 = torch.zeros(f.H.shape[0], dtype=torch.float64)
    sum_nis = loglik = 0.0
    samples = 0
    for exp, u, y in f.data:
        x, P = initial_belief(exp, theta, P_theta, f.P0_xx)
        dt = torch.tensor(exp.dt, dtype=torch.float64)
        try:
            state, stats = _filter_with_progress(EKFState(x[0], P[0]), u, y, dt, f, p, samples)
        except FilterFailure as fail:
            raise _divergence(fail, p, exp, ledger) from None
        s = f.states
        theta, P_theta = state.x[s:].clone()[None], state.P[s:, s:].clone()[None]
        sum_e2 += stats.sum_e2
        sum_nis += stats.sum_nis
        loglik += stats.loglik
        samples += stats.samples
    f64 = torch.float64
    return PassSums(
        theta, P_theta, state.P[None], sum_e2[None], torch.tensor([sum_nis], dtype=f64),
        torch.tensor([loglik], dtype=f64), samples, [""],
    )  # fmt: skip


def _divergence(
    fail: FilterFailure, p: int, exp: Experiment, ledger: PassLedger
) -> DivergenceError:
    """The error for a filter failure in pass `p`, with the last good result attached."""
    t_fail = float(exp.t[fail.sample])
    xs = ", ".join(f"{v:.4g}" for v in fail.state.x[:2].tolist())
    return DivergenceError(
        f"EKF diverged in pass {p}, experiment {exp.name!r}, sample {fail.sample} "
        f"(t = {t_fail:.4f} s, state [q, qdot] = [{xs}]): {fail.reason}. "
        "Fix: start from model.init = 'prefit', lower estimator.p0_theta, or check "
        "model.c_m and the data's units (t in seconds, q in data.position_unit); the last "
        "good parameters are kept",
        last_good=ledger.result(0),
    )


def _filter_with_progress(
    state: EKFState, u: Tensor, y: Tensor, dt: Tensor, f: Filtering, pass_index: int, offset: int
) -> tuple[EKFState, PassStats]:
    """`run_pass` over one experiment in stretches of `f.every` samples, reporting progress."""
    n = y.shape[0]
    acc = PassStats(sum_e2=torch.zeros(y.shape[1], dtype=torch.float64))
    start = 0
    while start < n:
        stop = min(n, start + f.every)
        lo = max(start - 1, 0)  # a continuing stretch starts at the last filtered sample
        state, stats = run_pass(
            state,
            u[lo:stop],
            y[lo:stop],
            dt,
            f.Q,
            f.H,
            f.R,
            f.step_fn,
            theta_bound=f.theta_bound,
            continuing=start > 0,
            sample_offset=lo,
        )
        acc.samples += stats.samples
        acc.sum_e2 = acc.sum_e2 + stats.sum_e2
        acc.sum_nis += stats.sum_nis
        acc.loglik += stats.loglik
        start = stop
        f.callback.on_progress(pass_index, offset + start, f.total)
    return state, acc
