"""The prediction-error stage of an EKF run: what its ± σ mean.

The augmented EKF ends every pass with a ``P_θθ``, but that is the filter's belief after it has
absorbed the same data once per pass under an assumed noise model (Q, R); on an independent
axis its σ were 10–1000× narrower than the real error. What a run reports instead
(`torchfric.app.run.confidence`) is built here, with θ held fixed (``P_θθ = 0``) and q as the one
measured channel:

1. `noise_model`: the likeliest Q and R factors of the fixed-θ filter (a grid, one batch), up
   to one sample's process noise on q of R/100 (`NOISE_STEP_LIMIT`).
2. `innovations`: per sample the innovation ``e_t(θ)`` and its variance ``S_t(θ)`` (a batch of
   fixed-θ filters; ``S_t`` from their NIS and log-likelihood outputs).
3. `pem_covariance`: the criterion ``V(θ) = Σ_t e_t²/S_t``; sensitivities ``∂e_t/∂θ`` by central
   differences of 2k + 1 filters; per-sample scores, the Gauss–Newton information
   ``I = Σ ∂eᵀ∂e / S`` (positive semi-definite by construction), the long-run covariance J of
   the scores summed over blocks (`torchfric.estimators.sandwich`) and the *sandwich*
   ``Cov[θ̂] = I⁻¹ J I⁻¹``. Why not ``I⁻¹`` alone: the noise model is still a model (the
   innovations are not white), and ``I⁻¹`` is then wrong in scale and shape; J is measured from
   the data's own scores.
4. `pem_refine`: Gauss–Newton steps on V from the kept θ to the prediction-error estimate,
   whose spread that covariance describes.

A static model's criterion leaves out the stuck samples (`moving`: `prefit.moving_samples`).
`tests/test_covariance.py` checks it against a 2-state EKF written from scratch, by autograd.

Why this size: the innovations, their sensitivities and the sums over them stream a long
record block by block together; the statistics they feed are apart (`sandwich`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor
from torch.func import vmap

from ..accel import Step, iter_chunks, structure_key
from ..data import Experiment
from ..errors import TorchfricError
from ..models.arm import ArmModel
from .ekf import (
    FIXED_CHUNK,
    MEASUREMENTS,
    EKFState,
    fixed_theta_chunks,
    make_fixed_theta_step,
    update,
)
from .ensemble import _first_sample, _keep_good
from .observers import Callback
from .passes import Filtering, measured_data, state_belief
from .sandwich import (
    BLOCKS,
    CONDITION_LIMIT,
    CORRELATION_LIMIT,
    Identifiability,
    PEMCovariance,
    held_entries,
    identifiability,
    long_run_covariance,
    sandwich,
    score_sums,
)
from .settings import EKFTuning

__all__ = [
    "FixedThetaLikelihood", "fixed_theta_loglik", "PEMCovariance", "Identifiability",
    "innovations", "pem_covariance", "pem_refine", "noise_model", "step_ratio", "identifiability",
    "CORRELATION_LIMIT", "BLOCKS", "long_run_covariance", "CONDITION_LIMIT",
]  # fmt: skip


@dataclass
class FixedThetaLikelihood:
    """The fixed-θ filter's log-likelihood for K parameter vectors.

    ``total`` `(K,)`: ℓ(θ_i) over every sample; ``blocks`` `(K, B)`: the same split into blocks of
    consecutive samples (``block`` samples each; an experiment's last block may be shorter);
    ``sum_nis`` `(K,)`; ``samples``: samples filtered; ``ok`` `(K,)`: the filter stayed healthy."""

    total: Tensor
    blocks: Tensor
    sum_nis: Tensor
    samples: int
    block: int
    ok: Tensor


def fixed_theta_loglik(
    model: ArmModel,
    experiments: Sequence[Experiment],
    tuning: EKFTuning,
    thetas: Tensor,
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
) -> FixedThetaLikelihood:
    """ℓ(θ_i) of the filter on ``[q, q̇(, z)]`` with θ held at each row of `thetas` `(K, k)`
    (estimation coordinates), under `tuning`'s Q and R scaled by `q_scale`, `r_scale`, in
    blocks of `FIXED_CHUNK` samples."""
    K = torch.as_tensor(thetas).shape[0]
    scales = torch.ones(K, dtype=torch.float64)
    return _batched_loglik(model, experiments, tuning, thetas, scales * q_scale, scales * r_scale)


def _batched_loglik(
    model: ArmModel,
    experiments: Sequence[Experiment],
    tuning: EKFTuning,
    thetas: Tensor,
    q_scales: Tensor,
    r_scales: Tensor,
) -> FixedThetaLikelihood:
    """`fixed_theta_loglik` with a Q and an R factor per row (`(K,)` each)."""
    thetas = torch.as_tensor(thetas, dtype=torch.float64)
    K, k = thetas.shape
    Q, P0_xx, H, R = tuning.fixed_theta_matrices(k, model.state_size)
    Qk, Rk = Q * q_scales[:, None, None], R * r_scales[:, None, None]
    step_fn = _fixed_theta_steps(model, tuning)[1]
    data = measured_data(list(experiments), tuning.measure)
    total_n = sum(e.n for e in experiments)
    f = Filtering(data, Qk, P0_xx, H, Rk, step_fn, 1e300, Callback(), 10**9, total_n)
    f64 = torch.float64
    good = torch.ones(K, dtype=torch.bool)
    fail_at = torch.full((K,), -1, dtype=torch.long)
    sum_nis_all = torch.zeros(K, dtype=f64)
    block, blocks = FIXED_CHUNK, list[Tensor]()
    bound = torch.tensor(1e300, dtype=f64)
    for exp, u, y in data:
        x, P = state_belief(exp, K, P0_xx)
        sums = (torch.zeros(K, H.shape[0], dtype=f64), *torch.zeros(2, K, dtype=f64))
        carry = _first_sample((x, P, good, fail_at, *sums), y[0], f)
        consts = (torch.tensor(exp.dt, dtype=f64), thetas, Qk, H, Rk, bound)
        index = torch.arange(exp.n)
        last = torch.zeros(K, dtype=f64)
        if step_fn.chunk is not None:
            for _, _, xs, valid in iter_chunks((index[1:], u[:-1], y[1:]), block):
                carry, _ = step_fn.chunk(carry, xs, valid, consts)
                blocks.append(carry[6] - last)
                last = carry[6].clone()
        else:
            for j in range(1, exp.n):
                carry = step_fn(*carry, index[j], u[j - 1], y[j], *consts)
                if j % block == 0 or j == exp.n - 1:
                    blocks.append(carry[6] - last)
                    last = carry[6].clone()
        good, fail_at = carry[2], carry[3]
        sum_nis_all = sum_nis_all + carry[5]
    B = torch.stack(blocks, dim=1)
    return FixedThetaLikelihood(B.sum(1), B, sum_nis_all, total_n, block, good.clone())


def innovations(
    model: ArmModel,
    experiments: Sequence[Experiment],
    tuning: EKFTuning,
    thetas: Tensor,
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    lenient: bool = False,
    variances: bool = True,
    moving: Sequence[Tensor] | None = None,
) -> list[tuple[Tensor, Tensor]]:
    """Per experiment, the one-step innovations ``e_t`` and their variances ``S_t`` of the
    fixed-θ filter (θ held: `make_fixed_theta_step`) with one measured channel (`tuning.measure`
    "position" or "velocity"): `(n,)` each for θ `(k,)`; for K filters at once, θ the rows of
    `thetas` `(K, k)`, `(n, K)`. From the per-sample outputs of the batched step
    (compiled, four filters per SIMD vector of the generated C, split
    across the cores; ``S_t = exp(−2 ℓ_t − NIS_t − ln 2π)``, exact for one channel); each
    filter's numbers are those of its own single filter (the same arithmetic).

    Without `variances`, S is not kept (an empty tensor in its place). `moving` (per
    experiment, bool `(n,)`): the samples in the criterion; e is 0 at the others.

    Raises:
        TorchfricError: a filter failed at its θ (with `lenient`, its e is NaN instead), or two
            channels measured.
    """
    if len(MEASUREMENTS[tuning.measure]) != 1:
        raise TorchfricError(
            f"the prediction-error covariance measures one channel; got measure = "
            f"{tuning.measure!r}: use its position-only form"
        )
    thetas = torch.as_tensor(thetas, dtype=torch.float64)
    one = thetas.ndim == 1
    thetas = thetas[None] if one else thetas
    K, k = thetas.shape
    Q, P0_xx, H, R = tuning.fixed_theta_matrices(k, model.state_size)
    Qk = (Q * q_scale).expand(K, *Q.shape).contiguous()
    Rk = (R * r_scale).expand(K, *R.shape).contiguous()
    step = _fixed_theta_steps(model, tuning)[0]
    bound = torch.tensor(1e300, dtype=torch.float64)
    out = []
    for r, (exp, u, y) in enumerate(measured_data(list(experiments), tuning.measure)):
        x, P = state_belief(exp, K, P0_xx)
        # e, and S = exp(−2ℓ − NIS − ln 2π) chunk by chunk, straight into arrays of the record's
        # length (16 bytes a sample and filter, 8 without `variances`)
        e_t = torch.empty(exp.n, K, dtype=torch.float64)
        S_t = torch.empty(exp.n, K, dtype=torch.float64) if variances else None
        x, P, e0, ll0, nis0 = vmap(_first_update, in_dims=(0, 0, None, None, 0))(x, P, y[0], H, Rk)
        bad = _keep(e_t, S_t, 0, 1, e0[None], ll0[None], nis0[None], None)
        consts = (torch.tensor(exp.dt, dtype=torch.float64), thetas, Qk, H, Rk, bound)
        if step.chunk is not None:
            for i, n, xs, valid in iter_chunks((u[:-1], y[1:]), step.size):
                (x, P), (e, nis, ll, ok) = step.chunk((x, P), xs, valid, consts)
                bad |= _keep(e_t, S_t, 1 + i, n, e[:n, :, 0], ll[:n], nis[:n], ok[:n])
        else:
            for j in range(1, exp.n):
                x, P, e, nis, ll, ok = step(x, P, u[j - 1], y[j], *consts)
                bad |= _keep(e_t, S_t, j, 1, e[None, :, 0], ll[None], nis[None], ok[None])
        if bool(bad.any()) and not lenient:
            raise TorchfricError(
                f"the fixed-θ filter failed on {exp.name!r} at this θ, so the likelihood has no "
                "derivatives there"
            )
        if moving is not None:
            e_t[~moving[r]] = 0.0
        e_t[:, bad] = math.nan
        S = S_t if S_t is not None else e_t[:0]
        out.append((e_t[:, 0], S[:, 0]) if one else (e_t, S))
    return out


def _keep(e_t: Tensor, S_t: Tensor | None, at: int, n: int, e: Tensor, ll: Tensor,
          nis: Tensor, ok: Tensor | None) -> Tensor:  # fmt: skip
    """Samples ``at …`` (`n`) of the filters' e into `e_t`, S into `S_t`; `(K,)` which failed."""
    e_t[at : at + n] = e
    if S_t is not None:
        S_t[at : at + n] = ll.mul(-2.0).sub_(nis).sub_(math.log(2.0 * math.pi)).exp_()
    failed = ~torch.isfinite(ll).all(0)
    return failed if ok is None else failed | ~ok.all(0)


def _first_update(x: Tensor, P: Tensor, y0: Tensor, H: Tensor, R: Tensor) -> tuple[Tensor, ...]:
    """Sample 0 of a fixed-θ filter: the measurement update alone (x, P, e, ℓ, NIS)."""
    state, inn = update(EKFState(x, P), y0, H, R)
    return state.x, state.P, inn.e.reshape(()), inn.loglik, inn.nis


def _fixed_theta_steps(model: ArmModel, tuning: EKFTuning) -> tuple[Step, Step]:
    """`make_fixed_theta_step` with per-sample outputs (e, NIS, ℓ, ok), and with the ensemble's
    masked bookkeeping (sums only, `_keep_good`), made once per model (`_STEPS`)."""
    key = (structure_key(model), tuning.substeps, tuning.compile)
    if key not in _STEPS:
        batched = make_fixed_theta_step(model, tuning.substeps)

        def masked(x, P, good, fail_at, sum_e2, sum_nis, loglik, j, u, y, *consts):  # type: ignore[no-untyped-def]
            carry = (x, P, good, fail_at, sum_e2, sum_nis, loglik)
            return _keep_good(carry, j, *batched(x, P, u, y, *consts))

        steps = tuple(
            fixed_theta_chunks(fn, batched, carry=carry, name=name, compile=tuning.compile)
            for fn, carry, name in ((batched, 2, "fixed-θ batch"), (masked, 7, "fixed-θ masked"))
        )
        _STEPS.clear()
        _STEPS[key] = steps
    return _STEPS[key]


_STEPS: dict[Any, tuple[Step, Step]] = {}  # the last model's fixed-θ steps (built once per run)
Innovations = list[tuple[Tensor, Tensor]]  # per experiment e_t and S_t of one θ (`innovations`)


def pem_covariance(
    model: ArmModel,
    experiments: Sequence[Experiment],
    tuning: EKFTuning,
    theta: Tensor,
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    block: int | None = None,
    moving: Sequence[Tensor] | None = None,
    base: Innovations | None = None,
    stick_speed: float | None = None,
) -> PEMCovariance:
    """The sandwich covariance of θ̂ = `theta` `(k,)` (module docstring).

    The criterion is the prediction error ``V(θ) = Σ_t e_t²/S_t`` (the innovations normalised
    by the filter's own variances; ``loglik`` reports ``−½ V``). Sensitivities ``∂e_t/∂θ_j`` by
    central differences of the innovations of 2k + 1 fixed-θ filters, with steps
    ``h_j = 1e-4 · max(|θ_j|, 1)`` in estimation coordinates (truncation ~1e-8 relative). Per
    sample the score ``−e_t ∂e_t / S_t`` and the Gauss–Newton information ``I = Σ_t ∂e_tᵀ∂e_t
    / S_t``, positive semi-definite (other forms, dropped: docs/estimators.md). The sandwich
    does not depend on the scale of S: I and J scale alike.

    Args:
        model, experiments, tuning: the run's model, identification records and EKF tuning
            with one measured channel (with the kept member's `q_scale`, `r_scale`).
        theta: θ̂ in estimation coordinates.
        block: samples per block of the score's long-run covariance (None: about `BLOCKS`
            blocks over all records).
        moving: per experiment, the samples in V (`innovations`); None: all.
        base: `innovations` at θ̂ when the caller has them (a trial step `pem_refine` took):
            not filtered again.
        stick_speed: `prefit.stick_band`'s speed: a neuron that is a step above it is held.

    Raises:
        TorchfricError: the fixed-θ filter fails at θ̂ or next to it.
    """
    theta = torch.as_tensor(theta, dtype=torch.float64).reshape(-1)
    k = theta.numel()
    names = model.theta_names
    h = 1e-4 * torch.maximum(theta.abs(), torch.ones_like(theta))
    run = functools.partial(innovations, model, experiments, tuning, q_scale=q_scale,
                            r_scale=r_scale, moving=moving)  # fmt: skip
    base = run(theta) if base is None else base
    info, block_scores, segment, loglik, samples = score_sums(
        base, _sensitivities(run, theta, h), block
    )
    scores = torch.stack(block_scores)
    if scores.shape[0] <= 2 * k:
        raise TorchfricError(
            f"{scores.shape[0]} blocks of samples for {k} parameters: too few to measure the "
            "score's covariance, so no σ can be given; use a longer record (or smaller blocks)"
        )
    gradient = scores.sum(0)
    J, bandwidth = long_run_covariance(scores, torch.tensor(segment))
    floor, steep = held_entries(model, theta, stick_speed)  # at the floor or a step: held
    inv, cov = sandwich(info, J, floor | steep)
    return PEMCovariance(
        theta=theta.clone(),
        cov=cov,
        information=info,
        score_cov=J,
        gradient=gradient,
        newton=inv @ gradient,
        loglik=loglik,
        samples=samples,
        blocks=scores.shape[0],
        bandwidth=bandwidth,
        names=list(names),
        identifiability=identifiability(info, cov, names, floor, steep),
        steps=h,
    )


def _sensitivities(run: Any, theta: Tensor, h: Tensor) -> list[Tensor]:
    """Per experiment ``∂e_t/∂θ`` `(n, k)` by central differences: column j from the filters
    at ``θ ± h_j e_j`` (`innovations`), `_GROUP` columns' filters a batch, taken at once (a
    20-minute record, k = 8: 8 filters' innovations held, 0.15 GB, rather than 2k)."""
    k = h.numel()
    De: list[Tensor] = []
    for j0 in range(0, k, _GROUP):
        cols = range(j0, min(k, j0 + _GROUP))
        steps = torch.diag(h)[list(cols)]
        parts = run(torch.cat([theta + steps, theta - steps]), variances=False)
        if not De:
            De = [torch.empty(e.shape[0], k, dtype=torch.float64) for e, _ in parts]
        g = len(cols)
        for i, (e, _) in enumerate(parts):
            De[i][:, j0 : j0 + g] = (e[:, :g] - e[:, g:]) / (2 * h[j0 : j0 + g])
        del parts
    return De


_GROUP = 4  # parameters whose ± filters run in one batch: 8 filters, two SIMD vectors


def _loglik(model: ArmModel, experiments: Sequence[Experiment], tuning: EKFTuning, thetas: Tensor, q_scale: float, r_scale: float, moving: Sequence[Tensor] | None, above: float = math.inf) -> tuple[Tensor, Innovations | None]:  # fmt: skip
    """ℓ = −½ V at each row of `thetas` `(K, k)`, `2 _GROUP` filters a batch, −inf on failure;
    and the innovations of the first row whose ℓ exceeds `above` (the numbers `innovations`
    gives for that row alone), or None."""
    out, first = [], None
    for part in torch.split(thetas, 2 * _GROUP):
        parts = innovations(model, experiments, tuning, part, q_scale=q_scale, r_scale=r_scale,
                            lenient=True, moving=moving)  # fmt: skip
        ll = sum(-0.5 * (e * e / S).sum(0) for e, S in parts)
        out.append(ll := torch.where(torch.isfinite(ll), ll, -math.inf))
        if first is None and bool((ll > above).any()):
            j = int(torch.nonzero(ll > above)[0])
            first = [(e[:, j].clone(), S[:, j].clone()) for e, S in parts]
    return torch.cat(out), first


NOISE_GRID_R = tuple(10.0**p for p in range(-8, 1))
"""Factors on the tuning's R tried by `noise_model` (the paper's R: 1000s × an encoder's)."""
NOISE_GRID_Q = tuple(10.0**p for p in range(-3, 4))
"""Factors on the tuning's Q tried by `noise_model`."""
NOISE_STEP_LIMIT = 1e-2
"""The largest ``q·dt³/R`` `noise_model` tries (q on q̇, dt the longest sample time): above it
the filter follows the encoder sample by sample and sees the friction through its noise."""


def step_ratio(tuning: EKFTuning, experiments: Sequence[Experiment], q_scale: float, r_scale: float) -> float:  # fmt: skip
    """One sample's process noise on q over R, ``q·dt³/R`` (q on q̇, dt the longest sample time)."""
    dt = max(e.dt for e in experiments)
    return q_scale * tuning.q_state[1] * dt**3 / (r_scale * tuning.r[0])


def noise_model(
    model: ArmModel,
    experiments: Sequence[Experiment],
    tuning: EKFTuning,
    theta: Tensor,
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
) -> list[tuple[float, float]]:
    """The Q and R factors (on the tuning's, times `q_scale`, `r_scale`) under which the
    fixed-θ filter's innovations are most likely: the grid `NOISE_GRID_Q` × `NOISE_GRID_R` up
    to ``q·dt³ = NOISE_STEP_LIMIT · R`` (at ``q·dt³ = R``, the likeliest on an EMPS-like axis
    with a 1 µm encoder, M and b were 10–160 σ off on 7 of 20 seeds, docs/results.md), filtered
    as one batch, ranked by the Gaussian log-likelihood (best first; failed filters left out).

    The criterion and its covariance are taken under it: under the tuning's R the one-step
    prediction is a long simulation, far from quadratic (docs/estimators.md)."""
    ratio = step_ratio(tuning, experiments, q_scale, r_scale)  # of the tuning's own Q and R
    whole = [(q, r) for q in NOISE_GRID_Q for r in NOISE_GRID_R]
    grid = [(q, r) for q, r in whole if q / r * ratio <= NOISE_STEP_LIMIT * (1 + 1e-9)]
    grid, best = grid or [min(whole, key=lambda g: g[0] / g[1])], (1.0, 1.0)
    theta = torch.as_tensor(theta, dtype=torch.float64).reshape(1, -1)
    rows = theta.expand(len(grid), -1)
    out = _batched_loglik(
        model, experiments, tuning, rows,
        torch.tensor([q * q_scale for q, _ in grid], dtype=torch.float64),
        torch.tensor([r * r_scale for _, r in grid], dtype=torch.float64),
    )  # fmt: skip
    ll = torch.where(out.ok & torch.isfinite(out.total), out.total, -torch.inf)
    ranked = [grid[i] for i in torch.argsort(ll, descending=True).tolist() if ll[i] > -math.inf]
    return [(q * q_scale, r * r_scale) for q, r in (ranked or [best])]


def _damped_steps(cov: PEMCovariance) -> list[Tensor]:
    """Levenberg–Marquardt steps ``(I + λ diag I)⁻¹ ∇ℓ`` from `cov`'s point, λ = 0.01 … 100:
    each raises ℓ when short enough, and diag I scales them to the parameters' own units. The
    entries held (`held_entries`) stay."""
    held = {*cov.identifiability.held, *cov.identifiability.steep}
    free = torch.tensor([n not in held for n in cov.names])
    info, steps = cov.information[free][:, free], torch.zeros(5, len(free), dtype=torch.float64)
    scale = torch.diagonal(info).clamp_min(1e-300)
    for i, lam in enumerate((1e-2, 1e-1, 1.0, 10.0, 100.0)):
        steps[i, free] = torch.linalg.solve(info + lam * torch.diag(scale), cov.gradient[free])
    return list(steps)


def pem_refine(
    model: ArmModel,
    experiments: Sequence[Experiment],
    tuning: EKFTuning,
    theta: Tensor,
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    iterations: int = 4,
    min_gain: float = 0.05,
    start: PEMCovariance | None = None,
    moving: Sequence[Tensor] | None = None,
    stick_speed: float | None = None,
) -> tuple[Tensor, PEMCovariance, list[float]]:
    """Newton steps on ℓ from `theta` to the prediction-error estimate, and its covariance.

    The EKF's passes end near, not at, the maximum of the fixed-θ likelihood (measured: the
    Newton step from a converged run's θ was up to 9 σ for curve parameters and 4–5 σ for b);
    the σ describe the spread of that maximum, so they can only cover the truth from there.
    Each iteration takes the Gauss–Newton step ``I⁻¹ ∇ℓ`` (`sandwich._inverse`: undetermined and
    held directions do not move), whole or halved up to four times, whichever first raises ℓ
    (one batch); when none does, Levenberg–Marquardt steps ``(I + λ diag I)⁻¹ ∇ℓ``, λ = 0.01 …
    100 (`_damped_steps`; without them 6 of 20 seeds of a Coulomb axis kept M 3.3–6 σ off).
    It stops when the expected gain ``½ ∇ℓᵀ I⁻¹ ∇ℓ`` falls below `min_gain` nats, when no trial
    raises ℓ, or after `iterations`. No trial puts any |θ| at half the filter's box
    (``tuning.theta_bound``: the rig's LuGre config walked there, ℓ rising by rounding).

    `start`: the covariance at `theta` when the caller has it already (not computed again);
    `moving`: the samples in V (`innovations`); `stick_speed`: as `pem_covariance`'s.

    Returns ``(θ, covariance at θ, ℓ after each accepted step, the first at the start)``."""
    at = functools.partial(pem_covariance, model, experiments, tuning, q_scale=q_scale,
                           r_scale=r_scale, moving=moving, stick_speed=stick_speed)  # fmt: skip
    cov = start or at(theta)
    theta = cov.theta
    trace = [cov.loglik]
    for _ in range(iterations):
        if 0.5 * float(cov.gradient @ cov.newton) < min_gain:
            break
        trial, base = None, None
        halved = [fraction * cov.newton for fraction in (1.0, 0.5, 0.25, 0.125, 0.0625)]
        for steps in (halved, _damped_steps(cov)):  # each list's trials in one batch, in order
            trials = theta + torch.stack(steps)
            trials = trials[(trials.abs() < 0.5 * tuning.theta_bound).all(1)]
            if not trials.shape[0]:
                continue
            ll, base = _loglik(model, experiments, tuning, trials, q_scale, r_scale, moving,
                               above=cov.loglik)  # fmt: skip
            raised = torch.nonzero(ll > cov.loglik).flatten()
            if raised.numel():
                trial = trials[int(raised[0])]
                break
        if trial is None:
            break
        theta = trial
        cov = at(theta, base=base)  # the trial's own filter, not run again
        trace.append(cov.loglik)
    return theta, cov, trace
