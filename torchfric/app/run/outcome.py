"""A run's outcome as a user reads it: the pass it keeps, its parameters ± σ, and the summary.

- `keep_best`: the final model of an EKF run is its pass with the best validation score
  (`torchfric.estimators.metrics.mean_fit`: the mean over the validation records of
  (FIT_q + FIT_q̇)/2), or with the highest innovation log-likelihood when there is no validation
  data. Passes that were rolled back never count. The filter's own θ after the last pass can be
  worse on held-out data than an earlier pass's (91.2 % → 85.6 % was seen on the rig), and the
  user gets the one that validated best. (Output error keeps its best epoch itself.)
- `parameter_table`: ``{name: {"value", "std"}}`` in physical units from the kept ``P_θθ``
  (std None where there is no covariance, as after output error).
- `summary_lines`: the human summary ``train`` prints on stdout.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from ...data import Experiment
from ...estimators.ensemble import EnsembleResult
from ...estimators.metrics import mean_fit
from ...estimators.passes import EKFResult, PassRecord
from ...estimators.selection import select_by_fit
from ...estimators.uncertainty import parameter_std
from ...models.arm import ArmModel
from ..config import Config
from .assessment import scoring_engine
from .autosize import dynamic_lines, size_lines
from .snapshots import ekf_payload

__all__ = [
    "keep_best",
    "kept_pass",
    "kept_payload",
    "parameter_lines",
    "parameter_table",
    "member_held_out",
    "note_held_out",
    "selection_records",
    "pass_fits",
    "score_passes",
    "summary_lines",
]


@torch.no_grad()
def _open_loop_scores(
    model: ArmModel, thetas: Tensor, alive: list[int], records: Sequence[Experiment],
    max_substeps: int, engine: str,
) -> tuple[list[dict[str, dict[str, float]]], dict[int, float]]:  # fmt: skip
    """The ensemble's own scorer (`select_by_fit`) on `records` alone, for the rows `alive` of
    `thetas`: each row's fits and its mean over `records` of (FIT_q + FIT_q̇)/2, −inf where its
    simulation fails (not the scorer's fallback to the likelihood)."""
    _, fits, _ = select_by_fit(
        model, thetas, alive, (), records, torch.zeros(thetas.shape[0]),
        max_substeps=max_substeps, engine=engine,
    )  # fmt: skip
    scores = {}
    for i in alive:
        score = mean_fit(fits[i])
        scores[i] = score if score is not None and math.isfinite(score) else -math.inf
    return fits, scores


def pass_fits(
    model: ArmModel,
    history: Sequence[PassRecord],
    records: Sequence[Experiment],
    *,
    max_substeps: int = 64,
    engine: str = "odeint",
) -> dict[int, float]:
    """The mean over `records` of (FIT_q + FIT_q̇)/2 of each pass of `history` not rolled back,
    by pass index, from one batched open-loop simulation per record; a simulation that fails
    scores −inf."""
    todo = [r for r in history if not r.rolled_back]
    if not todo or not records:
        return {}
    thetas = torch.tensor([r.theta for r in todo], dtype=torch.float64)
    alive = list(range(len(todo)))
    _, scores = _open_loop_scores(model, thetas, alive, records, max_substeps, engine)
    return {record.index: scores[i] for i, record in enumerate(todo)}


def score_passes(
    model: ArmModel,
    history: Sequence[PassRecord],
    validation: Sequence[Experiment],
    *,
    max_substeps: int = 64,
    engine: str = "odeint",
) -> None:
    """Set `PassRecord.val_score` of the records not scored yet (the ensemble's kept member; a
    resumed run's older passes): `pass_fits` on the validation records."""
    todo = [r for r in history if r.val_score is None]
    scores = pass_fits(model, todo, validation, max_substeps=max_substeps, engine=engine)
    for record in todo:
        if record.index in scores:
            record.val_score = scores[record.index]


HELD_OUT_GAP = 10.0
"""Points of validation FIT (mean of q and q̇) by which another pass or member may beat the one
a run kept by its identification records before the run warns (`note_held_out`)."""


def selection_records(
    select: str, train: Sequence[Experiment], validation: Sequence[Experiment]
) -> tuple[list[Experiment], list[Experiment], list[Experiment]]:
    """The records that choose the model a run keeps (``estimator.select``): the validation
    records that choose (all of them under "validation", else none), the identification
    records whose open-loop FIT chooses (under "identification": those with a velocity to
    start a simulation from, else none), and the validation records that only report (the
    kept model compared with the best-validating one: under "identification")."""
    if select == "validation":
        return list(validation), [], []
    return [], [e for e in train if e.qdot is not None], list(validation)


def member_held_out(
    model: ArmModel, ens: EnsembleResult, validation: Sequence[Experiment], cfg: Config
) -> dict[str, Any]:
    """The ensemble's members scored on `validation` (the validation records when they chose
    nothing, else none): each member's fits join its ``MemberSummary.fits``, which
    ensemble.json lists, and the kept member is compared with the best-validating one
    (`note_held_out`: the run's ``held_out`` and its warning, returned as metrics)."""
    alive = [m.index for m in ens.members if m.fits]
    if not alive or not validation:
        return {}
    engine = scoring_engine(cfg)
    fits, scores = _open_loop_scores(model, ens.thetas, alive, validation, 64, engine)
    for i in alive:
        ens.members[i].fits.update(fits[i])
    extra: dict[str, Any] = {}
    note_held_out(extra, "member", ens.best, scores)
    return extra


def note_held_out(extra: dict[str, Any], kind: str, kept: int, scores: dict[int, float]) -> None:
    """How the `kind` ("pass" or "member") a run kept by its identification records scores on
    the validation records against the best of the others (`scores`: index → validation
    score), into the run's metrics `extra`: ``held_out``, and a warning
    (``selection_warnings``) when the best beats it by more than `HELD_OUT_GAP` points. The
    validation records choose nothing here: they are reported."""
    if kept not in scores or not any(math.isfinite(v) for v in scores.values()):
        return
    best = max(scores, key=lambda i: (scores[i], i))
    extra["held_out"] = {
        kind: kept,
        "score": scores[kept],
        f"best_{kind}": best,
        "best_score": scores[best],
    }
    if not scores[best] - scores[kept] > HELD_OUT_GAP:
        return
    extra.setdefault("selection_warnings", []).append(
        f"the kept {kind} {kept}, chosen by the identification records, simulates the "
        f"validation records at {scores[kept]:.1f} % (mean FIT of q and q̇) where {kind} {best} "
        f"reaches {scores[best]:.1f} %: the identification records do not tell them apart. "
        "Compare the two (ensemble.json, report.html), or choose on validation with "
        'estimator.select = "validation" (its FIT is then no longer a held-out score)'
    )


def _candidates(result: EKFResult) -> list[tuple[PassRecord, Tensor, Tensor]]:
    """The passes that may be kept, each with its θ and ``P_θθ``: every pass not rolled back
    whose covariance is known (a record from before covariances were kept: only the last)."""
    out = []
    last = next((r for r in reversed(result.history) if not r.rolled_back), None)
    for r in result.history:
        if r.rolled_back:
            continue
        if r is last:
            out.append((r, result.theta, result.P_theta))
        elif r.P_theta is not None:
            theta = torch.tensor(r.theta, dtype=torch.float64)
            out.append((r, theta, torch.tensor(r.P_theta, dtype=torch.float64)))
    return out


def keep_best(
    result: EKFResult, *, validating: bool, scores: dict[int, float] | None = None
) -> tuple[EKFResult, int]:
    """The pass of `result` to keep and its number (0: no pass completed).

    By `scores` (pass index → score: `pass_fits` on the identification records) when given,
    else by validation score when `validating` (records need `val_score`: `score_passes`),
    else by log-likelihood; ties go to the later pass. The returned result has that pass's θ,
    ``P_θθ`` and a fitted copy of the model; its history and `converged` are the run's.
    """
    cands = _candidates(result)
    if not cands:
        return result, 0

    def key(c: tuple[PassRecord, Tensor, Tensor]) -> tuple[float, int]:
        r = c[0]
        if scores is not None:
            score = scores.get(r.index, -math.inf)
        else:
            score = r.val_score if validating else r.loglik
        if score is None or not math.isfinite(score):
            score = -math.inf
        return score, r.index

    record, theta, P_theta = max(cands, key=key)
    if record is cands[-1][0]:
        return result, record.index
    model = copy.deepcopy(result.model).set_theta(theta)
    return EKFResult(model, theta.clone(), P_theta.clone(), result.history, result.converged), (
        record.index
    )


def kept_pass(
    result: EKFResult,
    validation: Sequence[Experiment],
    engine: str = "odeint",
    tolerance: float | None = None,
    *,
    identification: Sequence[Experiment] = (),
    held_out: bool = False,
) -> tuple[EKFResult, dict[str, Any]]:
    """The pass of an EKF run to keep (`keep_best`, after `score_passes` with `engine`) and
    the metrics that say which, and why the passes ended ("stopped": converged, rolled_back
    or budget). With `identification` records (``estimator.select = "identification"``;
    `validation` is then empty) the passes are kept by their open-loop FIT on those; with
    `held_out` the kept pass is compared with the best-validating one (`note_held_out`, from
    the passes' ``val_score``: reported, not chosen by)."""
    score_passes(result.model, result.history, validation, engine=engine)
    chosen = None
    if identification and not validation:
        chosen = pass_fits(result.model, result.history, identification, engine=engine)
    kept, best = keep_best(result, validating=bool(validation), scores=chosen)
    # what chose it (metrics.json's selected_on): the validation records, the identification
    # records' open-loop FIT, or the likelihood (neither is there)
    on = "validation" if validation else "identification" if chosen is not None else "likelihood"
    last = result.history[-1] if result.history else None
    if last is not None and last.rolled_back:  # converged too: the pass before is the best
        stopped = "rolled_back"
    elif result.converged:
        stopped = "converged"
    else:
        stopped = "budget"
    extra = {
        "passes": result.passes,
        "best_pass": best,
        "converged": result.converged,
        "stopped": stopped,
        # ‖Δθ‖/‖θ‖ of the last pass, and its gain of innovation log-likelihood over the pass
        # before (what estimator.tolerance judges)
        "last_change": last.rel_change if last is not None else None,
        "last_gain": _last_gain(result.history),
        "tolerance": tolerance,
        "selected_on": on,
    }
    if held_out:
        scores = {r.index: r.val_score for r in result.history if r.val_score is not None}
        note_held_out(extra, "pass", best, scores)
    return kept, extra


def _last_gain(history: Sequence[PassRecord]) -> float | None:
    """The last pass's log-likelihood minus that of the pass before it (None for one pass)."""
    if len(history) < 2:
        return None
    before = [r for r in history[:-1] if not r.rolled_back]
    return history[-1].loglik - before[-1].loglik if before else None


def kept_payload(kept: EKFResult, extra: dict[str, Any]) -> dict[str, Any]:
    """The final checkpoint's estimator state: the kept pass's θ and ``P_θθ``, the run's
    history (`kept` carries it whole), and which pass was kept."""
    payload = ekf_payload(kept, kept.passes)
    payload["best_pass"] = extra["best_pass"]
    return payload


def parameter_table(model: ArmModel, P_theta: Tensor | None) -> dict[str, dict[str, float | None]]:
    """``{name: {"value": physical value, "std": its σ or None}}`` for every entry of θ."""
    values = model.physical_parameters()
    std: dict[str, float] = {}
    if P_theta is not None:
        P = torch.as_tensor(P_theta, dtype=torch.float64)
        if P.shape == (model.num_parameters,) * 2 and bool(torch.isfinite(P).all()):
            std = parameter_std(model, P)
    # a σ of exactly 0 is a parameter the data say nothing about (its information is 0 and
    # the pseudo-inverse left it out): no σ, not perfect certainty (identifiability names it)
    return {n: {"value": v, "std": std.get(n) or None} for n, v in values.items()}


def _value_pm(value: float, std: float | None) -> str:
    if std is None:
        return f"{value:.6g}"
    return f"{value:.6g} ± {std:.2g}"


def parameter_lines(table: dict[str, Any], limit: int = 12) -> list[str]:
    """The parameter table as aligned ``name  value ± σ`` lines (at most `limit` rows, the
    physical ones first: inertia, viscous, offset, c_m; then the friction model's entries)."""
    first = [n for n in ("inertia", "viscous", "offset", "c_m") if n in table]
    names = first + [n for n in table if n not in first]
    width = max(len(n) for n in names)
    lines = [f"  {n:<{width}}  {_value_pm(table[n]['value'], table[n]['std'])}" for n in names]
    if len(lines) > limit:
        rest = len(lines) - limit
        lines = lines[:limit] + [f"  … {rest} more in metrics.json and report.html"]
    return lines


_STOPPED = {
    "converged": "converged in {total} {units}: the last raised the innovation log-likelihood "
    "by {gain} nats (below estimator.tolerance {tolerance} × {k} parameters = {limit} nats)",
    "early": "converged: the validation score stopped improving (estimator.patience)",
    "rolled_back": "converged in {total} {units}: the last lowered the innovation likelihood "
    "and was undone, so the pass before is the filter's best fit of the data",
    "budget": "NOT converged: the last of all {total} {units} still raised the innovation "
    "log-likelihood by {gain} nats (estimator.tolerance {tolerance} × {k} parameters = {limit} "
    "nats); raise "
    "estimator.passes; the kept pass is the one that {kept_by}",
    "budget_oe": "NOT converged: the validation score was still improving at the last of the "
    "{total} epochs; run more, e.g. --set estimator.epochs={more}",
    "budget_oe_early_best": "NOT converged: all {total} epochs ran before estimator.patience "
    "ran out, and none validated better than epoch {best}; the result is that epoch's",
}


_KEPT_BY = {
    "identification": "best open-loop FIT on the identification records",
    "validation": "best validation FIT",
    "likelihood": "highest likelihood",
    "last_epoch": "the last: no validation record chooses it",
}
"""Why the kept pass or epoch was kept, by metrics.json's ``selected_on``."""
_BUDGET_KEPT_BY = {
    "identification": "simulated the identification records best",
    "validation": "validated best",
    "likelihood": "fit the data best",
}
_HELD_OUT = {
    "validation": "validation chose the kept model, so its FIT is not a held-out score "
    '(estimator.select = "identification" keeps it held out)',
    "identification": "validation: held out (it chose nothing; the identification records did)",
    "last_epoch": "validation: held out (it chose nothing)",
    "likelihood": "validation: held out (it chose nothing)",
}
"""The line after the validation FITs: whether they are held-out scores."""


def _g(x: float | None) -> str:
    return "?" if x is None else f"{x:.2g}"


def _stopped_lines(
    metrics: dict[str, Any], unit: str, total: int | None, best: int | None, on: str | None
) -> list[str]:
    """`summary_lines`' line on why the passes or epochs ended (`_STOPPED`), if any; an
    ensemble's is its kept member's."""
    reason = metrics.get("stopped", "")
    if (unit, reason) == ("epoch", "budget"):
        reason = "budget_oe" if best is None or best >= (total or 0) else "budget_oe_early_best"
    stopped = _STOPPED.get(reason, "")
    if not stopped:
        return []
    if metrics.get("ensemble") and unit == "pass":  # the kept member's passes
        stopped = ("the kept member " + stopped if stopped.startswith("converged")
                   else stopped.replace("NOT converged:", "NOT converged (the kept member):", 1))  # fmt: skip
    k = len(metrics["parameters"])
    return [stopped.format(
        unit=unit, total=total, units=unit + ("es" if unit == "pass" else "s"),
        more=2 * (total or 1), best=best, change=_g(metrics.get("last_change")),
        gain=_g(metrics.get("last_gain")), tolerance=_g(metrics.get("tolerance")), k=k,
        limit=_g((metrics.get("tolerance") or 0.0) * k),
        kept_by=_BUDGET_KEPT_BY.get(on)
        or ("validated best" if metrics.get("validation") else "fit the data best"),
    )]  # fmt: skip


def summary_lines(metrics: dict[str, Any], files: dict[str, str]) -> list[str]:
    """The human summary of a finished run: what was kept and why, parameters ± σ, validation
    FITs, convergence, warnings, and the files written (`files`: label → path)."""
    lines = []
    est = metrics.get("estimator", "")
    total = metrics.get("passes", metrics.get("epochs"))
    unit = "epoch" if "epochs" in metrics else "pass"
    best = metrics.get("best_pass")
    lines.append(f"torchfric: {metrics.get('name', '')} ({est}) in {metrics['seconds']:.1f} s")
    ens = metrics.get("ensemble")
    if ens:
        words = {"running": "ran every pass", "rolled_back": "stopped at a worse pass"}
        status = ", ".join(f"{c} {words.get(s, s)}" for s, c in ens["status"].items())
        lines.append(
            f"ensemble of {ens['members']} filters ({status}); kept member {ens['best']} "
            f"(Q ×{ens['best_q_scale']:g}, R ×{ens['best_r_scale']:g}) by "
            f"{ens['selected_by'].replace('_', ' ')}, after its {total} passes"
        )
    if metrics.get("sizes"):
        lines += size_lines(metrics["sizes"])
    if metrics.get("dynamics"):
        lines += dynamic_lines(metrics["dynamics"])
    on = metrics.get("selected_on")
    if best is not None and total:
        why = _KEPT_BY.get(on) or (
            "best validation FIT"
            if metrics.get("validation")
            else "the last: no validation data"
            if unit == "epoch"
            else "highest likelihood"
        )
        lines.append(f"kept {unit} {best} of {total} ({why})")
    lines += _stopped_lines(metrics, unit, total, best, on)
    table = metrics["parameters"]
    if any(v["std"] is not None for v in table.values()):
        lines.append("parameters (value ± σ):")
    elif metrics.get("estimator") == "output_error":
        lines.append("parameters (no σ: output error keeps no parameter covariance):")
    else:  # the covariance found no direction the data determine (its warnings name them)
        lines.append("parameters (no σ: the data determined none of them; see the warnings):")
    lines += parameter_lines(table)
    for group in ("validation", "test", "identification"):
        for name, m in metrics.get(group, {}).items():
            lines.append(f"{group} FIT ({name}): q {m['fit_q']:.2f} %, q̇ {m['fit_qdot']:.2f} %")
    if metrics.get("validation") and on in _HELD_OUT:
        lines.append(_HELD_OUT[on])
    if not metrics.get("validation"):
        lines.append(
            "validation: none (the identification FIT above flatters the model; add held-out "
            "records as data.validation)"
        )
    for w in metrics.get("warnings", []):
        lines.append(f"warning: {w}")
    notes = (metrics.get("identifiability") or {}).get("messages", [])
    lines += [f"note: {m}" for m in notes if m.startswith("(within")]
    width = max(len(k) for k in files)
    lines += [f"{k:<{width}}  {v}" for k, v in files.items()]
    return lines
