"""The friction model's size from data: every candidate size identified, one criterion picks.

`compare_sizes` takes one starting model per size (say tanh(1) … tanh(7), each from its own
pre-fit) and runs the iterative EKF on each, under every tuning of the ensemble (`EnsembleSpec`;
one filter under the base tuning without one), with the pass rules of `torchfric.estimators.
passes`. Then it scores each size by the Bayesian information criterion of the filter's one-step
innovations on the identification data:

    BIC = −2 ℓ̂ + k ln N

- ℓ̂ is the innovation log-likelihood of one more filter pass with θ held fixed at a member's
  identified value (``P_θθ = 0``, so θ does not move while it is scored), maximised over a
  common scale λ of the filter's noise model (P0_xx, Q and R all multiplied by λ: the gains and
  innovations stay the same and every innovation covariance S becomes λ S, so the maximum has a
  closed form, `concentrated_loglik`). The best member of the size gives the size's ℓ̂.
- k is the number of estimated parameters (``ArmModel.num_parameters``), N the number of
  samples filtered per pass.

Holding θ fixed makes ℓ̂ the likelihood of one model, not of a filter still adapting θ in the
pass it is scored on; concentrating λ out makes it independent of how well the assumed noise
variances match the data's (a tuning off by ×10 would otherwise weigh the fit ten times more or
less against the penalty). The size with the lowest BIC is chosen.

Sizes that nest run as one batch: a tanh(j) network is a tanh(n) network (n > j) whose extra
neurons have ``W1 = W2 = 0``, and with zero initial variance on those entries (``P_θθ`` rows and
columns zero, Q_θ zero) the filter never moves them: their rows of P stay zero through the
prediction (θ's dynamics are the identity) and the update (their gain rows are ``P Hᵀ S⁻¹ = 0``).
Every tanh size's members are therefore members of one tanh(n) ensemble, filtered in one
batch, with the results of the sizes run alone (same arithmetic, same pass rules). Other kinds
(polytopic local models come with their own centres and widths) run one size after another.

The friction class (``model.dynamic = "auto"``) is chosen here as well, by `compare_dynamics`,
and not by BIC: on a static Stribeck axis the one-step likelihood of the LuGre filter beats the
static filter's by more than its ln N penalty (the bristle state's extra freedom, not a better
model), so each class is identified on the first 70 % of the records (by `compare_sizes`, the
same ensemble and passes; on a long record, excerpts of it) and scored by how well it predicts
the held-out rest in 0.05-s open-loop windows from its own filter (`selection.window_errors`). Those
windows also reward a model that sticks, which a static curve through zero cannot; so LuGre is
kept only when its bristles are seen as well: their travel through a reversal, ``2 g(0)/σ0``,
must lie between the records' position step and span (`torchfric.models.lugre.bristles_seen`:
below, σ0 → ∞, the static model that sticks; beyond, σ0 → 0, bristles that never slide), and
their transient must last a couple of samples (`bristles_timed`; faster is σ0 → ∞ in time).

Why this size: one concept, the model's structure from the identification data, and one
machinery for it (every candidate identified by the same batched ensemble, `compare_sizes`,
then scored); the windows themselves live with the other open-loop scores in `selection`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import Tensor

from ..data import Experiment, position_step
from ..errors import TorchfricError
from ..models.arm import ArmModel
from ..models.lugre import (
    STICK_RATE_LIMIT,
    bristle_travel,
    bristles_seen,
    bristles_timed,
    stick_rate,
)
from .ekf import FilterFailure
from .ensemble import _filter_members, make_masked_step, member_grid
from .observers import Callback
from .passes import DIVERGED, Filtering, PassLedger, measured_data, prepared, run_passes
from .selection import window_errors
from .settings import EKFTuning, EnsembleSpec

__all__ = [
    "CRITERION",
    "DYNAMICS_CRITERION",
    "DynamicsResult",
    "compare_dynamics",
    "held_out_heads",
    "SizeScore",
    "SizingResult",
    "compare_sizes",
    "concentrated_loglik",
    "nests",
]

CRITERION = "bic_innovations"
"""The name metrics and reports give the criterion: BIC on the fixed-θ one-step innovations."""


@dataclass
class SizeScore:
    """One candidate size's result."""

    size: int
    parameters: int  # k: estimated θ entries of the model of this size
    loglik: float  # ℓ̂: concentrated innovation log-likelihood of the size's best member
    bic: float  # −2 ℓ̂ + k ln N (inf when every member of the size diverged)
    member: int  # that member's index in the size's own grid (-1: none)
    q_scale: float  # its tuning's Q and R factors
    r_scale: float
    passes: int  # passes it ran
    members: int  # filters this size ran
    diverged: int  # of which diverged
    chosen: bool = False

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class SizingResult:
    """What `compare_sizes` returns: one `SizeScore` per size (ascending) and the choice."""

    scores: list[SizeScore]
    chosen: int  # the size with the lowest BIC
    samples: int  # N of the penalty k ln N
    batched: bool  # the sizes ran as one batch (nested tanh sizes)
    seconds: float
    thetas: dict[int, Tensor] = dataclasses.field(default_factory=dict, repr=False)
    """Each size's identified θ (its best member's kept θ, in that size's own coordinates; not
    in `to_dict`): the start of whatever scores the sizes next."""

    def to_dict(self) -> dict[str, Any]:
        """For metrics.json: the criterion, the choice and the table of sizes."""
        return {
            "criterion": CRITERION,
            "chosen": self.chosen,
            "samples": self.samples,
            "batched": self.batched,
            "seconds": self.seconds,
            "table": [s.to_dict() for s in self.scores],
        }


def concentrated_loglik(loglik: Tensor, sum_nis: Tensor, samples: int, channels: int) -> Tensor:
    """The innovation log-likelihood maximised over a common scale λ of the noise model.

    A pass gives ``loglik = −½ Σ (eᵀS⁻¹e + ln det S + m ln 2π)`` and ``sum_nis = Σ eᵀS⁻¹e``
    over `samples` samples of `channels` (m) channels. With every S scaled by λ the maximum is
    at ``λ̂ = sum_nis / (m N)``, where the log-likelihood is
    ``loglik + ½ sum_nis − ½ m N (1 + ln λ̂)``."""
    mn = float(samples * channels)
    scale = sum_nis / mn
    return loglik + 0.5 * sum_nis - 0.5 * mn * (1.0 + torch.log(scale))


def nests(starts: Mapping[int, ArmModel]) -> bool:
    """True when the sizes nest by zero padding (tanh networks of the same arm): then they run
    as one batch of the largest."""
    models = list(starts.values())
    if not all(m.friction.kind == "tanh" for m in models):
        return False
    big = set(starts[max(starts)].theta_names)
    return all(set(m.theta_names) <= big for m in models)


def compare_sizes(
    starts: Mapping[int, ArmModel],
    experiments: Experiment | Sequence[Experiment],
    tuning: EKFTuning | None = None,
    spec: EnsembleSpec | None = None,
    *,
    callback: Callback | None = None,
    progress_every: int = 2000,
    device: torch.device | None = None,
) -> SizingResult:
    """Identify each size's model from its start and choose the size by BIC (module docstring).

    Args:
        starts: size → the starting model of that size (its θ is the start of the size's
            filters). Every model must have the same arm terms.
        experiments: the identification data.
        tuning: the base `EKFTuning` (the run's).
        spec: the ensemble's grid (each size runs every start and tuning of it); None: one
            filter per size under `tuning`.
        callback: `Callback.on_progress` inside each pass.
        device: a CUDA device filters the batch there (`make_masked_step`); None: the CPU.

    Raises:
        TorchfricError: no sizes, or every filter of every size diverged.
    """
    t0 = time.perf_counter()
    if not starts:
        raise TorchfricError("compare_sizes needs at least one size")
    sizes = sorted(starts)
    largest = starts[sizes[-1]]
    k = largest.num_parameters
    exps, tuning = prepared(experiments, tuning or EKFTuning(), k, "compare_sizes", largest)
    callback = callback or Callback()
    batched = len(sizes) > 1 and nests(starts)
    groups = [(largest, sizes)] if batched else [(starts[s], [s]) for s in sizes]
    samples = sum(e.n for e in exps)
    scores: list[SizeScore] = []
    thetas: dict[int, Tensor] = {}
    for model, group in groups:
        members = _members(model, {s: starts[s] for s in group}, tuning, spec)
        f = _filtering(model, exps, tuning, members, callback, progress_every, device)
        ledger = _train(model, tuning, members, f)
        ll = _fixed_loglik(model, tuning, ledger, f)
        scores += [_score(s, starts[s], members, ledger, ll, samples) for s in group]
        kept = ledger.kept_theta()
        for s in group:
            best = max(
                (i for i, o in enumerate(members.owner) if o == s), key=lambda i: float(ll[i])
            )
            names = model.theta_names
            thetas[s] = kept[best, [names.index(n) for n in starts[s].theta_names]].clone()
    best = min(scores, key=lambda s: (s.bic, s.size))
    if not math.isfinite(best.bic):
        raise TorchfricError(
            f"every filter of every size ({', '.join(map(str, sizes))}) diverged; start from "
            "model.init = 'prefit', lower estimator.p0_theta, or give model.sizes smaller sizes"
        )
    best.chosen = True
    seconds = time.perf_counter() - t0
    return SizingResult(scores, best.size, samples, batched, seconds, thetas)


@dataclass
class _Members:
    """The filters of one batch: θ starts `(K, k)`, ``P_θθ`` `(K, k, k)`, Q and R factors
    `(K,)`, each one's size `owner` and its index in that size's grid `index`."""

    theta: Tensor
    P_theta: Tensor
    q_scale: Tensor
    r_scale: Tensor
    owner: list[int]
    index: list[int]


def _members(
    model: ArmModel, starts: Mapping[int, ArmModel], tuning: EKFTuning, spec: EnsembleSpec | None
) -> _Members:
    """Every size's grid of filters in `model`'s coordinates: a smaller start's θ and ``P_θθ``
    go to the entries of the same name, the others stay zero (neurons that never move)."""
    f64 = torch.float64
    names = model.theta_names
    k = len(names)
    thetas, Ps, qs, rs, owner, index = [], [], [], [], [], []
    for size, start in starts.items():
        theta0 = start.get_theta()
        if spec is None:
            grid = (theta0[None], torch.ones(1, dtype=f64), torch.ones(1, dtype=f64))
        else:
            grid = member_grid(start, theta0, spec)
        idx = torch.tensor([names.index(n) for n in start.theta_names])
        if not bool((model.log_mask()[idx] == start.log_mask()).all()):
            raise TorchfricError(f"size {size}: its parameters are stored unlike the batch's")
        G = grid[0].shape[0]
        theta = torch.zeros(G, k, dtype=f64)
        theta[:, idx] = grid[0]
        P = torch.zeros(G, k, k, dtype=f64)
        P[:, idx[:, None], idx[None, :]] = tuning.initial_P_theta(start, grid[0])
        thetas.append(theta)
        Ps.append(P)
        qs.append(grid[1])
        rs.append(grid[2])
        owner += [size] * G
        index += list(range(G))
    cat = torch.cat
    return _Members(cat(thetas), cat(Ps), cat(qs), cat(rs), owner, index)


def _filtering(
    model: ArmModel,
    exps: list[Experiment],
    tuning: EKFTuning,
    members: _Members,
    callback: Callback,
    every: int,
    device: torch.device | None = None,
) -> Filtering:
    """The batch's `Filtering`: each member's Q and R scaled, the masked batched step (on
    `device` when given)."""
    Q, P0_xx, H, R = tuning.matrices(model.num_parameters, model.state_size)
    Qk = Q * members.q_scale[:, None, None]
    Rk = R * members.r_scale[:, None, None]
    step_fn = make_masked_step(model, tuning.substeps, compile=tuning.compile, device=device)
    data, total = measured_data(exps, tuning.measure), sum(e.n for e in exps)
    return Filtering(data, Qk, P0_xx, H, Rk, step_fn, tuning.theta_bound, callback, every, total,
                     tuning.substeps)  # fmt: skip


def _train(model: ArmModel, tuning: EKFTuning, members: _Members, f: Filtering) -> PassLedger:
    """The passes of every member (`run_passes`), from its start."""
    ledger = PassLedger(model, tuning, members.theta.clone(), members.P_theta.clone())
    run_passes(ledger, tuning.passes, lambda p: _filter_members(p, ledger, f), lambda p, r: None)
    return ledger


def _fixed_loglik(model: ArmModel, tuning: EKFTuning, ledger: PassLedger, f: Filtering) -> Tensor:
    """`(K,)` each member's concentrated log-likelihood (`concentrated_loglik`) of one pass
    with its kept θ held fixed; −inf for a member without a completed pass or whose pass
    fails."""
    K, k = ledger.theta.shape
    s = f.states
    Q = f.Q.clone()
    Q[:, s:, s:] = 0.0  # no process noise on θ either: it stays where it is
    zero = torch.zeros(K, k, k, dtype=torch.float64)
    scoring = PassLedger(model, tuning, ledger.kept_theta(), zero)
    sums = _filter_members(0, scoring, dataclasses.replace(f, Q=Q))
    ll = concentrated_loglik(sums.loglik, sums.sum_nis, sums.samples, f.H.shape[0])
    usable = torch.tensor(
        [bool(h) and not fail for h, fail in zip(ledger.histories, sums.failures, strict=True)]
    )
    return torch.where(usable & torch.isfinite(ll), ll, -math.inf)


def _score(
    size: int,
    start: ArmModel,
    members: _Members,
    ledger: PassLedger,
    ll: Tensor,
    samples: int,
) -> SizeScore:
    """The `SizeScore` of `size` from its members' log-likelihoods `ll`."""
    rows = [i for i, s in enumerate(members.owner) if s == size]
    best = max(rows, key=lambda i: float(ll[i]))
    k = start.num_parameters
    loglik = float(ll[best])
    found = math.isfinite(loglik)
    return SizeScore(
        size=size,
        parameters=k,
        loglik=loglik,
        bic=-2.0 * loglik + k * math.log(samples) if found else math.inf,
        member=members.index[best] if found else -1,
        q_scale=float(members.q_scale[best]),
        r_scale=float(members.r_scale[best]),
        passes=len(ledger.histories[best]),
        members=len(rows),
        diverged=sum(ledger.status[i] == DIVERGED for i in rows),
    )


DYNAMICS_CRITERION = "windowed_prediction"
"""The name metrics and reports give `compare_dynamics`' criterion."""
HOLDOUT = 0.3  # the share of each identification record held out (its end)
WINDOW_SECONDS = 0.05  # the windows' length (0.02, 0.05, 0.1 s measured: docs/results.md)
MIN_WINDOW = 10  # samples, whatever the sample time
T_MIN = 2.0  # standard errors by which the dynamic model's windows must beat the static's


@dataclass
class DynamicsResult:
    """What `compare_dynamics` returns: per model class (``"none"``, ``"lugre"``) its `SizeScore`
    on the head (`size` unused), its windows' RMS position error on the held-out end (``rmse``),
    the paired statistic and the choice."""

    scores: dict[str, SizeScore]
    rmse: dict[str, float]
    gain: float  # 1 − MSE(dynamic) / MSE(static) over the held-out windows
    t: float  # the mean per-window MSE difference over its standard error
    chosen: str
    windows: int
    window_seconds: float
    holdout: float
    seconds: float
    bristle_travel: float  # the dynamic model's travel through a reversal, 2 g(0)/σ0
    position_step: float  # the records' (`position_step`)
    position_span: float  # the longest record's position range, max q − min q
    stick_rate: float  # the dynamic model's `stick_rate` [1/s]
    sample_time: float  # the records' shortest
    thetas: dict[str, Tensor] = dataclasses.field(default_factory=dict, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """For metrics.json (``dynamic``): the criterion, the choice and the two classes."""
        table = [
            {"dynamic": d, **{k: v for k, v in s.to_dict().items() if k != "size"},
             "rmse_q": self.rmse[d], "chosen": d == self.chosen}
            for d, s in self.scores.items()
        ]  # fmt: skip
        plain = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                 if f.name not in ("scores", "rmse", "thetas")}  # fmt: skip
        limits = {"t_min": T_MIN, "stick_rate_limit": STICK_RATE_LIMIT}
        return {"criterion": DYNAMICS_CRITERION, **plain, **limits, "table": table}


def held_out_heads(experiments: Sequence[Experiment], holdout: float = HOLDOUT) -> list[Experiment]:
    """The part of each record `compare_dynamics` identifies on: all but its last `holdout`
    share (the starting models it compares must come from these heads alone)."""
    return [e.slice(0, e.n - round(holdout * e.n)) for e in experiments]


def compare_dynamics(
    static: ArmModel,
    dynamic: ArmModel,
    experiments: Experiment | Sequence[Experiment],
    tuning: EKFTuning | None = None,
    spec: EnsembleSpec | None = None,
    *,
    holdout: float = HOLDOUT,
    window_seconds: float = WINDOW_SECONDS,
    device: torch.device | None = None,
    heads: Sequence[Experiment] | None = None,
) -> DynamicsResult:
    """Static or dynamic friction, from the identification records alone.

    Both models are identified (`compare_sizes`: the same ensemble and pass rules) on the first
    ``1 − holdout`` of every record (`held_out_heads`, or `heads`: parts of them, e.g. a long
    record's excerpts; `static` and `dynamic` are their starts, made from those alone); the
    rest is held out. There each model's filter, θ fixed,
    starts an open-loop simulation every `window_seconds` (`window_errors`), and the windows'
    mean squared position errors are compared pair by pair. The dynamic model is kept only when
    its windows predict better by more than `T_MIN` standard errors of the mean difference and
    its bristles travel between one position step and the records' span (`bristles_seen`)
    and ring slowly enough for the samples to see them (`bristles_timed`: the stuck axis's
    `stick_rate` times the sample time at most `STICK_RATE_LIMIT`); otherwise (a tie,
    bristles the records cannot see or that never slide in them, or every dynamic filter
    diverging) the static model, the simpler one, is. The windows see stiction
    as much as bristle dynamics: a static curve through zero cannot stick, so on machines with
    sharp stiction LuGre predicts better whatever its σ0, and a σ0 too stiff for the encoder to
    see, or whose transient is over within a sample, is the static limit σ0 → ∞
    (docs/results.md, "Static, LuGre or auto").

    Raises:
        TorchfricError: no record is long enough to hold a window out, or the static model's
            filters all diverge.
    """
    t0 = time.perf_counter()
    exps = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    tuning = tuning or EKFTuning()
    cuts = [e.n - round(holdout * e.n) for e in exps]
    lengths = [max(MIN_WINDOW, round(window_seconds / e.dt)) for e in exps]
    scored = [i for i, e in enumerate(exps) if e.n - cuts[i] > lengths[i]]
    if not scored:
        raise TorchfricError(
            'model.dynamic = "auto" holds out the last '
            f"{holdout:.0%} of each identification record and needs at least one "
            f"{max(lengths) + 1}-sample window there; give longer records, or set "
            'model.dynamic = "none" or "lugre"'
        )
    heads = held_out_heads(exps, holdout) if heads is None else list(heads)
    picks = [(exps[i], cuts[i], lengths[i]) for i in scored]
    scores, thetas, mse = _identify_and_predict(
        {"none": static, dynamic.dynamic: dynamic}, heads, picks, tuning, spec, device
    )
    (a_key, a), (b_key, b) = mse.items()
    if not bool(torch.isfinite(a).all()):
        raise TorchfricError(
            'model.dynamic = "auto": the static model\'s filters diverged on the first '
            f"{1 - holdout:.0%} of the identification records; start from model.init = "
            "'prefit', lower estimator.p0_theta, or check model.c_m and the data's units"
        )
    d = a - b if bool(torch.isfinite(b).all()) else torch.full_like(a, -math.inf)
    n = d.numel()
    se = float(d.std() / math.sqrt(n)) if n > 1 and bool(torch.isfinite(d).all()) else math.nan
    t = float(d.mean()) / se if se > 0 else (math.inf if float(d.mean()) > 0 else -math.inf)
    gain = 1.0 - float(b.mean() / a.mean())
    fric, arm = dynamic.split(thetas[b_key])
    travel, rate = bristle_travel(dynamic.friction, fric, arm), stick_rate(arm)
    dt = min(e.dt for e in exps)
    step, span = position_step(exps), max(float(e.q.max() - e.q.min()) for e in exps)
    seen = bristles_seen(travel, step, span) and bristles_timed(rate, dt)
    chosen = b_key if t > T_MIN and seen else a_key
    rmse = {k: float(v.mean().sqrt()) for k, v in mse.items()}
    return DynamicsResult(scores, rmse, gain, t, chosen, n, window_seconds, holdout,
                          time.perf_counter() - t0, travel, step, span, rate, dt, thetas)  # fmt: skip


def _identify_and_predict(
    starts: Mapping[str, ArmModel],
    heads: list[Experiment],
    picks: list[tuple[Experiment, int, int]],
    tuning: EKFTuning,
    spec: EnsembleSpec | None,
    device: torch.device | None,
) -> tuple[dict[str, SizeScore], dict[str, Tensor], dict[str, Tensor]]:
    """Each class's `SizeScore` and θ identified on `heads`, and its windows' mean squared
    errors on the records `picks` = [(record, first held-out sample, window)] (inf for a class
    whose filters all diverged)."""
    scores, thetas, mse = {}, {}, {}
    for key, start in starts.items():
        mse[key] = torch.full((1,), math.inf, dtype=torch.float64)  # until it predicts
        try:
            r = compare_sizes({1: start}, heads, tuning, spec, device=device)
        except TorchfricError:  # every filter of this class diverged
            k = start.num_parameters
            scores[key] = SizeScore(1, k, -math.inf, math.inf, -1, math.nan, math.nan, 0, 0, 0)
            thetas[key] = start.get_theta()
            continue
        score, theta = r.scores[0], r.thetas[1]
        scores[key], thetas[key] = score, theta
        resolved = prepared(heads, tuning, start.num_parameters, "compare_dynamics", start)[1]
        kw = {"q_scale": score.q_scale, "r_scale": score.r_scale}
        try:
            errs = [window_errors(start, theta, e, resolved, c, w, **kw) for e, c, w in picks]
        except FilterFailure:  # its fixed-θ filter failed on a whole record: no prediction
            continue
        mse[key] = torch.nan_to_num(torch.cat(errs), nan=math.inf)
    return scores, thetas, mse
