"""Data-driven initial θ: an inverse-dynamics least-squares pre-fit (equation error).

``c_m u = M q̈ + b q̇ + C(q̇; θ) + offset + g_c sin q + a |q̇|`` (enabled terms) is fitted on zero-phase filtered velocity
and acceleration (`data.zero_phase_derivative` / `zero_phase_acceleration`), as in the EMPS
reference identification (IDIM-LS). Steps:

1. A linear least-squares fit of the white-box skeleton ``M, b, F_c`` (Coulomb ``F_c sign q̇``)
   plus the enabled offset/gravity/asymmetric terms gives the scales of inertia and friction.
2. The friction module is initialised from those scales (velocity scale: the 95th percentile
   of ``|q̇|``; torque scale: ``F_c``), then all of θ is refined by Levenberg–Marquardt on the
   equation error, with the Jacobian from autograd (`torch.func.vmap` of `torch.func.grad`
   over the samples; θ in estimation coordinates, so positive parameters stay positive). Several friction starts are tried; the best is kept.

Stick phases (``|q̇|`` below a threshold) are left out: there the friction is a pre-sliding
force, not a function of velocity, and the filtered acceleration is dominated by quantisation.
The 3 filter settling times at each end of every experiment are left out too, and the
low-passed signals are decimated to 4 samples per cut-off period; on a long record at most
`PREFIT_ROWS` rows are fitted.

Why this size: the regression rows, the starts, the batched Levenberg–Marquardt and the
generated per-row code are one procedure whose parts share the rows' layout.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.func import grad, vmap

from ..data import Experiment, quiet_cutoff_hz, zero_phase_acceleration, zero_phase_derivative
from ..errors import TorchfricError
from ..models.arm import ArmModel
from ..models.friction import make_friction

__all__ = [
    "PrefitResult", "prefit", "stick_band", "default_cutoff_hz", "CUTOFF_HZ", "NYQUIST_FRACTION", "PREFIT_ROWS",
]  # fmt: skip

CUTOFF_HZ = 50.0
"""The pre-fit's cut-off when the sampling is fast enough (the EMPS IDIM recipe's scale)."""
NYQUIST_FRACTION = 0.4
"""Otherwise the cut-off sits at this fraction of the Nyquist frequency (a cut-off at or above
Nyquist is no filter at all). There a central difference has gain sin(ω·dt)/(ω·dt) = 0.76, where
the forward-backward Butterworth is at 0.5 anyway; at a tenth of Nyquist the gain is 0.996."""
PREFIT_ROWS = 40_000
"""The most rows the Levenberg–Marquardt fits: above it every s-th moving row (s the smallest
stride that fits). Records up to ~200 s at 1 kHz stay whole; a 20-minute record's 198 k rows
took 32 s, and a start needs no such precision (the filter's passes take it from there)."""


def default_cutoff_hz(dt: float) -> float:
    """``min(CUTOFF_HZ, NYQUIST_FRACTION · 1/(2·dt))``: 50 Hz at 1 kHz, 8 Hz at 40 Hz."""
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
        raise TorchfricError(f"dt = {dt!r}; expected a positive finite sample period in s")
    return min(CUTOFF_HZ, NYQUIST_FRACTION * 0.5 / float(dt))


@dataclass
class PrefitResult:
    """Outcome of `prefit`: the initialised model and fit diagnostics."""

    model: ArmModel
    rms_residual: float  # RMS equation error [torque units] on the used samples
    relative_residual: float  # ‖residual‖ / ‖c_m u‖ on the used samples
    samples: int  # samples used (moving, away from the ends)
    iterations: int
    cutoff_hz: float = math.nan  # the low-pass of q̇ and q̈ (`quiet_cutoff_hz`)


def _regression_data(
    experiments: Sequence[Experiment], cutoff_hz: float, stick_fraction: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Stacked (q, q̇, q̈, u) of the moving samples of all experiments."""
    qs, vs, accs, us = [], [], [], []
    for exp in experiments:
        edge = int(math.ceil(3.0 / (cutoff_hz * exp.dt)))
        if exp.n <= 2 * edge + 10:
            raise TorchfricError(
                f"experiment {exp.name!r} has {exp.n} samples, too few for the pre-fit's "
                f"{cutoff_hz:g} Hz zero-phase filter; use model.init = 'config'"
            )
        v = zero_phase_derivative(exp.q, exp.dt, cutoff_hz)
        a = zero_phase_acceleration(exp.q, exp.dt, cutoff_hz)
        # After the low-pass, samples closer than 1/(4·cut-off) carry little new information:
        # decimate (the EMPS IDIM recipe does the same), which makes the fit ~5x cheaper at 1 kHz.
        every = max(1, int(1.0 / (4.0 * cutoff_hz * exp.dt)))
        sl = slice(edge, exp.n - edge, every)
        qs.append(exp.q[sl])
        vs.append(v[sl])
        accs.append(a[sl])
        us.append(exp.u[sl])
    q, v, a, u = (torch.cat(x).to(torch.float64) for x in (qs, vs, accs, us))
    v_max = float(v.abs().max())
    if v_max == 0.0:
        raise TorchfricError(
            "the data never move (velocity is zero everywhere): the pre-fit needs an experiment "
            "that excites the motion; use model.init = 'config'"
        )
    moving = v.abs() > stick_fraction * v_max
    if int(moving.sum()) < 50:
        raise TorchfricError(
            f"only {int(moving.sum())} moving samples for the pre-fit; record a richer experiment "
            "or use model.init = 'config'"
        )
    return q[moving], v[moving], a[moving], u[moving]


def moving_samples(
    experiments: Sequence[Experiment], *, cutoff_hz: float | None = None,
    stick_fraction: float = 0.02,
) -> list[Tensor]:  # fmt: skip
    """Per experiment, `(n,)` bool: the samples where the axis moves by the pre-fit's rule,
    ``|q̇| > stick_fraction · max |q̇|`` with q̇ the zero-phase derivative at the pre-fit's cut-off
    (the maximum over all experiments). A static friction curve is a torque at a speed; while
    the axis sticks its friction is whatever balances the other forces, so a static model's
    errors there measure its failure to stick, not M or b (the prediction-error criterion
    leaves those samples out, `torchfric.estimators.covariance`)."""
    return stick_band(experiments, cutoff_hz=cutoff_hz, stick_fraction=stick_fraction)[1]


def stick_band(
    experiments: Sequence[Experiment], *, cutoff_hz: float | None = None,
    stick_fraction: float = 0.02,
) -> tuple[float, list[Tensor]]:  # fmt: skip
    """``(stick speed, moving_samples)``: the speed ``stick_fraction · max |q̇|`` below which
    the axis counts as stuck, and per experiment the samples above it, from one filtering."""
    exps = list(experiments)
    cutoff = default_cutoff_hz(max(e.dt for e in exps)) if cutoff_hz is None else cutoff_hz
    speeds = [zero_phase_derivative(e.q, e.dt, cutoff).abs() for e in exps]
    stick = stick_fraction * max(float(v.max()) for v in speeds)
    return stick, [v > stick for v in speeds]


def _linear_skeleton(
    model: ArmModel, q: Tensor, v: Tensor, a: Tensor, u: Tensor
) -> dict[str, float]:
    """Least squares for c_m u = M a + b v + Fc sign(v) [+ offset] [+ g sin q] [+ a |v|]."""
    c_m = float(model.c_m.detach())
    names = ["inertia", "viscous", "coulomb"]
    cols = [a, v, torch.sign(v)]
    _, arm = model.split(model.get_theta())
    if "offset" in arm:
        names.append("offset")
        cols.append(torch.ones_like(v))
    if "gravity" in arm:
        names.append("gravity")
        cols.append(torch.sin(q))
    if "asymmetric" in arm:
        names.append("asymmetric")
        cols.append(v.abs())
    sol, _ = _least_squares(cols, c_m * u)
    return dict(zip(names, sol.tolist(), strict=True))


def _least_squares(cols: list[Tensor], rhs: Tensor) -> tuple[Tensor, float]:
    """The coefficients of `cols` that fit `rhs` and the residual's RMS (columns scaled to unit
    peak first). driver="gelsd", not the default "gelsy": torch hands gelsy's pivot array
    (JPVT, read on entry) to LAPACK uninitialised (pytorch#71222), so its result depended on
    what the allocator's block held before: the pre-fit's θ changed from call to call."""
    A = torch.stack(cols, dim=1)
    scale = A.abs().amax(0).clamp_min(1e-300)
    sol = torch.linalg.lstsq(A / scale, rhs.unsqueeze(1), driver="gelsd").solution.squeeze(1)
    sol = sol / scale
    return sol, float((rhs - A @ sol).pow(2).mean().sqrt())


def _starts(model: ArmModel, lin: dict[str, float], v_scale: float) -> list[ArmModel]:
    """Initial models for LM: friction shapes at the data's velocity and torque scales."""
    fc = max(abs(lin["coulomb"]), 1e-3 * abs(lin["viscous"]) * v_scale, 1e-12)
    M = lin["inertia"] if lin["inertia"] > 0 else float(model.inertia.detach())
    b = lin["viscous"] if lin["viscous"] > 0 else 1e-3 * fc / v_scale
    fr = model.friction
    kind, size, kwargs = fr.kind, fr.size or 1, fr.init_kwargs()
    variants: list[dict[str, object]] = []
    if kind == "tanh":
        # Slopes spread from "almost viscous" to "sharp Coulomb" at a few overall scales.
        floor = float(kwargs.get("min_slope", 0.0))
        spreads = ((0.3, 100.0), (1.0, 300.0), (0.1, 30.0))
        if floor:
            # a bounded slope (`OddTanhFriction.min_slope`): spreads that start above the floor,
            # from just above it and from a few times it
            f = floor * v_scale
            spreads += tuple((a * f, b) for a in (1.2, 2.0, 4.0) for b in (10.0, 30.0, 100.0))
        for lo, hi in spreads:
            hi = max(hi, 10.0 * lo)
            w1 = torch.logspace(math.log10(lo), math.log10(hi), size, dtype=torch.float64) / v_scale
            w1 = torch.maximum(
                w1, 1.2 * floor * torch.linspace(1.0, 1.5, size, dtype=torch.float64)
            )
            variants.append({"w1": w1, "w2": torch.full((size,), fc / size, dtype=torch.float64)})
    elif kind == "polytopic":
        # Pair centres and centre-model widths over two decades of the velocity scale: a narrow
        # centre model (a steep slope through zero) is often the best start, and LM does not
        # reach it from a wide one.
        m = (size - 1) // 2
        for frac in (0.04, 0.13, 0.4):
            for width in (0.01, 0.04, 0.13):
                c = frac * v_scale * torch.arange(1, m + 1, dtype=torch.float64)
                variants.append(
                    {
                        "c": c,
                        "sigma": torch.cat([torch.tensor([(width * v_scale) ** 2]), c**2]),
                        "a": torch.cat(
                            [
                                torch.tensor([fc / (width * v_scale)]),
                                torch.full((m,), 1e-3 * fc / v_scale),
                            ]
                        ),
                        "b": torch.full((m,), fc),
                    }
                )
    elif kind == "coulomb":
        variants.append({"fc": fc})
    elif kind == "stribeck":
        variants.append({"fc": fc, "fs": 1.5 * fc, "vs": 0.05 * v_scale})
    out = []
    for extra in variants:
        friction = make_friction(kind, size, **{**kwargs, **extra})
        spec = model.spec()
        start = ArmModel(
            friction,
            inertia=M,
            viscous=b if spec["viscous_enabled"] else None,
            c_m=spec["c_m"],
            offset=lin.get("offset") if "offset" in spec["arm"] else None,
            gravity=(max(lin["gravity"], 1e-12) if "gravity" in lin else None)
            if "gravity" in spec["arm"]
            else None,
            asymmetric=lin.get("asymmetric") if "asymmetric" in spec["arm"] else None,
            estimate_c_m=spec["estimate_c_m"],
            log_positive=spec["log_positive"],
        )
        out.append(start)
    return out


def _slope_bounds(model: ArmModel, v_stick: float) -> tuple[Tensor, Tensor]:
    """Box on θ that keeps the friction's slope finite where the fit cannot see it.

    Stick samples are excluded, so a tanh slope W1 (or a polytopic variance) is unconstrained
    below the stick band and would run to a discontinuity that no explicit solver can
    simulate. The box lets the steepest neuron saturate within a tenth of the stick band
    (|W1| ≤ 10/v_stick) and keeps polytopic variances above (v_stick/10)².
    """
    k = model.num_parameters
    lo = torch.full((k,), -math.inf, dtype=torch.float64)
    hi = torch.full((k,), math.inf, dtype=torch.float64)
    names = model.theta_names
    mask = model.log_mask()
    floor = float(getattr(model.friction, "min_slope", 0.0))
    for i, name in enumerate(names):
        if name.startswith("W1[") and floor:
            # a bounded slope (stored as r, W1 = floor (1 + softplus(r/floor))): the upper bound
            top = torch.tensor([max(10.0 / v_stick, 2.0 * floor)], dtype=torch.float64)
            hi[i] = float(model.friction.flat_from_physical_w1(top)[0])  # type: ignore[operator]
            # and a lower one at W1 = 1.13 floor (r = −2 floor), off the flat end of the
            # softplus, where LM's steps in r would no longer move W1
            lo[i] = -2.0 * floor
        elif name.startswith("W1["):
            lo[i], hi[i] = -10.0 / v_stick, 10.0 / v_stick
        elif name.startswith("sigma"):
            floor = (v_stick / 10.0) ** 2
            lo[i] = math.log(floor) if bool(mask[i]) else floor
    return lo, hi


def _scale(model: ArmModel, arm: dict[str, Tensor]) -> Tensor:
    """The residual's factor on the acceleration error: M (a torque residual), or M / c_m
    when c_m is estimated (in units of u: a torque residual would fall to 0 as c_m, M, b and C
    shrink together)."""
    return arm["inertia"] / arm["c_m"] if model.estimate_c_m else arm["inertia"]


def _normal_equations(J: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """``JᵀJ`` `(S, k, k)` and ``Jᵀr`` `(S, k)`, start by start: the same products whether a
    start runs alone or in a batch (batched BLAS may sum in another order, and LM's trajectory
    carries the last bit into the fifth digit)."""
    return torch.stack([j.T @ j for j in J]), torch.stack(
        [j.T @ x for j, x in zip(J, r, strict=True)]
    )


def _per_start_solve(A: Tensor, b: Tensor) -> Tensor:
    """``A_s⁻¹ b_s`` for each start, one solve each (as `_normal_equations`)."""
    return torch.stack([torch.linalg.solve(a, x) for a, x in zip(A, b, strict=True)])


def _levenberg_marquardt(
    model: ArmModel,
    thetas: Tensor,
    q: Tensor,
    v: Tensor,
    a: Tensor,
    u: Tensor,
    iterations: int,
    v_stick: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Minimise ‖c_m u − M a − (b v + C(v) + offset + g sin q)‖² (÷ c_m² when c_m is estimated,
    `_scale`) over θ (estimation coords), projected onto `_slope_bounds`, from S starts
    `thetas (S, k)` at once.

    Each start runs its own Levenberg–Marquardt iteration (its own damping λ, its own stop)
    exactly as it would alone; the starts only share the batched arithmetic (`vmap`), which
    saves the per-operation overhead that dominates at this size. Returns θ `(S, k)`, the
    costs `(S,)` and the iterations each start used `(S,)`."""
    lo, hi = _slope_bounds(model, v_stick)
    x = torch.stack([q, v], dim=-1)

    def residual(theta: Tensor) -> Tensor:
        # The field times M is the net torque c_m u − friction − ...: residual = M·(q̈_model − q̈).
        _, arm = model.split(theta)
        return (model.vector_field(x, u, theta)[:, 1] - a) * _scale(model, arm)

    def sample_residual(theta: Tensor, x1: Tensor, u1: Tensor, a1: Tensor) -> Tensor:
        _, arm = model.split(theta)
        return (model.vector_field(x1, u1, theta)[1] - a1) * _scale(model, arm)

    # J's rows are per-sample gradients: one batched reverse pass over the samples
    # (`vmap(grad)`) gives the same Jacobian as `jacfwd` (to rounding) 3–4× faster here, where
    # forward mode through the friction falls back to Python decompositions. Faster still
    # (polytopic(3): 1.0 → 0.47 s for the whole pre-fit), the same per-sample gradient and
    # residual traced into generated C (`_native_rows`), with these as the fallback.
    per_sample = vmap(
        vmap(grad(sample_residual), in_dims=(None, 0, 0, 0)), in_dims=(0, None, None, None)
    )
    jacobian, residuals = _native_rows(
        model, sample_residual, x, u, a, lambda th: per_sample(th, x, u, a), vmap(residual)
    )

    theta = torch.maximum(torch.minimum(thetas, hi), lo)
    S = theta.shape[0]
    r = residuals(theta)
    cost = (r * r).sum(-1)
    lam = torch.full((S,), 1e-3, dtype=theta.dtype)
    active = torch.ones(S, dtype=torch.bool)
    used = torch.zeros(S, dtype=torch.long)
    for it in range(1, iterations + 1):
        idx = active.nonzero().flatten()
        if idx.numel() == 0:
            break
        used[idx] = it
        th, rr, c, la = theta[idx], r[idx], cost[idx], lam[idx]
        J = jacobian(th)
        JtJ, g = _normal_equations(J, rr)
        diag = torch.diagonal(JtJ, dim1=1, dim2=2)  # Marquardt's scaling, floored in its units
        damp = torch.diag_embed(torch.maximum(diag, 1e-12 * diag.amax(-1, keepdim=True)))
        searching = torch.ones(idx.numel(), dtype=torch.bool)
        rel = torch.zeros(idx.numel(), dtype=theta.dtype)
        for _ in range(10):
            step = _per_start_solve(JtJ + la[:, None, None] * damp, -g)
            cand = torch.maximum(torch.minimum(th + step, hi), lo)
            r_new = residuals(cand)
            c_new = (r_new * r_new).sum(-1)
            ok = searching & torch.isfinite(c_new) & (c_new < c)
            rel = torch.where(ok, (c - c_new) / c.clamp_min(1e-300), rel)
            th = torch.where(ok[:, None], cand, th)
            rr = torch.where(ok[:, None], r_new, rr)
            c = torch.where(ok, c_new, c)
            la = torch.where(ok, (la / 3.0).clamp_min(1e-9), torch.where(searching, la * 4.0, la))
            searching = searching & ~ok
            if not bool(searching.any()):
                break
        theta[idx], r[idx], cost[idx], lam[idx] = th, rr, c, la
        # a start stops when no damping improved it or the improvement became negligible
        active[idx] = ~searching & (rel >= 1e-8)
    return theta, cost, used


# Generated per-sample rows, per model structure (θ is an input): (model, grad rows, values).
_ROW_CHUNKS: dict[str, tuple] = {}


def _native_rows(
    model: ArmModel, sample_residual, x: Tensor, u: Tensor, a: Tensor, jacobian, residuals
):  # type: ignore[no-untyped-def]
    """``(jacobian(θ), residuals(θ))`` for starts θ `(S, k)`: the per-sample gradients
    `(S, N, k)` and residuals `(S, N)` of `sample_residual` over the samples ``(x, u, a)`` as
    generated C (`torchfric.native`: the starts as members, the N samples as the loop), equal
    to the `vmap` forms to rounding. Each uses its given `vmap` form instead, from then on, if
    the translation fails or there is no C compiler. The generated code is kept per model
    structure, so later pre-fits of the same structure do not trace again."""
    from ..accel import step_key, structure_key
    from ..accel.native import NativeUnavailable, make_native_chunk

    key = structure_key(model)
    if key not in _ROW_CHUNKS:

        def grad_row(dummy, x1, u1, a1, theta):  # type: ignore[no-untyped-def]
            return (dummy,), (grad(sample_residual)(theta[0], x1, u1, a1).unsqueeze(0),)

        def value_row(dummy, x1, u1, a1, theta):  # type: ignore[no-untyped-def]
            return (dummy,), (sample_residual(theta[0], x1, u1, a1).unsqueeze(0),)

        _ROW_CHUNKS[key] = (model, *(
            make_native_chunk(f, members=True, member_consts=(True,),
                              key=step_key(f"prefit {f.__name__}", key))
            for f in (grad_row, value_row)))  # fmt: skip
    _, grad_chunk, value_chunk = _ROW_CHUNKS[key]
    valid = torch.ones(x.shape[0], dtype=torch.bool)

    def native(chunk, fallback):  # type: ignore[no-untyped-def]
        broken: list[bool] = []

        def evaluate(theta: Tensor) -> Tensor:
            if not broken:
                try:
                    dummy = (theta.new_zeros(theta.shape[0], 1),)
                    _, (out,) = chunk(dummy, (x, u, a), valid, (theta,))
                    return out.transpose(0, 1)  # (N, S, ...) -> (S, N, ...)
                except NativeUnavailable:
                    broken.append(True)
            return fallback(theta)

        return evaluate

    return native(grad_chunk, jacobian), native(value_chunk, residuals)


INERTIA_SHARE = 1e-6
"""The least share of ‖c_m u‖ that the pre-fit's M ‖q̈‖ may carry: a robot joint's record in
degrees read as rad, its 12 N m of gravity unmodelled, drove M to 7.9e-67 (1e-66 of it), and
`check` passed it on."""


def prefit(
    model: ArmModel,
    experiments: Experiment | Sequence[Experiment],
    *,
    cutoff_hz: float | None = None,
    stick_fraction: float = 0.02,
    iterations: int = 50,
) -> PrefitResult:
    """Initial θ for `model` from the data by inverse-dynamics least squares.

    Args:
        model: the arm whose structure (friction kind/size, enabled terms, c_m) is kept; its
            values are replaced. Not modified.
        experiments: identification data (positions q and inputs u; velocity is re-derived).
        cutoff_hz: zero-phase low-pass cut-off for velocity and acceleration; ``None`` =
            `default_cutoff_hz` of the coarsest sample step (50 Hz at 1 kHz, 0.4 × Nyquist for
            slowly sampled records such as the 40 Hz unbalanced disc), lowered until the
            records' position noise is at most 2 % of q̈'s variance (`quiet_cutoff_hz`: every
            shipped record keeps the default).
        stick_fraction: samples with ``|q̇| < stick_fraction · max|q̇|`` are left out.
            At most `PREFIT_ROWS` of the rest are fitted (every s-th on longer records).
        iterations: Levenberg–Marquardt iterations per start.

    Returns:
        `PrefitResult` with a new model holding the pre-fitted θ.
    """
    exps = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    if not exps:
        raise TorchfricError("prefit needs at least one experiment")
    if cutoff_hz is None:  # lowered where the encoder's noise would bias the inertia, while
        highest = default_cutoff_hz(max(e.dt for e in exps))  # the filter's ends (3 periods
        lowest = max(12.0 / (e.n * e.dt) for e in exps)  # each) leave half of every record
        cutoff_hz = quiet_cutoff_hz([(e.q, e.dt) for e in exps], highest, lowest=lowest)
    q, v, a, u = _regression_data(exps, cutoff_hz, stick_fraction)
    stride = -(-q.numel() // PREFIT_ROWS)  # 1 below the cap: every row, bit for bit as before
    if stride > 1:
        q, v, a, u = (x[::stride].contiguous() for x in (q, v, a, u))
    v_stick = stick_fraction * float(v.abs().max())
    lin = _linear_skeleton(model, q, v, a, u)
    v_scale = float(torch.quantile(v.abs(), 0.95))
    starts = _starts(model, lin, v_scale)
    thetas, costs, used = _levenberg_marquardt(
        starts[0], torch.stack([s.get_theta().detach() for s in starts]), q, v, a, u,
        iterations, v_stick,
    )  # fmt: skip
    best: tuple[float, ArmModel, int] | None = None
    for start, theta, cost, its in zip(starts, thetas, costs.tolist(), used.tolist(), strict=True):
        if math.isfinite(cost) and (best is None or cost < best[0]):
            best = (cost, copy.deepcopy(start).set_theta(theta), its)
    if best is None:
        raise TorchfricError(
            "the pre-fit failed to find finite parameters; use model.init = 'config'"
        )
    cost, fitted, its = best
    c_m = float(model.c_m.detach())
    inertia = fitted.physical_parameters()["inertia"]
    carried = inertia * float(a.norm()) / max(float((c_m * u).norm()), 1e-300)
    if not carried >= INERTIA_SHARE:  # M → 0: the record's c_m·u is not an inertia's
        raise TorchfricError(
            f"the pre-fit drove the inertia to {inertia:.3g}, where M·q̈ carries {carried:.1e} "
            "of c_m·u: the record's input is not explained by an inertia (q or t in other units "
            "than the config says, a wrong c_m, or a large missing term such as gravity or an "
            "offset); check data.position_unit, data.time_unit, model.c_m and the notes of "
            '`torchfric init`, or start from the config\'s values with model.init = "config"'
        )
    c_fit = float(fitted.c_m.detach()) if model.estimate_c_m else 1.0  # torque units
    rms = c_fit * math.sqrt(cost / q.numel())
    rel = c_fit * math.sqrt(cost) / max(float((c_m * u).norm()), 1e-300)
    return PrefitResult(fitted, rms, rel, q.numel(), its, cutoff_hz)
