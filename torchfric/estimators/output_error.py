"""Gradient output-error identification: minimise the open-loop simulation error by Adam (and an
optional L-BFGS polish) through the solver (DESIGN.md, "Estimators" 2.).

The same `ArmModel` and the same θ (estimation coordinates: log for positive parameters, so they
stay positive) as the EKF. θ is trained as one leaf tensor passed to `simulate(..., theta=θ)`;
the model itself is not modified.

Loss (mean over windows b and samples k = 1 … W−1 of each window; sample 0 is the measured start)::

    L(θ) = mean_{b,k} [ w_q ((q̂_bk − q_bk) / s_q)² + w_v ((q̂̇_bk − q̇_bk) / s_v)² ]

with the scales ``s_q`` and ``s_v`` the standard deviations of the measured q and (reconstructed)
q̇ over the training data, each experiment about its own mean (pooled). The loss is therefore
unit-free, and over full-length simulations it is ``w_q (1 − FIT_q)² + w_v (1 − FIT_q̇)²`` up to
the data's mean — the criterion the validation FIT measures.

Horizons:

- ``window = 0``: full-length simulation of every experiment from its measured initial state.
- ``window = W ≥ 2`` (multiple shooting): every epoch draws `batch` windows of W samples at random
  start indices over all experiments (seeded `torch.Generator`), each starting from the measured
  state ``[q, q̇]`` at its start, and simulates them as ONE batch (`simulate` with `u (W, B)`,
  `x0 (B, 2)`): per-op overhead dominates, so B windows cost about as much as one. Short windows
  keep the loss surface free of the long-horizon local minima; `schedule` lengthens them in stages
  (short to long, epochs split evenly).
- ``learn_states = true`` (with a fixed ``window = W``): multiple shooting proper. Every experiment
  is tiled into windows of W samples that share their end points (starts 0, W−1, 2(W−1), …); each
  tile starts from a *learned* state ``x0_j = [q, q̇]_measured + s ⊙ δ_j`` (δ trained with θ by the
  same optimiser, starting at 0), the loss also scores sample 0, and a continuity penalty
  ``continuity · mean_j Σ_c ((x̂_j(end) − x0_{j+1}) / s_c)²`` ties each tile's simulated end to
  the next tile's start. The reconstructed q̇ is then only the starting guess of the window
  states, not a hard initial condition; as the penalty grows the tiles join into one trajectory.

Gradients by backpropagation through the fixed-grid solver (default), or by the adjoint method
(`torchdiffeq.odeint_adjoint`, memory independent of the horizon, about twice the time).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torchdiffeq import odeint_adjoint

from ..data import Experiment
from ..errors import DivergenceError, TorchfricError
from ..models.arm import ArmModel
from ..models.simulate import ZOHField, auto_substeps, sample_grid, simulate
from .metrics import score_simulation
from .observers import OECallback
from .settings import OETuning

__all__ = ["OETuning", "EpochRecord", "OEResult", "OECallback", "identify_output_error"]

_METHOD = "rk4"


@dataclass
class EpochRecord:
    """Diagnostics of one epoch (index `epochs + 1` is the L-BFGS polish, with lr = 1)."""

    index: int  # 1-based epoch number
    loss: float  # training loss of this epoch's batch, before the step
    parameters: dict[str, float]  # physical values by name, after the step
    lr: float
    seconds: float
    val_fit: dict[str, dict[str, float]] | None  # {name: {"fit_q", "fit_qdot"}} when evaluated
    theta: list[float] = field(default_factory=list)  # estimation coordinates, after the step
    window: int = 0  # window length of this epoch (0 = full length)

    @property
    def val_score(self) -> float | None:
        """Mean over validation experiments of (FIT_q + FIT_q̇) / 2, or None."""
        if not self.val_fit:
            return None
        vals = [0.5 * (v["fit_q"] + v["fit_qdot"]) for v in self.val_fit.values()]
        return sum(vals) / len(vals)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class OEResult:
    """What `identify_output_error` returns (also `DivergenceError.last_good`)."""

    model: ArmModel  # fitted copy (θ = `theta`)
    theta: Tensor  # (k,) estimation coordinates: best by validation, else the last
    history: list[EpochRecord] = field(default_factory=list)
    best_epoch: int = 0  # epoch whose θ is returned (0 = the initial guess)
    stopped_early: bool = False  # patience ran out or the callback asked to stop
    optimizer_state: dict[str, Any] | None = None  # Adam state after the last epoch (resume)
    shooting: Tensor | None = None  # (tiles, 2) learned start offsets δ (learn_states), in units of s
    initial_theta: Tensor | None = None  # θ at epoch 0, the early stop's baseline (resume)

    def initial_states(self, experiments: Experiment | Sequence[Experiment]) -> Tensor:
        """The learned window start states ``[q, q̇]`` (tiles, 2) of the `learn_states` tiling of
        `experiments` (the training experiments, in training order)."""
        if self.shooting is None:
            raise TorchfricError("this result has no learned states (learn_states was off)")
        data = _prepare([experiments] if isinstance(experiments, Experiment) else experiments, "x")
        window = self.history[-1].window if self.history else 0
        tiles = _tiles(data, window)
        if len(tiles) != self.shooting.shape[0]:
            raise TorchfricError(
                f"these experiments give {len(tiles)} tiles, the result learned "
                f"{self.shooting.shape[0]}; pass the training experiments"
            )
        y0 = torch.stack([data[i].y[st] for i, st in tiles])
        return y0 + _scales(data) * self.shooting

    @property
    def epochs(self) -> int:
        return len(self.history)


@dataclass
class _Data:
    """Training tensors of one experiment: `u (N,)`, measured `y (N, 2)` = [q, q̇]."""

    t: Tensor
    u: Tensor
    y: Tensor
    dt: float


def _prepare(exps: Sequence[Experiment], what: str) -> list[_Data]:
    out = []
    for e in exps:
        if not isinstance(e, Experiment):
            raise TorchfricError(f"{what} must be Experiment objects, got {type(e).__name__}")
        if e.qdot is None:
            raise TorchfricError(
                f"experiment {e.name!r} has no velocity, but output-error training needs q̇ for "
                "the measured initial states and the q̇ loss; reconstruct it first "
                "(Experiment.with_velocity())"
            )
        y = torch.stack([e.q, e.qdot], dim=-1).to(torch.float64)
        out.append(_Data(e.t.to(torch.float64), e.u.to(torch.float64), y, e.dt))
    return out


def _scales(data: Sequence[_Data]) -> Tensor:
    """`(2,)` pooled standard deviations of measured [q, q̇], each experiment about its mean."""
    ss = sum(((d.y - d.y.mean(0)) ** 2).sum(0) for d in data)
    n = sum(d.y.shape[0] for d in data)
    s = (ss / n).sqrt()
    if not bool((s > 0).all()):
        raise TorchfricError(
            f"the training data have a constant q or q̇ (std = {s.tolist()}); output-error "
            "training needs motion in the data"
        )
    return s


def _substeps(model: ArmModel, theta: Tensor, dt: float, substeps: int | str) -> int:
    if substeps != "auto":
        return int(substeps)
    return auto_substeps(model, dt, _METHOD, theta=theta)


def _rollout(
    model: ArmModel,
    t: Tensor,
    u: Tensor,
    x0: Tensor,
    theta: Tensor,
    steps: int,
    adjoint: bool,
    engine: str = "odeint",
) -> Tensor:
    """Simulate `u (N[, B])` from `x0 ([B,] 2)` with parameters θ → `(N, [B,] 2)`; `engine` as in
    `simulate` (with `adjoint`, always torchdiffeq's adjoint)."""
    if not adjoint:
        return simulate(model, t, u, x0, method=_METHOD, substeps=steps, theta=theta, engine=engine)
    # Same exact-ZOH field as `simulate`; the grid is built per call from the requested times, so
    # the adjoint's backward integration over [t_i, t_{i−1}] gets its own sub-step grid.
    fieldfn = ZOHField(model, t, u, theta)
    options = {"grid_constructor": lambda _f, _y0, tt: sample_grid(tt, steps), "perturb": True}
    return odeint_adjoint(fieldfn, x0, t, method=_METHOD, options=options, adjoint_params=(theta,))


def _loss(sim: Tensor, y: Tensor, scale: Tensor, weights: Tensor) -> Tensor:
    """Mean of ``Σ_c w_c ((ŷ_c − y_c) / s_c)²`` over all samples but the first (the start)."""
    e = (sim[1:] - y[1:]) / scale
    return (e * e * weights).sum(-1).mean()


def _draw(data: Sequence[_Data], window: int, batch: int, gen: torch.Generator) -> list[tuple]:
    """`batch` (experiment, start) pairs, uniform over every valid window start."""
    counts = [max(d.y.shape[0] - window + 1, 0) for d in data]
    total = sum(counts)
    if total == 0:
        longest = max(d.y.shape[0] for d in data)
        raise TorchfricError(
            f"window = {window} samples is longer than every experiment (longest {longest}); "
            "lower window or use 0 for full-length simulation"
        )
    flat = torch.randint(total, (batch,), generator=gen).tolist()
    edges = np.cumsum([0, *counts])
    out = []
    for f in flat:
        i = int(np.searchsorted(edges, f, side="right") - 1)
        out.append((i, int(f - edges[i])))
    return out


def _tiles(data: Sequence[_Data], window: int) -> list[tuple]:
    """Every experiment cut into consecutive windows of `window` samples that share their end
    points (starts 0, W−1, 2(W−1), …), in order: the fixed L-BFGS loss and the shooting tiles."""
    return [
        (i, s) for i, d in enumerate(data) for s in range(0, d.y.shape[0] - window + 1, window - 1)
    ]


def _window_loss(
    model: ArmModel,
    data: Sequence[_Data],
    picks: Sequence[tuple],
    window: int,
    theta: Tensor,
    steps: int,
    scale: Tensor,
    weights: Tensor,
    adjoint: bool,
) -> Tensor:
    """Loss over the windows `picks` = [(experiment, start)], simulated as one batch."""
    t, u, y = _stack_windows(data, picks, window)
    sim = _rollout(model, t, u, y[0], theta, steps, adjoint)
    return _loss(sim, y, scale, weights)


def _stack_windows(
    data: Sequence[_Data], picks: Sequence[tuple], window: int
) -> tuple[Tensor, Tensor, Tensor]:
    """The windows `picks` = [(experiment, start)] as one batch: `t (W,)`, `u (W, B)`,
    `y (W, B, 2)`."""
    u = torch.stack([data[i].u[s : s + window] for i, s in picks], dim=1)
    y = torch.stack([data[i].y[s : s + window] for i, s in picks], dim=1)
    t = torch.arange(window, dtype=torch.float64) * data[picks[0][0]].dt
    return t, u, y


def _shooting_loss(
    model: ArmModel,
    data: Sequence[_Data],
    tiles: Sequence[tuple],
    picks: Sequence[int],
    window: int,
    theta: Tensor,
    delta: Tensor,
    steps: int,
    scale: Tensor,
    weights: Tensor,
    continuity: float,
    adjoint: bool,
) -> Tensor:
    """Multiple-shooting loss of the tiles `picks` (indices into `tiles`) from learned starts
    ``y_start + scale·δ``: data term over all W samples plus the continuity penalty."""
    t, u, y = _stack_windows(data, [tiles[j] for j in picks], window)
    x0 = y[0] + scale * delta[torch.tensor(list(picks))]
    sim = _rollout(model, t, u, x0, theta, steps, adjoint)
    e = (sim - y) / scale
    out = (e * e * weights).sum(-1).mean()
    # `_tiles` lists each experiment's tiles in order, so the next tile of the same experiment
    # is the next entry; it starts where this one ends (shared sample).
    nxt = [
        (b, j + 1)
        for b, j in enumerate(picks)
        if j + 1 < len(tiles) and tiles[j + 1][0] == tiles[j][0]
    ]
    if continuity > 0 and nxt:
        b_idx = torch.tensor([b for b, _ in nxt])
        n_idx = torch.tensor([n for _, n in nxt])
        starts = torch.stack([data[tiles[n][0]].y[tiles[n][1]] for _, n in nxt])
        gap = (sim[-1, b_idx] - (starts + scale * delta[n_idx])) / scale
        out = out + continuity * (gap * gap).sum(-1).sum() / len(picks)
    return out


def _full_loss(
    model: ArmModel,
    data: Sequence[_Data],
    theta: Tensor,
    steps: int,
    scale: Tensor,
    weights: Tensor,
    adjoint: bool,
    engine: str = "odeint",
) -> Tensor:
    """Sample-weighted loss of full-length simulations of every experiment.

    Experiments on the same time grid (e.g. repeats of one recording protocol) are simulated as
    one batch: one solver loop instead of one per file. `engine` as in `simulate`.
    """
    total = sum(d.y.shape[0] - 1 for d in data)
    out = theta.new_zeros(())
    for group in _same_grid(data):
        t = group[0].t
        u = torch.stack([d.u for d in group], dim=1)  # (N, B)
        y = torch.stack([d.y for d in group], dim=1)  # (N, B, 2)
        sim = _rollout(model, t, u, y[0], theta, steps, adjoint, engine)
        out = out + _loss(sim, y, scale, weights) * (len(group) * (t.shape[0] - 1) / total)
    return out


def _same_grid(data: Sequence[_Data]) -> list[list[_Data]]:
    """`data` grouped by identical time vectors, in first-seen order."""
    groups: list[list[_Data]] = []
    for d in data:
        for g in groups:
            if g[0].t.shape == d.t.shape and torch.equal(g[0].t, d.t):
                g.append(d)
                break
        else:
            groups.append([d])
    return groups


def _generator(seed: int, epoch: int) -> torch.Generator:
    """The window draws of `epoch` depend on (seed, epoch) only: resuming repeats them."""
    state = np.random.SeedSequence([seed, epoch]).generate_state(2, dtype=np.uint32)
    return torch.Generator().manual_seed(int(state[0]) << 32 | int(state[1]))


def identify_output_error(
    model: ArmModel,
    experiments: Experiment | Sequence[Experiment],
    tuning: OETuning | None = None,
    *,
    validation: Experiment | Sequence[Experiment] | None = None,
    callback: OECallback | None = None,
    start: tuple | None = None,
    initial_theta: Tensor | None = None,
) -> OEResult:
    """Identify θ of `model` by minimising the simulation error (module docstring).

    Args:
        model: the arm; its current θ is the initial guess (not modified) — e.g. an EKF result's
            model for "EKF first, then polish".
        experiments: training experiments with `qdot` (measured or reconstructed). Windows of one
            batch share one time grid: all experiments must have the same sample step.
        tuning: `OETuning`.
        validation: experiments for early stopping on the mean validation FIT (q and q̇), each
            simulated open loop from its measured initial state; the best θ is returned.
        callback: `OECallback` per epoch.
        start: resume from ``(θ, history, optimizer_state[, shooting])`` of completed epochs
            (`OEResult`'s `theta`, `history`, `optimizer_state`, `shooting`); equals an
            uninterrupted run.
        initial_theta: with `start`, the θ the run began from (`OEResult.initial_theta`): its
            validation score is epoch 0's, the baseline early stopping compares against.
            Without it a resumed run only knows the recorded epochs.

    Returns:
        `OEResult`: fitted copy of the model, θ, per-epoch `EpochRecord`s, best epoch.

    Raises:
        TorchfricError: bad tuning or data. DivergenceError: a non-finite loss or gradient;
            `.last_good` holds the result before that epoch.
    """
    tuning = tuning or OETuning()
    k = model.num_parameters
    tuning.check(k)
    exps = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    if not exps:
        raise TorchfricError("identify_output_error needs at least one training experiment")
    vals = [validation] if isinstance(validation, Experiment) else list(validation or [])
    data = _prepare(exps, "experiments")
    _prepare(vals, "validation experiments")  # the same q̇ check, before any training
    dts = [d.dt for d in data]
    if max(dts) - min(dts) > 1e-6 * max(dts):
        raise TorchfricError(
            f"training experiments have different sample steps {sorted(set(dts))}; windows are "
            "simulated on one time grid, so resample them to one step"
        )
    for w in (*tuning.schedule, tuning.window):
        if w > 0 and w > max(d.y.shape[0] for d in data):
            raise TorchfricError(
                f"window = {w!r} is invalid; allowed: 0 or 2 … "
                f"{max(d.y.shape[0] for d in data)} (samples)"
            )
    callback = callback or OECallback()
    scale = _scales(data)
    weights = torch.tensor(tuple(tuning.weights), dtype=torch.float64)
    names = _unique([e.name for e in vals])

    if start is not None:
        theta0, history, opt_state = start[0], list(start[1]), start[2]
    else:
        theta0, history, opt_state = model.get_theta(), [], None
    theta = torch.nn.Parameter(torch.as_tensor(theta0, dtype=torch.float64).detach().clone())
    if theta.numel() != k:
        raise TorchfricError(f"start theta has {theta.numel()} entries, the model has {k}")
    params = [theta]
    tiles: list[tuple] = []
    delta = None
    if tuning.learn_states:
        tiles = _tiles(data, tuning.window)
        saved = start[3] if start is not None and len(start) > 3 else None
        d0 = torch.zeros(len(tiles), 2, dtype=torch.float64) if saved is None else saved
        delta = torch.nn.Parameter(torch.as_tensor(d0, dtype=torch.float64).detach().clone())
        if delta.shape != (len(tiles), 2):
            raise TorchfricError(
                f"start shooting states have shape {tuple(delta.shape)}, the data give "
                f"{len(tiles)} tiles of {tuning.window} samples"
            )
        params.append(delta)
    opt = torch.optim.Adam(params, lr=tuning.lr)
    if opt_state is not None:
        opt.load_state_dict(opt_state)
    work = copy.deepcopy(model)

    # Full-length simulations (validation, and training with window 0) go through the compiled
    # rk4 when asked; the short batched windows stay on odeint (cheap, and one compiled shape
    # per window batch would add a compile each).
    full_engine = "compiled" if tuning.compile else "odeint"

    def validate(th: Tensor) -> dict[str, dict[str, float]] | None:
        if not vals:
            return None
        work.set_theta(th.detach())
        steps = _substeps(model, th, vals[0].dt, tuning.substeps)
        out = {}
        for name, e in zip(names, vals, strict=True):
            s = score_simulation(work, e, method=_METHOD, substeps=steps, engine=full_engine)
            out[name] = {"fit_q": s.fit_q, "fit_qdot": s.fit_qdot}
        return out

    theta_init = theta.detach().clone() if not history else initial_theta
    if theta_init is not None:
        theta_init = torch.as_tensor(theta_init, dtype=torch.float64).detach().clone()
    # Best θ so far: by validation score when validating, else simply the latest. Epoch 0 (the
    # initial θ) is the baseline; a resumed run replays the recorded epochs after it.
    best_epoch, best_theta, best_score, since = 0, theta.detach().clone(), -math.inf, 0
    if vals and theta_init is not None:
        fit0 = validate(theta_init)
        best_theta = theta_init.clone()
        best_score = EpochRecord(0, math.nan, {}, 0.0, 0.0, fit0).val_score or -math.inf
    for r in history:
        if r.val_score is not None:
            if r.val_score > best_score:
                best_epoch, best_theta, best_score, since = (
                    r.index,
                    torch.tensor(r.theta),
                    r.val_score,
                    0,
                )
            else:
                since += 1
    if not vals and history:
        best_epoch = history[-1].index

    def result(stopped: bool) -> OEResult:
        th = best_theta if vals else theta.detach().clone()
        fitted = copy.deepcopy(model).set_theta(th)
        return OEResult(
            fitted,
            th.clone(),
            list(history),
            best_epoch,
            stopped,
            copy.deepcopy(opt.state_dict()),
            None if delta is None else delta.detach().clone(),
            theta_init,
        )

    def record(index, loss, lr, t0, window, force_eval=False) -> EpochRecord:
        th = theta.detach().clone()
        fit = validate(th) if (force_eval or index % tuning.eval_every == 0) else None
        return EpochRecord(
            index=index,
            loss=loss,
            parameters=dict(zip(model.theta_names, model.to_physical(th).tolist(), strict=True)),
            lr=lr,
            seconds=time.perf_counter() - t0,
            val_fit=fit,
            theta=th.tolist(),
            window=window,
        )

    stopped = since >= tuning.patience if vals else False
    for epoch in range(len(history) + 1, tuning.epochs + 1):
        if stopped:
            break
        t0 = time.perf_counter()
        window = tuning.window_at(epoch)
        lr = tuning.lr_at(epoch)
        for g in opt.param_groups:
            g["lr"] = lr
        steps = _substeps(model, theta, dts[0], tuning.substeps)
        opt.zero_grad()
        if delta is not None:
            gen = _generator(tuning.seed, epoch)
            chosen = torch.randperm(len(tiles), generator=gen)[: tuning.batch].sort().values
            loss = _shooting_loss(
                model, data, tiles, chosen.tolist(), window, theta, delta, steps, scale,
                weights, tuning.continuity, tuning.adjoint,
            )  # fmt: skip
        elif window == 0:
            loss = _full_loss(
                model, data, theta, steps, scale, weights, tuning.adjoint, full_engine
            )
        else:
            picks = _draw(data, window, tuning.batch, _generator(tuning.seed, epoch))
            loss = _window_loss(
                model, data, picks, window, theta, steps, scale, weights, tuning.adjoint
            )
        loss.backward()
        grads_ok = all(bool(torch.isfinite(p.grad).all()) for p in params)
        if not (torch.isfinite(loss) and grads_ok):
            raise DivergenceError(
                f"output-error training diverged in epoch {epoch} (window {window}): loss = "
                f"{float(loss):.4g}, gradient finite = {grads_ok}. "
                "Fix: lower lr, use shorter windows, more substeps, or a better start "
                "(model.init = 'prefit' or an EKF result); the last good parameters are kept",
                last_good=result(False),
            )
        if tuning.clip > 0:
            for p in params:  # θ and the shooting states each to the threshold
                torch.nn.utils.clip_grad_norm_([p], tuning.clip)
        opt.step()
        rec = record(epoch, float(loss.detach()), lr, t0, window, epoch == tuning.epochs)
        history.append(rec)
        if rec.val_score is not None:
            if rec.val_score > best_score:
                best_epoch, best_theta, best_score, since = (
                    epoch,
                    theta.detach().clone(),
                    rec.val_score,
                    0,
                )
            else:
                since += 1
                stopped = since >= tuning.patience
        if not vals:
            best_epoch = epoch
        if callback.on_epoch_end(rec, result(stopped)) is False:
            stopped = True
            break

    if tuning.lbfgs_steps > 0 and not stopped and len(history) == tuning.epochs:
        t0 = time.perf_counter()
        if vals:  # polish from the best θ by validation
            with torch.no_grad():
                theta.copy_(best_theta)
        window = tuning.window_at(tuning.epochs)
        steps = _substeps(model, theta, dts[0], tuning.substeps)
        picks = _tiles(data, window) if window else []
        lbfgs = torch.optim.LBFGS(
            params,
            lr=1.0,
            max_iter=tuning.lbfgs_steps,
            tolerance_grad=1e-12,
            tolerance_change=1e-15,
            line_search_fn="strong_wolfe",
        )

        def closure() -> Tensor:
            lbfgs.zero_grad()
            if delta is not None:
                f = _shooting_loss(
                    model, data, tiles, list(range(len(tiles))), window, theta, delta, steps,
                    scale, weights, tuning.continuity, tuning.adjoint,
                )  # fmt: skip
            elif window == 0:
                f = _full_loss(
                    model, data, theta, steps, scale, weights, tuning.adjoint, full_engine
                )
            else:
                f = _window_loss(
                    model, data, picks, window, theta, steps, scale, weights, tuning.adjoint
                )
            f.backward()
            return f

        before = float(closure().detach())
        params_before = [p.detach().clone() for p in params]
        lbfgs.step(closure)
        after = float(closure().detach())
        if not math.isfinite(after) or after > before:
            with torch.no_grad():
                for p, b in zip(params, params_before, strict=True):
                    p.copy_(b)
            after = before
        rec = record(tuning.epochs + 1, after, 1.0, t0, window, force_eval=True)
        history.append(rec)
        if rec.val_score is not None and rec.val_score > best_score:
            best_epoch, best_theta, best_score = rec.index, theta.detach().clone(), rec.val_score
        if not vals:
            best_epoch = rec.index
        callback.on_epoch_end(rec, result(False))
    return result(stopped)


def _unique(names: Sequence[str]) -> list[str]:
    """Validation names made unique (``name``, ``name#2`` …) for the `val_fit` keys."""
    seen: dict[str, int] = {}
    out = []
    for n in names:
        seen[n] = seen.get(n, 0) + 1
        out.append(n if seen[n] == 1 else f"{n}#{seen[n]}")
    return out
