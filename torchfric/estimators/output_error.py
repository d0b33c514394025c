"""Gradient output-error identification: minimise the open-loop simulation error by Adam (and an
optional L-BFGS polish) through the solver (docs/estimators.md, "Output-error training").

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
Layout: `identify_output_error` checks the data (`shooting.training_data`), then `_Training` holds
θ (and the window states δ), the optimiser, the history and the best epoch, and steps through the
Adam epochs (`_Training.epoch`), the early stop (`_BestEpoch`) and the optional L-BFGS polish
(`_Training.polish`). The data tensors, windows, rollouts and losses are in `shooting`.

Why this size: `_Training` is one optimisation with its resumable state; the shooting windows
and the loss are already apart (`shooting`), and its covariance (`oe_covariance`).
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

from ..data import Experiment
from ..errors import DivergenceError, TorchfricError
from ..models.arm import ArmModel
from .metrics import mean_fit, score_simulation
from .observers import OECallback
from .settings import OETuning
from .shooting import (
    METHOD,
    ExperimentTensors,
    cut_tiles,
    draw_windows,
    epoch_generator,
    full_loss,
    prepare,
    scales,
    shooting_loss,
    solver_substeps,
    training_data,
    window_loss,
)

__all__ = ["OETuning", "EpochRecord", "OEResult", "OECallback", "identify_output_error"]

ValFit = dict[str, dict[str, float]]  # {validation name: {"fit_q", "fit_qdot"}}


@dataclass
class EpochRecord:
    """Diagnostics of one epoch (index `epochs + 1` is the L-BFGS polish, with lr = 1)."""

    index: int  # 1-based epoch number
    loss: float  # training loss of this epoch's batch, before the step
    parameters: dict[str, float]  # physical values by name, after the step
    lr: float
    seconds: float
    val_fit: ValFit | None  # {name: {"fit_q", "fit_qdot"}} when evaluated
    theta: list[float] = field(default_factory=list)  # estimation coordinates, after the step
    window: int = 0  # window length of this epoch (0 = full length)

    @property
    def val_score(self) -> float | None:
        """Mean over validation experiments of (FIT_q + FIT_q̇) / 2, or None."""
        return mean_fit(self.val_fit)

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
    shooting: Tensor | None = (
        None  # (tiles, 2) learned start offsets δ (learn_states), in units of s
    )
    initial_theta: Tensor | None = None  # θ at epoch 0, the early stop's baseline (resume)

    def initial_states(self, experiments: Experiment | Sequence[Experiment]) -> Tensor:
        """The learned window start states ``[q, q̇]`` (tiles, 2) of the `learn_states` tiling of
        `experiments` (the training experiments, in training order)."""
        if self.shooting is None:
            raise TorchfricError("this result has no learned states (learn_states was off)")
        data = prepare([experiments] if isinstance(experiments, Experiment) else experiments, "x")
        window = self.history[-1].window if self.history else 0
        tiles = cut_tiles(data, window)
        if len(tiles) != self.shooting.shape[0]:
            raise TorchfricError(
                f"these experiments give {len(tiles)} tiles, the result learned "
                f"{self.shooting.shape[0]}; pass the training experiments"
            )
        y0 = torch.stack([data[i].y[st] for i, st in tiles])
        return y0 + scales(data) * self.shooting

    @property
    def epochs(self) -> int:
        return len(self.history)


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
    tuning.check(model.num_parameters)
    data, vals = training_data(experiments, validation, (*tuning.schedule, tuning.window))
    callback = callback or OECallback()
    run = _Training(model, data, vals, tuning, start, initial_theta)
    run.train(callback)
    if tuning.lbfgs_steps > 0 and not run.stopped and len(run.history) == tuning.epochs:
        run.polish(callback)
    return run.result(run.stopped)


class _BestEpoch:
    """The epoch whose θ a run returns, and the early stop's count.

    With validation: the epoch with the best mean validation FIT so far. Epoch 0 (the initial θ)
    is the baseline when its score is known; a later evaluation must beat the best strictly, and
    `since` counts the evaluations since the last one that did (patience). Epochs that were not
    evaluated change nothing. Without validation the best epoch is simply the latest (and the
    returned θ the current one, see `_Training.result`).
    """

    def __init__(self, validating: bool, theta: Tensor) -> None:
        self.validating = validating
        self.epoch = 0
        self.theta = theta
        self.score = -math.inf
        self.since = 0

    def baseline(self, theta: Tensor, val_fit: ValFit | None) -> None:
        """Epoch 0: the initial θ and its validation FIT, the score to beat."""
        self.theta = theta
        self.score = mean_fit(val_fit) or -math.inf  # (a score of exactly 0 counts as none)

    def note(self, record: EpochRecord, theta: Tensor) -> None:
        """Take epoch `record` (θ after it: `theta`) into account."""
        if not self.validating:
            self.epoch = record.index
        elif record.val_score is not None:
            if record.val_score > self.score:
                self.epoch, self.theta = record.index, theta
                self.score, self.since = record.val_score, 0
            else:
                self.since += 1


class _Training:
    """One output-error run: θ (and the shooting offsets δ), Adam, the epoch history and the best
    epoch so far. Built from the checked data and an optional resume `start`."""

    def __init__(
        self,
        model: ArmModel,
        data: list[ExperimentTensors],
        vals: list[Experiment],
        tuning: OETuning,
        start: tuple | None,
        initial_theta: Tensor | None,
    ) -> None:
        self.model, self.data, self.vals, self.tuning = model, data, vals, tuning
        self.scale = scales(data)
        self.weights = torch.tensor(tuple(tuning.weights), dtype=torch.float64)
        self.names = _unique([e.name for e in vals])
        self._start_parameters(start)
        self.work = copy.deepcopy(model)  # validation simulates this copy, θ set per evaluation
        # Full-length simulations (validation, and training with window 0) go through the
        # compiled rk4 when asked; the short batched windows stay on odeint (cheap, and one
        # compiled shape per window batch would add a compile each).
        self.full_engine = "compiled" if tuning.compile else "odeint"
        self._replay(initial_theta)

    def _start_parameters(self, start: tuple | None) -> None:
        """θ, the shooting offsets δ (learn_states) and Adam: fresh, or from a resume `start`."""
        k = self.model.num_parameters
        if start is not None:
            theta0, self.history, opt_state = start[0], list(start[1]), start[2]
        else:
            theta0, self.history, opt_state = self.model.get_theta(), [], None
        t0 = torch.as_tensor(theta0, dtype=torch.float64).detach().clone()
        self.theta = torch.nn.Parameter(t0)
        if self.theta.numel() != k:
            raise TorchfricError(f"start theta has {self.theta.numel()} entries, the model has {k}")
        self.params = [self.theta]
        self.tiles: list[tuple] = []
        self.delta: torch.nn.Parameter | None = None
        if self.tuning.learn_states:
            self.tiles = cut_tiles(self.data, self.tuning.window)
            saved = start[3] if start is not None and len(start) > 3 else None
            n = len(self.tiles)
            d0 = torch.zeros(n, 2, dtype=torch.float64) if saved is None else saved
            self.delta = torch.nn.Parameter(
                torch.as_tensor(d0, dtype=torch.float64).detach().clone()
            )
            if self.delta.shape != (n, 2):
                raise TorchfricError(
                    f"start shooting states have shape {tuple(self.delta.shape)}, the data give "
                    f"{n} tiles of {self.tuning.window} samples"
                )
            self.params.append(self.delta)
        self.opt = torch.optim.Adam(self.params, lr=self.tuning.lr)
        if opt_state is not None:
            self.opt.load_state_dict(opt_state)

    def _replay(self, initial_theta: Tensor | None) -> None:
        """The best epoch and early-stop state at the start: epoch 0 (the initial θ) is the
        baseline; a resumed run replays its recorded epochs after it."""
        theta_init = self.theta.detach().clone() if not self.history else initial_theta
        if theta_init is not None:
            theta_init = torch.as_tensor(theta_init, dtype=torch.float64).detach().clone()
        self.theta_init = theta_init
        self.best = _BestEpoch(bool(self.vals), self.theta.detach().clone())
        if self.vals and theta_init is not None:
            self.best.baseline(theta_init.clone(), self.validate(theta_init))
        for r in self.history:
            self.best.note(r, torch.tensor(r.theta))
        self.stopped = self.best.since >= self.tuning.patience

    def train(self, callback: OECallback) -> None:
        """The Adam epochs after those already in the history, until the last, the early stop
        (patience) or a callback's False."""
        for index in range(len(self.history) + 1, self.tuning.epochs + 1):
            if self.stopped:
                break
            rec = self.epoch(index)
            self.history.append(rec)
            self.best.note(rec, self.theta.detach().clone())
            self.stopped = self.best.since >= self.tuning.patience
            if callback.on_epoch_end(rec, self.result(self.stopped)) is False:
                self.stopped = True
                break

    def epoch(self, index: int) -> EpochRecord:
        """One Adam step on epoch `index`'s loss (its windows, learning rate and window length)."""
        t0 = time.perf_counter()
        window = self.tuning.window_at(index)
        lr = self.tuning.lr_at(index)
        for g in self.opt.param_groups:
            g["lr"] = lr
        steps = self.substeps()
        self.opt.zero_grad()
        loss = self.loss(window, steps, self._epoch_picks(index, window))
        loss.backward()
        self._check_finite(loss, index, window)
        if self.tuning.clip > 0:
            for p in self.params:  # θ and the shooting states each to the threshold
                torch.nn.utils.clip_grad_norm_([p], self.tuning.clip)
        self.opt.step()
        last = index == self.tuning.epochs
        return self.record(index, float(loss.detach()), lr, t0, window, last)

    def _epoch_picks(self, index: int, window: int) -> list:
        """What epoch `index` simulates, drawn from (seed, epoch) only: `batch` shooting tiles
        (indices, sorted), `batch` random windows, or nothing (full length)."""
        if self.delta is not None:
            gen = epoch_generator(self.tuning.seed, index)
            chosen = torch.randperm(len(self.tiles), generator=gen)[: self.tuning.batch]
            return chosen.sort().values.tolist()
        if window == 0:
            return []
        return draw_windows(
            self.data, window, self.tuning.batch, epoch_generator(self.tuning.seed, index)
        )

    def _check_finite(self, loss: Tensor, index: int, window: int) -> None:
        """Raise `DivergenceError` (with the result before this epoch) on a non-finite loss or
        gradient."""
        grads_ok = all(bool(torch.isfinite(p.grad).all()) for p in self.params)
        if not (torch.isfinite(loss) and grads_ok):
            raise DivergenceError(
                f"output-error training diverged in epoch {index} (window {window}): loss = "
                f"{float(loss):.4g}, gradient finite = {grads_ok}. "
                "Fix: lower estimator.lr, use a shorter estimator.window, more "
                "estimator.substeps, or a better start (model.init = 'prefit', or the "
                "checkpoint of an EKF run); the last good parameters are kept",
                last_good=self.result(False),
            )

    def substeps(self) -> int:
        """Solver sub-steps per sample of the training data at the current θ."""
        return solver_substeps(self.model, self.theta, self.data[0].dt, self.tuning.substeps)

    def loss(self, window: int, steps: int, picks: list) -> Tensor:
        """The training loss: of the shooting tiles `picks` (learn_states), of full-length
        simulations (window 0), or of the windows `picks` = [(experiment, start)]."""
        t = self.tuning
        if self.delta is not None:
            return shooting_loss(
                self.model, self.data, self.tiles, picks, window, self.theta, self.delta, steps,
                self.scale, self.weights, t.continuity, t.adjoint,
            )  # fmt: skip
        if window == 0:
            return full_loss(
                self.model, self.data, self.theta, steps, self.scale, self.weights, t.adjoint,
                self.full_engine,
            )  # fmt: skip
        return window_loss(
            self.model, self.data, picks, window, self.theta, steps, self.scale, self.weights,
            t.adjoint,
        )  # fmt: skip

    def polish(self, callback: OECallback) -> None:
        """The L-BFGS polish after the last epoch (recorded as epoch `epochs + 1`): from the best
        θ by validation (else the last), on a fixed loss (every tile, or full length), kept only
        if it lowers that loss."""
        t0 = time.perf_counter()
        if self.vals:  # polish from the best θ by validation
            with torch.no_grad():
                self.theta.copy_(self.best.theta)
        window = self.tuning.window_at(self.tuning.epochs)
        steps = self.substeps()
        if self.delta is not None:
            picks = list(range(len(self.tiles)))
        else:
            picks = cut_tiles(self.data, window) if window else []
        lbfgs = torch.optim.LBFGS(
            self.params,
            lr=1.0,
            max_iter=self.tuning.lbfgs_steps,
            tolerance_grad=1e-12,
            tolerance_change=1e-15,
            line_search_fn="strong_wolfe",
        )

        def closure() -> Tensor:
            lbfgs.zero_grad()
            f = self.loss(window, steps, picks)
            f.backward()
            return f

        before = float(closure().detach())
        params_before = [p.detach().clone() for p in self.params]
        lbfgs.step(closure)
        after = float(closure().detach())
        if not math.isfinite(after) or after > before:
            with torch.no_grad():
                for p, b in zip(self.params, params_before, strict=True):
                    p.copy_(b)
            after = before
        rec = self.record(self.tuning.epochs + 1, after, 1.0, t0, window, force_eval=True)
        self.history.append(rec)
        self.best.note(rec, self.theta.detach().clone())
        callback.on_epoch_end(rec, self.result(False))

    def validate(self, theta: Tensor) -> ValFit | None:
        """FIT of q and q̇ per validation experiment, simulated open loop at `theta`."""
        if not self.vals:
            return None
        self.work.set_theta(theta.detach())
        steps = solver_substeps(self.model, theta, self.vals[0].dt, self.tuning.substeps)
        out = {}
        for name, e in zip(self.names, self.vals, strict=True):
            s = score_simulation(
                self.work, e, method=METHOD, substeps=steps, engine=self.full_engine
            )
            out[name] = {"fit_q": s.fit_q, "fit_qdot": s.fit_qdot}
        return out

    def record(
        self, index: int, loss: float, lr: float, t0: float, window: int, force_eval: bool = False
    ) -> EpochRecord:
        """The `EpochRecord` of epoch `index` at the current θ; validated every `eval_every`
        epochs or when `force_eval`."""
        th = self.theta.detach().clone()
        due = force_eval or index % self.tuning.eval_every == 0
        physical = self.model.to_physical(th).tolist()
        return EpochRecord(
            index=index,
            loss=loss,
            parameters=dict(zip(self.model.theta_names, physical, strict=True)),
            lr=lr,
            seconds=time.perf_counter() - t0,
            val_fit=self.validate(th) if due else None,
            theta=th.tolist(),
            window=window,
        )

    def result(self, stopped: bool) -> OEResult:
        """The `OEResult` so far: the best θ by validation (else the current one)."""
        th = self.best.theta if self.vals else self.theta.detach().clone()
        fitted = copy.deepcopy(self.model).set_theta(th)
        return OEResult(
            fitted,
            th.clone(),
            list(self.history),
            self.best.epoch,
            stopped,
            copy.deepcopy(self.opt.state_dict()),
            None if self.delta is None else self.delta.detach().clone(),
            self.theta_init,
        )


def _unique(names: Sequence[str]) -> list[str]:
    """Validation names made unique (``name``, ``name#2`` …) for the `val_fit` keys."""
    seen: dict[str, int] = {}
    out = []
    for n in names:
        seen[n] = seen.get(n, 0) + 1
        out.append(n if seen[n] == 1 else f"{n}#{seen[n]}")
    return out
