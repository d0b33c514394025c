"""The run's TensorBoard events: `TensorBoardLog` (an observer of the estimators) and what
the HParams tab compares runs by.

`hparam_values` flattens the resolved config into dotted keys with scalar values (the types the
HParams tab sorts and filters: numbers, strings, and booleans as "true"/"false"; lists and
missing values as text), and `final_metrics` picks the numbers that compare runs from
``metrics.json``, under the ``final/`` tags that `TensorBoardLog.log_hparams` also logs as
scalars: the HParams tab reads a metric's value from the scalar of the same tag in the run.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Mapping
from typing import Any

from ...errors import TorchfricError
from ...estimators.identify import EKFResult, PassRecord
from ...estimators.observers import Callback, RunEnd, RunStart
from ...estimators.output_error import EpochRecord, OEResult
from ...models.arm import ArmModel
from ..artifacts import friction_spec
from ..config import Config
from .monitors import (
    KeptFigures,
    ValidationScores,
    best_member_loglik,
    ekf_scalars,
    ensemble_spread,
)

__all__ = ["TensorBoardLog", "final_metrics", "hparam_values"]

# metrics.json keys that compare runs, in this order (present ones only)
_FINAL_KEYS = ("inertia", "best_pass", "passes", "epochs", "converged", "seconds")


def _text(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_text(v) for v in value) + "]"
    return str(value)


def hparam_values(config: Mapping[str, Any], prefix: str = "") -> dict[str, float | str]:
    """The config (`Config.to_dict`) as ``{"estimator.passes": 10, "data.train":
    "[rig:identification]", "estimator.compile": "true", …}``: tables become dotted keys,
    an empty table is the text "{}"."""
    out: dict[str, float | str] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(hparam_values(value, f"{name}.") if value else {name: "{}"})
        elif isinstance(value, int | float) and not isinstance(value, bool):
            out[name] = value
        else:
            out[name] = _text(value)
    return out


def final_metrics(metrics: Mapping[str, Any]) -> dict[str, float]:
    """The run's final numbers by TensorBoard tag: ``final/inertia``, ``final/best_pass``,
    ``final/passes`` (``final/epochs``), ``final/converged`` (1 or 0), ``final/seconds`` and
    ``final/validation/<record>/fit_q`` and ``…/fit_qdot``. Missing or non-finite ones are left
    out."""
    out: dict[str, float] = {}
    for key in _FINAL_KEYS:
        value = metrics.get(key)
        if isinstance(value, bool):
            value = 1.0 if value else 0.0
        if isinstance(value, int | float) and math.isfinite(value):
            out[f"final/{key}"] = float(value)
    for name, fits in (metrics.get("validation") or {}).items():
        for key in ("fit_q", "fit_qdot"):
            value = fits.get(key)
            if isinstance(value, int | float) and math.isfinite(value):
                out[f"final/validation/{name}/{key}"] = float(value)
    return out


class TensorBoardLog(Callback):
    """Scalars, text, figures and hparams in the run's TensorBoard events, under fixed tags.

    The resolved config is the text "config" (at the start); `log_hparams` adds the config's
    keys and the final metrics at the end, in the run's own event file, so that the HParams tab
    of ``tensorboard --logdir runs/`` compares runs. Scalars are written every pass or epoch;
    an ensemble's members each under ``ensemble/member_<i>/`` (inertia, loglik), overlaid in
    one chart per quantity in the Custom Scalars tab. Figures (the friction curve with its ±2σ
    band, each validation record's response and residuals) cost more to draw than a pass of
    the filter, so they are drawn when they are looked at (`torchfric.app.config.LogConfig`): for the
    starting model (step 0) and the kept one when the run ends (`on_run_end`: the same pixels
    that report.html shows, drawn once by `KeptFigures`), and in between every
    ``log.figure_every`` passes or epochs ("auto": at most once a minute). A figure not drawn
    at its pass keeps that pass's model and scores, so the end figures are those of their own
    steps. The writer is closed when the run ends or stops."""

    AUTO_SECONDS = 60.0

    def __init__(
        self,
        cfg: Config,
        writer: Any,
        scores: ValidationScores,
        drawing: KeptFigures,
        model: ArmModel,
    ) -> None:
        self.cfg, self.writer, self.scores, self.drawing = cfg, writer, scores, drawing
        self.v_max = drawing.v_max
        self.model = model  # the starting model: it splits an ensemble's θ into parameters
        self.drawn_at = time.perf_counter()
        # figures owed, by step: the start's (step 0) and the latest pass's or epoch's
        self.owed: dict[int, Callable[[], dict[str, int]]] = {}
        self.pending: dict[int, dict[str, int]] = {}  # handed to the painter, not yet written
        self.drawn: set[int] = set()  # the steps whose figures are written
        self.members_layout = False  # the Custom Scalars layout of the ensemble's members
        writer.add_text("config", f"```toml\n{cfg.to_toml()}```", 0)

    def due(self, step: int) -> bool:
        """Whether the figures of `step` are drawn now rather than at the end."""
        every = self.cfg.log.figure_every
        if every == "auto":
            return time.perf_counter() - self.drawn_at >= self.AUTO_SECONDS
        return every > 0 and step % every == 0

    def figures(self, step: int, draw: Callable[[], dict[str, int]]) -> None:
        """Hand `step`'s figures to the painter with `draw` now when it is the start's (the
        painter draws them while the run goes on) or `due`, else owe them: the latest owed
        figures replace the previous pass's. Figures handed over are written when drawn
        (`write_drawn`)."""
        if step == 0 or self.due(step):
            self.owed.pop(step, None)
            self.pending[step] = draw()
            if step:
                self.drawn_at = time.perf_counter()
            return
        self.owed = {k: v for k, v in self.owed.items() if k == 0}
        self.owed[step] = draw

    def write_drawn(self, wait: bool = False) -> None:
        """Write the figures the painter has drawn (all of them, waiting, with `wait`)."""
        for step in sorted(self.pending):
            if wait or self.drawing.ready(self.pending[step]):
                for tag, png in self.drawing.pngs(self.pending.pop(step)).items():
                    self._add_png(tag, png, step)
                self.drawn.add(step)

    def _add_png(self, tag: str, png: bytes, step: int) -> None:
        """An image summary of PNG bytes, as ``add_image`` writes one (without encoding the
        pixels again)."""
        from tensorboard.compat.proto.summary_pb2 import Summary

        width, height = struct.unpack(">II", png[16:24])  # the IHDR chunk
        image = Summary.Image(height=height, width=width, colorspace=3, encoded_image_string=png)
        summary = Summary(value=[Summary.Value(tag=tag, image=image)])
        self.writer._get_file_writer().add_summary(summary, step)

    def finish(self, kept: tuple[int, dict[str, int]] | None = None) -> None:
        """The figures still owed, handed over at the run's end and written with the others.

        `kept` is ``(step, figures by tag)`` of the model the run keeps (its best pass or
        epoch), drawn once for TensorBoard and report.html alike; it takes the place of the
        last pass's owed figures. Without it (a diverged run) the last pass's are drawn."""
        if 0 in self.owed:
            self.pending[0] = self.owed.pop(0)()
        if kept is not None:
            self.owed.clear()
            step, drawing = kept
            if step not in self.drawn and step not in self.pending:
                self.pending[step] = drawing
        for step in sorted(self.owed):
            self.pending[step] = self.owed.pop(step)()
        self.write_drawn(wait=True)
        self.writer.flush()

    def log_model(
        self, step: int, model: ArmModel, scalars: dict[str, float], P_theta: Any = None
    ) -> None:
        """`model`'s parameters, `scalars` and the latest validation scores; its friction curve
        (with the ±2σ band of `P_theta`, θ's covariance, when given), responses and residuals
        (`figures`)."""
        for name, value in model.physical_parameters().items():
            self.writer.add_scalar(f"parameters/{name}", value, step)
        for key, value in scalars.items():
            self.writer.add_scalar(key, value, step)
        for e, score in zip(self.scores.validation, self.scores.latest.values(), strict=True):
            self.writer.add_scalar(f"validation/{e.name}/fit_q", score.fit_q, step)
            self.writer.add_scalar(f"validation/{e.name}/fit_qdot", score.fit_qdot, step)
        # No copies for a figure owed until later: every caller hands over a model and a
        # P_θθ of its own (`PassLedger.result` copies both each pass; the starting model is
        # never changed by the estimator), and the scores are replaced, never changed.
        latest = self.scores.latest

        self.figures(step, lambda: self.drawing.draw(step, model, P_theta, latest))
        self.write_drawn()
        self.writer.flush()

    def on_run_start(self, start: RunStart) -> None:
        if not start.resumed:  # pass 0: the starting model (`ValidationScores` scored it)
            self.log_model(0, start.model, {})

    def on_run_end(self, end: RunEnd) -> None:
        self.finish((end.step, self.drawing.kept(end)))
        self.log_hparams(end.metrics)
        self.writer.close()

    def on_exception(self, error: BaseException) -> None:
        try:  # a diverged run's figures so far are worth a look; Ctrl-C should not wait
            if isinstance(error, TorchfricError):
                self.finish()
        finally:
            self.writer.close()

    def on_pass_end(self, record: PassRecord, result: EKFResult) -> bool | None:
        scalars = ekf_scalars(record, self.cfg.estimator.measure)
        self.log_model(record.index, result.model, scalars, result.P_theta)
        return None

    def on_ensemble_end(self, result: EKFResult) -> None:
        """The kept member's own pass history under the single filter's tags (parameters,
        trace(P), innovation RMS, NIS, log-likelihood per pass), so that a default run's
        TensorBoard reads like a single filter's; the members' spread is under ensemble/.
        Its final pass is logged with `log_model` (scores it on the validation records)."""
        for record in result.history[:-1]:
            for key, value in {
                **{f"parameters/{n}": v for n, v in record.parameters.items()},
                **ekf_scalars(record, self.cfg.estimator.measure),
            }.items():
                self.writer.add_scalar(key, value, record.index)
        last = result.history[-1] if result.history else None
        self.scores.update(result.model)
        scalars = ekf_scalars(last, self.cfg.estimator.measure) if last else {}
        self.log_model(max(result.passes, 1), result.model, scalars, result.P_theta)

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
        best = best_member_loglik(state, pass_index)
        if best is not None:
            self.writer.add_scalar("ensemble/loglik_best", best, pass_index)
        self.log_members(pass_index, state["histories"])
        self.writer.flush()
        return None

    def log_members(self, pass_index: int, histories: list[list[dict[str, Any]]]) -> None:
        """Each member's inertia and log-likelihood after pass `pass_index`, under its own tags
        (``ensemble/member_<i>/…``: one point per pass it ran; a stopped or diverged member's
        curve ends there). Separate tags rather than ``add_scalars``, whose sub-runs would add
        every member as a run of its own to TensorBoard's run list and HParams tab; the Custom
        Scalars tab overlays them, one chart per quantity."""
        if not self.members_layout:
            self.writer.add_custom_scalars({"ensemble members": {
                "inertia of each member": ["Multiline", [r"ensemble/member_\d+/inertia"]],
                "log-likelihood of each member": ["Multiline", [r"ensemble/member_\d+/loglik"]],
            }})  # fmt: skip
            self.members_layout = True
        for i, history in enumerate(histories):
            if history and history[-1]["index"] == pass_index:
                record = history[-1]
                inertia = record["parameters"]["inertia"]
                self.writer.add_scalar(f"ensemble/member_{i}/inertia", inertia, pass_index)
                self.writer.add_scalar(f"ensemble/member_{i}/loglik", record["loglik"], pass_index)

    def log_hparams(self, metrics: Mapping[str, Any]) -> None:
        """The run's config keys (`hparam_values`) and final metrics (`final_metrics`, also
        logged as scalars: the HParams tab reads their values from them) as hparams, in the
        run's own event file (``SummaryWriter.add_hparams`` would write a sub-run)."""
        from torch.utils.tensorboard.summary import hparams

        final = final_metrics(metrics)
        step = int(metrics.get("passes", metrics.get("epochs", 0)) or 0)
        experiment, start, end = hparams(hparam_values(self.cfg.to_dict()), final)
        events = self.writer._get_file_writer()
        for summary in (experiment, start, end):
            events.add_summary(summary, step)
        for tag, value in final.items():
            self.writer.add_scalar(tag, value, step)
        self.writer.flush()

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
            model, step, unit = result.model, record.index, self.cfg.data.axis_unit
            self.figures(step, lambda: {"friction_curve": self.drawing.painter.submit(
                *friction_spec(model, self.v_max, title, unit))})  # fmt: skip
            self.write_drawn()
        w.flush()
        return None
