"""The ± σ a run reports, made after the estimator (issue 31).

An EKF run ends with the filter's own ``P_θθ``; on an independent axis its σ were 10–1000×
narrower than the real error (it has absorbed the data once per pass under an assumed noise
model). `attach_covariance` replaces it, in the run's estimator state, by the prediction-error
stage of `torchfric.estimators.covariance`, with θ fixed and q the one measurement
(`_position_only`):

1. the noise model: the likeliest Q and R factors over a grid (`noise_model`; of the three
   likeliest, the first whose filter stays healthy), among those whose process noise over one
   sample stays below a hundredth of R (``step_ratio``, `NOISE_STEP_LIMIT`);
2. the polish: Gauss–Newton steps from the kept θ to the prediction-error estimate
   (`pem_refine`), kept only when it simulates the validation records (else the
   identification records) no worse than the kept θ by 0.1 point; otherwise θ stays. A static
   model's criterion leaves out the samples where the axis sticks, and a tanh neuron that is
   a step at every faster speed keeps its steepness (`_stick`, `sandwich.held_entries`);
3. the sandwich covariance at the reported θ (`pem_covariance`) plus the outer product of
   its offset from the run's other estimate (`offset_covariance`): the optimum's when the
   polish was rejected (its end plus the Gauss–Newton step still left there), the filter's
   kept pass when it was kept.

The filter's own matrix stays beside it (``filter_P_theta``), so does the kept pass's θ when
the polish moved it (``filter_theta``) and the kept member's tuning in absolute units
(``tuning``: what `torchfric track` runs). Everything that shows a σ (summary, metrics,
report, the curve's band, `evaluate`) reads ``P_theta`` and so shows the new one. An
output-error run gets the sandwich of its own criterion (`attach_oe_covariance`).

metrics.json gains ``covariance`` (method, samples, blocks, the bandwidth, the correlation
matrix, the noise model, the Newton step to the criterion's optimum in σ units, the offset:
``offset_to_optimum`` or ``offset_to_filter``), ``polished``
or ``polish_rejected``, and ``identifiability`` (groups of parameters the data cannot
separate, by name: the covariance's, and the tanh neurons that take part of b over the
identification data's speeds, `viscous_share`; `run_identifiability` joins them).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import torch

from ...data import Experiment
from ...errors import TorchfricError
from ...estimators.covariance import noise_model, pem_covariance, pem_refine, step_ratio
from ...estimators.passes import DIVERGED
from ...estimators.prefit import stick_band
from ...estimators.propagation import resolve_substeps
from ...estimators.sandwich import Identifiability, PEMCovariance, viscous_share
from ...estimators.settings import data_speeds
from ...estimators.uncertainty import physical_std
from ...models.arm import ArmModel
from ..config import Config

__all__ = [
    "attach_covariance",
    "attach_oe_covariance",
    "covariance_at",
    "member_spread",
    "near_members",
    "offset_covariance",
    "prediction_error",
    "PredictionError",
    "run_identifiability",
    "PHYSICAL",
]

PHYSICAL = ("inertia", "viscous", "offset", "gravity", "asymmetric", "c_m", "lugre_")
"""White-box names: a non-identifiable direction that involves one of them is a warning; one
inside the black-box curve alone (two neurons that trade off) is a note."""


def attach_covariance(
    cfg: Config,
    final: ArmModel,
    train: list[Experiment],
    state: dict[str, Any],
    extra: dict[str, Any],
    say: Callable[[str], None],
    validation: list[Experiment] | None = None,
) -> None:
    """Replace ``state["P_theta"]`` by the sandwich covariance at ``state["theta"]`` and add
    ``covariance`` and ``identifiability`` to `extra` (see the module docstring). When it
    cannot be computed, the filter's matrix stays and a warning says why. An ensemble's
    near members (``extra["near_members"]``, `near_members`; taken out of `extra`) may widen
    the σ (`member_spread`)."""
    near = extra.pop("near_members", None) or []
    run_tuning = _kept_substeps(cfg, final, train, extra, say).resolved(train)
    tuning = _position_only(run_tuning)
    q_scale, r_scale = extra.get("tuning_scales", (1.0, 1.0))
    theta = torch.as_tensor(state["theta"], dtype=torch.float64)
    P_filter = torch.as_tensor(state["P_theta"], dtype=torch.float64)
    # the kept member's filter, in absolute units: what `torchfric track` runs
    state["tuning"] = _tuning_dict(dataclasses.replace(
        run_tuning, q_state=tuple(q_scale * x for x in run_tuning.q_state),  # type: ignore[arg-type]
        r=tuple(r_scale * x for x in run_tuning.r)))  # fmt: skip
    try:
        found = prediction_error(final, train, tuning, theta, q_scale, r_scale)
    except TorchfricError as failure:
        extra.setdefault("covariance_warnings", []).append(
            f"the ± σ are the filter's own P_θθ (too narrow as a rule): {failure}"
        )
        return
    at_kept, polished, pem, trace = found.at_kept, found.polished, found.pem, found.trace
    moving, q_scale, r_scale = found.moving, found.q_scale, found.r_scale
    judged = validation or train
    offset = None
    if (
        len(trace) > 1
        and _score(cfg, final, polished, judged) < _score(cfg, final, theta, judged) - 0.1
    ):
        # The one-step prediction error's optimum simulates worse (a class that cannot reach
        # the machine, e.g. a static curve for LuGre friction, trades the long horizon for the
        # short one): the kept θ stays, its σ the sandwich's at it plus its offset from the
        # optimum (`offset_covariance`, `PredictionError.offset_from`); a warning:
        # `newton_step_sigma`.
        extra["polish_rejected"] = {"steps": len(trace) - 1, "loglik_gain": trace[-1] - trace[0]}
        say("  prediction-error polish simulated worse and was not kept")
        pem, offset = at_kept, found.offset_from(final, theta)
    elif len(trace) > 1:  # the prediction-error optimum: the model moves there
        # Its σ include its distance from the filter's kept pass (`offset_covariance`): about
        # σ where the class holds the machine, the size of its bias where it does not.
        final.set_theta(polished)
        state["filter_theta"], state["theta"] = theta, polished.clone()
        offset = pem.determined(physical_offset(final, polished, theta))
        extra["polished"] = {"steps": len(trace) - 1, "loglik_gain": trace[-1] - trace[0]}
        say(
            f"  prediction-error polish: {len(trace) - 1} Newton step(s) from the kept pass, "
            f"innovation log-likelihood +{trace[-1] - trace[0]:.3g}"
        )
    state["filter_P_theta"] = P_filter
    state["P_theta"] = pem.cov if offset is None else offset_covariance(pem.cov, offset)
    noise = _noise_dict(tuning, q_scale, r_scale, train)
    extra["covariance"] = {**pem.to_dict(), "noise_model": noise}
    if moving is not None:  # the share of samples left out of the criterion
        extra["covariance"]["stuck_left_out"] = 1 - sum(int(m.sum()) for m in moving) / pem.samples
    if offset is not None:
        where = "offset_to_filter" if "polished" in extra else "offset_to_optimum"
        extra["covariance"][where] = offset.tolist()
    spread = member_spread(final, torch.as_tensor(state["theta"]), state["P_theta"], near)
    if spread is not None:
        state["P_theta"], extra["covariance"]["member_spread"] = spread
        worst = spread[1]["worst"]
        say(f"  covariance: ensemble member {worst['member']} simulates nearly as well with "
            f"{worst['parameter']} {worst['sigmas']:.0f} σ away; the σ include the near "
            "members' spread")  # fmt: skip
    ident = run_identifiability(final, pem, train)
    extra["identifiability"] = {**ident.to_dict(), "messages": _messages(ident)}
    notes = "" if ident.ok else f"; {len(_messages(ident))} identifiability note(s)"
    notes += _stuck_note(extra["covariance"])
    say(f"  covariance: prediction-error sandwich over {pem.samples} samples "
        f"({pem.blocks} blocks, bandwidth {pem.bandwidth}){notes}")  # fmt: skip


@dataclasses.dataclass
class PredictionError:
    """The prediction-error stage at a θ (`prediction_error`): the sandwich there (`at_kept`),
    the polish's end (`polished`) with its sandwich (`pem`, whose ``newton`` is the step still
    left) and log-likelihood trace, the stuck samples left out, the noise model's factors."""

    at_kept: PEMCovariance
    polished: torch.Tensor
    pem: PEMCovariance
    trace: list[float]
    moving: list[torch.Tensor] | None
    q_scale: float
    r_scale: float

    def offset_from(self, model: ArmModel, theta: torch.Tensor) -> torch.Tensor:
        """θ's offset from the criterion's optimum: the polish's end and the Gauss–Newton step
        still left there (its budget ran out, ℓ still rising), measured as `physical_offset`
        and along the directions the information at θ determines (`PEMCovariance.determined`)."""
        optimum = self.polished + self.pem.newton
        return self.at_kept.determined(physical_offset(model, theta, optimum))


def physical_offset(model: ArmModel, theta: torch.Tensor, other: torch.Tensor) -> torch.Tensor:
    """``other − theta`` as the distance of their physical values, in θ's coordinates by the
    delta method's scale at `theta` (`ArmModel.physical_slope`, how the σ are reported), so a
    reported σ² is the sandwich's plus the square of that physical distance. A log-scaled b
    that the other estimate drives to 0 is 1 (all of b) away, not the 4e138 of log b that a
    polish walking off along a flat likelihood reached on a ball-screw table. Entries without
    a slope, or whose physical distance is not finite, keep ``other − theta``."""
    slope = model.physical_slope(theta)
    dist = model.to_physical(other) - model.to_physical(theta)
    usable = (slope.abs() > 0) & torch.isfinite(dist)
    return torch.where(usable, dist / torch.where(usable, slope, 1.0), other - theta)


def prediction_error(
    model: ArmModel, records: list[Experiment], tuning: Any, theta: torch.Tensor,
    q_scale: float = 1.0, r_scale: float = 1.0,
) -> PredictionError:  # fmt: skip
    """Steps 1–3 of the module docstring at `theta` over `records` (`tuning`: q the one
    measurement): of the three likeliest noise models the first whose filter stays healthy.
    A `TorchfricError` that names why when none does."""
    failure: Exception = TorchfricError("no noise model was found for the fixed-θ filter")
    try:
        ranked = noise_model(model, records, tuning, theta, q_scale=q_scale, r_scale=r_scale)
    except TorchfricError as err:
        ranked, failure = [], err
    moving, stick = _stick(model, records)
    for q_scale, r_scale in ranked[:3]:
        how = {"q_scale": q_scale, "r_scale": r_scale, "moving": moving, "stick_speed": stick}
        try:
            at_kept = pem_covariance(model, records, tuning, theta, **how)
            polished, pem, trace = pem_refine(model, records, tuning, theta, iterations=8,
                                              start=at_kept, **how)  # fmt: skip
        except TorchfricError as err:
            failure = err
            continue
        return PredictionError(at_kept, polished, pem, trace, moving, q_scale, r_scale)
    raise TorchfricError(str(failure))


def covariance_at(
    model: ArmModel, records: list[Experiment], tuning: Any, theta: torch.Tensor
) -> torch.Tensor:
    """The covariance of `theta` as it stands over `records` (`tuning`: the filter's, q made
    the one measurement): the sandwich at it plus its offset from the criterion's optimum, as a
    run whose polish was rejected reports it (`torchfric track` after a change,
    `torchfric.app.commands.bands`)."""
    found = prediction_error(model, records, _position_only(tuning), theta)
    return offset_covariance(found.at_kept.cov, found.offset_from(model, theta))


def start_substeps(
    cfg: Config, model: ArmModel, train: list[Experiment], say: Callable[[str], None]
) -> None:
    """Under ``substeps = "auto"``, says the filter's first RK4 sub-steps for `model`."""
    if cfg.estimator.substeps == "auto":
        n = resolve_substeps(cfg.estimator.ekf_tuning(), model, train).substeps
        say(f'  estimator.substeps = "auto": the filter starts with {n} RK4 step(s) per sample')


def _kept_substeps(cfg: Config, final: ArmModel, train: list, extra: dict, say: Callable) -> Any:
    """The run's EKF tuning for the covariance stage: under ``substeps = "auto"`` the RK4
    sub-steps the kept θ needs, at least those of the filter's last pass (metrics ``substeps``),
    said; the checkpoint keeps that count for `torchfric track`."""
    tuning = cfg.estimator.ekf_tuning()
    if tuning.substeps != "auto":
        return tuning
    ran = extra.get("substeps", 1)
    n = max(resolve_substeps(tuning, final, train).substeps, ran)
    say(f"  the passes ended at {ran} RK4 step(s) per sample; the covariance stage takes {n}")
    return dataclasses.replace(tuning, substeps=n)


def _stuck_note(cov: dict[str, Any]) -> str:
    """The progress line's note of the samples left out of the criterion, if any."""
    stuck = cov.get("stuck_left_out", 0.0)
    return f"; {stuck:.0%} of the samples stuck, left out" if stuck else ""


def _stick(
    model: ArmModel, train: list[Experiment]
) -> tuple[list[torch.Tensor] | None, float | None]:
    """``(moving, stick speed)`` of the records (`stick_band`). A static model's criterion
    leaves out the samples where the axis sticks (a static curve cannot hold a stuck axis, and
    its errors there biased M, docs/estimators.md); a dynamic model's bristles describe the
    stick, so it keeps them (moving None), as does a record with too few moving samples. Above
    the stick speed a tanh neuron that has risen fully is a step, its steepness held
    (`sandwich.held_entries`). Both None without positions or for a record too short for the
    zero-phase filter."""
    if any(e.q is None for e in train):
        return None, None
    try:
        stick, moving = stick_band(train)
    except TorchfricError:  # too short for the zero-phase filter: every sample, nothing held
        return None, None
    enough = sum(int(m.sum()) for m in moving) >= 50 * model.num_parameters
    return (moving if model.state_size == 2 and enough else None), stick


def _noise_dict(tuning: Any, q_scale: float, r_scale: float, train: list[Experiment]) -> dict:
    """metrics.json's ``covariance.noise_model``: Q and R in absolute units, what q measures,
    and one sample's process noise on q over R (``step_ratio``, `NOISE_STEP_LIMIT` at most)."""
    return {"q_state": [q_scale * x for x in tuning.q_state], "r": [r_scale * x for x in tuning.r],
            "measure": tuning.measure, "step_ratio": step_ratio(tuning, train, q_scale, r_scale)}  # fmt: skip


NEAR_FIT = 2.0
"""Ensemble members whose selection score (the mean FIT %, `select_by_fit`) is within this
many points of the kept member's: other estimates of θ from the same records that simulate
nearly as well (`near_members`)."""
SPREAD_LIMIT = 10.0
"""A near member that puts a white-box parameter (`SPREAD_TERMS`) this many reported σ from the
reported value: the estimate depends on the filter's tuning far beyond its σ (`member_spread`).
Measured (docs/results.md): 0.0–5.8 σ on the Stribeck axis and LuGre motor records, 10–3,800 σ
on the robot joint's seeds whose ±2σ missed the truth by 30–500 σ."""
SPREAD_TERMS = ("inertia", "viscous", "offset", "gravity", "asymmetric")


def near_members(ensemble: Any) -> list[tuple[int, torch.Tensor]]:
    """``(index, θ)`` of the members of an `EnsembleResult` other than the kept one that did not
    diverge and score within `NEAR_FIT` points of it."""
    best = ensemble.members[ensemble.best].score
    return [
        (m.index, ensemble.thetas[m.index].clone())
        for m in ensemble.members
        if m.index != ensemble.best and m.status != DIVERGED and math.isfinite(m.score)
        and best - m.score <= NEAR_FIT
    ]  # fmt: skip


def member_spread(
    model: ArmModel, theta: torch.Tensor, cov: torch.Tensor, near: list[tuple[int, torch.Tensor]]
) -> tuple[torch.Tensor, dict[str, Any]] | None:
    """The covariance of θ̂ = `theta` widened by the ensemble's near members (`near_members`),
    when one of them puts a white-box parameter more than `SPREAD_LIMIT` σ (of `cov`) from θ̂:
    ``cov + Σ_i d_i d_iᵀ``, ``d_i = θ_i − θ̂`` over the near members, each without the entries
    whose variance in `cov` is 0 (held, without σ); with metrics.json's record of it. None when
    no near member is that far: the σ stand.

    Where the model class holds the machine, members under other Q and R scales land within a
    few σ of each other; where it does not, each tuning weighs the misfit differently and lands
    on its own compromise, and their spread is the size of that bias, as the filter's offset is
    (`offset_covariance`). On the robot joint of docs/results.md the filter and the polish
    agreed while the members put M 0.36–0.42 against 0.4197 ± 0.0002 (truth 0.35)."""
    if not near:
        return None
    values = model.to_physical(theta)
    std = physical_std(model, theta, torch.diagonal(cov))
    names = list(model.theta_names)
    terms = [j for j, n in enumerate(names) if n in SPREAD_TERMS and float(std[j]) > 0]
    worst = (0.0, "", -1)  # (σ away, parameter, member)
    for index, other in near:
        far = (model.to_physical(other) - values).abs() / std.clamp_min(1e-300)
        for j in terms:
            if float(far[j]) > worst[0]:
                worst = (float(far[j]), names[j], index)
    if worst[0] <= SPREAD_LIMIT:
        return None
    free = (torch.diagonal(cov) > 0).to(cov.dtype)
    widened = cov.clone()
    for _, other in near:
        d = (other - theta) * free
        widened += torch.outer(d, d)
    record = {"members": [i for i, _ in near], "near_fit": NEAR_FIT, "limit": SPREAD_LIMIT,
              "worst": {"member": worst[2], "parameter": worst[1], "sigmas": worst[0]}}  # fmt: skip
    return 0.5 * (widened + widened.T), record


def offset_covariance(cov: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """The covariance of a reported θ that is `offset` away from the other estimate of the
    run, ``cov + offset offsetᵀ`` (`cov` the sandwich's at the reported θ).

    A run has two estimates of θ from one record: the filter's kept pass and the one-step
    prediction error's optimum (the polish). When the polish is rejected (the kept θ simulates
    better) the offset is to the optimum: if the optimum lies within its σ of the truth, the
    kept θ lies within ``√(σ_i² + offset_i²)`` of it as often or more. When the polish is kept
    the offset is to the filter's pass: where the model class holds the machine the two differ
    by about σ (the σ grow by up to √2), where it does not each criterion lands on its own
    compromise and their distance is the size of that bias. Measured on 20 seeds of a Stribeck
    axis (tanh(3), docs/results.md): b's ±2σ covered 11 of 20 with the sandwich alone, every
    miss in a polished run."""
    offset = torch.as_tensor(offset, dtype=cov.dtype).reshape(-1)
    return cov + torch.outer(offset, offset)


def attach_oe_covariance(
    cfg: Config,
    final: ArmModel,
    train: list[Experiment],
    state: dict[str, Any],
    extra: dict[str, Any],
    say: Callable[[str], None],
) -> None:
    """An output-error run's σ: the sandwich covariance of its own criterion, the full-length
    simulation error weighted as it trained (`simulation_covariance`), at the kept θ. Adds
    ``P_theta`` to `state` and ``covariance``, ``identifiability`` to `extra`; when it cannot be
    computed, a warning says why and the parameters keep no σ."""
    from ...estimators.oe_covariance import simulation_covariance

    tuning = cfg.estimator.oe_tuning(cfg.seed)
    try:
        cov = simulation_covariance(final, train, state["theta"], weights=tuple(tuning.weights),
                                    substeps=tuning.substeps)  # fmt: skip
    except TorchfricError as err:
        extra.setdefault("covariance_warnings", []).append(f"no ± σ for this result: {err}")
        return
    state["P_theta"] = cov.cov
    extra["covariance"] = cov.to_dict()
    ident = run_identifiability(final, cov, train)
    extra["identifiability"] = {**ident.to_dict(), "messages": _messages(ident)}
    say(f"  covariance: simulation-error sandwich over {cov.samples} samples "
        f"({cov.blocks} blocks, {cov.bandwidth} lags)")  # fmt: skip


def run_identifiability(
    model: ArmModel, pem: PEMCovariance, train: list[Experiment]
) -> Identifiability:
    """The run's identifiability report: the covariance's (`pem.identifiability`) and the tanh
    neurons that take part of b (`viscous_share`) at ``pem.theta``, b's σ the sandwich's
    (`physical_std` of ``pem.cov``: without a rejected polish's offset, which would hide a
    shared slope behind the distance to the optimum), over the identification records' velocity (reconstructed or measured;
    from position differences where there is none, as `velocity_scale` reads it)."""
    theta = torch.as_tensor(pem.theta, dtype=torch.float64)
    values = dict(zip(model.theta_names, model.to_physical(theta).tolist(), strict=True))
    std = physical_std(model, theta, torch.diagonal(pem.cov))
    sigma = dict(zip(model.theta_names, std.tolist(), strict=True)).get("viscous")
    shares = viscous_share(values, data_speeds(train), viscous_std=sigma)
    return dataclasses.replace(pem.identifiability, shares=shares)


def _score(cfg: Config, model: ArmModel, theta: Any, records: list[Experiment]) -> float:
    """Mean of (FIT q + FIT q̇)/2 over `records` of `model` at θ (the runs' validation score)."""
    import copy

    from .assessment import evaluate_model

    scores = evaluate_model(copy.deepcopy(model).set_theta(theta), records, cfg).values()
    fits = [0.5 * (s.fit_q + s.fit_qdot) for s in scores]
    fits = [f if f == f else -math.inf for f in fits]  # NaN: the simulation failed
    return sum(fits) / max(len(fits), 1)


def _position_only(tuning: Any) -> Any:
    """The tuning with q as the only measurement (its own R entry). The reconstructed velocity
    is q filtered, not a second sensor: counting it as one counts q's information twice, and a
    causal differentiator's lag biases M (measured: +0.03 % at 2 σ on every seed of a
    Coulomb-friction axis). A run that measures q̇ alone (``measure = "velocity"``) keeps it."""
    from ...estimators.ekf import MEASUREMENTS

    if tuning.measure != "both":
        return tuning
    r = tuple(tuning.r)[MEASUREMENTS["both"].index(0)]
    return dataclasses.replace(tuning, measure="position", r=(r,))


def _messages(ident: Any) -> list[str]:
    """The identifiability lines: those that involve a white-box parameter as they are, those
    inside the black-box curve marked "(within the friction curve)" (the curve itself can
    still be determined: two neurons that trade off draw the same curve)."""
    out = []
    for (names, _), message in zip(ident.groups, ident.messages, strict=True):
        physical = any(n.startswith(PHYSICAL) for n in names)
        out.append(message if physical else f"(within the friction curve) {message}")
    return sorted(out, key=lambda m: m.startswith("(within"))


def _tuning_dict(tuning: Any) -> dict[str, Any]:
    return {
        k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(tuning).items()
    }
