"""One trial of a sweep: the config with the trial's values, trained as an ordinary run in
``DIR/trials/NNNN``, its per-pass scores reported (`PassReports`) and its objective
(`trial_score`, of the kind `objective_kind` names: see `torchfric.app.sweep.driver`).
"""

from __future__ import annotations

import math
import pathlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ...errors import TorchfricError
from ...estimators.metrics import mean_fit
from ...estimators.observers import Callback
from ..config import Config, toml_value
from .space import Param

__all__ = [
    "OBJECTIVES",
    "PassReports",
    "SweepSpec",
    "objective_kind",
    "run_trial",
    "trial_dir",
    "trial_score",
    "values_text",
]

OBJECTIVES = {
    "validation_fit": "validation FIT [%]: mean over the validation records of (FIT q + FIT q̇)/2"
    " of the kept pass, maximised",
    "loglik": "identification log-likelihood of the kept pass (no validation data), maximised",
    "identification_fit": "identification FIT [%]: mean over the identification records of "
    "(FIT q + FIT q̇)/2 (no validation data), maximised",
}


def objective_kind(cfg: Config) -> str:
    """What a trial of `cfg` scores (a key of `OBJECTIVES`): as the run keeps its pass."""
    if cfg.data.validation:
        return "validation_fit"
    return "loglik" if cfg.estimator.method == "ekf" else "identification_fit"


@dataclass(frozen=True)
class SweepSpec:
    """What a trial needs, in any process: the base config (as plain tables, paths absolute),
    the space, where trials go, the study, what they score, and the pruner."""

    config: dict[str, Any]
    params: tuple[Param, ...]
    out: str
    storage: str
    study: str
    kind: str
    pruner: Any = None

    def base(self) -> Config:
        return Config.from_dict(self.config)


def trial_dir(out: str | pathlib.Path, number: int) -> pathlib.Path:
    """The run directory of trial `number`: ``DIR/trials/NNNN``."""
    return pathlib.Path(out) / "trials" / f"{number:04d}"


class PassReports(Callback):
    """A trial's per-pass scores to `report` (``report(value, step) -> prune?``); stops the
    run after the pass whose report says prune (`pruned_at`). Non-finite scores are skipped."""

    def __init__(self, report: Callable[[float, int], bool], kind: str) -> None:
        self.report, self.kind = report, kind
        self.pruned_at: int | None = None
        self.last: float | None = None

    def _step(self, value: float | None, step: int) -> bool | None:
        if value is None or not math.isfinite(value) or self.pruned_at is not None:
            return None
        self.last = float(value)
        if self.report(float(value), int(step)):
            self.pruned_at = int(step)
            return False
        return None

    def on_pass_end(self, record: Any, result: Any) -> bool | None:
        if record.rolled_back:
            return None
        value = record.val_score if self.kind == "validation_fit" else record.loglik
        return self._step(value, record.index)

    def on_ensemble_pass_end(self, pass_index: int, state: dict[str, Any]) -> bool | None:
        from ..run import best_member_loglik

        return self._step(best_member_loglik(state, pass_index), pass_index)

    def on_epoch_end(self, record: Any, result: Any) -> bool | None:
        value = record.val_score if self.kind == "validation_fit" else -record.loss
        return self._step(value, record.index)


def _field(record: Any, name: str) -> Any:
    return record.get(name) if isinstance(record, dict) else getattr(record, name, None)


def trial_score(result: Any, kind: str) -> float | None:
    """A finished run's objective value (`objective_kind`): its kept pass's score."""
    m = result.metrics
    if kind == "validation_fit":
        return mean_fit(m.get("validation"))
    if kind == "identification_fit":
        return mean_fit(m.get("identification"))
    best = m.get("best_pass")
    scores = [_field(r, "loglik") for r in result.history if _field(r, "index") == best]
    return scores[0] if scores else None


def run_trial(
    spec: SweepSpec, number: int, values: dict[str, Any], report: Callable[[float, int], bool]
) -> tuple[float | None, PassReports, Any]:
    """Trial `number`: `spec`'s config with `values`, trained quietly in ``DIR/trials/NNNN``.
    Returns its score, its `PassReports` and the `TrainResult`. Raises `TorchfricError` as
    the run does."""
    from ..run import train  # which runs under `torch_settings` itself

    sets = [f"{key}={toml_value(value)}" for key, value in values.items()]
    cfg = spec.base().with_overrides(sets)
    reports = PassReports(report, spec.kind)
    result = train(
        cfg, run_dir=trial_dir(spec.out, number), say=lambda msg: None, callbacks=(reports,)
    )
    score = trial_score(result, spec.kind)
    if reports.pruned_at is None and (score is None or math.isnan(score)):
        raise TorchfricError("the run finished without a score (no pass completed)")
    return score, reports, result


def values_text(values: dict[str, Any]) -> str:
    """``key = value, ...`` for a progress line or the summary."""
    return ", ".join(
        f"{k} = {v:.4g}" if isinstance(v, float) else f"{k} = {toml_value(v)}"
        for k, v in values.items()
    )
