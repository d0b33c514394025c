"""The run's observers of the estimators (one `torchfric.estimators.observers.Callback` each).

A run hands its estimator (single EKF, ensemble or output error) a `CallbackList` of:

- `ValidationScores`: the open-loop scores of each pass's model on the validation records,
  which the observers after it read;
- `TensorBoardLog`: parameters, filter diagnostics, validation FITs and figures per pass/epoch;
- `ProgressLines`: the progress lines (``say``) in and after each pass or epoch;
- `torchfric.app.snapshots.Snapshots`: the resumable per-pass snapshots.

They run in that order, so each pass's scores are there before they are logged, said or saved.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from typing import Any

from ..data import Experiment
from ..estimators.identify import EKFResult, PassRecord
from ..estimators.metrics import SimulationScore
from ..estimators.observers import Callback
from ..estimators.output_error import EpochRecord, OEResult
from ..models.arm import ArmModel
from .config import Config
from .evaluation import evaluate_model
from .figures import friction_figure, response_figure

__all__ = [
    "Printer",
    "ValidationScores",
    "TensorBoardLog",
    "ProgressLines",
    "duration",
    "ekf_scalars",
    "fit_text",
    "ensemble_spread",
]

Printer = Callable[[str], None]


def ekf_scalars(record: PassRecord) -> dict[str, float]:
    """A pass's filter diagnostics as TensorBoard scalars (`ekf/...`)."""
    scalars = {
        "ekf/trace_P": record.trace_P,
        "ekf/trace_P_theta": record.trace_P_theta,
        "ekf/nis": record.nis,
        "ekf/loglik": record.loglik,
        "ekf/rel_change": record.rel_change,
    }
    for i, v in enumerate(record.innovation_rms):
        scalars[f"ekf/innovation_rms/{i}"] = v
    return scalars


def duration(seconds: float) -> str:
    """A progress line's time: ``26 ms`` under a second (a pass often is), else ``3.4 s``."""
    return f"{seconds * 1e3:.0f} ms" if seconds < 1.0 else f"{seconds:.1f} s"


def fit_text(fits: dict[str, dict[str, float]]) -> str:
    """Validation FITs for a progress line: ``name FIT q 91.2 % q̇ 80.1 %, ...``."""
    return ", ".join(
        f"{n} FIT q {f['fit_q']:.1f} % q̇ {f['fit_qdot']:.1f} %" for n, f in fits.items()
    )


def ensemble_spread(model: ArmModel, state: dict[str, Any]) -> tuple[dict[str, int], list[float]]:
    """An ensemble pass's member count by status, and its live members' inertias, sorted."""
    status = state["status"]
    ok = [i for i, s in enumerate(status) if s != "diverged"]
    inertia = sorted(float(model.split(state["thetas"][i])[1]["inertia"]) for i in ok)
    counts = {s: status.count(s) for s in sorted(set(status))}
    return counts, inertia


class ValidationScores(Callback):
    """Scores the model on the validation records after each filter pass (`latest`)."""

    def __init__(self, cfg: Config, validation: list[Experiment]) -> None:
        self.cfg, self.validation = cfg, validation
        self.latest: dict[str, SimulationScore] = {}

    def update(self, model: ArmModel) -> dict[str, SimulationScore]:
        """Score `model`, keep the scores as `latest` and return them."""
        self.latest = evaluate_model(model, self.validation, self.cfg)
        return self.latest

    @property
    def fits(self) -> dict[str, dict[str, float]]:
        """The latest scores as plain dictionaries (FIT and RMS on q and q̇), by record."""
        return {name: score.to_dict() for name, score in self.latest.items()}

    def on_pass_end(self, record: PassRecord, result: EKFResult) -> bool | None:
        self.update(result.model)
        return None


class TensorBoardLog(Callback):
    """Scalars and figures in the run's TensorBoard events, under the run's fixed tags.

    Scalars are written every pass or epoch. Figures (the friction curve, each validation
    record's response) cost more to draw than a pass of the filter, so they are drawn when they
    are looked at (`torchfric.app.sections.LogConfig`): for the starting model (step 0) and the
    final one when the run ends (`finish`), and in between every ``log.figure_every`` passes
    or epochs ("auto": at most once a minute). A figure not drawn at its pass keeps that
    pass's model (a copy) and scores, so the end figures are those of their own steps."""

    AUTO_SECONDS = 60.0

    def __init__(
        self, cfg: Config, writer: Any, scores: ValidationScores, v_max: float, model: ArmModel
    ) -> None:
        self.cfg, self.writer, self.scores, self.v_max = cfg, writer, scores, v_max
        self.model = model  # the starting model: it splits an ensemble's θ into parameters
        self.drawn_at = time.perf_counter()
        # figures owed, by step: the start's (step 0) and the latest pass's or epoch's
        self.owed: dict[int, Callable[[], None]] = {}

    def due(self, step: int) -> bool:
        """Whether the figures of `step` are drawn now rather than at the end."""
        every = self.cfg.log.figure_every
        if every == "auto":
            return time.perf_counter() - self.drawn_at >= self.AUTO_SECONDS
        return every > 0 and step % every == 0

    def figures(self, step: int, draw: Callable[[], None]) -> None:
        """Draw `step`'s figures with `draw` now when `due`, else owe them: the latest owed
        figures replace the previous pass's (the start's are kept)."""
        if self.due(step):
            self.owed.pop(step, None)
            draw()
            self.drawn_at = time.perf_counter()
            return
        self.owed = {k: v for k, v in self.owed.items() if k == 0}
        self.owed[step] = draw

    def finish(self) -> None:
        """The figures still owed (the start's and the final model's), drawn at the run's end."""
        for step in sorted(self.owed):
            self.owed.pop(step)()
        self.writer.flush()

    def log_model(self, step: int, model: ArmModel, scalars: dict[str, float]) -> None:
        """`model`'s parameters, `scalars` and the latest validation scores; its friction curve
        and responses (`figures`)."""
        for name, value in model.physical_parameters().items():
            self.writer.add_scalar(f"parameters/{name}", value, step)
        for key, value in scalars.items():
            self.writer.add_scalar(key, value, step)
        for e, score in zip(self.scores.validation, self.scores.latest.values(), strict=True):
            self.writer.add_scalar(f"validation/{e.name}/fit_q", score.fit_q, step)
            self.writer.add_scalar(f"validation/{e.name}/fit_qdot", score.fit_qdot, step)
        frozen, latest = copy.deepcopy(model), list(self.scores.latest.values())
        unit = self.cfg.data.position_unit

        def draw() -> None:
            curve = friction_figure(frozen, self.v_max, f"pass {step}", unit)
            self.writer.add_figure("friction_curve", curve, step)
            for e, score in zip(self.scores.validation, latest, strict=True):
                self.writer.add_figure(
                    f"validation/{e.name}", response_figure(e, score, unit), step
                )

        self.figures(step, draw)
        self.writer.flush()

    def on_pass_end(self, record: PassRecord, result: EKFResult) -> bool | None:
        self.log_model(record.index, result.model, ekf_scalars(record))
        return None

    def log_ensemble_result(self, result: EKFResult) -> None:
        """The kept member's own pass history under the single filter's tags (parameters,
        trace(P), innovation RMS, NIS, log-likelihood per pass), so that a default run's
        TensorBoard reads like a single filter's; the members' spread is under ensemble/.
        Its final pass is logged with `log_model` (scores it on the validation records)."""
        for record in result.history[:-1]:
            for key, value in {
                **{f"parameters/{n}": v for n, v in record.parameters.items()},
                **ekf_scalars(record),
            }.items():
                self.writer.add_scalar(key, value, record.index)
        last = result.history[-1] if result.history else None
        self.scores.update(result.model)
        self.log_model(max(result.passes, 1), result.model, ekf_scalars(last) if last else {})

    def on_ensemble_pass_end(self, pass_index: int, state: dict[str, Any]) -> bool | None:
        counts, inertia = ensemble_spread(self.model, state)
        for s, c in counts.items():
            self.writer.add_scalar(f"ensemble/{s}", c, pass_index)
        if inertia:
            for tag, v in (
                ("min", inertia[0]),
                ("median", inertia[len(inertia) // 2]),
                ("max", inertia[-1]),
            ):
                self.writer.add_scalar(f"ensemble/inertia_{tag}", v, pass_index)
        lls = [h[-1]["loglik"] for h in state["histories"] if h and h[-1]["index"] == pass_index]
        if lls:
            self.writer.add_scalar("ensemble/loglik_best", max(lls), pass_index)
        self.writer.flush()
        return None

    def on_epoch_end(self, record: EpochRecord, result: OEResult) -> bool | None:
        w = self.writer
        for name, value in record.parameters.items():
            w.add_scalar(f"parameters/{name}", value, record.index)
        w.add_scalar("oe/loss", record.loss, record.index)
        w.add_scalar("oe/lr", record.lr, record.index)
        w.add_scalar("oe/window", record.window, record.index)
        if record.val_fit is not None:
            for name, f in record.val_fit.items():
                w.add_scalar(f"validation/{name}/fit_q", f["fit_q"], record.index)
                w.add_scalar(f"validation/{name}/fit_qdot", f["fit_qdot"], record.index)
            title = f"epoch {record.index} (best {result.best_epoch})"
            frozen, step, unit = (
                copy.deepcopy(result.model),
                record.index,
                self.cfg.data.position_unit,
            )
            self.figures(step, lambda: w.add_figure(
                "friction_curve", friction_figure(frozen, self.v_max, title, unit), step))  # fmt: skip
        w.flush()
        return None


class ProgressLines(Callback):
    """The run's progress lines through `say`: within a pass (``\\r`` lines a terminal
    overwrites), and one line after each pass, ensemble pass or validated epoch."""

    def __init__(self, cfg: Config, say: Printer, scores: ValidationScores, model: ArmModel):
        self.cfg, self.say, self.scores = cfg, say, scores
        self.model = model  # the starting model: it splits an ensemble's θ into parameters
        self.t_pass = time.perf_counter()

    def on_progress(self, pass_index: int, samples_done: int, samples_total: int) -> None:
        rate = samples_done / max(time.perf_counter() - self.t_pass, 1e-9)
        self.say(
            f"\r  pass {pass_index}/{self.cfg.estimator.passes}: {samples_done}/{samples_total} samples, {rate:,.0f} samples/s"
        )

    def on_pass_end(self, record: PassRecord, result: EKFResult) -> bool | None:
        text = fit_text(self.scores.fits)
        if record.rolled_back:
            self.say(
                f"\r  pass {record.index} lowered the innovation log-likelihood "
                f"({record.loglik:.6g}): undone, keeping pass {record.index - 1}; stopping\n"
            )
        self.say(
            f"\r  pass {record.index}/{self.cfg.estimator.passes} done in {duration(record.seconds)} "
            f"({record.samples / max(record.seconds, 1e-9):,.0f} samples/s): "
            f"inertia {record.parameters['inertia']:.6g}, Δθ {record.rel_change:.2e}"
            + (f", {text}" if text else "")
            + "\n"
        )
        self.t_pass = time.perf_counter()
        return None

    def on_ensemble_pass_end(self, pass_index: int, state: dict[str, Any]) -> bool | None:
        counts, inertia = ensemble_spread(self.model, state)
        spread = f"inertia {inertia[0]:.5g} … {inertia[-1]:.5g}" if inertia else "no member left"
        self.say(
            f"\r  pass {pass_index}/{self.cfg.estimator.passes} of {len(state['status'])} members "
            f"done in {duration(time.perf_counter() - self.t_pass)}: "
            + ", ".join(f"{c} {s}" for s, c in counts.items())
            + f"; {spread}\n"
        )
        self.t_pass = time.perf_counter()
        return None

    def on_epoch_end(self, record: EpochRecord, result: OEResult) -> bool | None:
        if record.val_fit is not None:
            text = fit_text(record.val_fit)
            self.say(
                f"  epoch {record.index}/{self.cfg.estimator.epochs}: loss {record.loss:.4g}, "
                f"inertia {record.parameters['inertia']:.6g}" + (f", {text}" if text else "") + "\n"
            )
        return None
