"""One observer protocol for every estimator (after PyTorch Lightning's single ``Callback``).

An estimator is handed one `Callback` and calls its named hooks; every hook has a default that
does nothing, so an observer overrides only what it watches. The app layer builds its
TensorBoard logging, progress display and snapshots as separate observers and hands them over
together as a `CallbackList`.

Hooks that end a step (`on_pass_end`, `on_ensemble_pass_end`, `on_epoch_end`) may return
``False`` to stop the estimator after that step; anything else continues.

Three more hooks frame a whole run, as Lightning's ``on_fit_start`` / ``on_fit_end`` /
``on_exception`` do; the estimators never call them, whoever runs an estimator does
(`torchfric.app.run.train`): `on_run_start` with a `RunStart`, `on_run_end` with a `RunEnd`,
and `on_exception` with the error that stops the run. An observer that holds a file, a bar or
a writer finishes it there.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from torch import Tensor

    from ..models.arm import ArmModel
    from .metrics import SimulationScore

__all__ = [
    "Callback",
    "CallbackList",
    "EKFCallback",
    "EnsembleCallback",
    "OECallback",
    "RunEnd",
    "RunStart",
]


@dataclass(frozen=True)
class RunStart:
    """What a run starts from (`Callback.on_run_start`)."""

    model: ArmModel
    """The model the estimator starts from (not changed by it)."""
    init: str
    """How that model was made: ``"prefit"``, ``"config"``, a checkpoint's path, ``"resume"``."""
    resumed: bool = False
    """Whether the run continues an interrupted one (its start was observed then)."""


@dataclass(frozen=True)
class RunEnd:
    """What a finished run keeps (`Callback.on_run_end`)."""

    model: ArmModel
    """The kept model (the best pass, epoch or ensemble member)."""
    metrics: Mapping[str, Any]
    """The run's metrics (what ``metrics.json`` holds)."""
    step: int
    """The kept pass or epoch."""
    covariance: Tensor | None = None
    """θ's covariance at the kept model, when the estimator gives one."""
    scores: Mapping[str, SimulationScore] = field(default_factory=dict)
    """The kept model's open-loop scores on the validation records, by record name."""
    history: Sequence[Any] = ()
    """The estimator's records (`PassRecord` or `EpochRecord`), up to the kept one."""


class Callback:
    """The hooks an estimator calls. Defaults do nothing."""

    def on_progress(self, pass_index: int, samples_done: int, samples_total: int) -> None:
        """Inside a filter pass (or an output-error epoch): `samples_done` of `samples_total`."""

    def on_pass_end(self, record: Any, result: Any) -> bool | None:
        """After each pass of the single EKF: its `PassRecord` and the `EKFResult` so far."""
        return None

    def on_ensemble_pass_end(self, pass_index: int, state: dict[str, Any]) -> bool | None:
        """After each pass of an ensemble, with its whole state: enough to resume from with
        ``identify_ekf_ensemble(start=state)``."""
        return None

    def on_epoch_end(self, record: Any, result: Any) -> bool | None:
        """After each output-error epoch: its `EpochRecord` and the `OEResult` so far."""
        return None

    def on_ensemble_end(self, result: Any) -> None:
        """After an ensemble's last pass: the kept member as one filter's `EKFResult`."""

    def on_run_start(self, start: RunStart) -> None:
        """Before the estimator's first pass or epoch (also when the run resumes)."""

    def on_estimate(self, end: RunEnd) -> None:
        """After the estimator, before the run's σ: the kept model, its history and step, the
        metrics known so far (``best_pass``) and its scores when the passes made them; the
        model may still change (a polish the run keeps) before `on_run_end`."""

    def on_run_end(self, end: RunEnd) -> None:
        """After the run's result is written: the kept model, its metrics and scores."""

    def on_exception(self, error: BaseException) -> None:
        """The run stops with `error` (a divergence, Ctrl-C, a failed write): finish what can
        be finished; the error is raised again after every observer has seen it."""


class CallbackList(Callback):
    """Several observers as one: each hook goes to every observer in order, and a step stops
    when any of them returns False (all of them still see it)."""

    def __init__(self, callbacks: Iterable[Callback]) -> None:
        self.callbacks = list(callbacks)

    def on_progress(self, pass_index: int, samples_done: int, samples_total: int) -> None:
        for cb in self.callbacks:
            cb.on_progress(pass_index, samples_done, samples_total)

    def _all(self, hook: str, *args: Any) -> bool | None:
        answers = [getattr(cb, hook)(*args) for cb in self.callbacks]
        return False if any(a is False for a in answers) else None

    def on_pass_end(self, record: Any, result: Any) -> bool | None:
        return self._all("on_pass_end", record, result)

    def on_ensemble_pass_end(self, pass_index: int, state: dict[str, Any]) -> bool | None:
        return self._all("on_ensemble_pass_end", pass_index, state)

    def on_epoch_end(self, record: Any, result: Any) -> bool | None:
        return self._all("on_epoch_end", record, result)

    def on_ensemble_end(self, result: Any) -> None:
        self._all("on_ensemble_end", result)

    def on_run_start(self, start: RunStart) -> None:
        self._all("on_run_start", start)

    def on_estimate(self, end: RunEnd) -> None:
        self._all("on_estimate", end)

    def on_run_end(self, end: RunEnd) -> None:
        self._all("on_run_end", end)

    def on_exception(self, error: BaseException) -> None:
        """Every observer sees `error`, even when one of them fails on it (that failure is
        dropped: the run's own error is the one to report)."""
        for cb in self.callbacks:
            try:
                cb.on_exception(error)
            except Exception:  # noqa: BLE001, S110 - the run's own error is the one to report
                pass


# The names each estimator's API has documented; all are the one protocol.
EKFCallback = Callback
EnsembleCallback = Callback
OECallback = Callback
