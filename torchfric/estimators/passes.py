"""The pass loop of the iterative off-line EKF, shared by the single filter and the ensemble.

Both estimators filter every experiment once per pass and then judge the pass, member by member
(the single EKF is the one-member case):

* a member whose filter failed is frozen at its last good pass and marked diverged (the single
  EKF never gets here: its failure raises `DivergenceError` inside the pass);
* a pass that lowers the member's innovation log-likelihood by more than ``1e-6·|best|`` is
  rolled back (with `EKFTuning.rollback`): θ and ``P_θθ`` return to the best pass and the member
  stops;
* otherwise the pass becomes the member's best, and the member has converged when the pass
  raised the innovation log-likelihood by less than ``tolerance · k`` nats over all records
  (`EKFTuning.tolerance`, ``> 0``; k the number of parameters). The default 0.5 is the
  likelihood-ratio yardstick: k parameters fitted to pure noise raise the log-likelihood by
  about k/2 (2Δℓ ~ χ²_k), so a smaller gain is no improvement any test could tell from none.
  A rolled-back member has converged too: the pass before was its best fit.

Why the likelihood and not θ: each pass re-reads the same data, so ``P_θθ`` shrinks and θ keeps
creeping by ~1 % a pass (measured on the rig) long after the fit stopped improving; a relative
change of θ below 1e-4 was reached by no run. The likelihood's gain per pass falls to a few
tenths of a nat within 3–6 passes on the rig, on EMPS and on a user-style axis. How far the
kept θ still is from the likelihood's maximum, in units of each parameter's σ, is reported
after the run (`torchfric.estimators.covariance`, ``newton_step_sigma``).

The passes stop when no member is running, when `EKFTuning.passes` are done, or when the
estimator's end-of-pass hook returns False. `PassLedger` holds that bookkeeping (status, history
of `PassRecord`, best log-likelihood, θ and ``P_θθ`` per member); `run_passes` drives the loop
around a per-pass filtering function that each estimator supplies.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from torch import Tensor

from ..data import Experiment
from ..errors import TorchfricError
from ..models.arm import ArmModel
from .ekf import MEASUREMENTS
from .observers import Callback
from .propagation import resolve_substeps
from .settings import EKFTuning

__all__ = [
    "RUNNING",
    "CONVERGED",
    "ROLLED_BACK",
    "DIVERGED",
    "PassRecord",
    "EKFResult",
    "Filtering",
    "PassSums",
    "PassLedger",
    "pass_record",
    "run_passes",
    "experiment_list",
    "prepared",
    "measurements",
    "measured_data",
    "initial_belief",
    "state_belief",
    "belief",
]

RUNNING, CONVERGED, ROLLED_BACK, DIVERGED = "running", "converged", "rolled_back", "diverged"


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
    # ``P_θθ`` after the pass (estimation coordinates), so that any pass can be the kept one
    P_theta: list[list[float]] | None = None
    # validation score of the pass's θ: mean over the validation records of (FIT_q + FIT_q̇)/2
    # (`torchfric.estimators.metrics.mean_fit`); None until scored, or without validation data
    val_score: float | None = None

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
    substeps: int | None = None  # RK4 sub-steps of the last pass's step (None: not recorded)

    @property
    def passes(self) -> int:
        return len(self.history)


@dataclass
class Filtering:
    """What every pass filters with, fixed for the whole run (but for the step's RK4
    `substeps`, which ``"auto"`` raises between passes: `finer_steps`). For an ensemble, Q
    `(K, n, n)` and R `(K, m, m)` are per member and `step_fn` is its masked batched step."""

    data: list[tuple[Experiment, Tensor, Tensor]]  # (experiment, u (N,), y (N, m)), float64
    Q: Tensor
    P0_xx: Tensor
    H: Tensor
    R: Tensor
    step_fn: Any
    theta_bound: float
    callback: Callback
    every: int  # samples between progress reports (where the filter reports per sample)
    total: int  # samples per pass
    substeps: int = 1  # RK4 sub-steps per sample of `step_fn`

    @property
    def states(self) -> int:
        """Entries of the belief before θ: 2, or 3 with a bristle state."""
        return self.P0_xx.shape[0]


@dataclass
class PassSums:
    """What one pass's filtering hands back, batched over the K members."""

    theta: Tensor  # (K, k) θ after the pass (a failed member's row is not used)
    P_theta: Tensor  # (K, k, k)
    P: Tensor  # (K, n, n) the full covariance at the end of the pass
    sum_e2: Tensor  # (K, m) Σ e² per measured channel
    sum_nis: Tensor  # (K,)
    loglik: Tensor  # (K,) summed innovation log-likelihood
    samples: int
    failures: list[str]  # per member: "" when healthy, else why it diverged

    def spread(self, rows: Tensor, theta: Tensor, P_theta: Tensor) -> PassSums:
        """These sums of the members `rows` of a batch whose θ and ``P_θθ`` are `theta`,
        `P_theta` `(K, ...)`, as the whole batch's: the other members keep their θ and
        ``P_θθ``, with zero sums and no failure."""
        K = theta.shape[0]

        def full(x: Tensor, base: Tensor | None = None) -> Tensor:
            out = torch.zeros((K, *x.shape[1:]), dtype=x.dtype) if base is None else base.clone()
            out[rows] = x
            return out

        failures = [""] * K
        for j, i in enumerate(rows.tolist()):
            failures[i] = self.failures[j]
        return PassSums(full(self.theta, theta), full(self.P_theta, P_theta), full(self.P),
                        full(self.sum_e2), full(self.sum_nis), full(self.loglik), self.samples,
                        failures)  # fmt: skip


def pass_record(
    model: ArmModel, index: int, sums: PassSums, i: int, rel: float, seconds: float
) -> PassRecord:
    """The `PassRecord` of member `i` after pass `index`."""
    theta = sums.theta[i]
    return PassRecord(
        index=index,
        theta=theta.tolist(),
        parameters=dict(zip(model.theta_names, model.to_physical(theta).tolist(), strict=True)),
        trace_P=float(torch.diagonal(sums.P[i]).sum()),
        trace_P_theta=float(torch.diagonal(sums.P_theta[i]).sum()),
        innovation_rms=(sums.sum_e2[i] / sums.samples).sqrt().tolist(),
        nis=float(sums.sum_nis[i]) / sums.samples,
        loglik=float(sums.loglik[i]),
        rel_change=rel,
        seconds=seconds,
        samples=sums.samples,
        P_theta=sums.P_theta[i].tolist(),
    )


class PassLedger:
    """The pass bookkeeping of K members: θ `(K, k)` and ``P_θθ`` `(K, k, k)` now, and per member
    its status, divergence reason, `PassRecord` history and best pass (log-likelihood, θ,
    ``P_θθ``; the rollback target). ``next_pass`` is the 1-based pass to run next and
    ``filter_steps`` counts member-samples filtered (the running members of each pass)."""

    def __init__(self, model: ArmModel, tuning: EKFTuning, theta: Tensor, P_theta: Tensor) -> None:
        K = theta.shape[0]
        self.model, self.rollback = model, tuning.rollback
        self.tolerance = tuning.tolerance * model.num_parameters  # nats a pass (module docstring)
        self.theta, self.P_theta = theta, P_theta
        self.status, self.reasons = [RUNNING] * K, [""] * K
        self.histories: list[list[PassRecord]] = [[] for _ in range(K)]
        self.best_ll = torch.full((K,), -math.inf, dtype=torch.float64)
        self.best_theta, self.best_P = theta.clone(), P_theta.clone()
        self.next_pass, self.filter_steps = 1, 0

    @classmethod
    def from_history(
        cls,
        model: ArmModel,
        tuning: EKFTuning,
        theta: Tensor,
        P_theta: Tensor,
        history: Sequence[PassRecord],
    ) -> PassLedger:
        """One member resuming after the completed passes `history`, at `theta` (k,) and
        `P_theta` (k, k) (the single EKF's ``start``). Its status is read off the last record:
        rolled back when it was (a rolled-back pass never counts as converged, as in an
        uninterrupted run), else converged when its gain is below the tolerance."""
        ledger = cls(model, tuning, theta.clone()[None], P_theta.clone()[None])
        if history:
            last = history[-1]
            ledger.histories[0] = list(history)
            kept = [r for r in history if not r.rolled_back]
            ledger.best_ll[0] = kept[-1].loglik if kept else -math.inf
            ledger.next_pass = len(history) + 1
            before = kept[-2].loglik if len(kept) >= 2 else -math.inf
            if last.rolled_back:
                ledger.status[0] = ROLLED_BACK
            elif ledger.tolerance > 0 and last.loglik - before < ledger.tolerance:
                ledger.status[0] = CONVERGED
        return ledger

    @classmethod
    def from_state(cls, model: ArmModel, tuning: EKFTuning, state: dict[str, Any]) -> PassLedger:
        """The ledger saved by `state` after pass ``state["pass"]`` (an ensemble snapshot)."""
        ledger = cls(model, tuning, state["thetas"].clone(), state["P_thetas"].clone())
        ledger.best_theta, ledger.best_P = state["best_theta"].clone(), state["best_P"].clone()
        ledger.best_ll = state["best_loglik"].clone()
        ledger.status, ledger.reasons = list(state["status"]), list(state["reasons"])
        ledger.histories = [[PassRecord(**r) for r in h] for h in state["histories"]]
        ledger.next_pass = int(state["pass"]) + 1
        ledger.filter_steps = int(state["filter_steps"])
        return ledger

    def state(self) -> dict[str, Any]:
        """Copies of everything `from_state` needs (the ensemble snapshot's ledger part)."""
        return {
            "thetas": self.theta.clone(),
            "P_thetas": self.P_theta.clone(),
            "best_theta": self.best_theta.clone(),
            "best_P": self.best_P.clone(),
            "best_loglik": self.best_ll.clone(),
            "status": list(self.status),
            "reasons": list(self.reasons),
            "histories": [[r.to_dict() for r in h] for h in self.histories],
            "filter_steps": self.filter_steps,
        }

    @property
    def finished(self) -> bool:
        """No member is running any more."""
        return all(s != RUNNING for s in self.status)

    def running(self) -> Tensor:
        """`(K,)` bool: the members that take part in the next pass."""
        return torch.tensor([s == RUNNING for s in self.status])

    def kept_theta(self) -> Tensor:
        """`(K, k)` θ of every member, a diverged one at its last good pass."""
        diverged = torch.tensor([s == DIVERGED for s in self.status])
        return torch.where(diverged[:, None], self.best_theta, self.theta)

    def result(self, i: int) -> EKFResult:
        """Member `i` as a single-filter result (a diverged member at its last good pass)."""
        diverged = self.status[i] == DIVERGED
        theta = self.best_theta[i] if diverged else self.theta[i]
        P_theta = self.best_P[i] if diverged else self.P_theta[i]
        fitted = copy.deepcopy(self.model).set_theta(theta)
        converged = self.status[i] in (CONVERGED, ROLLED_BACK)
        return EKFResult(fitted, theta.clone(), P_theta.clone(), list(self.histories[i]), converged)

    def judge(self, index: int, sums: PassSums, seconds: float) -> list[PassRecord | None]:
        """Take the finished pass `index`: record, roll back, keep best, converge or diverge each
        running member; members that had stopped stay at their best pass. Returns the new
        record of each member (None for members without one)."""
        theta_old, P_old = self.theta, self.P_theta
        running = sum(status == RUNNING for status in self.status)
        theta, P_theta = sums.theta.clone(), sums.P_theta.clone()
        rel = (theta - theta_old).norm(dim=1) / theta_old.norm(dim=1).clamp_min(1e-12)
        records: list[PassRecord | None] = [None] * len(self.status)
        for i, status in enumerate(self.status):
            if status != RUNNING:
                theta[i], P_theta[i] = self.best_theta[i], self.best_P[i]
            elif sums.failures[i]:
                self.status[i], self.reasons[i] = DIVERGED, sums.failures[i]
                theta[i], P_theta[i] = theta_old[i], P_old[i]
            else:
                records[i] = pass_record(self.model, index, sums, i, float(rel[i]), seconds)
                self._keep_or_roll_back(i, records[i], theta, P_theta)
        self.theta, self.P_theta = theta, P_theta
        self.next_pass = index + 1
        self.filter_steps += running * sums.samples  # the members filtered in this pass
        return records

    def _keep_or_roll_back(
        self, i: int, record: PassRecord, theta: Tensor, P_theta: Tensor
    ) -> None:
        """The rollback rule (a relative margin of 1e-6 below the best log-likelihood), else
        the new best pass and the convergence rule (a gain below ``tolerance · k`` nats); appends
        `record` to member i's history."""
        ll_best = float(self.best_ll[i])
        if self.rollback and self.histories[i] and record.loglik < ll_best - 1e-6 * abs(ll_best):
            record.rolled_back = True
            theta[i], P_theta[i] = self.best_theta[i], self.best_P[i]
            self.status[i] = ROLLED_BACK
        else:
            self.best_ll[i] = record.loglik
            self.best_theta[i], self.best_P[i] = theta[i].clone(), P_theta[i].clone()
            if self.tolerance > 0 and record.loglik - ll_best < self.tolerance:
                self.status[i] = CONVERGED
        self.histories[i].append(record)


def run_passes(
    ledger: PassLedger,
    passes: int,
    filter_pass: Callable[[int], PassSums],
    on_pass_end: Callable[[int, list[PassRecord | None]], bool | None],
) -> None:
    """Run passes ``ledger.next_pass … passes``: ``filter_pass(p)`` filters every experiment
    once from the ledger's θ and ``P_θθ``, the ledger judges the pass, and
    ``on_pass_end(p, records)`` reports it (False stops). Stops early when no member runs."""
    for p in range(ledger.next_pass, passes + 1):
        if ledger.finished:
            break
        t0 = time.perf_counter()
        sums = filter_pass(p)
        records = ledger.judge(p, sums, time.perf_counter() - t0)
        if on_pass_end(p, records) is False:
            break


def experiment_list(
    experiments: Experiment | Sequence[Experiment], tuning: EKFTuning, k: int, who: str
) -> list[Experiment]:
    """The experiments as a non-empty list, after checking `tuning` for `k` parameters."""
    exps = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    if not exps:
        raise TorchfricError(f"{who} needs at least one experiment")
    tuning.check(k)
    return exps


def prepared(
    experiments: Experiment | Sequence[Experiment], tuning: EKFTuning, k: int, who: str,
    model: ArmModel | None = None,
) -> tuple[list[Experiment], EKFTuning]:  # fmt: skip
    """`experiment_list`, and `tuning` resolved against those experiments (`EKFTuning.resolved`:
    relative variances at the data's velocity scale; ``substeps = "auto"`` for `model` at its
    own θ, `resolve_substeps`)."""
    exps = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    tuning = tuning if model is None else resolve_substeps(tuning, model, exps)
    exps = experiment_list(exps, tuning, k, who)
    return exps, tuning.resolved(exps)


def measurements(exp: Experiment, measure: str) -> Tensor:
    """The measured channels `(N, m)` of `exp` for `measure` ("both", "position", ...)."""
    idx = MEASUREMENTS[measure]
    if 1 in idx and exp.qdot is None:
        raise TorchfricError(
            f"experiment {exp.name!r} has no velocity but measure = {measure!r} needs one; "
            "reconstruct it first (Experiment.with_velocity) or use measure = 'position'"
        )
    cols = [exp.q if i == 0 else exp.qdot for i in idx]
    return torch.stack(cols, dim=-1).to(torch.float64)


def measured_data(
    exps: Sequence[Experiment], measure: str
) -> list[tuple[Experiment, Tensor, Tensor]]:
    """``(experiment, u, y)`` per experiment, in float64."""
    return [(e, e.u.to(torch.float64), measurements(e, measure)) for e in exps]


def initial_belief(
    exp: Experiment, theta: Tensor, P_theta: Tensor, P0_xx: Tensor
) -> tuple[Tensor, Tensor]:
    """The belief at the start of `exp` for K members: ``x = [q_0, q̇_0, θ]`` `(K, n)` (q̇_0 = 0
    without a velocity) and P `(K, n, n)` with ``P_xx = P0_xx``, ``P_θθ`` carried, cross terms
    zero. A dynamic model's P0_xx `(3, 3)` adds its bristle state, started at rest (z = 0)."""
    x0 = torch.stack([exp.q[0], exp.qdot[0] if exp.qdot is not None else exp.q.new_zeros(())])
    return belief(x0.to(torch.float64), theta, P_theta, P0_xx)


def state_belief(exp: Experiment, K: int, P0_xx: Tensor) -> tuple[Tensor, Tensor]:
    """`initial_belief`'s state block for K filters with θ held: x `(K, s)`, P `(K, s, s)`."""
    none = torch.zeros(K, 0, dtype=torch.float64)
    return initial_belief(exp, none, none.reshape(K, 0, 0), P0_xx)


def belief(x0: Tensor, theta: Tensor, P_theta: Tensor, P0_xx: Tensor) -> tuple[Tensor, Tensor]:
    """``x = [x0, 0…, θ]`` `(K, n)` and block-diagonal ``P = diag(P0_xx, P_θθ)`` `(K, n, n)` for
    K members' θ `(K, k)`: `x0` holds [q, q̇]; the states after them (z) start at 0."""
    K, k = theta.shape
    s = P0_xx.shape[0]
    x0 = torch.cat([x0, x0.new_zeros(s - x0.numel())])
    x = torch.cat([x0.expand(K, s), theta], dim=1)
    P = torch.zeros(K, s + k, s + k, dtype=torch.float64)
    P[:, :s, :s] = P0_xx
    P[:, s:, s:] = P_theta
    return x, P
