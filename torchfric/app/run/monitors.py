"""The scores every observer reads, and the progress a user watches.

- `ValidationScores`: the open-loop scores of each pass's model on the validation records (the
  first observer of a run: the others read its scores, and the run keeps the pass it scores
  best);
- `KeptFigures`: a model's figures (friction curve with its ±2σ band, each validation
  record's response and residuals), drawn as PNG by the run's helper process; the kept
  model's once per run, for TensorBoard and report.html alike;
- `ProgressLines`: the progress lines (``say``) in and after each pass or epoch, and tqdm bars
  on a terminal;
- the helpers that format a pass for them (`ekf_scalars`, `fit_text`, `duration`,
  `ensemble_spread`, `best_member_loglik`).

The run's whole list of observers is built in `torchfric.app.run.views.run_observers`.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any, TextIO

import torch

from ...data import Experiment
from ...estimators.ekf import MEASUREMENTS
from ...estimators.identify import EKFResult, PassRecord
from ...estimators.metrics import SimulationScore, mean_fit
from ...estimators.observers import Callback, RunEnd, RunStart
from ...estimators.output_error import EpochRecord, OEResult
from ...models.arm import ArmModel
from ..artifacts import model_specs, render, shared_painter, trajectory_spec
from ..config import Config
from .assessment import evaluate_model

__all__ = [
    "KeptFigures",
    "Printer",
    "ValidationScores",
    "ProgressLines",
    "duration",
    "ekf_scalars",
    "fit_text",
    "ensemble_spread",
    "best_member_loglik",
    "bar_size",
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


def bar_size(stream: Any) -> tuple[int, int] | None:
    """None when `stream` is a terminal that reports its size (tqdm follows it as it changes),
    else the columns and rows to draw bars in: ``COLUMNS`` and ``LINES``, else 80 × 24. A
    pseudo-terminal opened without a size (``script``, an IDE's console, ``docker run -t``)
    reports 0 × 0: tqdm then draws no bar (0 columns), and under ``script``, which gives it
    −1 rows, hides every bar: no rate, no ETA, only the lines after each pass."""
    try:
        size = os.get_terminal_size(stream.fileno())
        if size.columns > 0 and size.lines > 0:
            return None
    except (AttributeError, OSError, ValueError):  # no file descriptor, or not a terminal
        pass
    fallback = shutil.get_terminal_size()
    return fallback.columns, fallback.lines


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

    def on_run_start(self, start: RunStart) -> None:
        if not start.resumed:  # pass 0's scores, which the start's log and line show
            self.update(start.model)

    def on_pass_end(self, record: PassRecord, result: EKFResult) -> bool | None:
        self.update(result.model)
        # the pass's score goes into its record (and so into the snapshots): the run keeps the
        # pass that validates best (`torchfric.app.run.outcome.keep_best`)
        if not record.rolled_back:
            record.val_score = score = mean_fit(self.fits)
            if score is not None and (self.best is None or score >= self.best[1]):
                self.best = (record.index, score, self.latest)
        return None

    def scores_at(self, index: int | None) -> dict[str, SimulationScore] | None:
        """The validation scores of pass `index` when it is the best-scored pass (the one a
        run keeps), else None."""
        return self.best[2] if self.best is not None and self.best[0] == index else None


class KeptFigures:
    """A model's figures (`draw`), drawn as PNG in the process's helper
    (`torchfric.app.artifacts.shared_painter`, started here) while the run goes on; the kept
    model's once per run (`kept`), with the report's parameter trajectories (`trajectory`).
    A drawing is a mapping of tag to figure id; `pngs` collects it.

    What does not wait for the run's σ is handed over when the estimator ends (`early`): the
    kept model's responses and residuals and the trajectories, drawn while the σ are computed;
    `kept` then only adds the friction curve with its band, unless the model changed since."""

    def __init__(self, cfg: Config, validation: Sequence[Experiment], v_max: float) -> None:
        self.cfg, self.validation, self.v_max = cfg, list(validation), v_max
        self._kept: tuple[RunEnd, dict[str, int]] | None = None
        self._early: tuple[Any, ...] | None = None
        self._pngs: dict[int, bytes] = {}
        self._trajectory: int | bytes | None = None  # figure id or PNG
        self.painter = shared_painter()

    def draw(
        self,
        step: int,
        model: ArmModel,
        P_theta: Any,
        scores: Mapping[str, SimulationScore],
        skip: Collection[str] = (),
        title: str | None = None,
    ) -> dict[str, int]:
        """`model`'s figures (`model_specs`) at `step`, handed to the painter, by tag (but
        those of `skip`); the friction curve titled `title` (default "pass STEP")."""
        specs = model_specs(
            model, self.v_max, title or f"pass {step}", self.cfg.data.axis_unit, P_theta,
            self.validation, dict(scores),
        )  # fmt: skip
        return {t: self.painter.submit(*spec) for t, spec in specs.items() if t not in skip}

    def ready(self, drawing: Mapping[str, int]) -> bool:
        """Whether `pngs` of `drawing` returns without waiting."""
        return all(f in self._pngs or self.painter.ready(f) for f in drawing.values())

    def pngs(self, drawing: Mapping[str, int]) -> dict[str, bytes]:
        """The PNG of each figure of `drawing`, by tag (waiting for the painter)."""
        for fid in drawing.values():
            if fid not in self._pngs:
                self._pngs[fid] = self.painter.png(fid)
        return {tag: self._pngs[fid] for tag, fid in drawing.items()}

    @staticmethod
    def _best(end: RunEnd) -> Any:
        return end.metrics.get("best_pass", end.metrics.get("best_epoch"))

    def early(self, end: RunEnd) -> None:
        """Hand over the figures of the estimator's kept model that do not need its σ: the
        responses and residuals (when `end` has the scores of every validation record) and
        the trajectories."""
        scored = all(e.name in end.scores for e in self.validation)
        drawing = self.draw(end.step, end.model, None, end.scores, {"friction_curve"}) if scored else {}  # fmt: skip
        if end.history:
            drawing["trajectory"] = self.painter.submit(*trajectory_spec(end.history, self._best(end)))  # fmt: skip
        theta = end.model.get_theta().detach().clone()
        self._early = (theta, end.scores, end.step, self._best(end), len(end.history), drawing)

    def _early_for(self, end: RunEnd) -> dict[str, int]:
        """The figures `early` handed over, when they are `end`'s (the same θ, scores, step,
        kept pass and history)."""
        if self._early is None:
            return {}
        theta, scores, step, best, n, drawing = self._early
        same = (end.scores is scores and end.step == step and self._best(end) == best
                and len(end.history) == n and torch.equal(end.model.get_theta().detach(), theta))  # fmt: skip
        return drawing if same else {}

    def kept(self, end: RunEnd) -> dict[str, int]:
        """The kept model's figures (`draw`), handed over at the first call for `end` (those
        `early` handed over are reused); then, while the painter draws them, the trajectories
        drawn here when `early` did not hand them over (`trajectory`, for report.html): the
        run waits for both at once, not one after the other."""
        if self._kept is None or self._kept[0] is not end:
            early = dict(self._early_for(end))
            self._trajectory = early.pop("trajectory", None)
            # a kept polish moved θ from the pass: the curve drawn is the polished one
            title = f"pass {end.step}, polished" if "polished" in end.metrics else None
            drawn = self.draw(end.step, end.model, end.covariance, end.scores, early, title)
            drawing = {**early, **drawn}
            self._kept = (end, drawing)
            if self._trajectory is None and end.history:
                self._trajectory = render(*trajectory_spec(end.history, self._best(end)))
        return self._kept[1]

    def trajectory(self) -> bytes | None:
        """The kept run's parameter trajectories as PNG (after `kept`), None without history."""
        if isinstance(self._trajectory, int):
            self._trajectory = self.painter.png(self._trajectory)
        return self._trajectory


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

        size = bar_size(self.bars)
        shape: dict[str, Any] = (
            {"dynamic_ncols": True} if size is None else {"ncols": size[0], "nrows": size[1]}
        )
        return tqdm(file=self.bars, mininterval=0.2, **shape, **kwargs)

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
    def on_run_start(self, start: RunStart) -> None:
        if start.resumed:
            return
        text = fit_text(self.scores.fits)
        self.say(
            f"  pass 0 ({start.init}): inertia {float(start.model.inertia.detach()):.6g}"
            + (f", {text}" if text else "")
        )

    def on_run_end(self, end: RunEnd) -> None:
        self.close()

    def on_exception(self, error: BaseException) -> None:
        self.close()

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
