"""The estimators' settings: one frozen dataclass per estimator, the same one the config's
sections build (`torchfric.app.config`) and the Python API takes.

- `EKFTuning`: the iterative augmented-state EKF (`identify_ekf`, and each ensemble member);
- `EnsembleSpec`: which members an EKF ensemble holds (`identify_ekf_ensemble`);
- `OETuning`: output-error training (`identify_output_error`);
- what a record's inverse dynamics ask for (`static_terms`, `constant_force`,
  `input_delay_found`): least squares of ``c_m u`` by ``M q̈ + b q̇ + Fc sign(q̇)`` with and
  without a term; `init` turns it on, `check` and `train` warn when a config lacks it.

Why this size: every number an estimator is set by, from the config or from the data, in one
place, so that nothing else restates a default.

Each class holds its defaults and checks itself against a model (`check(k)`); a run's
``[estimator]`` section holds these very objects, so the Python API's defaults are the CLI's.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..errors import TorchfricError
from ..models.arm import ArmModel
from .ekf import MEASUREMENTS, measurement_matrix

__all__ = [
    "EKFTuning",
    "EnsembleSpec",
    "OETuning",
    "RUN_ENSEMBLE",
    "REFERENCE_VELOCITY",
    "TUNING_UNITS",
    "as_vector",
    "velocity_scale",
    "data_speeds",
    "speed_quantiles",
    "OFFSET_SHARE",
    "GRAVITY_PHASE",
    "constant_force",
    "static_terms",
    "input_delay_found",
    "DELAY_SHARE",
]

REFERENCE_VELOCITY = 6.64
"""The velocity scale [rad/s] of the paper's rig as the built-in synthetic rig reproduces it
(95th percentile of |q̇| of its identification record, 6.636 rad/s): the machine the paper's
tuning R = diag(1e-3, 1e-2), Q_q̇ = 1e-3 was made for. Relative tuning (`EKFTuning.units`)
reads those numbers at this scale."""

TUNING_UNITS: tuple[str, ...] = ("relative", "absolute")


def data_speeds(experiments: Sequence[Any]) -> Tensor:
    """|q̇| of the experiments, flat: their reconstructed or measured velocity, from position
    differences where there is none (empty for no experiments)."""
    parts = [(e.qdot if e.qdot is not None else torch.diff(e.q) / e.dt) for e in experiments]
    return torch.cat([v.abs().reshape(-1).to(torch.float64) for v in parts] or [torch.zeros(0)])


def speed_quantiles(speeds: Tensor, qs: Sequence[float]) -> list[float] | None:
    """The quantiles `qs` of ``|speeds|`` (finite entries; past 2 M entries a stride, as
    quantile's limit is 16 M), or None for fewer than two entries."""
    v = speeds.detach().reshape(-1).abs().to(torch.float64)
    v = v[torch.isfinite(v)]
    if v.numel() > 2_000_000:
        v = v[:: v.numel() // 1_000_000]
    if v.numel() < 2:
        return None
    return torch.quantile(v, torch.tensor(list(qs), dtype=torch.float64)).tolist()


def velocity_scale(experiments: Sequence[Any]) -> float:
    """The data's velocity scale: the 95th percentile of |q̇| over the experiments
    (`data_speeds`), as the model's initial shape and `OddTanhFriction.min_slope` use it. 1.0
    for data at rest."""
    found = speed_quantiles(data_speeds(experiments), [0.95])
    return (found[0] or 1.0) if found else 1.0


def as_vector(value: float | Sequence[float], n: int, name: str) -> Tensor:
    """`value` (one number for all, or n numbers) as n finite variances >= 0 named `name`."""
    t = torch.as_tensor(value, dtype=torch.float64).reshape(-1)
    if t.numel() == 1:
        t = t.expand(n).clone()
    if t.numel() != n:
        raise TorchfricError(
            f"{name} needs 1 or {n} values, got {t.numel()} ({value!r}); give one number for "
            f"every entry or {n} (estimator.{name} in a run config)"
        )
    if not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
        raise TorchfricError(
            f"{name} must be finite variances >= 0, got {value!r} (estimator.{name} in a run "
            "config)"
        )
    return t


@dataclass(frozen=True)
class EKFTuning:
    """Filter tuning; defaults are the paper's (§5).

    Attributes:
        p0_state: initial variances of [q, q̇] (paper: 0, 0 — the initial state is known).
        p0_theta: initial variance(s) of θ in estimation coordinates (paper: 1).
        q_state: continuous process-noise intensities of [q, q̇] (paper: 0, 0.001).
        q_theta: process-noise intensity of θ (paper: 0 — constant parameters).
        r: measurement variances of the measured channels (paper: 0.001 for q, 0.01 for q̇).
        measure: "both" (q and reconstructed q̇), "position" or "velocity".
        passes: the most off-line passes (paper: 10; default 30, which the likelihood rule
            ends long before on ordinary data: a pass over 30 k samples costs ~35 ms).
        tolerance: the passes end, converged, after a pass that raised the innovation
            log-likelihood over all records by less than ``tolerance · k`` nats, k the number
            of parameters (default 0.5: what k parameters fitted to pure noise would gain,
            2Δℓ ~ χ²_k); 0 disables the early stop.
        substeps: RK4 sub-steps per sample interval in the prediction, or "auto": the fewest that
            keep RK4 stable on the model's stiffest mode, raised between passes (`finer_steps`).
        theta_bound: divergence box on |θ| (estimation coordinates).
        p0_relative: read `p0_theta` in units of each parameter's own size: the initial
            variance of a linearly stored θ_i is ``p0_theta · θ_i²`` (log-stored entries are
            already relative). The paper's P0 = 1 is absolute, which suits weights of order 1
            but lets a centre of 0.04 rad/s jump by ±1 in the first pass.
        units: "relative" (default): `r`, `q_state` and `p0_state` are read at the data's own
            velocity scale v_s (`velocity_scale`): each is multiplied by ``(v_s /
            REFERENCE_VELOCITY)²``, and `p0_theta` is relative (`p0_relative`). The paper's
            numbers then mean on any machine, in any units, what they meant on the paper's rig,
            and data written in degrees, counts or mm, or with another c_m, identify the same
            physical model (scaled exactly by the units). "absolute": the numbers as written,
            in the data's units (the paper's literal tuning). `resolved` turns a relative
            tuning into the absolute one for given data; the estimators call it.
        rollback: undo a pass that lowers the innovation log-likelihood (θ and P_θθ go back to
            the best pass) and stop there. Re-running the same pass from the same state would
            repeat the same step, so stopping is the only sensible continuation. The undone pass
            stays in the history with ``rolled_back = True``.
        compile: run the per-sample step compiled, in chunks of samples: as C generated from
            its traced graph (`torchfric.native`; a few seconds' build, cached on disk across
            runs; over 1000× the eager step here), else through the Inductor scan, else eager —
            the same arithmetic to rounding on every path. On by default (as in a config);
            False runs the eager per-sample step.
    """

    p0_state: tuple[float, float] = (0.0, 0.0)
    p0_theta: float | tuple[float, ...] = 1.0
    q_state: tuple[float, float] = (0.0, 1e-3)
    q_theta: float | tuple[float, ...] = 0.0
    r: tuple[float, ...] = (1e-3, 1e-2)
    measure: str = "both"
    passes: int = 30
    tolerance: float = 0.5
    substeps: int | str = 1
    theta_bound: float = 1e6
    compile: bool = True
    p0_relative: bool = False
    rollback: bool = True
    units: str = "relative"

    def resolved(self, experiments: Sequence[Any]) -> EKFTuning:
        """The absolute tuning this one means on `experiments` (itself when already absolute):
        relative variances scaled by ``(v_s / REFERENCE_VELOCITY)²`` and `p0_relative` on."""
        if self.units == "absolute":
            return self
        if self.units not in TUNING_UNITS:
            raise TorchfricError(
                f"units = {self.units!r} is not known; choose one of {list(TUNING_UNITS)}"
            )
        scale = (velocity_scale(experiments) / REFERENCE_VELOCITY) ** 2

        def times(value: Any) -> tuple[float, ...]:
            return tuple(float(x) * scale for x in torch.as_tensor(value).reshape(-1).tolist())

        return dataclasses.replace(
            self,
            r=times(self.r),
            q_state=times(self.q_state),  # type: ignore[arg-type]
            p0_state=times(self.p0_state),  # type: ignore[arg-type]
            p0_relative=True,
            units="absolute",
        )

    def check(self, k: int) -> None:
        """Validate against a model with k parameters; raises TorchfricError naming the field."""
        if self.units not in TUNING_UNITS:
            raise TorchfricError(
                f"units = {self.units!r} is not known; choose one of {list(TUNING_UNITS)}"
            )
        if self.measure not in MEASUREMENTS:
            raise TorchfricError(
                f"measure = {self.measure!r} is not known; choose one of {sorted(MEASUREMENTS)}"
            )
        m = len(MEASUREMENTS[self.measure])
        if len(self.r) != m:
            raise TorchfricError(
                f"r has {len(self.r)} values but measure = {self.measure!r} measures {m} channel(s); "
                f"give {m}"
            )
        if any((not math.isfinite(v)) or v <= 0 for v in self.r):
            raise TorchfricError(f"r must be positive measurement variances, got {list(self.r)}")
        as_vector(self.p0_state, 2, "p0_state")
        as_vector(self.q_state, 2, "q_state")
        as_vector(self.p0_theta, k, "p0_theta")
        as_vector(self.q_theta, k, "q_theta")
        if not isinstance(self.passes, int) or isinstance(self.passes, bool) or self.passes < 1:
            raise TorchfricError(f"passes must be an integer >= 1, got {self.passes!r}")
        if not (self.tolerance >= 0):
            raise TorchfricError(
                f"tolerance must be >= 0 (0 disables early stop), got {self.tolerance!r}"
            )
        if not _is_int(self.substeps) or self.substeps < 1:  # "auto" is resolved before this
            raise TorchfricError(f"substeps must be an integer >= 1, got {self.substeps!r}")
        if not (self.theta_bound > 0):
            raise TorchfricError(f"theta_bound must be > 0, got {self.theta_bound!r}")

    def matrices(self, k: int, states: int = 2) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(Q (n,n), P0_xx (s,s), H (m,n), R (m,m))`` for a model with k parameters and s
        states (3 for a dynamic model: its bristle state z gets no process noise and P0 = 0,
        z starts at rest), ``n = s + k``."""
        n = states + k
        pad = torch.zeros(states - 2, dtype=torch.float64)
        q_x = torch.cat([as_vector(self.q_state, 2, "q_state"), pad])
        Q = torch.diag(torch.cat([q_x, as_vector(self.q_theta, k, "q_theta")]))
        P0_xx = torch.diag(torch.cat([as_vector(self.p0_state, 2, "p0_state"), pad]))
        H = measurement_matrix(self.measure, n)
        R = torch.diag(torch.as_tensor(self.r, dtype=torch.float64))
        return Q, P0_xx, H, R

    def fixed_theta_matrices(self, k: int, states: int = 2) -> tuple[Tensor, ...]:
        """`matrices` for the filter with θ held (`make_fixed_theta_step`): the state blocks
        ``(Q (s,s), P0_xx (s,s), H (m,s), R (m,m))``; θ's process noise does not apply."""
        Q, P0_xx, H, R = self.matrices(k, states)
        return Q[:states, :states], P0_xx, H[:, :states].contiguous(), R

    def initial_P_theta(self, model: ArmModel, theta: Tensor) -> Tensor:
        """P_θθ at the start for θ `(..., k)` (a batch of starts gives `(..., k, k)`); with
        `p0_relative` (or relative `units`), each start's linearly stored entries are scaled
        by its own size."""
        p0 = as_vector(self.p0_theta, theta.shape[-1], "p0_theta")
        if self.p0_relative or self.units == "relative":
            size = torch.where(model.log_mask(), torch.ones_like(theta), theta.abs())
            floor = 1e-6 * size.amax(dim=-1, keepdim=True)
            p0 = p0 * torch.maximum(size, floor) ** 2
        return torch.diag_embed(p0.expand_as(theta).clone())


@dataclass(frozen=True)
class EnsembleSpec:
    """Which members an ensemble holds.

    Attributes:
        members: random starts (member 0 is the given start itself).
        spread: every θ entry of a random start is the start's value times a log-uniform factor
            in ``[1/spread, spread]`` (log-stored entries: shifted by ``±ln spread``; a zero entry
            stays zero): 3 draws from a ×/÷ 3 box around the start.
        q_scales: factors applied to the whole process-noise intensity Q.
        r_scales: factors applied to the measurement variances R.
        seed: seed of the random starts.

    The ensemble holds ``members × len(q_scales) × len(r_scales)`` filters: every start with
    every tuning.
    """

    members: int = 16
    spread: float = 3.0
    q_scales: tuple[float, ...] = (1.0,)
    r_scales: tuple[float, ...] = (1.0,)
    seed: int = 0

    def check(self) -> None:
        """Raise `TorchfricError` naming the first bad field."""
        if not isinstance(self.members, int) or isinstance(self.members, bool) or self.members < 1:
            raise TorchfricError(f"ensemble members must be an integer >= 1, got {self.members!r}")
        if not (math.isfinite(self.spread) and self.spread >= 1.0):
            raise TorchfricError(
                f"ensemble spread must be a finite factor >= 1, got {self.spread!r}"
            )
        for name, scales in (("q_scales", self.q_scales), ("r_scales", self.r_scales)):
            if not scales or any((not math.isfinite(s)) or s <= 0 for s in scales):
                raise TorchfricError(
                    f"ensemble {name} must be a non-empty list of positive factors, got {list(scales)}"
                )

    @property
    def size(self) -> int:
        """Number of filters: starts × Q scalings × R scalings."""
        return self.members * len(self.q_scales) * len(self.r_scales)


RUN_ENSEMBLE = EnsembleSpec(members=1, q_scales=(0.1, 1.0, 10.0), r_scales=(0.1, 1.0, 10.0))
"""The ensemble a run holds without ensemble keys (``[estimator]`` ``ensemble = 1``,
``ensemble_q_scales = ensemble_r_scales = [0.1, 1.0, 10.0]``): the initial θ under Q × {÷10, 1,
×10} and R × {÷10, 1, ×10}, 9 filters, so that a tuning off by up to ×/÷ 10 still ends at the
physical model (measured on the rig, `benchmarks/robustness.py`: 180 of 180 runs for tanh(3) and
for polytopic(3)). `EnsembleSpec()` itself stays the plain random-start ensemble (16 starts, one
tuning) that `identify_ekf_ensemble` runs when given no spec."""


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _bad(key: str, value: Any, allowed: str) -> TorchfricError:
    return TorchfricError(f"{key} = {value!r} is invalid; allowed: {allowed}")


@dataclass(frozen=True)
class OETuning:
    """Output-error training settings.

    Attributes:
        epochs: Adam epochs (one batch of windows, or one full-length pass, per epoch); 0 with
            `lbfgs_steps` > 0 runs L-BFGS alone (no Adam step, whose ≈ lr-sized move in every
            coordinate can wreck a parameter whose own scale is below lr).
        lr: initial Adam learning rate on θ in estimation coordinates.
        lr_final: learning rate at the last epoch; cosine decay from `lr` (0 < lr_final <= lr).
        window: samples per truncated window (multiple shooting); 0 = full length.
        batch: windows per epoch, drawn at random start indices (seeded).
        weights: loss weights ``(w_q, w_v)`` of the normalised q and q̇ errors.
        clip: gradient-norm clipping threshold (0 = off).
        lbfgs_steps: L-BFGS iterations after Adam on a fixed loss: full length when the last
            window is 0, else every experiment tiled into non-overlapping windows of that length.
        patience: early stop after this many validation evaluations without a better mean FIT.
        eval_every: epochs between validation evaluations (and after the last epoch).
        seed: window draws are a function of (seed, epoch) only (resumable, deterministic).
        substeps: RK4 steps per sample interval, or "auto" (re-chosen every epoch from θ).
        schedule: window lengths per stage, short to long; overrides `window`; epochs split
            evenly over the stages (each entry >= 2, or 0 for full length).
        adjoint: gradients by `torchdiffeq.odeint_adjoint` instead of backpropagation.
        learn_states: multiple shooting with learned window initial states (module docstring);
            needs a fixed `window` >= 2 and no `schedule`.
        continuity: weight of the continuity penalty between consecutive tiles (learn_states).
        compile: full-length simulations — validation, and training losses with window 0
            (full-length Adam and L-BFGS) — through `simulate(..., engine="compiled")`: the same
            rk4 steps as a compiled scan, its gradient by a compiled discrete adjoint (equal to
            backpropagation through odeint to rounding). Windowed training stays on odeint.
            On by default (as in a config); False runs them through odeint too.
    """

    epochs: int = 200
    lr: float = 1e-2
    lr_final: float = 1e-4
    window: int = 200
    batch: int = 64
    weights: tuple[float, float] = (1.0, 1.0)
    clip: float = 1.0
    lbfgs_steps: int = 0
    patience: int = 20
    eval_every: int = 10
    seed: int = 0
    substeps: int | str = 1
    schedule: tuple[int, ...] = ()
    adjoint: bool = False
    learn_states: bool = False
    continuity: float = 1.0
    compile: bool = True

    def check(self, k: int) -> None:
        """Validate against a model with k parameters; raises TorchfricError naming the key."""
        if not _is_int(k) or k < 1:
            raise _bad("k (number of parameters)", k, "an integer >= 1")
        lbfgs_only = self.epochs == 0 and _is_int(self.lbfgs_steps) and self.lbfgs_steps > 0
        if not _is_int(self.epochs) or (self.epochs < 1 and not lbfgs_only):
            raise _bad("epochs", self.epochs, "an integer >= 1, or 0 with lbfgs_steps > 0")
        for key in ("lr", "lr_final"):
            v = getattr(self, key)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise _bad(key, v, "a finite number > 0")
        if self.lr_final > self.lr:
            raise _bad("lr_final", self.lr_final, f"a number in (0, lr = {self.lr!r}]")
        if not _is_int(self.window) or self.window < 0 or self.window == 1:
            raise _bad("window", self.window, "0 (full length) or an integer >= 2 (samples)")
        if not _is_int(self.batch) or self.batch < 1:
            raise _bad("batch", self.batch, "an integer >= 1 (windows per epoch)")
        w = tuple(self.weights)
        if (
            len(w) != 2
            or not all(isinstance(x, (int, float)) and math.isfinite(x) and x >= 0 for x in w)
            or sum(w) == 0
        ):
            raise _bad("weights", self.weights, "two finite numbers >= 0 (w_q, w_v), not both 0")
        if not isinstance(self.clip, (int, float)) or not math.isfinite(self.clip) or self.clip < 0:
            raise _bad("clip", self.clip, "a finite number >= 0 (0 = off)")
        if not _is_int(self.lbfgs_steps) or self.lbfgs_steps < 0:
            raise _bad("lbfgs_steps", self.lbfgs_steps, "an integer >= 0 (0 = no polish)")
        if not _is_int(self.patience) or self.patience < 1:
            raise _bad("patience", self.patience, "an integer >= 1 (validation evaluations)")
        if not _is_int(self.eval_every) or self.eval_every < 1:
            raise _bad("eval_every", self.eval_every, "an integer >= 1 (epochs)")
        if not _is_int(self.seed) or self.seed < 0:
            raise _bad("seed", self.seed, "an integer >= 0")
        if self.substeps != "auto" and (not _is_int(self.substeps) or self.substeps < 1):
            raise _bad("substeps", self.substeps, "an integer >= 1 or 'auto'")
        s = tuple(self.schedule)
        if not all(_is_int(x) and (x == 0 or x >= 2) for x in s) or len(s) > self.epochs:
            raise _bad(
                "schedule",
                self.schedule,
                f"at most epochs = {self.epochs} window lengths, each 0 (full length) or >= 2",
            )
        if not isinstance(self.adjoint, bool):
            raise _bad("adjoint", self.adjoint, "true or false")
        if not isinstance(self.learn_states, bool):
            raise _bad("learn_states", self.learn_states, "true or false")
        c = self.continuity
        if isinstance(c, bool) or not isinstance(c, (int, float)) or not math.isfinite(c) or c < 0:
            raise _bad("continuity", c, "a finite number >= 0")
        if self.learn_states and (self.window < 2 or s):
            raise _bad(
                "learn_states",
                self.learn_states,
                "false, or true with a fixed window >= 2 and no schedule (the learned states "
                f"belong to one tiling; got window = {self.window}, schedule = {list(s)})",
            )

    def window_at(self, epoch: int) -> int:
        """Window length of (1-based) `epoch`: the schedule's stage, else `window`."""
        if not self.schedule:
            return self.window
        if self.epochs == 0:
            return self.schedule[-1]
        stage = (epoch - 1) * len(self.schedule) // self.epochs
        return self.schedule[stage]

    def lr_at(self, epoch: int) -> float:
        """Cosine decay ``lr_final + ½ (lr − lr_final)(1 + cos(π (e−1)/(E−1)))``, e = 1 … E."""
        if self.epochs == 1:
            return self.lr
        frac = (epoch - 1) / (self.epochs - 1)
        return self.lr_final + 0.5 * (self.lr - self.lr_final) * (1.0 + math.cos(math.pi * frac))


OFFSET_SHARE = 0.1  # the share of the residual a term must take for a record to carry it
GRAVITY_PHASE = math.radians(20.0)  # the farthest from q = 0 `model.gravity`'s lowest point lies


def _columns(experiments: Sequence[Any], c_m: float) -> tuple[list[Tensor], Tensor, Tensor]:
    """The base columns (q̈, q̇, sign q̇), ``c_m u`` and q of the pre-fit's moving samples."""
    from .prefit import _regression_data, default_cutoff_hz

    exps = list(experiments)
    q, v, a, u = _regression_data(exps, default_cutoff_hz(max(e.dt for e in exps)), 0.02)
    return [a, v, torch.sign(v)], c_m * u, q


def static_terms(
    experiments: Sequence[Any], c_m: float, rotary: bool
) -> tuple[tuple[float, float], tuple[float, float, float, float] | None]:
    """``((constant, share), (g, q0, share, constant beside it) or None)``: a constant and, if
    `rotary`, ``g sin(q − q0)`` beyond it (the disc: 4.80, 3°, 84 %; the rig 0.0 %), with the
    constant fitted beside that (alone it is g sin's mean: 5.8 for a robot joint's 0.2).
    A share is ``1 − RMS with / RMS without`` the term."""
    from .prefit import _least_squares

    cols, rhs, q = _columns(experiments, c_m)
    _, base = _least_squares(cols, rhs)
    cols.append(torch.ones_like(rhs))
    sol, with_it = _least_squares(cols, rhs)
    offset = (float(sol[-1]), (1.0 - with_it / base) if base > 0 else 0.0)
    if not rotary:
        return offset, None
    sol, arm = _least_squares([*cols, torch.sin(q), torch.cos(q)], rhs)
    s, c = float(sol[-2]), float(sol[-1])
    g = (math.hypot(s, c), -math.atan2(c, s), (1 - arm / with_it) if with_it else 0.0)
    return offset, (*g, float(sol[-3]))


def constant_force(experiments: Sequence[Any], c_m: float) -> tuple[float, float]:
    """`static_terms`' constant and its share: a 12-kg vertical axis's 117.7 N 98 %, EMPS 43 %,
    HSM150 72 %, the rig, the disc and the coverage study's axes 0.0–0.1 %, in any q unit."""
    return static_terms(experiments, c_m, rotary=False)[0]


DELAY_SHARE = 0.2  # the share of the residual a whole-sample input delay must remove


def input_delay_found(
    experiments: Sequence[Any], c_m: float, rotary: bool, longest: int = 3
) -> tuple[int, float]:
    """``(k, share)``: the smallest input delay (`Experiment.delay_input`, ≤ `longest` samples)
    within 2 % of the best inverse-dynamics fit (a constant, ``sin q``, ``cos q`` if `rotary`),
    and the share of the undelayed residual it removes. The disc: 1, 60 %; EMPS 1, 2.8 %."""
    from .prefit import _least_squares

    residuals = []
    for k in range(longest + 1):
        cols, rhs, q = _columns([e.delay_input(k) for e in experiments], c_m)
        cols.append(torch.ones_like(rhs))
        if rotary:
            cols += [torch.sin(q), torch.cos(q)]
        residuals.append(_least_squares(cols, rhs)[1])
    k = next(k for k, r in enumerate(residuals) if r <= 1.02 * min(residuals))
    return k, (1.0 - residuals[k] / residuals[0]) if residuals[0] > 0 else 0.0
