"""Parameter covariance of an output-error estimate: the simulation-error sandwich.

An output-error θ̂ minimises the open-loop simulation error. Its covariance is taken here from
the loss Hessian at the optimum, in White's robust (sandwich) form, for the criterion

    ℓ(θ) = −½ Σ_t r_tᵀ W r_t,      r_t = y_t − ŷ_t(θ),      W = diag(w_c / σ̂_c²)

over samples t = 1 … N−1 of every experiment (sample 0 is the measured start), where ``y_t =
[q, q̇]`` are the measured channels as output-error training uses them (`shooting.prepare`),
``ŷ_t(θ)`` the full-length open-loop simulation from the measured initial state (a dynamic
model's bristle state starts at its steady deflection and is not an output), ``σ̂_c²`` the
residual variance of channel c at θ̂ and ``w_c`` the channel `weights`. With ``w = (1, 1)``
this is the Gaussian log-likelihood with its noise scale concentrated out (the profile
likelihood ``−(n/2) Σ_c w_c ln σ̂_c²`` has exactly this gradient). The scales ``s_q``, ``s_v``
of the training loss cancel here: W is set by the residuals, not by the data's spread, and θ̂ is
this criterion's optimum only where the run's loss (windows, the scales) has the same one; the
returned `newton` step says how far it is. At θ̂:

* sensitivities ``D_t = ∂ŷ_t/∂θ`` `(2, k)`;
* information (the Gauss–Newton form of the loss Hessian) ``I = Σ_t D_tᵀ W D_t``;
* scores ``s_t = D_tᵀ W r_t`` summed over blocks of consecutive samples, and their long-run
  covariance ``J`` (Bartlett kernel over blocks, bandwidth below);
* ``Cov[θ̂] = I⁻¹ J I⁻¹`` with `sandwich.sandwich` (its `_inverse`: no inverse on near-null directions;
  `identifiability` names them), the gradient ``g = Σ_t s_t = ∇ℓ`` and the Gauss–Newton step
  ``I⁻¹ g`` to the criterion's optimum.

Why the sandwich: ``I⁻¹`` alone is the covariance only when the residuals are white with the
variances σ̂². Open-loop residuals are not: a position error is an integrated velocity error and
model error persists over seconds, so the scores are autocorrelated over long stretches and
``I⁻¹`` is too narrow. ``J`` is measured from the data's own scores.

**Sensitivities** are central differences of simulations, ``D ≈ (ŷ(θ + h e_i) − ŷ(θ − h e_i)) /
2h_i``, all 2k + 1 parameter vectors of one experiment simulated as ONE batch (``simulate`` takes
θ `(K, k)` with ``u (N, K)``, ``x0 (K, 2)``; the compiled engine runs the batch in about the time
of one simulation: 17 simulations of 30 k samples in 0.07 s). Autograd was the alternative: the
compiled engine differentiates only by its reverse adjoint, which would take 2(N−1) reverse passes
for the full ``D`` (one per output), or forward mode through the uncompiled loop, which takes
about 10 s for a single simulation of 30 k samples; the differences are two batched simulations.
As in covariance.py the steps come in two stages: a first batch with a small relative step
(``1e-6 · max(|θ_i|, 1)``) gives ``I``, whose diagonal sets the real steps to half a standard
deviation with the other parameters held, ``h_i = ½ / sqrt(I_ii)`` (bounded below by the first
step and above by ``0.1 · max(|θ_i|, 1)``, so that a parameter the data barely see is not moved
out of the solver's stable range); at half a σ the differences are far above rounding and the
secant is the slope over the range θ̂ actually varies. `tests/test_oe_covariance.py` checks
``I`` against the Gauss–Newton matrix of autograd Jacobians.

**Bandwidth.** The scores are summed over short blocks (by default the record cut into about
`BLOCKS` = 256: 117 samples for 30 k) and their long-run covariance is a Bartlett sum over block
lags whose bandwidth adapts to the data: Andrews' (1991) AR(1) plug-in ``S = 1.1447 (α̂ B)^{1/3}``,
``α̂`` the mean over θ's components of ``4ρ_j² / ((1 − ρ_j)² (1 + ρ_j)²)``, ``ρ_j`` the lag-one
autocorrelation of component j of the centred block scores (|ρ| ≤ 0.95); lags ``⌊S⌋``, at least 1
(neighbouring blocks share the memory at their boundary), at most ``B / 4`` (further lags of
centred block scores mostly add noise and the downward bias of centring), never across two
experiments (independent records); `torchfric.estimators.sandwich.long_run_covariance`, shared
with the EKF's prediction-error form. A fixed Newey–West rule (3 lags of 30 blocks of 1000, this
module's first version) does not do: open-loop residuals carry model error and the
disturbance's response over seconds (on the rig: q's residual still correlates 0.96 after 1000 samples, q̇'s 0.3 after
100), so the lags must follow the data. Why short blocks: with white residuals, long blocks leave
J to a few dozen terms whose noise makes ``I⁻¹ J I⁻¹`` scatter (coverage of ±2σ was 85–90 % over
100 white-box fits with 33 blocks, 96–98 % with 280); with correlated residuals the plug-in
lengthens the lags instead (on the rig 24–47 lags of 117 samples, 3–5 s).

Limits, measured by re-identifying the rig's tanh(3) model for 43–44 seeds (excitation and
disturbance drawn per seed; each θ̂ the criterion's optimum by Gauss–Newton with `newton`): the position residual of an open-loop
simulation is the twice-integrated disturbance, close to a random walk over a 30 s record, and
no long-run covariance from one record sees all of it; with ``weights = (1, 1)`` the inertia's σ
came out about 1.4× too small (±2σ covered the seeds' spread 75 % of the time), with
``weights = (0, 1)`` (q̇ alone, a stationary residual) 0.95× (95–98 %), and the q̇-only
estimate scattered 3× less. Directions near the pseudo-inverse's cut (the tanh units' W2 here,
named by `identifiability`) and structural bias (the static curve against LuGre friction: the
estimates sit 0.5 % above the rig's inertia) are not in any σ.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from ..data import Experiment
from ..errors import TorchfricError
from ..models.arm import ArmModel
from ..models.simulate import simulate
from .sandwich import (
    BLOCKS,
    PEMCovariance,
    at_bound,
    identifiability,
    long_run_covariance,
    sandwich,
)
from .shooting import METHOD, ExperimentTensors, prepare, scales, solver_substeps

__all__ = ["simulation_covariance", "BLOCKS"]

"""Blocks of the score sums a record is cut into by default (about; ``block=None``)."""
_FIRST_STEP = 1e-6  # relative size of the first-stage difference step
_MAX_STEP = 0.1  # relative bound of the second-stage step
_EXACT = 1e-10  # residual RMS per the channel's spread below which a fit counts as exact


def simulation_covariance(
    model: ArmModel,
    experiments: Experiment | Sequence[Experiment],
    theta: Tensor,
    *,
    weights: tuple[float, float] = (1.0, 1.0),
    substeps: int | str | None = None,
    engine: str = "compiled",
    block: int | None = None,
) -> PEMCovariance:
    """The sandwich covariance of the output-error estimate θ̂ = `theta` (module docstring).

    Args:
        model: the arm (static or dynamic); only its structure is used, θ comes from `theta`.
        experiments: the identification records, with q̇ (measured or reconstructed).
        theta: θ̂ `(k,)` in estimation coordinates.
        weights: ``(w_q, w_v)`` on top of the residual variances (``(1, 0)``: q alone).
        substeps: solver steps per sample as the run's `OETuning.substeps` (an int or "auto");
            None takes "auto" at θ̂ (simulate's stability rule). Pass the run's value so that
            the criterion is the run's discrete simulation.
        engine: `simulate`'s engine ("compiled", as output-error training's full-length
            simulations, or "odeint").
        block: samples per block of the score sums; None: ``⌊n / BLOCKS⌋`` (n the samples).

    Returns:
        `PEMCovariance` with ``method = "sandwich_simulation"`` (``newton``: the Gauss–Newton
        step to the criterion's optimum; ``loglik``: ``−(n/2) Σ_c w_c (ln 2π σ̂_c² + 1)``).

    Raises:
        TorchfricError: bad arguments; a simulation that is not finite at θ̂ or at a
            perturbed θ; residuals at rounding level in a weighted channel (simulated data).
    """
    data = _records(experiments)
    theta = _theta(model, theta)
    w = _weights(weights)
    if block is not None and (isinstance(block, bool) or not isinstance(block, int) or block < 1):
        raise TorchfricError(f"block must be a positive integer (samples) or None, got {block!r}")
    names = list(model.theta_names)
    steps = [_steps(model, theta, d.dt, substeps) for d in data]

    def run(h: Tensor) -> tuple[list[Tensor], list[Tensor]]:
        return _differences(model, data, theta, h, steps, engine)

    # Stage 1: small steps; the residuals at θ̂ fix W, the diagonal of I sizes the real steps.
    floor = _FIRST_STEP * torch.maximum(theta.abs(), torch.ones_like(theta))
    resid, sens = run(floor)
    var, n = _residual_variance(resid)
    # A residual at rounding level (simulated data fitted by its own model) gives no noise level.
    exact = (var.sqrt() <= _EXACT * scales(data)) & (w > 0)
    if bool(exact.any()):
        raise TorchfricError(
            f"the simulation at θ reproduces the measured {_CHANNELS[int(exact.nonzero()[0])]} "
            "exactly (residual at rounding level); no noise level can be estimated from it, so "
            "no σ can be given (use measured, not simulated, data, or weight that channel 0)"
        )
    W = torch.where(w > 0, w / var.clamp_min(1e-300), torch.zeros_like(w))
    h = _half_sigma(_information(sens, W), theta, floor)
    # Stage 2: half a standard deviation.
    resid, sens = run(h)
    information = _information(sens, W)
    scores, segment = _block_scores(resid, sens, W, block)
    gradient = scores.sum(0)
    J, lags = long_run_covariance(scores, segment)
    held = at_bound(model, theta)  # a neuron's slope pinned at its floor: held there
    inv, cov = sandwich(information, J, held)
    # ℓ concentrated in σ̂² (channels of weight 0 do not count): −(n/2) Σ_c w_c (ln 2πσ̂_c² + 1)
    per_channel = torch.log(2.0 * math.pi * var.clamp_min(1e-300)) + 1.0
    loglik = -0.5 * n * float(torch.where(w > 0, w * per_channel, 0.0).sum())
    return PEMCovariance(theta.clone(), cov, information, J, gradient, inv @ gradient, loglik, n,
                         scores.shape[0], lags, names, identifiability(information, cov, names, held),
                         steps=h, method="sandwich_simulation")  # fmt: skip


def _half_sigma(info: Tensor, theta: Tensor, floor: Tensor) -> Tensor:
    """Steps of half a conditional σ from the first stage's information, between `floor` and
    `_MAX_STEP` of each entry's size (a barely seen parameter must not push the solver into
    instability)."""
    cap = _MAX_STEP * torch.maximum(theta.abs(), torch.ones_like(theta))
    d0 = torch.diagonal(info)
    h = torch.where(d0 > 0, 0.5 / d0.clamp_min(1e-300).sqrt(), cap)
    return torch.minimum(torch.maximum(h, floor), cap)


_CHANNELS = ("q", "q̇")


def _records(experiments: Experiment | Sequence[Experiment]) -> list[ExperimentTensors]:
    """The experiments as output-error training's tensors (q̇ required), at least one, each with
    at least 3 samples."""
    exps = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    if not exps:
        raise TorchfricError("simulation_covariance needs at least one experiment")
    data = prepare(exps, "experiments")
    for e, d in zip(exps, data, strict=True):
        if d.y.shape[0] < 3:
            raise TorchfricError(
                f"experiment {e.name!r} has {d.y.shape[0]} samples; a simulation-error "
                "covariance needs at least 3"
            )
    return data


def _theta(model: ArmModel, theta: Tensor) -> Tensor:
    """θ̂ as a detached float64 `(k,)`, checked against the model."""
    if not isinstance(theta, Tensor):
        raise TorchfricError(f"theta must be a torch.Tensor, got {type(theta).__name__}")
    th = theta.detach().to(torch.float64).reshape(-1).clone()
    if th.numel() != model.num_parameters:
        raise TorchfricError(
            f"theta has {th.numel()} entries but this model has {model.num_parameters} "
            f"({', '.join(model.theta_names)})"
        )
    if not bool(torch.isfinite(th).all()):
        raise TorchfricError(f"theta must be finite, got {th.tolist()}")
    return th


def _weights(weights: tuple[float, float]) -> Tensor:
    """`(2,)` channel weights: finite, >= 0, not both 0."""
    try:
        w = torch.as_tensor([float(v) for v in weights], dtype=torch.float64)
    except (TypeError, ValueError):
        raise TorchfricError(f"weights must be two numbers (w_q, w_v), got {weights!r}") from None
    if w.numel() != 2 or not bool(torch.isfinite(w).all() and (w >= 0).all() and (w > 0).any()):
        raise TorchfricError(
            f"weights must be two finite numbers >= 0, not both 0 (w_q, w_v), got {weights!r}"
        )
    return w


def _steps(model: ArmModel, theta: Tensor, dt: float, substeps: int | str | None) -> int:
    """Solver sub-steps per sample: the run's value, or "auto" at θ̂ for None."""
    if substeps is not None and substeps != "auto":
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise TorchfricError(
                f"substeps must be a positive integer, 'auto' or None, got {substeps!r}"
            )
    return solver_substeps(model, theta, dt, "auto" if substeps is None else substeps)


def _differences(
    model: ArmModel,
    data: Sequence[ExperimentTensors],
    theta: Tensor,
    h: Tensor,
    steps: Sequence[int],
    engine: str,
) -> tuple[list[Tensor], list[Tensor]]:
    """Per experiment the residuals ``r = y − ŷ(θ)`` `(N−1, 2)` and the central differences
    ``D ≈ ∂ŷ/∂θ`` `(N−1, 2, k)` with steps `h` `(k,)`: θ, θ + h_i e_i, θ − h_i e_i simulated as
    one batch of 2k + 1. Raises on a non-finite simulation, naming the parameters."""
    k = theta.numel()
    step = torch.diag(h)
    rows = torch.cat([theta[None], theta + step, theta - step])  # (K, k), K = 2k + 1
    K = rows.shape[0]
    resid, sens = [], []
    for d, s in zip(data, steps, strict=True):
        with torch.no_grad():
            sim = simulate(
                model, d.t, d.u[:, None].expand(-1, K), d.y[0].expand(K, -1),
                method=METHOD, substeps=s, theta=rows, engine=engine,
            )  # fmt: skip
        ok = torch.isfinite(sim).all(0).all(-1)  # (K,)
        if not bool(ok[0]):
            raise TorchfricError(
                "the open-loop simulation at θ is not finite; θ is unusable for a σ (more "
                "substeps, or check the parameters)"
            )
        if not bool(ok.all()):
            bad = sorted({model.theta_names[(int(j) - 1) % k] for j in (~ok).nonzero()})
            raise TorchfricError(
                f"the open-loop simulation is not finite when {', '.join(bad)} moves by "
                f"{', '.join(f'{float(h[model.theta_names.index(b)]):.3g}' for b in bad)} from "
                "θ (half a standard deviation, or the first small step); the criterion is not "
                "smooth there, so no σ can be given (more substeps may help)"
            )
        resid.append(d.y[1:] - sim[1:, 0])
        sens.append((sim[1:, 1 : k + 1] - sim[1:, k + 1 :]).permute(0, 2, 1) / (2.0 * h))
    return resid, sens


def _residual_variance(resid: Sequence[Tensor]) -> tuple[Tensor, int]:
    """`(2,)` mean square residual of each channel over every sample, and the sample count."""
    n = sum(r.shape[0] for r in resid)
    return sum((r * r).sum(0) for r in resid) / n, n  # type: ignore[return-value]


def _information(sens: Sequence[Tensor], W: Tensor) -> Tensor:
    """``I = Σ_t D_tᵀ W D_t`` `(k, k)`."""
    info = sum(torch.einsum("tci,c,tcj->ij", D, W, D) for D in sens)
    return 0.5 * (info + info.T)  # type: ignore[operator]


def _block_scores(
    resid: Sequence[Tensor], sens: Sequence[Tensor], W: Tensor, block: int | None
) -> tuple[Tensor, Tensor]:
    """Scores ``s_t = D_tᵀ W r_t`` summed over blocks of consecutive samples: `(B, k)`, and
    each block's experiment `(B,)`. A block is `block` samples (None: about `BLOCKS` blocks in
    all); an experiment's last block may be shorter."""
    n = sum(r.shape[0] for r in resid)
    size = max(1, n // BLOCKS) if block is None else block
    out, seg = [], []
    for i, (r, D) in enumerate(zip(resid, sens, strict=True)):
        s = torch.einsum("tci,c,tc->ti", D, W, r)  # (N−1, k)
        for part in torch.split(s, size):
            out.append(part.sum(0))
            seg.append(i)
    return torch.stack(out), torch.tensor(seg)
