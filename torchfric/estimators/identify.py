"""Off-line iterative EKF identification (Hensen et al. §4–5).

Each pass filters every experiment in turn. At the start of each experiment the state part of
the belief is re-initialised (``x = [q_0, q̇_0]``, ``P_xx = P0_xx``, cross terms zero) while θ and
``P_θθ`` carry over from the previous experiment / pass. After a pass whose relative change of θ
is below `tolerance`, the passes stop early.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from torch import Tensor

from ..data import Experiment
from ..errors import DivergenceError, TorchfricError
from ..models.arm import ArmModel
from .ekf import (
    MEASUREMENTS,
    EKFState,
    FilterFailure,
    PassStats,
    StepFn,
    make_propagator,
    make_step,
    run_pass,
)
from .observers import EKFCallback
from .settings import EKFTuning

__all__ = ["EKFTuning", "PassRecord", "EKFResult", "EKFCallback", "identify_ekf"]


@dataclass
class PassRecord:
    """Diagnostics of one completed pass (over all experiments)."""

    index: int  # 1-based pass number
    theta: list[float]  # estimation coordinates, after the pass
    parameters: dict[str, float]  # physical values by name
    trace_P: float  # trace of the full P at the end of the pass
    trace_P_theta: float  # trace of the parameter block
    innovation_rms: list[float]  # per measured channel
    nis: float  # mean normalised innovation squared (≈ m for a consistent filter)
    loglik: float  # summed innovation log-likelihood
    rel_change: float  # ‖θ_new − θ_old‖ / ‖θ_old‖
    seconds: float
    samples: int
    rolled_back: bool = False  # this pass lowered the log-likelihood and was undone

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class EKFResult:
    """What `identify_ekf` returns (also attached to DivergenceError.last_good)."""

    model: ArmModel
    theta: Tensor  # (k,) estimation coordinates
    P_theta: Tensor  # (k, k)
    history: list[PassRecord] = field(default_factory=list)
    converged: bool = False

    @property
    def passes(self) -> int:
        return len(self.history)


def _measurements(exp: Experiment, measure: str) -> Tensor:
    idx = MEASUREMENTS[measure]
    if 1 in idx and exp.qdot is None:
        raise TorchfricError(
            f"experiment {exp.name!r} has no velocity but measure = {measure!r} needs one; "
            "reconstruct it first (Experiment.with_velocity) or use measure = 'position'"
        )
    cols = [exp.q if i == 0 else exp.qdot for i in idx]
    return torch.stack(cols, dim=-1).to(torch.float64)


def identify_ekf(
    model: ArmModel,
    experiments: Experiment | Sequence[Experiment],
    tuning: EKFTuning | None = None,
    *,
    callback: EKFCallback | None = None,
    start: tuple[Tensor, Tensor, list[PassRecord]] | None = None,
    progress_every: int = 2000,
) -> EKFResult:
    """Identify θ of `model` with the iterative off-line augmented-state EKF.

    Args:
        model: the arm; its current θ is the initial guess (not modified).
        experiments: one or more experiments with `qdot` when velocity is measured.
        tuning: `EKFTuning` (paper defaults).
        callback: `EKFCallback` for progress and per-pass hooks.
        start: resume from ``(θ, P_θθ, history)`` of completed passes.

    Returns:
        `EKFResult` with a fitted copy of the model, θ, P_θθ and per-pass `PassRecord`s.

    Raises:
        DivergenceError: naming pass, experiment, sample and reason; `.last_good` holds the
            result after the last completed pass (or the initial guess).
    """
    tuning = tuning or EKFTuning()
    exps = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    if not exps:
        raise TorchfricError("identify_ekf needs at least one experiment")
    k = model.num_parameters
    tuning.check(k)
    callback = callback or EKFCallback()
    n = 2 + k
    Q, P0_xx, H, R = tuning.matrices(k)
    data = [(e, e.u.to(torch.float64), _measurements(e, tuning.measure)) for e in exps]
    flow = make_propagator(model, tuning.substeps)
    step_fn = make_step(flow, compile=tuning.compile)

    if start is not None:
        theta, P_theta, history = start[0].clone(), start[1].clone(), list(start[2])
    else:
        theta = model.get_theta()
        P_theta = tuning.initial_P_theta(model, theta)
        history = []

    def result_for(th: Tensor, Pt: Tensor, hist: list[PassRecord], converged: bool) -> EKFResult:
        fitted = copy.deepcopy(model).set_theta(th)
        return EKFResult(fitted, th.clone(), Pt.clone(), list(hist), converged)

    total = sum(e.n for e, _, _ in data)
    converged = bool(history) and tuning.tolerance > 0 and history[-1].rel_change < tuning.tolerance
    stopped = bool(history) and history[-1].rolled_back
    # Best pass so far (for rollback). A pass that was not rolled back is always the best one.
    best = (history[-1].loglik, theta.clone(), P_theta.clone()) if history else None
    for p in range(len(history) + 1, tuning.passes + 1):
        if converged or stopped:
            break
        t0 = time.perf_counter()
        theta_old, P_theta_old = theta.clone(), P_theta.clone()
        sum_e2 = torch.zeros(H.shape[0], dtype=torch.float64)
        sum_nis = loglik = 0.0
        samples = 0
        state = None
        for exp, u, y in data:
            x0 = torch.stack(
                [exp.q[0], exp.qdot[0] if exp.qdot is not None else exp.q.new_zeros(())]
            )
            P = torch.zeros(n, n, dtype=torch.float64)
            P[:2, :2] = P0_xx
            P[2:, 2:] = P_theta
            state = EKFState(torch.cat([x0.to(torch.float64), theta]), P)
            dt = torch.tensor(exp.dt, dtype=torch.float64)
            try:
                state, stats = _filter_with_progress(
                    state,
                    u,
                    y,
                    dt,
                    Q,
                    H,
                    R,
                    step_fn,
                    tuning.theta_bound,
                    callback,
                    p,
                    samples,
                    total,
                    progress_every,
                )
            except FilterFailure as fail:
                last = result_for(theta_old, P_theta_old, history, False)
                t_fail = float(exp.t[fail.sample])
                xs = ", ".join(f"{v:.4g}" for v in fail.state.x[:2].tolist())
                raise DivergenceError(
                    f"EKF diverged in pass {p}, experiment {exp.name!r}, sample {fail.sample} "
                    f"(t = {t_fail:.4f} s, state [q, qdot] = [{xs}]): {fail.reason}. "
                    "Fix: start from model.init = 'prefit', lower estimator.p0_theta, or check c_m "
                    "and the data units; the last good parameters are kept",
                    last_good=last,
                ) from None
            theta = state.x[2:].clone()
            P_theta = state.P[2:, 2:].clone()
            sum_e2 += stats.sum_e2
            sum_nis += stats.sum_nis
            loglik += stats.loglik
            samples += stats.samples
        rel = float((theta - theta_old).norm() / theta_old.norm().clamp_min(1e-12))
        record = PassRecord(
            index=p,
            theta=theta.tolist(),
            parameters=dict(zip(model.theta_names, model.to_physical(theta).tolist(), strict=True)),
            trace_P=float(torch.diagonal(state.P).sum()),
            trace_P_theta=float(torch.diagonal(P_theta).sum()),
            innovation_rms=(sum_e2 / samples).sqrt().tolist(),
            nis=sum_nis / samples,
            loglik=loglik,
            rel_change=rel,
            seconds=time.perf_counter() - t0,
            samples=samples,
        )
        if tuning.rollback and best is not None and record.loglik < best[0] - 1e-6 * abs(best[0]):
            record.rolled_back = True
            theta, P_theta = best[1].clone(), best[2].clone()
            stopped = True
        else:
            best = (record.loglik, theta.clone(), P_theta.clone())
        history.append(record)
        converged = not stopped and tuning.tolerance > 0 and rel < tuning.tolerance
        if callback.on_pass_end(record, result_for(theta, P_theta, history, converged)) is False:
            break
    return result_for(theta, P_theta, history, converged)


def _filter_with_progress(
    state: EKFState,
    u: Tensor,
    y: Tensor,
    dt: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    step_fn: StepFn,
    theta_bound: float,
    callback: EKFCallback,
    pass_index: int,
    offset: int,
    total: int,
    every: int,
) -> tuple[EKFState, PassStats]:
    """`run_pass` over one experiment in stretches of `every` samples, reporting progress."""
    n = y.shape[0]
    acc = PassStats(sum_e2=torch.zeros(y.shape[1], dtype=torch.float64))
    start = 0
    while start < n:
        stop = min(n, start + every)
        lo = max(start - 1, 0)  # a continuing stretch starts at the last filtered sample
        state, stats = run_pass(
            state,
            u[lo:stop],
            y[lo:stop],
            dt,
            Q,
            H,
            R,
            step_fn,
            theta_bound=theta_bound,
            continuing=start > 0,
            sample_offset=lo,
        )
        acc.samples += stats.samples
        acc.sum_e2 = acc.sum_e2 + stats.sum_e2
        acc.sum_nis += stats.sum_nis
        acc.loglik += stats.loglik
        start = stop
        callback.on_progress(pass_index, offset + start, total)
    return state, acc
