"""Runs from a config: data → initial θ → estimator → checkpoint, metrics and TensorBoard.

The library core (`identify_ekf`, `prefit`, …) does no I/O; this module attaches logging,
progress, snapshots and the final checkpoint through `EKFCallback`.
"""

from __future__ import annotations

import json
import pathlib
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from ..models.arm import ArmModel
from .checkpoint import (
    build_checkpoint,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
    sha256_file,
)
from .config import POSITION_UNITS, RIG_PREFIX, Config
from ..data import Experiment, data_warnings, load_experiment, make_experiment
from ..estimators.ensemble import EnsembleCallback, identify_ekf_ensemble
from ..errors import DivergenceError, RunInterrupted, TorchfricError
from ..models.friction import make_friction
from ..estimators.identify import EKFCallback, EKFResult, PassRecord, identify_ekf
from ..estimators.metrics import SimulationScore, score_simulation
from ..estimators.output_error import EpochRecord, OECallback, OEResult, identify_output_error
from ..estimators.prefit import prefit
from ..resources import ekf_bytes, prefit_bytes, require_memory
from ..files import atomic_write_text, json_safe, write_json
from .rundir import RunDir, claim_run_dir, locked

__all__ = ["load_data", "initial_model", "train", "TrainResult", "evaluate_model"]

Printer = Callable[[str], None]


# -- data ----------------------------------------------------------------------------------------
def _load_one(cfg: Config, path: str, warnings: list[str] | None = None) -> tuple[Experiment, str]:
    """One experiment with velocity per `data.velocity`, and its fingerprint.

    `torchfric.data.data_warnings` about the record (on the file's own columns, before the
    velocity is rebuilt) are appended to `warnings`; when the velocity cannot be rebuilt they
    are folded into the error instead.
    """
    d = cfg.data
    if path.startswith(RIG_PREFIX):
        from ..data.rig import rig_experiment

        name = path[len(RIG_PREFIX) :]
        arrays = rig_experiment(name, seed=cfg.seed)
        exp = make_experiment(arrays["t"], arrays["u"], arrays["q"], name=name)
        if d.start or d.stop is not None:
            exp = exp.slice(d.start, d.stop)
        digest = exp.fingerprint()
    else:
        exp = load_experiment(
            path, columns=d.columns or None, time_step=d.time_step, start=d.start, stop=d.stop
        )
        digest = sha256_file(path)
    factor = POSITION_UNITS[d.position_unit]
    if factor != 1.0:
        exp = make_experiment(
            exp.t,
            exp.u,
            exp.q * factor,
            None if exp.qdot is None else exp.qdot * factor,
            name=exp.name,
        )
    found = data_warnings(exp, velocity=d.velocity, velocity_cutoff_hz=d.velocity_cutoff_hz)
    if warnings is not None:
        warnings.extend(found)
    if d.velocity == "measured":
        if exp.qdot is None:
            raise TorchfricError(
                f"data.velocity = 'measured' but {path} has no qdot column; map one in data.columns "
                "or set data.velocity = 'highpass'"
            )
    else:
        try:
            exp = exp.with_velocity(d.velocity, cutoff_hz=d.velocity_cutoff_hz)
        except TorchfricError as err:
            if not found:
                raise
            raise TorchfricError(
                f"{'; '.join(found)} (the velocity reconstruction: {err})"
            ) from None
    return exp, digest


def load_data(
    cfg: Config, *, warnings: list[str] | None = None
) -> tuple[list[Experiment], list[Experiment], list[Experiment], dict[str, str]]:
    """(train, validation, test) experiments and SHA-256 fingerprints by path.

    Warnings about the identification and validation records are appended to `warnings`.
    """
    prints: dict[str, str] = {}
    groups = []
    for group, paths in enumerate((cfg.data.train, cfg.data.validation, cfg.data.test)):
        exps = []
        for p in paths:
            exp, digest = _load_one(cfg, p, warnings if group < 2 else None)
            if cfg.data.input_delay:
                exp = exp.delay_input(cfg.data.input_delay)
            prints[p] = digest
            exps.append(exp)
        groups.append(exps)
    if not groups[0]:
        raise TorchfricError("data.train is empty: give at least one identification file")
    return groups[0], groups[1], groups[2], prints


def check_resources(cfg: Config, train: list[Experiment], model: ArmModel) -> None:
    """Refuse, before anything runs, a `model` (the configured one) or ensemble too large for
    this machine's memory."""
    n_theta = model.get_theta().numel()
    samples = sum(e.n for e in train)
    size = f"model.size = {cfg.model.size} ({n_theta} parameters)"
    if cfg.model.init == "prefit":
        require_memory(
            prefit_bytes(n_theta, samples),
            f"the pre-fit of {size} over {samples} samples",
            "lower model.size, or use data.stop to fit on fewer samples",
        )
    est = cfg.estimator
    if est.method == "ekf":
        members = est.ensemble_spec(cfg.seed).size if est.ensemble > 0 else 1
        what = (
            f"an EKF ensemble of {members} filters (estimator.ensemble = {est.ensemble} starts × "
            f"{len(est.ensemble_q_scales)} Q × {len(est.ensemble_r_scales)} R scales) with {size}"
            if est.ensemble > 0
            else f"the EKF with {size}"
        )
        require_memory(ekf_bytes(n_theta, members), what, "lower estimator.ensemble or model.size")


def result_warnings(
    cfg: Config, final: ArmModel, metrics: dict[str, Any], init_kind: str
) -> list[str]:
    """Plain warnings about a result that is almost certainly wrong (`metrics.json` "warnings")."""
    out = []
    inertia, start = metrics["inertia"], metrics.get("initial_inertia")
    source = "pre-fit" if init_kind == "prefit" else "initial value"
    if start and inertia > 0 and max(inertia / start, start / inertia) > 3.0:
        out.append(
            f"inertia {inertia:.4g} is {inertia / start:.3g}× the {source}'s {start:.4g}: the "
            "estimate moved far from what the data's inverse dynamics say; check model.c_m, the "
            "units of t and q, and the filter's tuning (estimator.r, estimator.p0_theta)"
        )
    theta = final.get_theta().detach()
    bound = cfg.estimator.theta_bound
    at_bound = [
        n for n, v in zip(final.theta_names, theta.tolist(), strict=True) if abs(v) >= 0.5 * bound
    ]
    if at_bound or not inertia > 1e-12:
        out.append(
            f"parameter(s) {', '.join(at_bound) or 'inertia'} at a bound (|θ| near "
            f"estimator.theta_bound = {bound:g}, or inertia ≈ 0): the model is not physical"
        )
    for group in ("validation", "test"):
        for name, m in metrics.get(group, {}).items():
            fit = m.get("fit_q")
            if fit is None or not fit == fit or fit < 0.0:
                out.append(
                    f"{group} {name}: FIT on q is {fit if fit is None else f'{fit:.1f} %'} (below 0: "
                    "worse than a constant); the model does not simulate this record"
                )
    if (
        cfg.estimator.tolerance > 0  # tolerance 0 asks for exactly `passes` passes
        and metrics.get("converged") is False
        and metrics.get("passes", 0) >= cfg.estimator.passes
    ):
        out.append(
            f"stopped at the pass limit (estimator.passes = {cfg.estimator.passes}) without "
            f"converging to estimator.tolerance = {cfg.estimator.tolerance:g}; raise "
            "estimator.passes or check the tuning"
        )
    return out


# -- model ---------------------------------------------------------------------------------------
def config_model(cfg: Config, train: list[Experiment] | None = None) -> ArmModel:
    """The model with the configured initial guesses (friction sized to the data when unset)."""
    m = cfg.model
    kwargs: dict[str, Any] = {}
    if m.friction in ("tanh", "polytopic"):
        v_scale = m.velocity_scale
        if v_scale is None and train:
            v_all = torch.cat(
                [e.qdot.abs() for e in train if e.qdot is not None] or [torch.ones(1)]
            )
            v_scale = float(torch.quantile(v_all, 0.95)) or 1.0
        kwargs["velocity_scale"] = v_scale or 1.0
        kwargs["torque_scale"] = m.torque_scale if m.torque_scale is not None else 0.1
    kwargs["log_positive"] = m.log_positive
    friction = make_friction(m.friction, m.size, **kwargs)
    return ArmModel(
        friction,
        inertia=m.inertia,
        viscous=None if m.friction == "polytopic" else m.viscous,
        c_m=m.c_m,
        offset=m.offset,
        gravity=m.gravity,
        asymmetric=m.asymmetric,
        estimate_c_m=m.estimate_c_m,
        log_positive=m.log_positive,
    )


def initial_model(
    cfg: Config, train: list[Experiment], base: ArmModel | None = None
) -> tuple[ArmModel, str]:
    """Initial model per `model.init`: "prefit" (default), "config", or a checkpoint (warm start).

    `base` is `config_model(cfg, train)` when the caller has it already."""
    init = cfg.model.init
    base = config_model(cfg, train) if base is None else base
    if init == "config":
        return base, "config"
    if init == "prefit":
        return prefit(base, train).model, "prefit"
    warm = load_checkpoint(init)
    if warm.theta_names != base.theta_names:
        raise TorchfricError(
            f"model.init checkpoint {init} has parameters {warm.theta_names} but this config's model "
            f"has {base.theta_names}; use the same model.friction, model.size and terms"
        )
    return warm, f"checkpoint:{init}"


# -- figures -------------------------------------------------------------------------------------
def friction_figure(model: ArmModel, v_max: float, title: str, unit: str = "rad") -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    v = torch.linspace(-v_max, v_max, 801, dtype=torch.float64)
    with torch.no_grad():
        f = model.friction_torque(v)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(v.numpy(), f.numpy())
    force = "N" if unit in ("m", "mm") else "N m"
    ax.set_xlabel(f"velocity q̇ [{_si(unit)}/s]")
    ax.set_ylabel(f"friction b·q̇ + C(q̇) + offset [{force}]")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


def _si(unit: str) -> str:
    """The unit positions are converted to (data.position_unit → SI)."""
    return "m" if unit in ("m", "mm") else "rad"


def response_figure(exp: Experiment, score: SimulationScore, unit: str = "rad") -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = exp.t.numpy()
    fig, ax = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    ax[0].plot(t, exp.q.numpy(), label="measured")
    ax[0].plot(t, score.states[:, 0].numpy(), "--", label="simulated")
    ax[0].set_ylabel(f"q [{_si(unit)}]")
    ax[0].legend(loc="best")
    ax[1].plot(t, exp.qdot.numpy(), label="reconstructed")
    ax[1].plot(t, score.states[:, 1].numpy(), "--", label="simulated")
    ax[1].set_ylabel(f"q̇ [{_si(unit)}/s]")
    ax[1].set_xlabel("t [s]")
    ax[0].set_title(f"{exp.name}: FIT q {score.fit_q:.1f} %, q̇ {score.fit_qdot:.1f} %")
    fig.tight_layout()
    return fig


# -- evaluation ----------------------------------------------------------------------------------
def evaluate_model(
    model: ArmModel, exps: list[Experiment], cfg: Config
) -> dict[str, SimulationScore]:
    out = {}
    for e in exps:
        out[e.name] = score_simulation(
            model,
            e,
            method=cfg.simulation.method,
            substeps=cfg.simulation.substeps,
            # The fast path scores through the compiled twin of odeint's rk4 (same steps).
            engine="compiled" if cfg.estimator.compile else "odeint",
        )
    return out


# -- training ------------------------------------------------------------------------------------
@dataclass
class TrainResult:
    model: ArmModel
    run_dir: pathlib.Path
    checkpoint: pathlib.Path
    metrics: dict[str, Any]
    history: list[PassRecord] = field(default_factory=list)


class _RunLogger(EKFCallback):
    """TensorBoard scalars/figures, progress lines and per-pass snapshots."""

    def __init__(
        self,
        cfg: Config,
        run_dir: pathlib.Path,
        validation: list[Experiment],
        fingerprints: dict[str, str],
        writer: Any,
        say: Printer,
        v_max: float,
    ) -> None:
        self.cfg, self.run_dir, self.validation = cfg, run_dir, validation
        self.fingerprints, self.writer, self.say, self.v_max = fingerprints, writer, say, v_max
        self.t_pass = time.perf_counter()
        self.last_fit: dict[str, dict[str, float]] = {}

    def on_progress(self, pass_index: int, samples_done: int, samples_total: int) -> None:
        rate = samples_done / max(time.perf_counter() - self.t_pass, 1e-9)
        self.say(
            f"\r  pass {pass_index}/{self.cfg.estimator.passes}: {samples_done}/{samples_total} samples, {rate:,.0f} samples/s"
        )

    def log_model(
        self, step: int, model: ArmModel, scalars: dict[str, float]
    ) -> dict[str, dict[str, float]]:
        for name, value in model.physical_parameters().items():
            self.writer.add_scalar(f"parameters/{name}", value, step)
        for key, value in scalars.items():
            self.writer.add_scalar(key, value, step)
        fits: dict[str, dict[str, float]] = {}
        self.writer.add_figure(
            "friction_curve",
            friction_figure(model, self.v_max, f"pass {step}", self.cfg.data.position_unit),
            step,
        )
        for e, score in zip(
            self.validation, evaluate_model(model, self.validation, self.cfg).values(), strict=True
        ):
            fits[e.name] = score.to_dict()
            self.writer.add_scalar(f"validation/{e.name}/fit_q", score.fit_q, step)
            self.writer.add_scalar(f"validation/{e.name}/fit_qdot", score.fit_qdot, step)
            self.writer.add_figure(
                f"validation/{e.name}", response_figure(e, score, self.cfg.data.position_unit), step
            )
        self.writer.flush()
        return fits

    def snapshot(
        self, path: pathlib.Path, model: ArmModel, state: dict[str, Any], metrics: dict[str, Any]
    ) -> None:
        """An incomplete checkpoint (pass/epoch snapshot, last good pass), written atomically."""
        run_info = {
            "init": getattr(self, "init_kind", ""),
            "initial_inertia": getattr(self, "initial_inertia", None),
        }
        payload = build_checkpoint(
            model,
            config=self.cfg,
            estimator_state=state,
            metrics=json_safe({**run_info, **metrics})[0],
            data_fingerprints=self.fingerprints,
            name=self.cfg.name,
            complete=False,
        )
        save_checkpoint(path, payload)
        if path.parent.name == "passes":
            # Keep the two newest pass/epoch snapshots (the newest, and one before it in case
            # the newest is damaged): each holds the whole history, so keeping all of them would
            # grow with the square of the number of passes.
            for older in sorted(path.parent.glob("*.pt"), key=_snapshot_index)[:-2]:
                older.unlink(missing_ok=True)

    def on_pass_end(self, record: PassRecord, result: EKFResult) -> bool | None:
        fits = self.log_model(record.index, result.model, ekf_scalars(record))
        self.last_fit = fits
        fit_txt = ", ".join(
            f"{n} FIT q {f['fit_q']:.1f} % q̇ {f['fit_qdot']:.1f} %" for n, f in fits.items()
        )
        if record.rolled_back:
            self.say(
                f"\r  pass {record.index} lowered the innovation log-likelihood "
                f"({record.loglik:.6g}): undone, keeping pass {record.index - 1}; stopping\n"
            )
        self.say(
            f"\r  pass {record.index}/{self.cfg.estimator.passes} done in {record.seconds:.1f} s "
            f"({record.samples / max(record.seconds, 1e-9):,.0f} samples/s): "
            f"inertia {record.parameters['inertia']:.6g}, Δθ {record.rel_change:.2e}"
            + (f", {fit_txt}" if fit_txt else "")
            + "\n"
        )
        self.snapshot(
            self.run_dir / "passes" / f"pass_{record.index:03d}.pt",
            result.model,
            _estimator_payload(result, record.index),
            {"validation": fits},
        )
        self.t_pass = time.perf_counter()
        return None


def _estimator_payload(result: EKFResult, pass_index: int) -> dict[str, Any]:
    return {
        "method": "ekf",
        "pass": pass_index,
        "theta": result.theta.clone(),
        "P_theta": result.P_theta.clone(),
        "history": [r.to_dict() for r in result.history],
        "converged": result.converged,
    }


def _latest_snapshot(run_dir: pathlib.Path) -> pathlib.Path | None:
    folder = run_dir / "passes"
    snaps = (
        sorted(folder.glob("pass_*.pt"), key=_snapshot_index)
        or sorted(folder.glob("epoch_*.pt"), key=_snapshot_index)
        or sorted(folder.glob("ensemble_*.pt"), key=_snapshot_index)
    )
    return snaps[-1] if snaps else None


def _snapshot_index(path: pathlib.Path) -> int:
    """The pass or epoch number in a snapshot's name (``pass_012.pt`` → 12)."""
    digits = path.stem.rpartition("_")[2]
    return int(digits) if digits.isdigit() else -1


def _provenance(cfg: Config, init_kind: str) -> str:
    """Which estimator(s) produced the model: this run's, after a warm start's chain."""
    method = cfg.estimator.method
    if init_kind.startswith("checkpoint:"):
        raw = read_checkpoint(init_kind[len("checkpoint:") :])
        before = raw.get("metrics", {}).get("estimator") or raw.get("estimator", {}).get("method")
        if before:
            return f"{before}+{method}"
    return method


def _run_ekf(
    cfg: Config,
    model: ArmModel,
    train_exps: list[Experiment],
    logger: _RunLogger,
    est: dict[str, Any] | None,
    run: pathlib.Path,
):  # type: ignore[no-untyped-def]
    if cfg.estimator.ensemble > 0 or (est is not None and est.get("method") == "ekf_ensemble"):
        return _run_ensemble(cfg, model, train_exps, logger, est, run)
    start = None
    if est is not None:
        start = (est["theta"], est["P_theta"], [PassRecord(**r) for r in est["history"]])
    try:
        result = identify_ekf(
            model, train_exps, cfg.estimator.ekf_tuning(), callback=logger, start=start
        )
    except DivergenceError as err:
        last = err.last_good
        if isinstance(last, EKFResult) and last.history:
            logger.snapshot(
                run / "last_good.pt",
                last.model,
                _estimator_payload(last, last.passes),
                {"diverged": str(err)},
            )
            raise DivergenceError(
                f"{err} (last good pass saved to {run / 'last_good.pt'})", last_good=last
            ) from None
        raise
    extra = {
        "passes": result.passes,
        "converged": result.converged,
        "samples_per_second": sum(r.samples for r in result.history)
        / max(sum(r.seconds for r in result.history), 1e-9),
    }
    return result.model, _estimator_payload(result, result.passes), extra


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


class _EnsembleLogger(EnsembleCallback):
    """Ensemble passes: progress, spread scalars in TensorBoard, resumable snapshots."""

    def __init__(self, base: _RunLogger, model: ArmModel) -> None:
        self.base, self.model = base, model

    def on_progress(self, pass_index: int, samples_done: int, samples_total: int) -> None:
        self.base.on_progress(pass_index, samples_done, samples_total)

    def on_ensemble_pass_end(self, pass_index: int, state: dict[str, Any]) -> bool | None:
        b = self.base
        status = state["status"]
        ok = [i for i, s in enumerate(status) if s != "diverged"]
        inertia = sorted(float(self.model.split(state["thetas"][i])[1]["inertia"]) for i in ok)
        counts = {s: status.count(s) for s in sorted(set(status))}
        for s, c in counts.items():
            b.writer.add_scalar(f"ensemble/{s}", c, pass_index)
        if inertia:
            for tag, v in (
                ("min", inertia[0]),
                ("median", inertia[len(inertia) // 2]),
                ("max", inertia[-1]),
            ):
                b.writer.add_scalar(f"ensemble/inertia_{tag}", v, pass_index)
        lls = [h[-1]["loglik"] for h in state["histories"] if h and h[-1]["index"] == pass_index]
        if lls:
            b.writer.add_scalar("ensemble/loglik_best", max(lls), pass_index)
        b.writer.flush()
        spread = f"inertia {inertia[0]:.5g} … {inertia[-1]:.5g}" if inertia else "no member left"
        b.say(
            f"\r  pass {pass_index}/{b.cfg.estimator.passes} of {len(status)} members done in "
            f"{time.perf_counter() - b.t_pass:.1f} s: "
            + ", ".join(f"{c} {s}" for s, c in counts.items())
            + f"; {spread}\n"
        )
        b.snapshot(b.run_dir / "passes" / f"ensemble_{pass_index:03d}.pt", self.model, state, {})
        b.t_pass = time.perf_counter()
        return None


def _scales(scales: tuple[float, ...]) -> str:
    return "{" + ", ".join(f"{v:g}" for v in scales) + "}" if len(scales) > 1 else f"{scales[0]:g}"


def _run_ensemble(
    cfg: Config,
    model: ArmModel,
    train_exps: list[Experiment],
    logger: _RunLogger,
    est: dict[str, Any] | None,
    run: pathlib.Path,
):  # type: ignore[no-untyped-def]
    spec = cfg.estimator.ensemble_spec(cfg.seed)
    starts = (
        "the initial θ"
        if spec.members == 1
        else f"{spec.members} starts ×/÷ {spec.spread:g} around the initial θ"
    )
    logger.say(
        f"  ensemble of {spec.size} filters ({starts} × Q ×{_scales(spec.q_scales)} × "
        f"R ×{_scales(spec.r_scales)}), one batch; estimator.ensemble = 0 runs one filter"
    )
    ens = identify_ekf_ensemble(
        model,
        train_exps,
        cfg.estimator.ekf_tuning(),
        spec,
        validation=logger.validation,
        callback=_EnsembleLogger(logger, model),
        start=est,
    )
    summary = ens.summary()
    (run / "ensemble.json").write_text(
        json.dumps({"summary": summary, "members": [m.to_dict() for m in ens.members]}, indent=2)
    )
    best = ens.members[ens.best]
    logger.say(
        f"  kept member {best.index} (Q ×{best.q_scale:g}, R ×{best.r_scale:g}, {best.status}) by "
        f"{ens.selected_by.replace('_', ' ')} {best.score:.6g}; "
        f"{summary['status'].get('diverged', 0)} of {len(ens.members)} members diverged; "
        f"{summary['filter_steps_per_second']:,.0f} filter-steps/s"
    )
    result = ens.result
    # The kept member's own pass history under the single filter's tags (parameters, trace(P),
    # innovation RMS, NIS, log-likelihood per pass), so that a default run's TensorBoard reads
    # like a single filter's; the members' spread is under ensemble/.
    for record in result.history[:-1]:
        for key, value in {
            **{f"parameters/{n}": v for n, v in record.parameters.items()},
            **ekf_scalars(record),
        }.items():
            logger.writer.add_scalar(key, value, record.index)
    last = result.history[-1] if result.history else None
    logger.last_fit = logger.log_model(
        max(result.passes, 1), result.model, ekf_scalars(last) if last else {}
    )
    extra = {
        "passes": result.passes,
        "converged": result.converged,
        "samples_per_second": sum(r.samples for r in result.history) / max(ens.seconds, 1e-9),
        "ensemble": summary,
    }
    return result.model, _estimator_payload(result, result.passes), extra


class _OELogger(OECallback):
    """Output-error epochs to TensorBoard, the terminal and per-block snapshots."""

    def __init__(self, base: _RunLogger) -> None:
        self.base = base

    def on_epoch_end(self, record: EpochRecord, result: OEResult) -> bool | None:
        b = self.base
        for name, value in record.parameters.items():
            b.writer.add_scalar(f"parameters/{name}", value, record.index)
        b.writer.add_scalar("oe/loss", record.loss, record.index)
        b.writer.add_scalar("oe/lr", record.lr, record.index)
        b.writer.add_scalar("oe/window", record.window, record.index)
        if record.val_fit is not None:
            for name, f in record.val_fit.items():
                b.writer.add_scalar(f"validation/{name}/fit_q", f["fit_q"], record.index)
                b.writer.add_scalar(f"validation/{name}/fit_qdot", f["fit_qdot"], record.index)
            b.writer.add_figure(
                "friction_curve",
                friction_figure(
                    result.model,
                    b.v_max,
                    f"epoch {record.index} (best {result.best_epoch})",
                    b.cfg.data.position_unit,
                ),
                record.index,
            )
            fit_txt = ", ".join(
                f"{n} FIT q {f['fit_q']:.1f} % q̇ {f['fit_qdot']:.1f} %"
                for n, f in record.val_fit.items()
            )
            b.say(
                f"  epoch {record.index}/{b.cfg.estimator.epochs}: loss {record.loss:.4g}, "
                f"inertia {record.parameters['inertia']:.6g}"
                + (f", {fit_txt}" if fit_txt else "")
                + "\n"
            )
            b.snapshot(
                b.run_dir / "passes" / f"epoch_{record.index:05d}.pt",
                result.model,
                _oe_payload(result, record.index),
                {"validation": record.val_fit, "init": getattr(b, "init_kind", "")},
            )
        b.writer.flush()
        return None


def _oe_payload(result: OEResult, epoch: int) -> dict[str, Any]:
    state: dict[str, Any] = {
        "method": "output_error",
        "epoch": epoch,
        "theta": result.theta.clone(),
        "best_epoch": result.best_epoch,
        "history": [r.to_dict() for r in result.history],
    }
    if result.optimizer_state is not None:
        state["optimizer_state"] = result.optimizer_state
    if result.shooting is not None:
        state["shooting"] = result.shooting.clone()
    if result.initial_theta is not None:
        state["initial_theta"] = result.initial_theta.clone()
    return state


def _run_output_error(
    cfg: Config,
    model: ArmModel,
    train_exps: list[Experiment],
    val_exps: list[Experiment],
    logger: _RunLogger,
    est: dict[str, Any] | None,
    run: pathlib.Path,
):  # type: ignore[no-untyped-def]
    start = None
    if est is not None:
        history = [
            EpochRecord(**{k: v for k, v in r.items() if k != "val_score"}) for r in est["history"]
        ]
        # Continue from the latest θ (the last record's), not the best-by-validation θ the
        # snapshot reports as its model: they differ whenever validation peaked earlier.
        latest = torch.tensor(history[-1].theta, dtype=torch.float64) if history else est["theta"]
        start = (latest, history, est.get("optimizer_state"), est.get("shooting"))
    result = identify_output_error(
        model,
        train_exps,
        cfg.estimator.oe_tuning(cfg.seed),
        validation=val_exps or None,
        callback=_OELogger(logger),
        start=start,
        initial_theta=None if est is None else est.get("initial_theta"),
    )
    extra = {
        "epochs": result.epochs,
        "best_epoch": result.best_epoch,
        "stopped_early": result.stopped_early,
    }
    return result.model, _oe_payload(result, result.epochs), extra


def _default_say(msg: str) -> None:
    sys.stderr.write(msg if msg.startswith("\r") or msg.endswith("\n") else msg + "\n")
    sys.stderr.flush()


def _check_checkpoint_target(path: pathlib.Path) -> None:
    """``--checkpoint PATH`` may replace only an earlier torchfric checkpoint, never other files."""
    if path.is_dir():
        raise TorchfricError(f"--checkpoint {path} is a directory; give a .pt file name")
    if path.exists():
        try:
            read_checkpoint(path)
        except TorchfricError:
            raise TorchfricError(
                f"--checkpoint {path} exists and is not a torchfric checkpoint; torchfric "
                "replaces only its own checkpoints there: give another file name"
            ) from None


def _snapshot_label(snap: pathlib.Path | None) -> str | None:
    if snap is None:
        return None
    kind, _, index = snap.stem.partition("_")
    return f"{'pass' if kind in ('pass', 'ensemble') else kind} {int(index)}"


def _resume_state(run: pathlib.Path, cfg: Config) -> dict[str, Any]:
    snap = _latest_snapshot(run)
    if snap is None:
        raise TorchfricError(
            f"--resume: no pass snapshots in {run / 'passes'}; start the run without --resume"
        )
    saved = read_checkpoint(snap)
    if saved["config"] != cfg.to_dict():
        raise TorchfricError(
            f"--resume: the config differs from the one saved in {run}; resume with the same "
            "config and --set values"
        )
    return saved


def train(
    cfg: Config,
    *,
    run_dir: str | pathlib.Path | None = None,
    resume: bool = False,
    overwrite: bool = False,
    checkpoint: str | pathlib.Path | None = None,
    say: Printer | None = None,
) -> TrainResult:
    """Run the configured identification end to end; returns the fitted model and metrics.

    Everything is checked (config, data, memory, the ``checkpoint`` target) before anything is
    written. The run writes only inside its run directory (`torchfric.rundir.claim_run_dir`:
    ``out_dir/name`` or a fresh ``name-2``…, or `run_dir`), the final checkpoint included as
    ``<run directory>/<name>.pt``; `checkpoint` copies it to one more, explicit path. With
    `resume`, continue from the last completed pass snapshot in `run_dir` (the result equals an
    uninterrupted run's). Ctrl-C raises `RunInterrupted` naming the run to resume.
    """
    say = say or _default_say
    torch.manual_seed(cfg.seed)
    default = pathlib.Path(cfg.out_dir) / cfg.name
    explicit = pathlib.Path(run_dir) if run_dir is not None else None
    saved = _resume_state(explicit or default, cfg) if resume else None
    if checkpoint is not None:
        checkpoint = pathlib.Path(checkpoint)
        _check_checkpoint_target(checkpoint)
    t_start = time.perf_counter()
    warnings: list[str] = []
    train_exps, val_exps, test_exps, fingerprints = load_data(cfg, warnings=warnings)
    base = config_model(cfg, train_exps)
    check_resources(cfg, train_exps, base)
    model, init_kind = (None, "resume") if resume else initial_model(cfg, train_exps, base)
    claim = claim_run_dir(default, explicit=explicit, overwrite=overwrite, resume=resume)
    with locked(*([claim.replaces] if claim.replaces else []), claim.path):
        try:
            result = _train_in(
                cfg,
                claim,
                saved,
                model,
                init_kind,
                (train_exps, val_exps, test_exps),
                fingerprints,
                warnings,
                say,
                t_start,
            )
        except KeyboardInterrupt:
            snap = _latest_snapshot(claim.path)
            label = _snapshot_label(snap)
            where = (
                f"the last completed {label} is saved in {snap}"
                if snap
                else "no pass had completed yet"
            )
            raise RunInterrupted(
                f"interrupted: {where}",
                run_dir=claim.path if snap else None,
                last=label,
            ) from None
    if checkpoint is not None:
        save_checkpoint(checkpoint, read_checkpoint(result.checkpoint))
        say(f"  copied the checkpoint to {checkpoint} (--checkpoint)")
    return result


def _train_in(
    cfg: Config,
    claim: RunDir,
    saved: dict[str, Any] | None,
    model: ArmModel | None,
    init_kind: str,
    data: tuple[list[Experiment], list[Experiment], list[Experiment]],
    fingerprints: dict[str, str],
    warnings: list[str],
    say: Printer,
    t_start: float,
) -> TrainResult:
    """The run itself, in the claimed and locked directory `claim.path`."""
    run = claim.path
    train_exps, val_exps, test_exps = data
    atomic_write_text(run / "config.toml", cfg.to_toml())
    say(
        f"torchfric: {cfg.name}: {len(train_exps)} identification experiment(s), "
        f"{sum(e.n for e in train_exps)} samples; run directory {claim.final}"
    )
    for w in warnings:
        say(f"  warning: {w}")
    if not val_exps:
        say(
            "  no validation data: the model is checked on the identification data only; "
            "add held-out records as data.validation"
        )

    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(log_dir=str(run))
    v_max = 1.2 * max(float(e.qdot.abs().max()) for e in train_exps if e.qdot is not None)
    logger = _RunLogger(cfg, run, val_exps, fingerprints, writer, say, v_max)
    try:
        if saved is not None:
            model = ArmModel.from_spec(saved["model"])
            est = saved["estimator"]["state"]
            if "theta" in est:  # an ensemble snapshot holds every member's θ instead
                model.set_theta(est["theta"])
            init_kind = saved["metrics"].get("init", "resume")
            initial_inertia = saved["metrics"].get("initial_inertia")
            say(
                f"  resuming after {'epoch' if est['method'] == 'output_error' else 'pass'} "
                f"{est.get('pass', est.get('epoch'))}"
            )
        else:
            assert model is not None
            est = None
            initial_inertia = float(model.inertia.detach())
            fits = logger.log_model(0, model, {})
            fit_txt = ", ".join(
                f"{n} FIT q {f['fit_q']:.1f} % q̇ {f['fit_qdot']:.1f} %" for n, f in fits.items()
            )
            say(
                f"  pass 0 ({init_kind}): inertia {initial_inertia:.6g}"
                + (f", {fit_txt}" if fit_txt else "")
            )
        logger.init_kind = init_kind
        logger.initial_inertia = initial_inertia
        if cfg.estimator.method == "ekf":
            final, state, extra = _run_ekf(cfg, model, train_exps, logger, est, run)
        else:
            final, state, extra = _run_output_error(
                cfg, model, train_exps, val_exps, logger, est, run
            )
        seconds = time.perf_counter() - t_start
        metrics: dict[str, Any] = {
            "name": cfg.name,
            "estimator": _provenance(cfg, init_kind),
            "init": init_kind,
            **extra,
            "seconds": seconds,
            "inertia": float(final.inertia.detach()),
            "initial_inertia": initial_inertia,
            "parameters": final.physical_parameters(),
            "dt": train_exps[0].dt,
            "validation": {},
            "test": {},
        }
        for group, exps in (("validation", val_exps), ("test", test_exps)):
            for name, score in evaluate_model(final, exps, cfg).items():
                metrics[group][name] = score.to_dict()
        metrics["warnings"] = warnings + result_warnings(cfg, final, metrics, init_kind)
        write_json(run / "metrics.json", metrics)
        payload = build_checkpoint(
            final,
            config=cfg,
            estimator_state=state,
            metrics=json_safe(metrics)[0],
            data_fingerprints=fingerprints,
            name=cfg.name,
            complete=True,
        )
        save_checkpoint(run / f"{cfg.name}.pt", payload)
    finally:
        writer.close()
    folder = claim.finish()
    ckpt = folder / f"{cfg.name}.pt"
    say(
        f"  done in {seconds:.1f} s ({metrics['estimator']}): inertia {metrics['inertia']:.6g}; "
        f"checkpoint {ckpt}; metrics {folder / 'metrics.json'}"
    )
    for name, m in metrics["validation"].items():
        say(f"  validation {name}: FIT q {m['fit_q']:.2f} %, q̇ {m['fit_qdot']:.2f} %")
    return TrainResult(final, folder, ckpt, metrics, list(state.get("history", [])))
