"""One observer protocol for every estimator (after PyTorch Lightning's single ``Callback``).

An estimator is handed one `Callback` and calls its named hooks; every hook has a default that
does nothing, so an observer overrides only what it watches. The app layer builds its
TensorBoard logging, progress display and snapshots as separate observers and hands them over
together as a `CallbackList`.

Hooks that end a step (`on_pass_end`, `on_ensemble_pass_end`, `on_epoch_end`) may return
``False`` to stop the estimator after that step; anything else continues.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

__all__ = ["Callback", "CallbackList", "EKFCallback", "EnsembleCallback", "OECallback"]


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


# The names each estimator's API has documented; all are the one protocol.
EKFCallback = Callback
EnsembleCallback = Callback
OECallback = Callback
