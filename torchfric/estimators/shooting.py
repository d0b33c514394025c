"""Data, windows, rollouts and losses of output-error training (the method: `output_error`).

The pieces one training step is made of, free of any optimiser state:

- `training_data` checks the training and validation experiments; `prepare` turns experiments
  into `ExperimentTensors` (t, u and measured ``y = [q, q̇]`` in float64), and `scales` gives
  the pooled standard deviations that make the loss unit-free;
- `draw_windows` (random window starts, seeded per epoch by `epoch_generator`) and `cut_tiles`
  (consecutive windows sharing their end points) pick what is simulated;
- `rollout` simulates through `simulate` (or torchdiffeq's adjoint on the same exact-ZOH field);
- `window_loss`, `shooting_loss` and `full_loss` are the three horizons' losses.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..data import Experiment
from ..errors import TorchfricError
from ..models.arm import ArmModel
from ..models.simulate import ZOHField, auto_substeps, sample_grid, simulate

__all__ = [
    "METHOD",
    "ExperimentTensors",
    "prepare",
    "training_data",
    "scales",
    "solver_substeps",
    "rollout",
    "output_loss",
    "draw_windows",
    "cut_tiles",
    "stack_windows",
    "window_loss",
    "shooting_loss",
    "full_loss",
    "group_by_grid",
    "epoch_generator",
]

METHOD = "rk4"  # the fixed-grid solver of every output-error simulation


@dataclass
class ExperimentTensors:
    """Training tensors of one experiment: `u (N,)`, measured `y (N, 2)` = [q, q̇]."""

    t: Tensor
    u: Tensor
    y: Tensor
    dt: float


def prepare(exps: Sequence[Experiment], what: str) -> list[ExperimentTensors]:
    """`exps` as float64 tensors; `what` names them in the errors (non-`Experiment`, no q̇)."""
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
        out.append(ExperimentTensors(e.t.to(torch.float64), e.u.to(torch.float64), y, e.dt))
    return out


def training_data(
    experiments: Experiment | Sequence[Experiment],
    validation: Experiment | Sequence[Experiment] | None,
    windows: Sequence[int],
) -> tuple[list[ExperimentTensors], list[Experiment]]:
    """The training tensors and the validation experiments of `identify_output_error`, after
    every check on them that can be made before training: at least one experiment, q̇ present
    (validation too), one sample step, and each of `windows` (the tuning's window lengths) 0 or
    no longer than the longest experiment."""
    exps = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    if not exps:
        raise TorchfricError("identify_output_error needs at least one training experiment")
    vals = [validation] if isinstance(validation, Experiment) else list(validation or [])
    data = prepare(exps, "experiments")
    prepare(vals, "validation experiments")  # the same q̇ check, before any training
    dts = [d.dt for d in data]
    if max(dts) - min(dts) > 1e-6 * max(dts):
        raise TorchfricError(
            f"training experiments have different sample steps {sorted(set(dts))}; windows are "
            "simulated on one time grid, so resample them to one step"
        )
    for w in windows:
        if w > 0 and w > max(d.y.shape[0] for d in data):
            raise TorchfricError(
                f"window = {w!r} is invalid; allowed: 0 or 2 … "
                f"{max(d.y.shape[0] for d in data)} (samples; estimator.window and the "
                "entries of estimator.schedule in a run config)"
            )
    return data, vals


def scales(data: Sequence[ExperimentTensors]) -> Tensor:
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


def solver_substeps(model: ArmModel, theta: Tensor, dt: float, substeps: int | str) -> int:
    """Solver sub-steps per sample: `substeps` itself, or for "auto" `auto_substeps` at θ."""
    if substeps != "auto":
        return int(substeps)
    return auto_substeps(model, dt, METHOD, theta=theta)


def rollout(
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
        return simulate(model, t, u, x0, method=METHOD, substeps=steps, theta=theta, engine=engine)
    # Same exact-ZOH field as `simulate`; the grid is built per call from the requested times, so
    # the adjoint's backward integration over [t_i, t_{i−1}] gets its own sub-step grid.
    fieldfn = ZOHField(model, t, u, theta)
    options = {"grid_constructor": lambda _f, _y0, tt: sample_grid(tt, steps), "perturb": True}
    from torchdiffeq import odeint_adjoint  # on use: it imports scipy.integrate (0.4 s)

    return odeint_adjoint(fieldfn, x0, t, method=METHOD, options=options, adjoint_params=(theta,))


def output_loss(sim: Tensor, y: Tensor, scale: Tensor, weights: Tensor) -> Tensor:
    """Mean of ``Σ_c w_c ((ŷ_c − y_c) / s_c)²`` over all samples but the first (the start)."""
    e = (sim[1:] - y[1:]) / scale
    return (e * e * weights).sum(-1).mean()


def draw_windows(
    data: Sequence[ExperimentTensors], window: int, batch: int, gen: torch.Generator
) -> list[tuple]:
    """`batch` (experiment, start) pairs, uniform over every valid window start."""
    counts = [max(d.y.shape[0] - window + 1, 0) for d in data]
    total = sum(counts)
    if total == 0:
        longest = max(d.y.shape[0] for d in data)
        raise TorchfricError(
            f"window = {window} samples is longer than every experiment (longest {longest}); "
            "lower window (estimator.window in a run config) or use 0 for full-length "
            "simulation"
        )
    flat = torch.randint(total, (batch,), generator=gen).tolist()
    edges = np.cumsum([0, *counts])
    out = []
    for f in flat:
        i = int(np.searchsorted(edges, f, side="right") - 1)
        out.append((i, int(f - edges[i])))
    return out


def cut_tiles(data: Sequence[ExperimentTensors], window: int) -> list[tuple]:
    """Every experiment cut into consecutive windows of `window` samples that share their end
    points (starts 0, W−1, 2(W−1), …), in order: the fixed L-BFGS loss and the shooting tiles."""
    return [
        (i, s) for i, d in enumerate(data) for s in range(0, d.y.shape[0] - window + 1, window - 1)
    ]


def stack_windows(
    data: Sequence[ExperimentTensors], picks: Sequence[tuple], window: int
) -> tuple[Tensor, Tensor, Tensor]:
    """The windows `picks` = [(experiment, start)] as one batch: `t (W,)`, `u (W, B)`,
    `y (W, B, 2)`."""
    u = torch.stack([data[i].u[s : s + window] for i, s in picks], dim=1)
    y = torch.stack([data[i].y[s : s + window] for i, s in picks], dim=1)
    t = torch.arange(window, dtype=torch.float64) * data[picks[0][0]].dt
    return t, u, y


def window_loss(
    model: ArmModel,
    data: Sequence[ExperimentTensors],
    picks: Sequence[tuple],
    window: int,
    theta: Tensor,
    steps: int,
    scale: Tensor,
    weights: Tensor,
    adjoint: bool,
) -> Tensor:
    """Loss over the windows `picks` = [(experiment, start)], simulated as one batch."""
    t, u, y = stack_windows(data, picks, window)
    sim = rollout(model, t, u, y[0], theta, steps, adjoint)
    return output_loss(sim, y, scale, weights)


def shooting_loss(
    model: ArmModel,
    data: Sequence[ExperimentTensors],
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
    t, u, y = stack_windows(data, [tiles[j] for j in picks], window)
    x0 = y[0] + scale * delta[torch.tensor(list(picks))]
    sim = rollout(model, t, u, x0, theta, steps, adjoint)
    e = (sim - y) / scale
    out = (e * e * weights).sum(-1).mean()
    # `cut_tiles` lists each experiment's tiles in order, so the next tile of the same experiment
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


def full_loss(
    model: ArmModel,
    data: Sequence[ExperimentTensors],
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
    for group in group_by_grid(data):
        t = group[0].t
        u = torch.stack([d.u for d in group], dim=1)  # (N, B)
        y = torch.stack([d.y for d in group], dim=1)  # (N, B, 2)
        sim = rollout(model, t, u, y[0], theta, steps, adjoint, engine)
        out = out + output_loss(sim, y, scale, weights) * (len(group) * (t.shape[0] - 1) / total)
    return out


def group_by_grid(data: Sequence[ExperimentTensors]) -> list[list[ExperimentTensors]]:
    """`data` grouped by identical time vectors, in first-seen order."""
    groups: list[list[ExperimentTensors]] = []
    for d in data:
        for g in groups:
            if g[0].t.shape == d.t.shape and torch.equal(g[0].t, d.t):
                g.append(d)
                break
        else:
            groups.append([d])
    return groups


def epoch_generator(seed: int, epoch: int) -> torch.Generator:
    """The window draws of `epoch` depend on (seed, epoch) only: resuming repeats them."""
    state = np.random.SeedSequence([seed, epoch]).generate_state(2, dtype=np.uint32)
    return torch.Generator().manual_seed(int(state[0]) << 32 | int(state[1]))
