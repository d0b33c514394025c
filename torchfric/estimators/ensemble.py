"""Ensembles of the iterative EKF: many starts and tunings filtered in one vectorised pass.

The paper warns that "the filter tuning is mainly based on experience and trial and error" and that
"parameter divergence can occur". An ensemble answers both at the cost of roughly one filter: K
members, differing in their initial θ (every entry scaled by a log-uniform factor in ``[1/spread,
spread]``, member 0 the start itself) and in the tuning's scale (Q and R times factors from a
grid), run through the same per-sample step as one batch: generated C by default (four members per
SIMD vector), else `torch.func.vmap` of the step compiled once; on a CUDA device, the generated
step with one member per GPU thread.

Each member is an independent iterative off-line EKF exactly as in `identify_ekf`: the same passes,
per-experiment state reset, per-member early stop on the θ tolerance and per-member rollback of a
pass that lowers its innovation log-likelihood. A member whose belief becomes unhealthy (NaN,
negative variance, θ out of the box) is frozen at its last good pass and marked diverged; the
others carry on. Health flags are folded into masks on the device, read once per stretch.

After the passes, the member with the best open-loop FIT is kept — the mean of the q and q̇ FIT of
an open-loop simulation (all members simulated as one batch), averaged over the validation
experiments and, with equal weight, over the training experiments (those alone without
validation data) — and the spread of all members' results is reported (`selection`).

Why this size: the batch's one pass loop, its stretch masks and its selection call must change
together; the pass ledger and the selection are already apart (`passes`, `selection`)."""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from torch import Tensor
from torch.func import vmap

from ..accel import (
    CHUNK,
    Step,
    chunk_options,
    compile_step,
    compile_with_fallback,
    iter_chunks,
    product_name,
    step_key,
)
from ..data import Experiment
from ..errors import TorchfricError
from ..models.arm import ArmModel
from .ekf import EKFState, MatMul, StepFn, make_propagator, make_step, update
from .observers import Callback, EnsembleCallback
from .passes import (
    DIVERGED,
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
from .selection import select_by_fit
from .settings import EKFTuning, EnsembleSpec

__all__ = [
    "EnsembleSpec",
    "MemberSummary",
    "EnsembleResult",
    "EnsembleCallback",
    "random_thetas",
    "member_grid",
    "make_batched_step",
    "make_masked_step",
    "identify_ekf_ensemble",
]


def random_thetas(
    model: ArmModel, theta0: Tensor, count: int, spread: float, generator: torch.Generator
) -> Tensor:
    """`(count, k)` random starts around θ₀ (estimation coordinates); row 0 is θ₀ itself. Log-stored
    entries move by ``U(−ln s, ln s)``; linear entries are multiplied by ``exp(U(−ln s, ln s))``
    (sign kept): either way the physical value is scaled by a log-uniform factor in ``[1/s, s]``."""
    theta0 = theta0.detach().to(torch.float64).reshape(-1)
    k = theta0.numel()
    shift = (2.0 * torch.rand(count, k, generator=generator, dtype=torch.float64) - 1.0) * math.log(
        spread
    )
    shift[0] = 0.0
    log = model.log_mask()
    return torch.where(log, theta0 + shift, theta0 * shift.exp())


def member_grid(
    model: ArmModel, theta0: Tensor, spec: EnsembleSpec
) -> tuple[Tensor, Tensor, Tensor]:
    """The ensemble's members: θ starts `(K, k)`, Q scales `(K,)`, R scales `(K,)`; member 0 is
    θ₀ with the first scales of each grid."""
    spec.check()
    g = torch.Generator().manual_seed(spec.seed)
    starts = random_thetas(model, theta0, spec.members, spec.spread, g)
    rows, qs, rs = [], [], []
    for i in range(spec.members):
        for q in spec.q_scales:
            for r in spec.r_scales:
                rows.append(starts[i])
                qs.append(q)
                rs.append(r)
    f64 = torch.float64
    return torch.stack(rows), torch.tensor(qs, dtype=f64), torch.tensor(rs, dtype=f64)


def make_batched_step(
    model: ArmModel, substeps: int, *, compile: bool = False, mm: MatMul | None = None
) -> StepFn:
    """The per-sample step of `make_step`, vectorised over members with `torch.func.vmap`.

    ``fn(x (K,n), P (K,n,n), u, y (m,), dt, Q (K,n,n), H, R (K,m,m), bound)
    -> (x⁺, P⁺, e (K,m), nis (K,), loglik (K,), ok (K,))``. Member j's outputs equal the
    single-filter step on member j's inputs (same arithmetic, tested). Its `.key` names its
    code (`torchfric.accel.step_key`)."""
    # The product rule of one filter (`matmul_for`; with the chunked scan, tanh(3): 186 k / 272 k
    # / 328 k filter-steps/s at K = 16 / 256 / 1024 fused, against 92 k / 126 k / 125 k BLAS).
    flow = make_propagator(model, substeps, mm=mm)  # mm None: `matmul_for` the filter's size
    batched = vmap(make_step(flow), in_dims=(0, 0, None, None, None, 0, None, 0, None))
    out = compile_with_fallback(batched) if compile else batched
    out.key = step_key("batched step", flow.key, product_name(flow.mm))  # type: ignore[attr-defined]
    out.mm = flow.mm  # type: ignore[attr-defined]
    return out


def make_masked_step(
    model: ArmModel,
    substeps: int,
    *,
    compile: bool = False,
    chunk: int = CHUNK,
    mm: MatMul | None = None,
    native: bool = True,
    device: torch.device | None = None,
) -> Step:
    """`make_batched_step` plus the ensemble's per-sample bookkeeping, as one function (one
    compiled graph, so the masking costs no extra per-sample dispatch):

    ``fn(x, P, good, fail_at, sum_e2, sum_nis, loglik, j, u, y, dt, Q, H, R, bound)`` returns the
    same seven state tensors, updated: members still `good` take the step and add its
    diagnostics; a member whose step is unhealthy keeps its last belief, records sample `j`
    (a 0-d tensor) in `fail_at` and drops out of `good`.

    Compiled (`torchfric.accel.compile_step`), it also filters `chunk` samples per call (`Step.chunk`):
    ``chunk((x, P, good, fail_at, sum_e2, sum_nis, loglik), (j (C,), u (C,), y (C, m)),
    valid (C,), (dt, Q, H, R, bound))`` returns the seven state tensors after the chunk's valid
    samples (and no per-sample outputs). With `native` (the default) that chunk is generated C
    (`torchfric.native`: one member traced, four per SIMD vector, split across the cores); else,
    or when that path cannot translate the model, the Inductor scan of the vmapped step. A CUDA
    `device`: first the generated step on that GPU, one member per thread (`make_chunk`)."""
    batched = make_batched_step(model, substeps, mm=mm)
    mm = batched.mm  # type: ignore[attr-defined]  # the filter's product (`matmul_for` by default)
    key = step_key("ensemble masked step", batched.key)  # type: ignore[attr-defined]

    def masked(
        x: Tensor,
        P: Tensor,
        good: Tensor,
        fail_at: Tensor,
        sum_e2: Tensor,
        sum_nis: Tensor,
        loglik: Tensor,
        j: Tensor,
        u: Tensor,
        y: Tensor,
        dt: Tensor,
        Q: Tensor,
        H: Tensor,
        R: Tensor,
        bound: Tensor,
    ):  # type: ignore[no-untyped-def]
        carry = (x, P, good, fail_at, sum_e2, sum_nis, loglik)
        return _keep_good(carry, j, *batched(x, P, u, y, dt, Q, H, R, bound))

    if not compile:
        return Step(masked)
    # All seven outputs are carried from sample to sample. Native path: every carry has the
    # member axis, and of the constants Q and R do.
    return compile_step(masked, carry=7, size=chunk, options=chunk_options(mm), native=native,
                        members=True, member_consts=(False, True, False, True, False),
                        key=key, device=device)  # fmt: skip


def _keep_good(
    carry: tuple[Tensor, ...],
    j: Tensor | int,
    x1: Tensor,
    P1: Tensor,
    e: Tensor,
    nis: Tensor,
    ll: Tensor,
    ok: Tensor,
) -> tuple[Tensor, ...]:
    """The masked step's bookkeeping: members still `good` whose step is healthy (`ok`) take
    ``x1, P1`` and add the diagnostics; a member that is not `ok` keeps its last belief,
    records sample `j` in `fail_at` (if not already failed) and drops out of `good`."""
    x, P, good, fail_at, sum_e2, sum_nis, loglik = carry
    fail_at = torch.where(good & ~ok & (fail_at < 0), j, fail_at)
    good = good & ok
    return (
        torch.where(good[:, None], x1, x),
        torch.where(good[:, None, None], P1, P),
        good,
        fail_at,
        sum_e2 + torch.where(good[:, None], e * e, 0.0),
        sum_nis + torch.where(good, nis, 0.0),
        loglik + torch.where(good, ll, 0.0),
    )


def _first_sample(carry: tuple[Tensor, ...], y0: Tensor, f: Filtering) -> tuple[Tensor, ...]:
    """Sample 0 of an experiment: the measurement update alone (nothing to predict from), for
    every member, with the bookkeeping of the masked step."""
    x, P = carry[0], carry[1]

    def one(x1: Tensor, P1: Tensor, R1: Tensor):  # type: ignore[no-untyped-def]
        state, inn = update(EKFState(x1, P1), y0, f.H, R1)
        return state.x, state.P, inn.e, inn.nis, inn.loglik

    x1, P1, e, nis, ll = vmap(one)(x, P, f.R)
    ok = (
        torch.isfinite(nis)
        & torch.isfinite(x1).all(1)
        & torch.isfinite(P1).flatten(1).all(1)
        & (x1[:, f.states :].abs() <= f.theta_bound).all(1)
    )
    return _keep_good(carry, 0, x1, P1, e, nis, ll, ok)


@dataclass
class MemberSummary:
    """One member's outcome."""

    index: int
    q_scale: float
    r_scale: float
    status: str  # running (passes exhausted) | converged | rolled_back | diverged
    passes: int
    loglik: float  # of the member's kept pass (-inf if none)
    inertia: float
    score: float  # selection score: mean FIT % of q and q̇, validation and training files
    fits: dict[str, dict[str, float]] = field(default_factory=dict)
    reason: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class EnsembleResult:
    """What `identify_ekf_ensemble` returns."""

    best: int
    result: EKFResult  # the kept member, as a single-filter result
    thetas: Tensor  # (K, k) final θ of every member
    P_thetas: Tensor  # (K, k, k)
    members: list[MemberSummary]
    selected_by: str  # "validation_and_train_fit" | "train_fit" | "loglik" (none simulates)
    seconds: float
    filter_steps: int  # member-samples filtered (each pass: its running members × samples)

    def summary(self) -> dict[str, Any]:
        """Counts and spread of the members' results (for metrics.json and reports)."""
        ok = [m for m in self.members if m.status != DIVERGED]
        scores = sorted(m.score for m in ok if math.isfinite(m.score))
        inertias = sorted(m.inertia for m in ok)

        def spread(v: list[float]) -> dict[str, float] | None:
            if not v:
                return None
            return {"min": v[0], "median": v[len(v) // 2], "max": v[-1]}

        counts: dict[str, int] = {}
        for m in self.members:
            counts[m.status] = counts.get(m.status, 0) + 1
        best = self.members[self.best]
        return {
            "members": len(self.members),
            "status": counts,
            "selected_by": self.selected_by,
            "best": best.index,
            "best_q_scale": best.q_scale,
            "best_r_scale": best.r_scale,
            "score": spread(scores),
            "inertia": spread(inertias),
            "seconds": self.seconds,
            "filter_steps_per_second": self.filter_steps / max(self.seconds, 1e-9),
        }


def identify_ekf_ensemble(
    model: ArmModel,
    experiments: Experiment | Sequence[Experiment],
    tuning: EKFTuning | None = None,
    spec: EnsembleSpec | None = None,
    *,
    members: tuple[Tensor, Tensor, Tensor] | None = None,
    validation: Sequence[Experiment] = (),
    max_substeps: int = 64,
    callback: Callback | None = None,
    start: dict[str, Any] | None = None,
    progress_every: int = 2000,
    device: torch.device | None = None,
) -> EnsembleResult:
    """Run K iterative EKFs as one batch and keep the best member.

    Args:
        model: the arm; its θ is the ensemble's centre (member 0) unless `members` is given.
        experiments: the identification data (as `identify_ekf`).
        tuning: the base `EKFTuning`; each member scales its Q and R.
        spec: `EnsembleSpec` (used when `members` is None).
        members: explicit ``(θ (K,k), q_scale (K,), r_scale (K,))``.
        validation: experiments for the selection by open-loop FIT, weighted equally with
            the training experiments' FIT (without validation: the training FIT alone).
        max_substeps: a member too stiff for this many RK4 sub-steps a sample scores as failed.
        callback: a `Callback` (`EnsembleCallback`) for progress and per-pass snapshots.
        start: a state passed to `Callback.on_ensemble_pass_end`: continue after that pass
            (the result equals an uninterrupted run's).
        device: a CUDA device filters the members there (the selection stays on the CPU).

    Returns:
        `EnsembleResult`; `.result` is the kept member as an `EKFResult` with its pass history.

    Raises:
        TorchfricError: bad inputs, or every member diverged (the message says where).
    """
    t_start = time.perf_counter()
    k, auto = model.num_parameters, tuning is not None and tuning.substeps == "auto"
    exps, tuning = prepared(experiments, tuning or EKFTuning(), k, "identify_ekf_ensemble", model)
    thetas, q_scale, r_scale = _member_starts(model, spec, members, start)
    callback = callback or Callback()
    Q, P0_xx, H, R = tuning.matrices(k, model.state_size)
    Qk, Rk = Q * q_scale[:, None, None], R * r_scale[:, None, None]
    P_theta = tuning.initial_P_theta(model, thetas)
    make = functools.partial(make_masked_step, model, compile=tuning.compile, device=device)
    data, total = measured_data(exps, tuning.measure), sum(e.n for e in exps)
    f = Filtering(data, Qk, P0_xx, H, Rk, make(tuning.substeps), tuning.theta_bound, callback,
                  progress_every, total, tuning.substeps)  # fmt: skip
    if start is not None:
        ledger = PassLedger.from_state(model, tuning, start)
    else:
        ledger = PassLedger(model, tuning, thetas.clone(), P_theta)

    def on_pass_end(p: int, records: list[PassRecord | None]) -> bool | None:
        state = {
            "method": "ekf_ensemble",
            "pass": p,
            "members_theta": thetas.clone(),
            "q_scale": q_scale.clone(),
            "r_scale": r_scale.clone(),
        }
        return callback.on_ensemble_pass_end(p, {**state, **ledger.state()})

    one_pass = finer_steps(lambda p: _filter_members(p, ledger, f), f, ledger, exps, make, auto)
    run_passes(ledger, tuning.passes, one_pass, on_pass_end)
    choice = (validation, max_substeps, "compiled" if tuning.compile else "odeint")
    ens = _finish(model, exps, ledger, q_scale, r_scale, choice, t_start)
    ens.result.substeps = f.substeps  # the kept member's, as every member's: one shared step
    return ens


def _member_starts(
    model: ArmModel,
    spec: EnsembleSpec | None,
    members: tuple[Tensor, Tensor, Tensor] | None,
    start: dict[str, Any] | None,
) -> tuple[Tensor, Tensor, Tensor]:
    """The members' ``(θ (K, k), q_scale (K,), r_scale (K,))``: from the `start` snapshot, else
    `members`, else the grid of `spec`."""
    if start is not None:
        members = (start["members_theta"], start["q_scale"], start["r_scale"])
    if members is None:
        return member_grid(model, model.get_theta(), spec or EnsembleSpec())
    thetas, q_scale, r_scale = (torch.as_tensor(m, dtype=torch.float64) for m in members)
    k = model.num_parameters
    if thetas.ndim != 2 or thetas.shape[1] != k:
        raise TorchfricError(f"ensemble θ must have shape (K, {k}), got {tuple(thetas.shape)}")
    if q_scale.shape != (thetas.shape[0],) or r_scale.shape != (thetas.shape[0],):
        raise TorchfricError("ensemble q/r scales need one value per member")
    return thetas, q_scale, r_scale


def _filter_members(p: int, ledger: PassLedger, f: Filtering) -> PassSums:
    """Pass `p` of the running members over every experiment, as one batch of those only (each
    member's arithmetic is its own: the batch's size changes no bit; `PassSums.spread` gives the
    others' rows back). Health flags are folded into masks on the device and read once per
    experiment; a member that fails keeps its θ and ``P_θθ`` from before that experiment and
    gets the reason (pass, experiment, sample) in `PassSums.failures`."""
    run = torch.nonzero(ledger.running()).flatten()
    f = dataclasses.replace(f, Q=f.Q[run], R=f.R[run])
    theta, P_theta = ledger.theta[run], ledger.P_theta[run]
    f64, K = torch.float64, run.numel()
    good = torch.ones(K, dtype=torch.bool)
    fail_at = torch.full((K,), -1, dtype=torch.long)
    sums = [torch.zeros(K, f.H.shape[0], dtype=f64), *torch.zeros(2, K, dtype=f64)]  # Σe², NIS, ℓ
    samples, failures = 0, [""] * K
    for exp, u, y in f.data:
        x, P = initial_belief(exp, theta, P_theta, f.P0_xx)
        was_good = good.clone()
        carry = _first_sample((x, P, good, fail_at, *sums), y[0], f)
        x, P, good, fail_at, *sums = _filter_rest(carry, exp, u, y, p, samples, f)
        for i in torch.nonzero(was_good & ~good).flatten().tolist():
            failures[i] = (f"diverged in pass {p}, experiment {exp.name!r}, sample "
                           f"{int(fail_at[i])}: the belief became non-finite, non-PSD or θ left "
                           f"the box |θ| <= {f.theta_bound:g}")  # fmt: skip
        samples += exp.n
        f.callback.on_progress(p, samples, f.total)
        theta = torch.where(good[:, None], x[:, f.states :], theta)
        P_theta = torch.where(good[:, None, None], P[:, f.states :, f.states :], P_theta)
    return PassSums(theta, P_theta, P, *sums, samples, failures).spread(
        run, ledger.theta, ledger.P_theta
    )


def _filter_rest(
    carry: tuple[Tensor, ...], exp: Experiment, u: Tensor, y: Tensor, p: int, offset: int,
    f: Filtering,
) -> tuple[Tensor, ...]:  # fmt: skip
    """Samples 1 … N−1 of `exp` through the masked step (compiled chunks when there are),
    reporting progress."""
    bound = torch.tensor(f.theta_bound, dtype=torch.float64)
    consts = (torch.tensor(exp.dt, dtype=torch.float64), f.Q, f.H, f.R, bound)
    index = torch.arange(exp.n)
    if f.step_fn.chunk is not None:
        # sample j = 1 + i is driven by u[j − 1] and measured by y[j]
        for i, m, xs, valid in iter_chunks((index[1:], u[:-1], y[1:]), f.step_fn.size):
            carry, _ = f.step_fn.chunk(carry, xs, valid, consts)
            f.callback.on_progress(p, offset + 1 + i + m, f.total)
    else:
        for j in range(1, exp.n):
            carry = f.step_fn(*carry, index[j], u[j - 1], y[j], *consts)
            if j % f.every == 0:
                f.callback.on_progress(p, offset + j, f.total)
    return tuple(c.cpu() for c in carry)  # a GPU chunk's carry stays there until here


def _finish(
    model: ArmModel,
    exps: list[Experiment],
    ledger: PassLedger,
    q_scale: Tensor,
    r_scale: Tensor,
    choice: tuple[Sequence[Experiment], int, str],
    t_start: float,
) -> EnsembleResult:
    """Keep the member with the best open-loop FIT (`select_by_fit`; `choice` is its
    validation experiments, max_substeps and engine) and summarise every member."""
    K = len(ledger.status)
    alive = [i for i in range(K) if ledger.status[i] != DIVERGED or ledger.histories[i]]
    if not alive:
        first = next((r for r in ledger.reasons if r), "every member diverged")
        raise TorchfricError(
            f"every one of the {K} ensemble members diverged (member 0: {first}). Fix: start "
            "from model.init = 'prefit', lower estimator.p0_theta or estimator.ensemble_spread"
        )
    # A member that diverged after good passes keeps its last good pass (like identify_ekf's
    # last_good); it stays eligible but is reported as diverged.
    theta = ledger.kept_theta()
    validation, max_substeps, engine = choice
    scores, fits, selected_by = select_by_fit(
        model, theta, alive, exps, validation, ledger.best_ll, max_substeps=max_substeps,
        engine=engine,
    )  # fmt: skip
    best = int(torch.argmax(scores))
    summaries = [
        MemberSummary(
            index=i,
            q_scale=float(q_scale[i]),
            r_scale=float(r_scale[i]),
            status=ledger.status[i],
            passes=len(ledger.histories[i]),
            loglik=float(ledger.best_ll[i]),
            inertia=float(model.split(theta[i])[1]["inertia"]),
            score=float(scores[i]),
            fits=fits[i],
            reason=ledger.reasons[i],
        )
        for i in range(K)
    ]
    return EnsembleResult(
        best=best,
        result=ledger.result(best),
        thetas=theta,
        P_thetas=ledger.P_theta,
        members=summaries,
        selected_by=selected_by,
        seconds=time.perf_counter() - t_start,
        filter_steps=ledger.filter_steps,
    )
