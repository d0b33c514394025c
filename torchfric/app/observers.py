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

import time
from collections.abc import Callable
from typing import Any, TextIO

from ..data import Experiment
from ..estimators.ekf import MEASUREMENTS
from ..estimators.identify import EKFResult, PassRecord
from ..estimators.metrics import SimulationScore, mean_fit
from ..estimators.observers import Callback
from ..estimators.output_error import EpochRecord, OEResult
from ..models.arm import ArmModel
from .config import Config
from .evaluation import evaluate_model
from .figures import friction_figure, model_figures, pixels
from .hparams import final_metrics, hparam_values

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


# The names of the state entries [q, q̇] a filter measures (`MEASUREMENTS` gives their indices).
CHANNELS = ("q", "qdot")


def ekf_scalars(record: PassRecord, measure: str = "both") -> dict[str, float]:
    """A pass's filter diagnostics as TensorBoard scalars (`ekf/...`); the innovation RMS per
    measured channel (`estimator.measure`) by name: ``ekf/innovation_rms/q``, ``…/qdot``."""
    scalars = {
        "ekf/trace_P": record.trace_P,
        "ekf/trace_P_theta": record.trace_P_theta,
        "ekf/nis": record.nis,
        "ekf/loglik": record.loglik,
        "ekf/rel_change": record.rel_change,
    }
    channels = [CHANNELS[i] for i in MEASUREMENTS[measure]]
    for name, v in zip(channels, record.innovation_rms, strict=True):
        scalars[f"ekf/innovation_rms/{name}"] = v
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
        # (pass, score, scores) of the best-scored pass so far, ties to the later (as
        # `keep_best` chooses): the run's final scores when it keeps that pass
        self.best: tuple[int, float, dict[str, SimulationScore]] | None = None

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
        # the pass's score goes into its record (and so into the snapshots): the run keeps the
        # pass that validates best (`torchfric.app.outcome.keep_best`)
        if not record.rolled_back:
            record.val_score = score = mean_fit(self.fits)
            if score is not None and (self.best is None or score >= self.best[1]):
                self.best = (record.index, score, self.latest)
        return None

    def scores_at(self, index: int | None) -> dict[str, SimulationScore] | None:
        """The validation scores of pass `index` when it is the best-scored pass (the one a
        run keeps), else None."""
        return self.best[2] if self.best is not None and self.best[0] == index else None


class TensorBoardLog(Callback):
    """Scalars, text, figures and hparams in the run's TensorBoard events, under fixed tags.

    The resolved config is the text "config" (at the start); `log_hparams` adds the config's
    keys and the final metrics at the end, in the run's own event file, so that the HParams tab
    of ``tensorboard --logdir runs/`` compares runs. Scalars are written every pass or epoch;
    an ensemble's members each under ``ensemble/member_<i>/`` (inertia, loglik), overlaid in
    one chart per quantity in the Custom Scalars tab. Figures (the friction curve with its ±2σ
    band, each validation record's response and residuals) cost more to draw than a pass of
    the filter, so they are drawn when they are looked at (`torchfric.app.sections.LogConfig`): for the starting model (step 0) and the
    final one when the run ends (`finish`), and in between every ``log.figure_every`` passes
    or epochs ("auto": at most once a minute). A figure not drawn at its pass keeps that
    pass's model and scores, so the end figures are those of their own steps."""

    AUTO_SECONDS = 60.0

    def __init__(
        self, cfg: Config, writer: Any, scores: ValidationScores, v_max: float, model: ArmModel
    ) -> None:
        self.cfg, self.writer, self.scores, self.v_max = cfg, writer, scores, v_max
        self.model = model  # the starting model: it splits an ensemble's θ into parameters
        self.drawn_at = time.perf_counter()
        # figures owed, by step: the start's (step 0) and the latest pass's or epoch's
        self.owed: dict[int, Callable[[], None]] = {}
        self.drawn: set[int] = set()  # the steps whose figures are written
        self.members_layout = False  # the Custom Scalars layout of the ensemble's members
        writer.add_text("config", f"```toml\n{cfg.to_toml()}```", 0)

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

    def model_pixels(
        self, step: int, model: ArmModel, P_theta: Any, scores: dict[str, SimulationScore]
    ) -> dict[str, Any]:
        """`model`'s figures (`model_figures`) drawn to pixels, by tag."""
        figs = model_figures(
            model, self.v_max, f"pass {step}", self.cfg.data.position_unit, P_theta,
            self.scores.validation, scores,
        )  # fmt: skip
        return {tag: pixels(fig) for tag, fig in figs.items()}

    def add_images(self, step: int, images: dict[str, Any]) -> None:
        """Figures drawn to pixels (`pixels`), by tag, at `step`."""
        for tag, chw in images.items():
            self.writer.add_image(tag, chw, step, dataformats="CHW")
        self.drawn.add(step)

    def finish(self, kept: tuple[int, dict[str, Any]] | None = None) -> None:
        """The figures still owed, drawn at the run's end: the start's, and the final model's.

        `kept` is ``(step, pixels by tag)`` of the model the run keeps (its best pass or
        epoch), drawn once by the runner for TensorBoard and report.html alike; it takes the
        place of the last pass's owed figures. Without it (a diverged run) the last pass's are
        drawn."""
        if 0 in self.owed:
            self.owed.pop(0)()
        if kept is not None:
            self.owed.clear()
            if kept[0] not in self.drawn:
                self.add_images(*kept)
        for step in sorted(self.owed):
            self.owed.pop(step)()
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

        def draw() -> None:
            self.add_images(step, self.model_pixels(step, model, P_theta, latest))

        self.figures(step, draw)
        self.writer.flush()

    def on_pass_end(self, record: PassRecord, result: EKFResult) -> bool | None:
        scalars = ekf_scalars(record, self.cfg.estimator.measure)
        self.log_model(record.index, result.model, scalars, result.P_theta)
        return None

    def log_ensemble_result(self, result: EKFResult) -> None:
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

    def log_hparams(self, metrics: dict[str, Any]) -> None:
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
            model, step, unit = result.model, record.index, self.cfg.data.position_unit
            self.figures(step, lambda: self.add_images(step, {
                "friction_curve": pixels(friction_figure(model, self.v_max, title, unit))}))  # fmt: skip
        w.flush()
        return None


class ProgressLines(Callback):
    """The run's progress on stderr: one line after each pass, ensemble pass or validated epoch
    (through `say`), and, when `bars` is a stream (a terminal), tqdm progress bars: passes or
    epochs with their rate and ETA, and the samples within a pass. Without bars the samples
    within a pass are ``\\r`` lines that only a terminal shows."""

    def __init__(
        self,
        cfg: Config,
        say: Printer,
        scores: ValidationScores,
        model: ArmModel,
        bars: TextIO | None = None,
    ):
        self.cfg, self.say, self.scores = cfg, say, scores
        self.model = model  # the starting model: it splits an ensemble's θ into parameters
        self.t_pass = time.perf_counter()
        self.bars = bars
        self._outer: Any = None  # passes or epochs
        self._inner: Any = None  # samples of the running pass

    # -- bars ----------------------------------------------------------------------------------
    def _bar(self, **kwargs: Any) -> Any:
        from tqdm import tqdm

        return tqdm(file=self.bars, dynamic_ncols=True, mininterval=0.2, **kwargs)

    def _advance(self, index: int, unit: str, total: int, postfix: str) -> None:
        """Move the passes (or epochs) bar to `index` of `total` and show `postfix`."""
        if self.bars is None:
            return
        if self._inner is not None:
            self._inner.close()
            self._inner = None
        self._open(index, unit, total)
        self._outer.set_postfix_str(postfix, refresh=False)
        self._outer.update(index - self._outer.n)
        self._outer.refresh()  # once per pass: the last pass shows even when it was quick

    def _open(self, index: int, unit: str, total: int) -> None:
        """The passes (or epochs) bar, opened at the first report of `index` (so that a
        resumed run starts where it left off)."""
        if self._outer is None:
            self._outer = self._bar(
                total=total, initial=index - 1, desc=f"{unit}es" if unit == "pass" else f"{unit}s",
                unit=unit, leave=False,
            )  # fmt: skip

    def close(self) -> None:
        """Close the bars (the per-pass lines stay on the screen)."""
        for bar in (self._inner, self._outer):
            if bar is not None:
                bar.close()
        self._inner = self._outer = None

    # -- callbacks ----------------------------------------------------------------------------
    def on_progress(self, pass_index: int, samples_done: int, samples_total: int) -> None:
        if self.bars is not None:
            self._open(pass_index, "pass", self.cfg.estimator.passes)
            if self._inner is None:
                self._inner = self._bar(
                    total=samples_total, desc=f"pass {pass_index}", unit="sample",
                    unit_scale=True, leave=False,
                )  # fmt: skip
            self._inner.update(samples_done - self._inner.n)
            return
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
        self._advance(
            record.index, "pass", self.cfg.estimator.passes,
            f"inertia {record.parameters['inertia']:.5g}, Δθ {record.rel_change:.1e}",
        )  # fmt: skip
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
        members = ", ".join(f"{c} {s}" for s, c in counts.items())
        self._advance(pass_index, "pass", self.cfg.estimator.passes, f"members: {members}")
        self.say(
            f"\r  pass {pass_index}/{self.cfg.estimator.passes} of {len(state['status'])} members "
            f"done in {duration(time.perf_counter() - self.t_pass)}: {members}; {spread}\n"
        )
        self.t_pass = time.perf_counter()
        return None

    def on_epoch_end(self, record: EpochRecord, result: OEResult) -> bool | None:
        total = self.cfg.estimator.epochs + (1 if self.cfg.estimator.lbfgs_steps else 0)
        self._advance(
            record.index, "epoch", max(total, record.index),
            f"loss {record.loss:.3g}, best epoch {result.best_epoch}",
        )  # fmt: skip
        if record.val_fit is not None:
            text = fit_text(record.val_fit)
            self.say(
                f"  epoch {record.index}/{self.cfg.estimator.epochs}: loss {record.loss:.4g}, "
                f"inertia {record.parameters['inertia']:.6g}" + (f", {text}" if text else "") + "\n"
            )
        return None


def best_member_loglik(state: dict[str, Any], pass_index: int) -> float | None:
    """The best innovation log-likelihood of an ensemble's members that ran pass `pass_index`
    (`EnsembleCallback.on_ensemble_pass_end`'s `state`); None when none did."""
    lls = [h[-1]["loglik"] for h in state["histories"] if h and h[-1]["index"] == pass_index]
    return max(lls) if lls else None
