"""Ensembles of the iterative EKF: many starts and tunings filtered in one vectorised pass.

The paper warns that "the filter tuning is mainly based on experience and trial and error" and
that "parameter divergence can occur". An ensemble answers both at the cost of roughly one filter:
K members, differing in their initial θ (random, physically plausible: every entry scaled by a
log-uniform factor in ``[1/spread, spread]`` around the start, member 0 being the start itself)
and in the scaling of the tuning (Q and R multiplied by factors from a grid), run through the
same per-sample step, run as one batch: generated C by default (`torchfric.native`, four members
per SIMD vector), else `torch.func.vmap` of the step compiled once for the whole batch.

Each member is an independent iterative off-line EKF exactly as in `identify_ekf`: the same
passes, per-experiment state reset, per-member early stop on the θ tolerance and per-member
rollback of a pass that lowers its innovation log-likelihood. A member whose belief becomes
unhealthy (NaN, negative variance, θ out of the box) is frozen at its last good pass and marked
diverged; the others carry on. No per-sample host synchronisation: health flags are folded into
masks on the device and read once per stretch.

After the passes, the member with the best open-loop FIT is kept — the mean of the q and q̇
FIT of an open-loop simulation (all members simulated as one batch), averaged over the
validation experiments and, with equal weight, over the training experiments (the training
experiments alone when no validation data are given) — and the spread of all members' results
is reported: a cheap measure of how trustworthy the identification is.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from torch import Tensor
from torch.func import vmap

from ..data import Experiment
from ..errors import TorchfricError
from ..models.arm import ArmModel
from ..models.simulate import auto_substeps, simulate
from .ekf import (
    CHUNK,
    EKFState,
    MatMul,
    Step,
    StepFn,
    chunk_options,
    compile_with_fallback,
    iter_chunks,
    make_chunk,
    make_propagator,
    make_step,
    matmul_for,
    update,
)
from .identify import (
    EKFResult,
    PassRecord,
    _measurements,
)
from .observers import EnsembleCallback
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
    "simulate_members",
]

RUNNING, CONVERGED, ROLLED_BACK, DIVERGED = "running", "converged", "rolled_back", "diverged"


def random_thetas(
    model: ArmModel, theta0: Tensor, count: int, spread: float, generator: torch.Generator
) -> Tensor:
    """`(count, k)` random starts around θ₀ (estimation coordinates); row 0 is θ₀ itself.

    Log-stored entries move by ``U(−ln s, ln s)``; linear entries are multiplied by
    ``exp(U(−ln s, ln s))`` (sign kept). Either way the physical value is scaled by a log-uniform
    factor in ``[1/s, s]``.
    """
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
    single-filter step on member j's inputs (same arithmetic, tested).
    """
    # The same product rule as one filter (`matmul_for`): fused up to 20 states, compiled as
    # scalar code (`chunk_options`). Measured with the chunked scan, tanh(3): 186 k / 272 k /
    # 328 k filter-steps/s at K = 16 / 256 / 1024 against 92 k / 126 k / 125 k with BLAS calls.
    mm = mm or matmul_for(2 + model.num_parameters)
    eager = make_step(make_propagator(model, substeps, mm=mm), mm=mm)
    batched = vmap(eager, in_dims=(0, 0, None, None, None, 0, None, 0, None))
    return compile_with_fallback(batched) if compile else batched


def make_masked_step(
    model: ArmModel,
    substeps: int,
    *,
    compile: bool = False,
    chunk: int = CHUNK,
    mm: MatMul | None = None,
    native: bool = True,
) -> Step:
    """`make_batched_step` plus the ensemble's per-sample bookkeeping, as one function (one
    compiled graph, so the masking costs no extra per-sample dispatch):

    ``fn(x, P, good, fail_at, sum_e2, sum_nis, loglik, j, u, y, dt, Q, H, R, bound)`` returns the
    same seven state tensors, updated: members still `good` take the step and add its
    diagnostics; a member whose step is unhealthy keeps its last belief, records sample `j`
    (a 0-d tensor) in `fail_at` and drops out of `good`.

    Compiled, it also filters `chunk` samples per call (`Step.chunk`, `torchfric.ekf.make_chunk`):
    ``chunk((x, P, good, fail_at, sum_e2, sum_nis, loglik), (j (C,), u (C,), y (C, m)),
    valid (C,), (dt, Q, H, R, bound))`` returns the seven state tensors after the chunk's valid
    samples (and no per-sample outputs). With `native` (the default) that chunk is generated C
    (`torchfric.native`): the step traced for one member, four members per SIMD vector, the
    members split across the cores; otherwise, or when that path cannot translate the model,
    the Inductor scan of the vmapped step.
    """
    mm = mm or matmul_for(2 + model.num_parameters)
    batched = make_batched_step(model, substeps, mm=mm)

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
        x1, P1, e, nis, ll, ok = batched(x, P, u, y, dt, Q, H, R, bound)
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

    if not compile:
        return Step(masked)

    def one(*args: Tensor):  # type: ignore[no-untyped-def]
        return masked(*args), ()

    options = chunk_options(mm)
    # Native path: every carry has the member axis, and of the constants Q and R do.
    scan = make_chunk(one, options=options, native=native, members=True,
                      member_consts=(False, True, False, True, False))  # fmt: skip
    return Step(masked, compile_with_fallback(masked), scan, chunk)


def _batched_update(x: Tensor, P: Tensor, y: Tensor, H: Tensor, R: Tensor):  # type: ignore[no-untyped-def]
    def one(x1: Tensor, P1: Tensor, R1: Tensor):  # type: ignore[no-untyped-def]
        state, inn = update(EKFState(x1, P1), y, H, R1)
        return state.x, state.P, inn.e, inn.nis, inn.loglik

    return vmap(one)(x, P, R)


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
    out = torch.full((exp.n, K, 2), float("nan"), dtype=torch.float64)
    x0 = torch.stack([exp.q[0], exp.qdot[0]]).to(torch.float64)
    u = exp.u.to(torch.float64)
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


def _fit(y: Tensor, y_hat: Tensor) -> Tensor:
    """FIT % per member: `y (N,)`, `y_hat (N, K)` → `(K,)`; NaN where the simulation failed."""
    den = (y - y.mean()).norm()
    return 100.0 * (1.0 - (y[:, None] - y_hat).norm(dim=0) / den)


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
    filter_steps: int  # member-samples filtered (K × samples × passes run)

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
    callback: EnsembleCallback | None = None,
    start: dict[str, Any] | None = None,
    progress_every: int = 2000,
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
        max_substeps: members too stiff to simulate with this many RK4 sub-steps per sample
            are scored as failed runs in the selection.
        callback: `EnsembleCallback`.
        start: a state passed to `EnsembleCallback.on_ensemble_pass_end`: continue after that
            pass (members, tuning scales and histories come from it; the result equals an
            uninterrupted run's).

    Returns:
        `EnsembleResult`; `.result` is the kept member as an `EKFResult` with its pass history.

    Raises:
        TorchfricError: bad inputs, or every member diverged (the message says where).
    """
    t_start = time.perf_counter()
    tuning = tuning or EKFTuning()
    exps = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    if not exps:
        raise TorchfricError("identify_ekf_ensemble needs at least one experiment")
    k = model.num_parameters
    tuning.check(k)
    if start is not None:
        members = (start["members_theta"], start["q_scale"], start["r_scale"])
    if members is None:
        spec = spec or EnsembleSpec()
        thetas, q_scale, r_scale = member_grid(model, model.get_theta(), spec)
    else:
        thetas, q_scale, r_scale = (torch.as_tensor(m, dtype=torch.float64) for m in members)
        if thetas.ndim != 2 or thetas.shape[1] != k:
            raise TorchfricError(f"ensemble θ must have shape (K, {k}), got {tuple(thetas.shape)}")
        if q_scale.shape != (thetas.shape[0],) or r_scale.shape != (thetas.shape[0],):
            raise TorchfricError("ensemble q/r scales need one value per member")
    K = thetas.shape[0]
    callback = callback or EnsembleCallback()
    n = 2 + k
    f64 = torch.float64
    Q, P0_xx, H, R = tuning.matrices(k)
    Qk = Q * q_scale[:, None, None]
    Rk = R * r_scale[:, None, None]
    P_theta = tuning.initial_P_theta(model, thetas)
    theta = thetas.clone()
    bound = torch.tensor(tuning.theta_bound, dtype=f64)
    step_fn = make_masked_step(model, tuning.substeps, compile=tuning.compile)
    data = [(e, e.u.to(f64), _measurements(e, tuning.measure)) for e in exps]
    total = sum(e.n for e in exps)

    status = [RUNNING] * K
    reasons = [""] * K
    histories: list[list[PassRecord]] = [[] for _ in range(K)]
    best_ll = torch.full((K,), -math.inf, dtype=f64)
    best_theta, best_P = theta.clone(), P_theta.clone()
    filter_steps = 0
    first_pass = 1
    if start is not None:
        first_pass = int(start["pass"]) + 1
        theta, P_theta = start["thetas"].clone(), start["P_thetas"].clone()
        best_theta, best_P = start["best_theta"].clone(), start["best_P"].clone()
        best_ll = start["best_loglik"].clone()
        status, reasons = list(start["status"]), list(start["reasons"])
        histories = [[PassRecord(**r) for r in h] for h in start["histories"]]
        filter_steps = int(start["filter_steps"])

    def snapshot(p: int) -> dict[str, Any]:
        return {
            "method": "ekf_ensemble",
            "pass": p,
            "members_theta": thetas.clone(),
            "q_scale": q_scale.clone(),
            "r_scale": r_scale.clone(),
            "thetas": theta.clone(),
            "P_thetas": P_theta.clone(),
            "best_theta": best_theta.clone(),
            "best_P": best_P.clone(),
            "best_loglik": best_ll.clone(),
            "status": list(status),
            "reasons": list(reasons),
            "histories": [[r.to_dict() for r in h] for h in histories],
            "filter_steps": filter_steps,
        }

    for p in range(first_pass, tuning.passes + 1):
        if all(s != RUNNING for s in status):
            break
        t0 = time.perf_counter()
        theta_old, P_old = theta.clone(), P_theta.clone()
        good = torch.tensor([s == RUNNING for s in status])
        fail_at = torch.full((K,), -1, dtype=torch.long)
        sum_e2 = torch.zeros(K, H.shape[0], dtype=f64)
        sum_nis = torch.zeros(K, dtype=f64)
        loglik = torch.zeros(K, dtype=f64)
        samples = 0
        fail_exp = [""] * K
        for exp, u, y in data:
            x0 = torch.stack(
                [exp.q[0], exp.qdot[0] if exp.qdot is not None else exp.q.new_zeros(())]
            )
            x = torch.cat([x0.to(f64).expand(K, 2), theta], dim=1)
            P = torch.zeros(K, n, n, dtype=f64)
            P[:, :2, :2] = P0_xx
            P[:, 2:, 2:] = P_theta
            dt = torch.tensor(exp.dt, dtype=f64)
            was_good = good.clone()
            x1, P1, e, nis, ll = _batched_update(x, P, y[0], H, Rk)
            ok = (
                torch.isfinite(nis)
                & torch.isfinite(x1).all(1)
                & torch.isfinite(P1).flatten(1).all(1)
                & (x1[:, 2:].abs() <= bound).all(1)
            )
            x = torch.where(ok[:, None], x1, x)
            P = torch.where(ok[:, None, None], P1, P)
            fail_at = torch.where(good & ~ok & (fail_at < 0), 0, fail_at)
            good = good & ok
            sum_e2 += torch.where(good[:, None], e * e, 0.0)
            sum_nis += torch.where(good, nis, 0.0)
            loglik += torch.where(good, ll, 0.0)
            index = torch.arange(exp.n)
            carry = (x, P, good, fail_at, sum_e2, sum_nis, loglik)
            if step_fn.chunk is not None:
                # sample j = 1 + i is driven by u[j − 1] and measured by y[j]
                for i, m, xs, valid in iter_chunks((index[1:], u[:-1], y[1:]), step_fn.size):
                    carry, _ = step_fn.chunk(carry, xs, valid, (dt, Qk, H, Rk, bound))
                    callback.on_progress(p, samples + 1 + i + m, total)
            else:
                for j in range(1, exp.n):
                    carry = step_fn(*carry, index[j], u[j - 1], y[j], dt, Qk, H, Rk, bound)
                    if j % progress_every == 0:
                        callback.on_progress(p, samples + j, total)
            x, P, good, fail_at, sum_e2, sum_nis, loglik = carry
            for i in torch.nonzero(was_good & ~good).flatten().tolist():
                fail_exp[i] = f"pass {p}, experiment {exp.name!r}, sample {int(fail_at[i])}"
            samples += exp.n
            callback.on_progress(p, samples, total)
            theta = torch.where(good[:, None], x[:, 2:], theta)
            P_theta = torch.where(good[:, None, None], P[:, 2:, 2:], P_theta)
        filter_steps += K * samples
        seconds = time.perf_counter() - t0
        rel = (theta - theta_old).norm(dim=1) / theta_old.norm(dim=1).clamp_min(1e-12)
        for i in range(K):
            if status[i] != RUNNING:
                theta[i], P_theta[i] = best_theta[i], best_P[i]
                continue
            if not bool(good[i]):
                status[i] = DIVERGED
                reasons[i] = (
                    f"diverged in {fail_exp[i]}: the belief became non-finite, non-PSD or θ left "
                    f"the box |θ| <= {tuning.theta_bound:g}"
                )
                theta[i], P_theta[i] = theta_old[i], P_old[i]
                continue
            record = PassRecord(
                index=p,
                theta=theta[i].tolist(),
                parameters=dict(
                    zip(model.theta_names, model.to_physical(theta[i]).tolist(), strict=True)
                ),
                trace_P=float(torch.diagonal(P[i]).sum()),
                trace_P_theta=float(torch.diagonal(P_theta[i]).sum()),
                innovation_rms=(sum_e2[i] / samples).sqrt().tolist(),
                nis=float(sum_nis[i]) / samples,
                loglik=float(loglik[i]),
                rel_change=float(rel[i]),
                seconds=seconds,
                samples=samples,
            )
            ll_best = float(best_ll[i])
            if tuning.rollback and histories[i] and record.loglik < ll_best - 1e-6 * abs(ll_best):
                record.rolled_back = True
                theta[i], P_theta[i] = best_theta[i], best_P[i]
                status[i] = ROLLED_BACK
            else:
                best_ll[i] = record.loglik
                best_theta[i], best_P[i] = theta[i].clone(), P_theta[i].clone()
                if tuning.tolerance > 0 and record.rel_change < tuning.tolerance:
                    status[i] = CONVERGED
            histories[i].append(record)
        if callback.on_ensemble_pass_end(p, snapshot(p)) is False:
            break

    alive = [i for i in range(K) if status[i] != DIVERGED or histories[i]]
    if not alive:
        first = next((r for r in reasons if r), "every member diverged")
        raise TorchfricError(
            f"every one of the {K} ensemble members diverged (member 0: {first}). Fix: start "
            "from model.init = 'prefit', lower estimator.p0_theta or the ensemble spread"
        )
    # A member that diverged after good passes keeps its last good pass (like identify_ekf's
    # last_good); it stays eligible but is reported as diverged.
    theta = torch.where(torch.tensor([s == DIVERGED for s in status])[:, None], best_theta, theta)
    # Selection by open-loop simulation of every record there is: the mean FIT (q and q̇) on
    # the validation files and the mean FIT on the training files, weighted equally (training
    # files alone when there is no validation). The EKF never fits open-loop simulations, so
    # the training files are a second check, not a fitted score; on the rig, validation alone
    # kept a polytopic member 3 % off in inertia for one user tuning in nine, both kept a
    # physical member for all nine (benchmarks/robustness.py, which shows each rule).
    # Not by the innovation likelihood: members differ in R and Q, and the likelihood prefers the
    # smallest R that the data allow, which on the rig is the member with the worst friction
    # curve. The likelihood only decides when no member simulates.
    scores = torch.full((K,), -math.inf, dtype=f64)
    fits: list[dict[str, dict[str, float]]] = [{} for _ in range(K)]
    engine = "compiled" if tuning.compile else "odeint"
    idx = torch.tensor(alive)
    # (training files without a velocity, e.g. measure = "position", cannot be simulated from
    # their measured state and are left out)
    groups = [g for g in (list(validation), [e for e in exps if e.qdot is not None]) if g]
    total = torch.zeros(len(alive), dtype=f64)
    for group in groups:
        group_fit = torch.zeros(len(alive), dtype=f64)
        for v in group:
            sim = simulate_members(
                model, theta[idx], v, max_substeps=max_substeps, engine=engine
            )
            fq, fv = _fit(v.q.to(f64), sim[..., 0]), _fit(v.qdot.to(f64), sim[..., 1])
            group_fit += 0.5 * (fq + fv) / len(group)
            for a, i in enumerate(alive):
                fits[i][v.name] = {"fit_q": float(fq[a]), "fit_qdot": float(fv[a])}
        total += group_fit / len(groups)
    if groups:
        scores[idx] = torch.nan_to_num(total, nan=-math.inf)
    selected_by = "validation_and_train_fit" if validation else "train_fit"
    if not bool(torch.isfinite(scores).any()):
        for i in alive:
            scores[i] = best_ll[i]
        selected_by = "loglik"
    best = int(torch.argmax(scores))
    fitted = copy.deepcopy(model).set_theta(theta[best])
    result = EKFResult(
        fitted,
        theta[best].clone(),
        best_P[best].clone() if status[best] == DIVERGED else P_theta[best].clone(),
        list(histories[best]),
        status[best] == CONVERGED,
    )
    summaries = [
        MemberSummary(
            index=i,
            q_scale=float(q_scale[i]),
            r_scale=float(r_scale[i]),
            status=status[i],
            passes=len(histories[i]),
            loglik=float(best_ll[i]),
            inertia=float(model.split(theta[i])[1]["inertia"]),
            score=float(scores[i]),
            fits=fits[i],
            reason=reasons[i],
        )
        for i in range(K)
    ]
    return EnsembleResult(
        best=best,
        result=result,
        thetas=theta,
        P_thetas=P_theta,
        members=summaries,
        selected_by=selected_by,
        seconds=time.perf_counter() - t_start,
        filter_steps=filter_steps,
    )
