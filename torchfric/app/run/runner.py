"""Runs from a config: data → initial θ → estimator → checkpoint, metrics and TensorBoard.

The library core (`identify_ekf`, `prefit`, …) does no I/O; this module hands the estimator
the run's observers (`torchfric.app.run.views.run_observers`) as one `CallbackList`, calls
their run hooks (`on_run_start`, `on_estimate`, `on_run_end`, `on_exception`: TensorBoard,
progress bars, snapshots and report.html finish there) and writes the final checkpoint and
metrics. Loading the data and building the initial model are in `torchfric.app.run.inputs`;
scoring the result in `torchfric.app.run.assessment`."""

from __future__ import annotations

import json
import pathlib
import sys
import time
from dataclasses import dataclass, field
from typing import Any, TextIO

import torch

from ...data import Experiment
from ...environment import torch_settings
from ...errors import RunInterrupted
from ...estimators.ensemble import identify_ekf_ensemble
from ...estimators.identify import EKFResult, PassRecord, identify_ekf
from ...estimators.metrics import SimulationScore
from ...estimators.observers import Callback, CallbackList, RunEnd, RunStart
from ...estimators.output_error import identify_output_error
from ...files import atomic_write_text, json_safe, write_json
from ...models.arm import ArmModel
from ..artifacts import (
    RunDir,
    build_checkpoint,
    check_checkpoint_target,
    claim_run_dir,
    locked,
    read_checkpoint,
    save_checkpoint,
)
from ..config import Config
from .assessment import evaluate_model, provenance, result_warnings, scoring_engine
from .autosize import choose_dynamic, choose_size_and_start, with_dynamic
from .confidence import attach_covariance, attach_oe_covariance, near_members, start_substeps
from .inputs import check_resources, config_model, device_named, initial_model, load_data
from .monitors import Printer, ValidationScores
from .outcome import kept_pass, kept_payload, member_held_out, parameter_table, selection_records
from .snapshots import (
    EKFResume,
    EnsembleResume,
    OEResume,
    Resume,
    latest_snapshot,
    oe_payload,
    resume_from,
    resume_state,
    snapshot_label,
)
from .views import run_observers

__all__ = ["train", "TrainResult"]

# What an estimator's run returns: the final model, its estimator state and its metrics.
_Outcome = tuple[ArmModel, dict[str, Any], dict[str, Any]]


@dataclass
class TrainResult:
    """A finished run: the fitted model, where it was written, and its metrics and history."""

    model: ArmModel
    run_dir: pathlib.Path
    checkpoint: pathlib.Path
    metrics: dict[str, Any]
    history: list[PassRecord] = field(default_factory=list)


@dataclass
class _Watch:
    """What an estimator's run is handed: the validation scorer, the run's observers as one
    list, the progress printer, and the records that choose (`outcome.selection_records`)."""

    scores: ValidationScores
    callbacks: CallbackList
    say: Printer
    device: torch.device | None = None  # where an ensemble filters (None: the CPU)
    choosing: list[Experiment] = field(default_factory=list)
    identification: list[Experiment] = field(default_factory=list)
    reported: list[Experiment] = field(default_factory=list)  # validation that chose nothing


def _run_ekf(
    cfg: Config,
    model: ArmModel,
    train_exps: list[Experiment],
    obs: _Watch,
    est: Resume | None,
    run: pathlib.Path,
) -> _Outcome:
    """The single filter (or the ensemble, when configured or resumed from one)."""
    if cfg.estimator.ensemble > 0 or isinstance(est, EnsembleResume):
        return _run_ensemble(cfg, model, train_exps, obs, est, run)
    start = est.start if isinstance(est, EKFResume) else None
    _on_cpu(obs, "the single filter")
    start_substeps(cfg, model, train_exps, obs.say)
    result = identify_ekf(
        model, train_exps, cfg.estimator.ekf_tuning(), callback=obs.callbacks, start=start
    )
    return _kept(cfg, result, obs, sum(r.seconds for r in result.history), {})


def _kept(
    cfg: Config, result: EKFResult, obs: _Watch, seconds: float, more: dict[str, Any]
) -> _Outcome:
    """The pass a filter's (or the kept member's) `result` keeps (`kept_pass`), its state, and
    the run's extra metrics; the observers see it (`on_estimate`) before the σ are computed."""
    kept, extra = kept_pass(
        result, obs.choosing, scoring_engine(cfg), cfg.estimator.tolerance,
        identification=obs.identification,
        held_out=bool(obs.reported) and "ensemble" not in more,
    )  # fmt: skip
    extra["samples_per_second"] = sum(r.samples for r in result.history) / max(seconds, 1e-9)
    extra.update(more)
    if cfg.estimator.substeps == "auto":  # the count the filter's last pass ran
        extra["substeps"] = result.substeps
    state, best = kept_payload(kept, extra), extra.get("best_pass")
    scores, history = obs.scores.scores_at(best) or {}, state.get("history", ())
    obs.callbacks.on_estimate(
        RunEnd(kept.model, {"best_pass": best}, best or 0, None, scores, history)
    )
    return kept.model, state, extra


def _on_cpu(obs: _Watch, what: str) -> None:
    """The note that `what` runs on the CPU although ``--device`` names a GPU."""
    if obs.device is not None:
        obs.say(f"  note: {what} runs on the CPU; --device {obs.device} serves ensembles "
                '(estimator.ensemble > 0) and model.size = "auto"')  # fmt: skip


def _scales(scales: tuple[float, ...]) -> str:
    return "{" + ", ".join(f"{v:g}" for v in scales) + "}" if len(scales) > 1 else f"{scales[0]:g}"


def _run_ensemble(
    cfg: Config,
    model: ArmModel,
    train_exps: list[Experiment],
    obs: _Watch,
    est: Resume | None,
    run: pathlib.Path,
) -> _Outcome:
    """The EKF ensemble in one batch; keeps the best member (`ensemble.json` lists them all)."""
    spec = cfg.estimator.ensemble_spec(cfg.seed)
    many = f"{spec.members} starts ×/÷ {spec.spread:g} around the initial θ"
    starts = "the initial θ" if spec.members == 1 else many
    obs.say(
        f"  ensemble of {spec.size} filters ({starts} × Q ×{_scales(spec.q_scales)} × "
        f"R ×{_scales(spec.r_scales)}), one batch; estimator.ensemble = 0 runs one filter"
    )
    start_substeps(cfg, model, train_exps, obs.say)
    ens = identify_ekf_ensemble(
        model,
        train_exps,
        cfg.estimator.ekf_tuning(),
        spec,
        validation=obs.choosing,
        callback=obs.callbacks,
        start=est.state if isinstance(est, EnsembleResume) else None,
        device=obs.device,
    )
    # under select = "identification", every member's validation FIT: reported, not chosen by
    held_out = member_held_out(model, ens, obs.reported, cfg)
    summary = ens.summary()
    (run / "ensemble.json").write_text(
        json.dumps({"summary": summary, "members": [m.to_dict() for m in ens.members]}, indent=2)
    )
    best = ens.members[ens.best]
    obs.say(
        f"  kept member {best.index} (Q ×{best.q_scale:g}, R ×{best.r_scale:g}, {best.status}) by "
        f"{ens.selected_by.replace('_', ' ')} {best.score:.6g}"
        f"{' nats' if ens.selected_by == 'loglik' else ' % (mean FIT of q and q̇)'}; "
        f"{summary['status'].get('diverged', 0)} of {len(ens.members)} members diverged; "
        f"{summary['filter_steps_per_second']:,.0f} filter-steps/s"
    )
    obs.callbacks.on_ensemble_end(ens.result)
    # the kept member's tuning scales (its covariance is computed under them), near members
    more = {"ensemble": summary, "tuning_scales": (best.q_scale, best.r_scale), **held_out}
    more["near_members"] = near_members(ens)  # other estimates: `member_spread`
    return _kept(cfg, ens.result, obs, ens.seconds, more)


def _run_output_error(
    cfg: Config,
    model: ArmModel,
    train_exps: list[Experiment],
    obs: _Watch,
    est: Resume | None,
) -> _Outcome:
    """Output-error training by gradient descent through the simulation."""
    resume = est if isinstance(est, OEResume) else None
    _on_cpu(obs, "output error")
    result = identify_output_error(
        model,
        train_exps,
        cfg.estimator.oe_tuning(cfg.seed),
        validation=obs.choosing or None,
        callback=obs.callbacks,
        start=None if resume is None else resume.start,
        initial_theta=None if resume is None else resume.initial_theta,
    )
    extra = {
        "epochs": result.epochs,
        "best_epoch": result.best_epoch,
        "best_pass": result.best_epoch,
        # output error has no filter convergence test: it has converged when its validation
        # score stopped improving (patience ran out) before the epoch budget did
        "converged": result.stopped_early,
        "stopped": "early" if result.stopped_early else "budget",
        "stopped_early": result.stopped_early,
        "selected_on": "validation" if obs.choosing else "last_epoch",
    }
    return result.model, oe_payload(result, result.epochs), extra


def _default_say(msg: str) -> None:
    sys.stderr.write(msg if msg.startswith("\r") or msg.endswith("\n") else msg + "\n")
    sys.stderr.flush()


@torch_settings()  # float64, TORCHFRIC_THREADS threads: the arithmetic of the CLI and `fit`
def train(
    cfg: Config,
    *,
    run_dir: str | pathlib.Path | None = None,
    resume: bool = False,
    overwrite: bool = False,
    checkpoint: str | pathlib.Path | None = None,
    say: Printer | None = None,
    bars: TextIO | None = None,
    callbacks: tuple[Callback, ...] = (),
    device: str | None = None,
) -> TrainResult:
    """Run the configured identification end to end; returns the fitted model and metrics.

    Everything is checked (config, data, memory, the ``checkpoint`` target) before anything is
    written. The run writes only inside its run directory (`torchfric.rundir.claim_run_dir`:
    ``out_dir/name`` or a fresh ``name-2``…, or `run_dir`), the final checkpoint included as
    ``<run directory>/<name>.pt``; `checkpoint` copies it to one more, explicit path. With
    `resume`, continue from the last completed pass snapshot in `run_dir` (the result equals an
    uninterrupted run's). Ctrl-C raises `RunInterrupted` naming the run to resume. `say`
    prints the progress lines (default: stderr); `bars` is a stream for tqdm progress bars
    (a terminal; default none); `callbacks`: more `Callback`s, called after the run's own.
    `device`: ``"cuda"`` filters ensembles and ``model.size = "auto"`` on the GPU (`device_named`).
    """
    say = say or _default_say
    on = device_named(device)  # an unusable device is refused before anything is written
    torch.manual_seed(cfg.seed)
    default = pathlib.Path(cfg.out_dir) / cfg.name
    explicit = pathlib.Path(run_dir) if run_dir is not None else None
    saved = resume_state(explicit or default, cfg) if resume else None
    if checkpoint is not None:
        checkpoint = pathlib.Path(checkpoint)
        check_checkpoint_target(checkpoint)
    run = _Run(cfg, say, time.perf_counter(), saved, bars, on)
    run.prepare()
    claim = claim_run_dir(default, explicit=explicit, overwrite=overwrite, resume=resume)
    with locked(*([claim.replaces] if claim.replaces else []), claim.path):
        try:
            result = run.run_in(claim, callbacks)
        except KeyboardInterrupt:
            snap = latest_snapshot(claim.path)
            label = snapshot_label(snap)
            where = (
                f"the last completed {label} is saved in {snap}"
                if snap
                else "no pass had completed yet"
            )
            raise RunInterrupted(
                f"interrupted: {where}", run_dir=claim.path if snap else None, last=label
            ) from None
    if checkpoint is not None:
        save_checkpoint(checkpoint, read_checkpoint(result.checkpoint))
        say(f"  copied the checkpoint to {checkpoint} (--checkpoint)")
    return result


class _Run:
    """One run's steps: `prepare` (data, memory check, initial model; writes nothing), then
    `run_in` the claimed and locked run directory."""

    def __init__(
        self,
        cfg: Config,
        say: Printer,
        t_start: float,
        saved: dict[str, Any] | None,
        bars: TextIO | None = None,
        device: torch.device | None = None,
    ) -> None:
        self.cfg, self.say, self.t_start, self.saved = cfg, say, t_start, saved
        self.bars, self.device = bars, device
        self.warnings: list[str] = []

    def prepare(self) -> None:
        """Load the data, size and class "auto", check memory and build the initial model (not
        on resume)."""
        cfg = self.cfg
        self.train, self.val, self.test, self.fingerprints = load_data(cfg, warnings=self.warnings)
        auto = cfg.model.dynamic == "auto"  # the size is chosen for the static model first
        cfg, self.sizes, start = choose_size_and_start(  # model.size = "auto"
            with_dynamic(cfg, "none") if auto else cfg, self.train, self.say, device=self.device
        )
        cfg, self.dynamics = choose_dynamic(  # model.dynamic = "auto"
            with_dynamic(cfg, "auto") if auto else cfg, self.train, self.say, device=self.device
        )
        start = None if self.dynamics and self.dynamics["chosen"] != "none" else start
        base = config_model(cfg, self.train)
        check_resources(cfg, self.train, base)
        resume = self.saved is not None
        self.model, self.init_kind = (
            (None, "resume") if resume else start or initial_model(cfg, self.train, base)
        )

    def run_in(self, claim: RunDir, callbacks: tuple[Callback, ...] = ()) -> TrainResult:
        """The run itself, in the claimed and locked directory `claim.path`."""
        run = claim.path
        atomic_write_text(run / "config.toml", self.cfg.to_toml())
        self._say_start(claim)

        model, est = self._starting_point()
        watch = self._watch(run, model, callbacks)
        try:
            watch.callbacks.on_run_start(RunStart(model, self.init_kind, resumed=est is not None))
            if self.cfg.estimator.method == "ekf":
                final, state, extra = _run_ekf(self.cfg, model, self.train, watch, est, run)
                attach_covariance(
                    self.cfg, final, self.train, state, extra, self.say, watch.choosing
                )
            else:
                final, state, extra = _run_output_error(self.cfg, model, self.train, watch, est)
                attach_oe_covariance(self.cfg, final, self.train, state, extra, self.say)
            seconds = time.perf_counter() - self.t_start
            self.covariance = state.get("P_theta")  # the kept θ's (None after output error)
            self.filter_cov = state.get("filter_P_theta", self.covariance)  # the filter's own
            # the kept pass's scores, when the filter's own pass loop already made them
            scores = None if "polished" in extra else watch.scores.scores_at(extra.get("best_pass"))
            scores = scores if scores is not None else evaluate_model(final, self.val, self.cfg)
            metrics = self._metrics(final, extra, seconds, scores)
            self._write_result(run, final, state, metrics)
            history = list(state.get("history", []))
            step = int(metrics.get("best_pass") or 0)
            watch.callbacks.on_run_end(
                RunEnd(final, metrics, step, self.covariance, scores, history)
            )
        except BaseException as err:
            watch.callbacks.on_exception(err)
            raise
        folder = claim.finish()
        ckpt = folder / f"{self.cfg.name}.pt"
        self.say(f"  done in {seconds:.1f} s; run directory {folder}")
        return TrainResult(final, folder, ckpt, metrics, history)

    def _say_start(self, claim: RunDir) -> None:
        """What the run works on, the data's warnings, and a note when nothing validates it."""
        self.say(
            f"torchfric: {self.cfg.name}: {len(self.train)} identification experiment(s), "
            f"{sum(e.n for e in self.train)} samples; run directory {claim.final}"
        )
        for w in self.warnings:
            self.say(f"  warning: {w}")
        if not self.val:
            self.say(
                "  no validation data: the model is checked on the identification data only; "
                "add held-out records as data.validation"
            )

    def _starting_point(self) -> tuple[ArmModel, Resume | None]:
        """The model to start from and, when resuming, the saved estimator state; sets
        `init_kind` and `initial_inertia`."""
        if self.saved is None:
            assert self.model is not None
            self.initial_inertia = float(self.model.inertia.detach())
            return self.model, None
        model = ArmModel.from_spec(self.saved["model"])
        est = resume_from(self.saved["estimator"]["state"])
        if not isinstance(est, EnsembleResume):  # an ensemble's holds every member's θ instead
            model.set_theta(est.theta)
        self.init_kind = self.saved["metrics"].get("init", "resume")
        self.initial_inertia = self.saved["metrics"].get("initial_inertia")
        after = f"epoch {est.epoch}" if isinstance(est, OEResume) else f"pass {est.pass_index}"
        self.say(f"  resuming after {after}")
        return model, est

    def _watch(self, run: pathlib.Path, model: ArmModel, callbacks: tuple[Callback, ...]) -> _Watch:
        """The run's observers of `model`'s estimation (`run_observers`), then `callbacks`."""
        scores, observers = run_observers(
            self.cfg, run, (self.train, self.val), model, self.say, bars=self.bars,
            snapshot_info=(self.fingerprints, self.init_kind, self.initial_inertia),
            extra=callbacks,
        )  # fmt: skip
        records = selection_records(self.cfg.estimator.select, self.train, self.val)
        return _Watch(scores, observers, self.say, self.device, *records)

    def _metrics(
        self,
        final: ArmModel,
        extra: dict[str, Any],
        seconds: float,
        scores: dict[str, SimulationScore],
    ) -> dict[str, Any]:
        """`metrics.json`: the result, its scores on validation (`scores`) and test data (and on
        the identification data when nothing is held out), and warnings."""
        cfg = self.cfg
        metrics: dict[str, Any] = {
            "name": cfg.name,
            "estimator": provenance(cfg, self.init_kind),
            "init": self.init_kind,
            **extra,
            "seconds": seconds,
            "inertia": float(final.inertia.detach()),
            "initial_inertia": self.initial_inertia,
            "parameters": parameter_table(final, self.covariance),
            "dt": self.train[0].dt,
            **({"sizes": self.sizes} if self.sizes else {}),
            **({"dynamics": self.dynamics} if self.dynamics else {}),
        }
        groups = {"validation": scores, "test": evaluate_model(final, self.test, cfg)}
        if not self.val:  # nothing held out: the identification records are scored at least
            groups["identification"] = evaluate_model(final, self.train, cfg)
        for group, by_name in groups.items():
            metrics[group] = {name: score.to_dict() for name, score in by_name.items()}
        metrics["warnings"] = self.warnings + result_warnings(cfg, final, metrics, self.init_kind,
            covariance=self.filter_cov, start=self.model, train=self.train)  # fmt: skip
        return metrics

    def _write_result(
        self, run: pathlib.Path, final: ArmModel, state: dict[str, Any], metrics: dict[str, Any]
    ) -> None:
        """`metrics.json` and the complete checkpoint ``<name>.pt`` in the run directory."""
        write_json(run / "metrics.json", metrics)
        payload = build_checkpoint(
            final,
            config=self.cfg,
            estimator_state=state,
            metrics=json_safe(metrics)[0],
            data_fingerprints=self.fingerprints,
            name=self.cfg.name,
            complete=True,
        )
        save_checkpoint(run / f"{self.cfg.name}.pt", payload)
