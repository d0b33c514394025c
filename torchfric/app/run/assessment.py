"""Judging a run's model: open-loop scores, the warnings about a doubtful result, provenance."""

from __future__ import annotations

from typing import Any

import torch

from ...data import Experiment
from ...errors import TorchfricError
from ...estimators.metrics import SimulationScore, score_simulation
from ...estimators.settings import data_speeds, speed_quantiles
from ...models.arm import ArmModel
from ...models.simulate import AUTO_SUBSTEPS, filter_substeps
from ..artifacts import read_checkpoint
from ..config import Config

__all__ = [
    "evaluate_model", "missing_terms", "needed_terms", "result_warnings", "provenance",
    "scoring_engine",
]  # fmt: skip


def scoring_engine(cfg: Config) -> str:
    """The engine a run scores open-loop simulations with: the compiled twin of odeint's rk4
    (the same steps) when the compiled paths are on (`estimator.compile`), else odeint."""
    return "compiled" if cfg.estimator.compile else "odeint"


def evaluate_model(
    model: ArmModel, exps: list[Experiment], cfg: Config
) -> dict[str, SimulationScore]:
    """Open-loop simulation scores of `model` on each record, by record name."""
    out = {}
    for e in exps:
        out[e.name] = score_simulation(
            model,
            e,
            method=cfg.simulation.method,
            substeps=cfg.simulation.substeps,
            engine=scoring_engine(cfg),
        )
    return out


def _bound_warnings(cfg: Config, final: ArmModel, inertia: float) -> list[str]:
    """A parameter at the search bound, or no inertia: the model is not physical."""
    theta = final.get_theta().detach()
    bound = cfg.estimator.theta_bound
    at_bound = [
        n for n, v in zip(final.theta_names, theta.tolist(), strict=True) if abs(v) >= 0.5 * bound
    ]
    if at_bound or not inertia > 1e-12:
        return [
            f"parameter(s) {', '.join(at_bound) or 'inertia'} at a bound (|θ| near "
            f"estimator.theta_bound = {bound:g}, or inertia ≈ 0): the model is not physical"
        ]
    return []


def _v95(train: list[Experiment]) -> float:
    """The records' 95th-percentile |q̇|, as `velocity_scale` reads it (0 without records)."""
    found = speed_quantiles(data_speeds(train), [0.95])
    return found[0] if found else 0.0


def _active_friction(final: ArmModel, speed: float, compared: bool = False) -> list[str]:
    """Friction that drives the axis instead of braking it: the steady-state friction's odd
    part (offset and asymmetric slope are even) below zero somewhere in ``0 < q̇ <= speed``
    (the records' v95; beyond 0.1 % of its largest value, against rounding). A passive
    friction has ``F q̇ >= 0``; a static curve fitted to a record that sticks can draw the stick
    as a negative lobe near rest (a belt-driven stage of a user walk: −4.7 N below 2.4 mm/s,
    where its static friction is +9 N), which simulates as a push at every start. Where
    `model.dynamic = "auto"` has compared LuGre and kept the static model (`compared`), LuGre
    is not what to try: the line says the curve there draws the stick."""
    if not speed > 0:
        return []
    v = torch.logspace(-5.0, 0.0, 501, dtype=torch.float64) * speed
    with torch.no_grad():
        odd = 0.5 * (final.friction_torque(v) - final.friction_torque(-v))
    low = odd < -1e-3 * float(odd.abs().max())
    if not bool(low.any()):
        return []
    where = v[low]
    advice = (
        'model.dynamic = "auto" compared LuGre on these records and kept the static model, so '
        "below that speed the curve is the stick drawn, not friction: a simulation that starts "
        "from rest is pushed there"
        if compared
        else 'try model.dynamic = "lugre", whose bristles hold it'
    )
    return [
        f"the friction curve pushes the axis instead of braking it at {float(where.min()):.3g} "
        f"<= |q̇| <= {float(where.max()):.3g} (down to {float(odd.min()):.3g}): friction there "
        "feeds energy in, which a real machine's cannot; a static curve fitted to a record that "
        f"sticks draws the stick this way: {advice}"
    ]


def _uninformed(
    cfg: Config, final: ArmModel, covariance: Any, start: ArmModel | None, metrics: dict[str, Any]
) -> list[str]:
    """Parameters the data did not inform: their σ after the passes is still ≥ 90 % of the
    start's (the filter's prior, `EKFTuning.initial_P_theta` at the starting θ). Those held at
    their bound or as a step are left out (identifiability says so), and where the run reports the
    sandwich's σ (`metrics` ``covariance``) the ± are not the prior's."""
    if covariance is None or start is None or cfg.estimator.method != "ekf":
        return []
    ident = metrics.get("identifiability") or {}
    held = set(ident.get("held_at_bound") or []) | set(ident.get("held_steep") or [])
    P = torch.as_tensor(covariance, dtype=torch.float64)
    P0 = cfg.estimator.ekf_tuning().initial_P_theta(start, start.get_theta())
    prior, now = torch.diagonal(P0).sqrt(), torch.diagonal(P).clamp_min(0.0).sqrt()
    names = [
        n
        for n, a, b in zip(final.theta_names, prior.tolist(), now.tolist(), strict=True)
        if a > 0 and b >= 0.9 * a and n not in held
    ]
    if not names:
        return []
    which = "σ is" if len(names) == 1 else "σ are"
    shown = (
        "the ± shown are the data's (the run's covariance)"
        if metrics.get("covariance")
        else "so the ± shows the prior, not what the data say"
    )
    return [
        f"the data hardly informed {', '.join(names)}: the filter's {which} still at least 90 % "
        f"of its prior (estimator.p0_theta); {shown}; a smaller model (model.size) or richer "
        "excitation would pin them down"
    ]


def _below_constant(cfg: Config, metrics: dict[str, Any]) -> list[str]:
    """`result_warnings`' lines on records whose open-loop simulation scores a FIT on q below 0
    (or none at all)."""
    out: list[str] = []
    for group in ("validation", "test", "identification"):
        for name, m in metrics.get(group, {}).items():
            fit = m.get("fit_q")
            if fit is None or not fit == fit or fit < 0.0:
                hint = (
                    "; when the simulation drifts one way, a constant force or torque may be "
                    "missing (gravity on a tilted axis, a cable, an amplifier offset): try "
                    "--set model.offset=0.0"
                    if cfg.model.offset is None
                    else ""
                )
                fv = m.get("fit_qdot")
                speed = "" if fv is None or not fv == fv else f" (FIT on q̇ {fv:.1f} %)"
                out.append(
                    f"{group} {name}: FIT on q is {fit if fit is None else f'{fit:.1f} %'} (below 0: "
                    f"worse than a constant); the model's open-loop simulation does not follow "
                    f"this record{hint}. A record of an axis that sticks drifts so even under its "
                    f"true model (each error in where it stops adds to the next): judge by the "
                    f"report's validation figure and the speeds{speed} too"
                )
    return out


PREFIT_SHARE = 0.25
"""The relative distance between the run's inertia and the pre-fit's beyond which, with the two
more than 2 of the run's σ apart, the summary warns (`_inertia_from_start`). Measured: the
shipped ensemble and filter configs' runs lie 1.1–1.7 % from their pre-fits (the rig's LuGre
model 1.1 %, 9.5 σ: the static pre-fit's own bias; EMPS 1.6 %, the disc 1.4 %), HSM150's 3.2×
(the 3× warning's); a user walk's LuGre Z axis (3.2 kg) 36–59 % above its pre-fit on five of
six seeds and 8.2× on the sixth, where the pre-fit was within 0.9–6.3 % of the truth, and a
LuGre run forced on it 62 % below with a σ of 0.006 %. A run without σ (its covariance stage
failed) is not judged by it."""


def _inertia_from_start(metrics: dict[str, Any], init_kind: str) -> list[str]:
    """`result_warnings`' lines on an inertia far from the run's start: more than 3× from it, or,
    from a pre-fit, more than `PREFIT_SHARE` and 2 σ: two estimates of one mass from the same
    records (the pre-fit's inverse dynamics need no filter tuning) that the σ do not hold."""
    inertia, first = metrics["inertia"], metrics.get("initial_inertia")
    source = "pre-fit" if init_kind == "prefit" else "initial value"
    if not first or not inertia > 0:
        return []
    if max(inertia / first, first / inertia) > 3.0:
        better = ("; where those are right, the pre-fit may be the better estimate: compare the "
                  "start's and the kept model's figures in report.html") if init_kind == "prefit" else ""  # fmt: skip
        return [
            f"inertia {inertia:.4g} is {inertia / first:.3g}× the {source}'s {first:.4g}: the "
            "estimate moved far from what the data's inverse dynamics say; check model.c_m, the "
            "units of t (seconds) and q (data.position_unit), and the filter's tuning "
            f"(estimator.r, estimator.p0_theta){better}"
        ]
    std = ((metrics.get("parameters") or {}).get("inertia") or {}).get("std")
    share = inertia / first - 1.0
    apart = bool(std) and abs(share) > PREFIT_SHARE and abs(inertia - first) > 2 * std
    if init_kind != "prefit" or not apart:
        return []
    return [
        f"inertia {inertia:.4g} ± {std:.2g} is {share:+.0%} from the pre-fit's {first:.4g} "
        f"({(inertia - first) / std:+.3g} σ): two estimates of one mass from the same records "
        "disagree beyond the σ, and the σ do not hold that; the pre-fit (inverse dynamics, no "
        "filter tuning) can be the better one, as on a user's LuGre axis where it was within 6 "
        "% and the filter 40–63 % off: compare the start's and the kept model's figures in "
        "report.html, and try model.dynamic, model.size or estimator.r"
    ]


def result_warnings(
    cfg: Config,
    final: ArmModel,
    metrics: dict[str, Any],
    init_kind: str,
    *,
    covariance: Any = None,
    start: ArmModel | None = None,
    train: list[Experiment] | None = None,
) -> list[str]:
    """Plain warnings about a result that is almost certainly wrong, or a part of it the data
    did not inform (`metrics.json` "warnings"). `covariance` is the kept pass's P_θθ and `start`
    the model the estimator started from (for the parameters the data left at their prior);
    `train` the identification records (the curve is checked up to their 95th-percentile |q̇|)."""
    out = _inertia_from_start(metrics, init_kind)
    out += _bound_warnings(cfg, final, metrics["inertia"])
    out += missing_terms(cfg, final, train or [])
    v95 = _v95(train or [])
    compared = (metrics.get("dynamics") or {}).get("chosen") == "none"
    out += _active_friction(final, v95, compared)
    out += _uninformed(cfg, final, covariance, start, metrics)
    out += _below_constant(cfg, metrics)
    out += _coarse_filter(cfg, final, metrics, train or [])
    if (
        cfg.estimator.tolerance > 0  # tolerance 0 asks for exactly `passes` passes
        and metrics.get("converged") is False
        and metrics.get("passes", 0) >= cfg.estimator.passes
    ):
        gain = metrics.get("last_gain")
        moving = f" by {gain:.3g} nats" if gain is not None else ""
        out.append(
            f"stopped at the pass limit (estimator.passes = {cfg.estimator.passes}) with the "
            f"innovation log-likelihood still rising{moving} a pass, above estimator.tolerance "
            f"{cfg.estimator.tolerance:g} × {final.num_parameters} parameters = "
            f"{cfg.estimator.tolerance * final.num_parameters:.3g} nats: raise estimator.passes "
            f"(each pass over {metrics.get('samples_per_pass', 'the')} samples is cheap); the "
            f"kept pass stands meanwhile{_noisy_velocity(cfg, train or [], v95)}"
        )
    ident = metrics.get("identifiability") or {}
    out += [m for m in ident.get("messages", []) if not m.startswith("(within")]
    out += metrics.get("covariance_warnings", [])
    out += metrics.get("selection_warnings", [])
    far = _far_from_maximum(final, metrics)
    if far:
        out.append(far)
    spread = (metrics.get("covariance") or {}).get("member_spread")
    if spread:
        worst = spread["worst"]
        out.append(
            f"ensemble member {worst['member']} simulates within {spread['near_fit']:g} FIT "
            f"points of the kept one with {worst['parameter']} {worst['sigmas']:.0f} σ away: "
            "the estimate depends on the filter's tuning far beyond the sandwich's σ, "
            "a sign that the model class does not hold this machine (a friction law it cannot "
            "draw, a missing term); the ± σ include the near members' spread"
        )
    return out


def _coarse_filter(
    cfg: Config, final: ArmModel, metrics: dict[str, Any], train: list[Experiment]
) -> list[str]:
    """The warning when the kept model is stiffer than the filter's RK4 step holds:
    `filter_substeps` at the kept θ above the sub-steps the passes ran (the config's count, or
    under ``"auto"`` the last pass's, metrics ``substeps``)."""
    used = metrics.get("substeps", cfg.estimator.substeps)
    if cfg.estimator.method != "ekf" or not train or not isinstance(used, int):
        return []
    need = filter_substeps(final, max(e.dt for e in train), max_substeps=64)  # past auto's cap
    if need <= used:
        return []
    return [
        f"the kept model is stiffer than the filter's step holds: RK4 needs {need} steps per "
        f"sample to stay stable on its steepest friction slope, the passes ran {used} "
        "(estimator.substeps); a filter that cannot follow its model can move θ away from "
        "stiff friction (on one Stribeck axis: inertia +14 %, docs/results.md): rerun with "
        f"estimator.substeps = {need}"
        + (', or "auto" with model.init = this run\'s checkpoint' if need <= AUTO_SUBSTEPS else "")
    ]


def needed_terms(experiments: list[Experiment], c_m: float, rotary: bool) -> dict[str, tuple]:
    """The white-box terms of `torchfric.estimators.settings.static_terms` that take at least
    `OFFSET_SHARE` of the residual:
    ``{"offset": (constant, share), "gravity": (g, q0, share, at_zero)}``, ``at_zero`` when the
    lowest point q0 lies within `GRAVITY_PHASE` of q = 0 (``model.gravity``'s ``g_c sin q``
    takes q = 0 hanging down). With a gravity term that `init` turns on (``at_zero``) the offset
    comes too, as the constant fitted beside it and a share of None. Empty for records that never
    move. What `init` turns on and `check`/`train` warn of (`torchfric.app.commands.columns.terms_found`, `missing_terms`)."""
    from ...estimators.settings import GRAVITY_PHASE, OFFSET_SHARE, static_terms

    try:
        (force, share), arm = static_terms(experiments, c_m, rotary)
    except TorchfricError:  # never moves: the pre-fit and check say so
        return {}
    found: dict[str, tuple] = {}
    if arm is not None and arm[2] >= OFFSET_SHARE:
        found["gravity"] = (*arm[:3], abs(arm[1]) <= GRAVITY_PHASE)
    if "gravity" in found and found["gravity"][3]:
        # beside an arm's gravity (on: q = 0 at the bottom) a constant goes with it (a cable,
        # a spring, friction that differs by direction: its mean while moving): the robot
        # joint of docs/results.md (0.2 of 12 N m, 0.1–3 % of the residual) without it: M
        # +16 %, b −18 %
        found["offset"] = (arm[3], None)
    elif share >= OFFSET_SHARE:
        found["offset"] = (force, share)
    return found


def missing_terms(cfg: Config, model: ArmModel, train: list[Experiment]) -> list[str]:
    """Warnings for white-box terms the records' inverse dynamics ask for and the model lacks
    (`torchfric.estimators.settings`, each taking at least `OFFSET_SHARE` of the residual):
    a constant force without ``model.offset`` (a vertical axis's gravity, EMPS's and HSM150's
    offsets; a 12-kg vertical axis without it ran to an inertia of 7e42 and a validation FIT
    of −50 %), an unbalanced arm's ``g sin(q − q0)`` without ``model.gravity``."""
    import math

    from ...data.units import force_unit

    m, out = cfg.model, []
    if not train or (
        m.offset is not None and (m.gravity is not None or cfg.data.axis_unit != "rad")
    ):
        return out
    needed = needed_terms(train, float(model.c_m.detach()), cfg.data.axis_unit == "rad")
    if m.offset is None and "offset" in needed:
        force, share = needed["offset"]
        how = (
            f"terms: a constant takes {share:.0%} of the residual"
            if share is not None
            else "terms and an unbalanced arm's torque g·sin(q − q0), beside which a constant "
            "goes (a cable, a spring, friction that differs by direction)"
        )
        out.append(
            f"the records' inverse dynamics leave a constant {force:.4g} "
            f"{force_unit(cfg.data.axis_unit)} (c_m·u fitted by inertia, viscous and Coulomb "
            f"{how}); the model has no offset term, so the friction curve and the inertia take "
            "it up: set model.offset = 0.0 (gravity on a vertical or tilted axis, a cable, an "
            "amplifier offset)"
        )
    if "gravity" in needed and m.gravity is None:
        g, q0, share, at_zero = needed["gravity"]
        fix = (
            f"set model.gravity = {g:.3g}"
            if at_zero
            else "re-zero q at the lowest point and set model.gravity (g_c sin q takes q = 0 "
            "hanging straight down)"
        )
        out.append(
            f"the records' inverse dynamics carry a torque {g:.3g}·sin(q − q0), lowest at "
            f"q0 = {math.degrees(q0):.0f}° (it takes {share:.0%} of the residual), as an "
            f"unbalanced arm does, and the model has no gravity term: {fix}"
        )
    return out


def _noisy_velocity(cfg: Config, train: list[Experiment], v95: float) -> str:
    """For the not-converged warning: where the velocity the filter measures is noisy
    (`torchfric.data.velocity.quieter_cutoff_hz`: a coarse encoder), the cut-off to try."""
    from ...data.velocity import DEFAULT_CUTOFF_HZ, quieter_cutoff_hz

    method = cfg.data.velocity
    if method not in DEFAULT_CUTOFF_HZ or not train:
        return ""
    cutoff = cfg.data.velocity_cutoff_hz or DEFAULT_CUTOFF_HZ[method]
    longest = max(train, key=lambda e: e.n)
    found = quieter_cutoff_hz(longest.q, longest.dt, method, cutoff, v95)
    if found is None:
        return ""
    share, quieter = found
    return (
        f"; the velocity the filter measures carries noise of {share:.1%} of the data's v95 "
        f'(data.velocity = "{method}" at {cutoff:g} Hz, from the position\'s steps), which '
        f"can bias it away: try data.velocity_cutoff_hz = {quieter:g}"
    )


def _far_from_maximum(final: ArmModel, metrics: dict[str, Any]) -> str | None:
    """A white-box parameter whose kept value is more than 2 σ from the optimum of the error
    criterion its σ belongs to (one Newton step away, `PEMCovariance.newton`)."""
    cov = metrics.get("covariance") or {}
    steps = cov.get("newton_step_sigma")
    if not steps:
        return None
    far = [
        f"{n} ({s:+.1f} σ)"
        for n, s in zip(cov.get("names", []), steps, strict=False)
        if n in ("inertia", "viscous", "offset", "gravity", "asymmetric") and abs(s) > 2.0
    ]
    if not far:
        return None
    if "offset_to_optimum" in cov:  # the ± σ include the distance (`offset_covariance`)
        tail = ", in σ of that optimum; it simulates better and was kept, and its ± σ include that distance"
    else:
        tail = "; its ± σ describe the spread around that optimum, so the error may exceed them"
    return (
        f"the kept θ is not at the optimum of its error criterion ({cov.get('method')}): "
        f"{', '.join(far)} away{tail}"
    )


def provenance(cfg: Config, init_kind: str) -> str:
    """Which estimator(s) produced the model: this run's, after a warm start's chain."""
    method = cfg.estimator.method
    if init_kind.startswith("checkpoint:"):
        raw = read_checkpoint(init_kind[len("checkpoint:") :])
        before = raw.get("metrics", {}).get("estimator") or raw.get("estimator", {}).get("method")
        if before:
            return f"{before}+{method}"
    return method
