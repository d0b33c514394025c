"""From a config to what a run starts with: experiments, a memory check and the initial model.

`load_data` reads the config's identification, validation and test groups the way a run does
(a record that gaps or missing values cut as its segments); `load_record` reads one whole
record, for ``torchfric evaluate``/``simulate``/``track``; `check_resources` refuses a run too large
for this machine before anything is written; `config_model` and `initial_model` build the model
the estimator starts from; `estimate_run` gives the time and peak memory ``check`` prints.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

import torch

from ...data import Experiment, data_warnings, load_segments, make_experiment, position_step
from ...data.velocity import settling_samples
from ...errors import MissingColumn, TorchfricError
from ...estimators.observers import Callback
from ...estimators.prefit import PREFIT_ROWS, prefit
from ...models.arm import ArmModel
from ...models.friction import make_friction
from ...resources import (
    available_memory,
    ekf_bytes,
    nominal_rate,
    prefit_bytes,
    require_memory,
    run_peak_bytes,
    run_seconds,
)
from ..artifacts import load_checkpoint, sha256_file
from ..config import RIG_PREFIX, Config

__all__ = [
    "device_named",
    "load_record",
    "load_data",
    "check_resources",
    "config_model",
    "initial_model",
    "RunEstimate",
    "estimate_run",
]


def _read_record(cfg: Config, path: str) -> tuple[list[Experiment], str, list[str]]:
    """The record at `path` (or the rig's ``rig:NAME``) in SI units as its segments (one for a
    whole record), with its fingerprint and notes of what was left out."""
    d = cfg.data
    if not path.startswith(RIG_PREFIX):
        exps, notes = load_segments(
            path, columns=d.columns or None, time_step=d.time_step, start=d.start, stop=d.stop,
            time_unit=d.time_unit, position_unit=d.position_unit, counts_per_rev=d.counts_per_rev,
            counts_per_m=d.counts_per_m, wrap_period=d.wrap_period,
        )  # fmt: skip
        return exps, sha256_file(path), notes
    from ...accel.native.lugre import lugre_integrator
    from ...data.rig import rig_experiment

    name = path[len(RIG_PREFIX) :]
    arrays = rig_experiment(name, seed=cfg.seed, integrate=lugre_integrator())
    exp = make_experiment(arrays["t"], arrays["u"], arrays["q"], name=name)
    if d.start or d.stop is not None:
        exp = exp.slice(d.start, d.stop)
    digest = exp.fingerprint()
    factor = d.position_factor
    if factor != 1.0:
        exp = make_experiment(exp.t, exp.u, exp.q * factor, name=exp.name)
    return [exp], digest, []


def _prepared(
    cfg: Config, exp: Experiment, path: str, warnings: list[str] | None, *, cut: bool = False
) -> Experiment:
    """`exp` with velocity per `data.velocity` and input per `data.input_delay`; a segment of a
    `cut` record (which may start in motion) also without its velocity filter's start
    transient (`settling_samples`), so that its state starts at the motion's velocity."""
    d = cfg.data
    found = data_warnings(exp, velocity=d.velocity, velocity_cutoff_hz=d.velocity_cutoff_hz)
    if warnings is not None:
        warnings.extend(found)
    if d.velocity == "measured":
        if exp.qdot is None:
            raise MissingColumn(
                f"data.velocity = 'measured' but {path} has no qdot column; map one in data.columns "
                "or set data.velocity = 'highpass'",
                role="qdot",
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
    if cut:
        exp = exp.slice(settling_samples(d.velocity, exp.dt, d.velocity_cutoff_hz))
    if d.input_delay:
        exp = exp.delay_input(d.input_delay)
    return exp


def load_record(
    cfg: Config, path: str, warnings: list[str] | None = None
) -> tuple[Experiment, str]:
    """One whole experiment, as `load_data` reads it, and its fingerprint; a record that
    gaps or missing values cut is refused (``evaluate``, ``simulate`` and ``track`` need one)."""
    exps, digest, notes = _read_record(cfg, path)
    if notes:
        raise TorchfricError(
            f"{notes[0].split(' (', 1)[0].split(': read as')[0]}; this command needs one whole "
            "record: fill or cut the missing samples (train and check read it as segments)"
        )
    return _prepared(cfg, exps[0], path, warnings), digest


def load_data(
    cfg: Config, *, warnings: list[str] | None = None
) -> tuple[list[Experiment], list[Experiment], list[Experiment], dict[str, str]]:
    """(train, validation, test) experiments and SHA-256 fingerprints by path; a record that
    gaps or missing values cut gives one experiment per segment, each without its velocity
    filter's start transient.

    Warnings about the identification and validation records, and notes of rows left out of
    any record, are appended to `warnings`.
    """
    prints: dict[str, str] = {}
    groups = []
    for group, paths in enumerate((cfg.data.train, cfg.data.validation, cfg.data.test)):
        exps = []
        for p in paths:
            segments, prints[p], notes = _read_record(cfg, p)
            if warnings is not None:
                warnings.extend(notes)
            shown = warnings if group < 2 else None
            cut = len(segments) > 1
            exps.extend(_prepared(cfg, e, p, shown, cut=cut) for e in segments)
        groups.append(exps)
    if not groups[0]:
        raise TorchfricError("data.train is empty: give at least one identification file")
    return groups[0], groups[1], groups[2], prints


def device_named(name: str | None) -> torch.device | None:
    """The `torch.device` a run's filters use (``--device``): None for the CPU (the default);
    ``"cuda"`` or ``"cuda:N"`` when torch sees that GPU, else a `TorchfricError` naming the fix
    (checked before the run writes anything)."""
    if name is None or name == "cpu":
        return None
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise TorchfricError(
            f"--device {name!r} is not a device; use cpu, cuda or cuda:N"
        ) from None
    if device.type != "cuda":
        raise TorchfricError(f"--device {name!r}: only cpu and cuda (cuda:N) are supported")
    if not torch.cuda.is_available():
        raise TorchfricError(
            f"--device {name}: this torch ({torch.__version__}) sees no CUDA GPU. Fix: leave "
            "--device out (the CPU), or run where torch.cuda.is_available() is True"
        )
    index = device.index or 0
    if index >= torch.cuda.device_count():
        raise TorchfricError(
            f"--device {name}: torch sees {torch.cuda.device_count()} CUDA device(s); use "
            f"cuda:0 … cuda:{torch.cuda.device_count() - 1}"
        )
    return torch.device("cuda", index)


def check_resources(cfg: Config, train: list[Experiment], model: ArmModel) -> None:
    """Refuse, before anything runs, a `model` (the configured one) or ensemble too large for
    this machine's memory."""
    n_theta = model.get_theta().numel()
    samples = sum(e.n for e in train)
    size = f"model.size = {cfg.model.size} ({n_theta} parameters)"
    if cfg.model.init == "prefit":
        require_memory(
            prefit_bytes(n_theta, min(samples, PREFIT_ROWS)),  # its rows: at most the cap
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


STATIC_SATURATION, DYNAMIC_SATURATION = 6.0, 3.0  # model.saturation = "auto"


def saturation_floor(saturation: float | str, dynamic: str) -> float:
    """``model.saturation`` as a number: "auto" is 6 for a static model and 3 for LuGre (and
    for "auto" before its class is chosen; `config_model` is then called with each class)."""
    if saturation != "auto":
        return float(saturation)
    return STATIC_SATURATION if dynamic == "none" else DYNAMIC_SATURATION


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
        saturation = saturation_floor(m.saturation, m.dynamic)
        if m.friction == "tanh" and saturation > 0 and m.log_positive:
            kwargs["min_slope"] = saturation / kwargs["velocity_scale"]
    kwargs["log_positive"] = m.log_positive
    friction = make_friction(m.friction, m.size, **kwargs)
    v_scale = kwargs.get("velocity_scale") or m.velocity_scale or 1.0
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
        **_bristles(m, v_scale),
    )


def _bristles(m: Any, v_scale: float) -> dict[str, Any]:
    """The dynamic-friction arguments of `ArmModel` from `[model]` (none for a static model);
    σ1 unset is critically damped, ``2 sqrt(σ0 M)``; the stick velocity unset is 1 % of the
    velocity scale (for tanh and polytopic the data's 95th percentile of |q̇| when
    `model.velocity_scale` is unset too; for the baselines `model.velocity_scale`, else 1))."""
    if m.dynamic == "none":
        return {}
    sigma0 = m.sigma0 if m.sigma0 is not None else 1000.0  # (then set from the data, `_from_data`)
    sigma1 = m.sigma1 if m.sigma1 is not None else 2.0 * math.sqrt(sigma0 * m.inertia)
    v_stick = m.stick_velocity if m.stick_velocity is not None else 0.01 * v_scale
    return {"dynamic": m.dynamic, "sigma0": sigma0, "sigma1": sigma1, "stick_velocity": v_stick}


def _from_data(m: Any, model: ArmModel, train: list[Experiment]) -> ArmModel:
    """A dynamic `model` whose unset σ0 (and σ1) start from the data (`ModelConfig.sigma0`):
    one position step of pre-sliding under the model's static friction, critically damped
    with the model's inertia."""
    if m.sigma0 is not None and m.sigma1 is not None:
        return model
    params = model.physical_parameters()
    v_stick = torch.tensor([params["lugre_vstick"]], dtype=torch.float64)
    with torch.no_grad():
        level = float(model.static_twin().friction_torque(v_stick).abs()[0])
    drive = max(float(torch.quantile((e.u * model.c_m).abs().to(torch.float64), 0.95))
                for e in train)  # fmt: skip
    step = position_step(train)
    sigma0 = m.sigma0
    if sigma0 is None and math.isfinite(step):
        sigma0 = max(level, 1e-3 * drive) / step
    sigma0 = sigma0 if sigma0 is not None else params["lugre_sigma0"]
    sigma1 = m.sigma1 if m.sigma1 is not None else 2.0 * math.sqrt(sigma0 * params["inertia"])
    values = model.to_physical(model.get_theta()).clone()
    names = model.theta_names
    values[names.index("lugre_sigma0")] = sigma0
    values[names.index("lugre_sigma1")] = sigma1
    return model.set_theta(model.from_physical(values))


def initial_model(
    cfg: Config, train: list[Experiment], base: ArmModel | None = None
) -> tuple[ArmModel, str]:
    """Initial model per `model.init`: "prefit" (default), "config", or a checkpoint (warm start).

    `base` is `config_model(cfg, train)` when the caller has it already."""
    init = cfg.model.init
    base = config_model(cfg, train) if base is None else base
    if init == "config":
        return (base if base.state_size == 2 else _from_data(cfg.model, base, train)), "config"
    if init == "prefit":
        if base.state_size == 2:
            return prefit(base, train).model, "prefit"
        # A dynamic model: the static twin's pre-fit (its θ is the dynamic θ without σ0, σ1,
        # which keep their configured guesses or start from the data: equation error cannot
        # see the bristles).
        static = prefit(base.static_twin(), train).model
        return _from_data(cfg.model, base.with_static(static), train), "prefit"
    warm = load_checkpoint(init)
    if (
        base.state_size != 2
        and warm.state_size == 2
        and warm.theta_names == base.static_twin().theta_names
    ):
        # a static fit starts a LuGre one
        return _from_data(cfg.model, base.with_static(warm), train), f"checkpoint:{init}"
    if warm.theta_names != base.theta_names:
        raise TorchfricError(
            f"model.init checkpoint {init} has parameters {warm.theta_names} but this config's model "
            f"has {base.theta_names}; use the same model.friction, model.size and terms"
        )
    return warm, f"checkpoint:{init}"


@dataclass(frozen=True)
class RunEstimate:
    """What a run will cost, before it runs: ``seconds`` (after one pass, after every pass; None
    for output error) of the filtering after the pre-fit at ``rate`` member-steps a second
    (``timed`` here, else `torchfric.resources.nominal_rate`), with ``members`` filters, and its
    ``peak`` resident bytes (``available``: what this machine has free, None when it does not
    say). Under ``model.dynamic = "auto"`` (`torchfric.app.run.autosize.auto_estimate`)
    ``rate`` is the LuGre model's, ``static_rate`` the static one's, and ``compared`` the
    samples both are first identified on; else those two are None."""

    seconds: tuple[float, float] | None
    rate: float | None
    timed: bool
    members: int
    peak: int
    available: int | None
    static_rate: float | None = None
    compared: int | None = None


class _Clock(Callback):
    """The times of a pass's progress reports (samples done, seconds)."""

    def __init__(self) -> None:
        self.marks: list[tuple[int, float]] = []

    def on_progress(self, pass_index: int, samples_done: int, samples_total: int) -> None:
        self.marks.append((samples_done, time.perf_counter()))

    def rate(self) -> float | None:
        """Samples a second between the first report and the last (none: None)."""
        if len(self.marks) < 2 or self.marks[-1][1] <= self.marks[0][1]:
            return None
        (n0, t0), (n1, t1) = self.marks[0], self.marks[-1]
        return (n1 - n0) / (t1 - t0)


def _step_rate(cfg: Config, model: ArmModel, train: list[Experiment], members: int) -> float | None:
    """Member-steps a second of the configured filters on this machine: one pass of `members`
    filters (the run's ensemble, or one) over the first 5000 samples of the longest record,
    timed between its progress reports, so that building or loading the compiled step does not
    count. None when the timing fails (a filter that diverges there)."""
    from ...estimators.ensemble import identify_ekf_ensemble
    from ...estimators.settings import EnsembleSpec

    exp = max(train, key=lambda e: e.n)
    part = exp.slice(0, min(exp.n, 5000))
    est = cfg.estimator
    spec = est.ensemble_spec(cfg.seed) if est.ensemble > 0 else EnsembleSpec(members=1)
    tuning = dataclasses.replace(est.ekf_tuning(), passes=1)
    clock = _Clock()
    try:
        identify_ekf_ensemble(model, [part], tuning, spec, callback=clock, progress_every=500)
    except TorchfricError:
        return None
    rate = clock.rate()
    return None if rate is None else rate * members


def estimate_run(
    cfg: Config, train: list[Experiment], model: ArmModel, *, timed: bool = False
) -> RunEstimate:
    """The time and peak memory of a run of `cfg` on `train` from `model` (`RunEstimate`; the
    memory from `torchfric.resources.run_peak_bytes`, the time from `run_seconds` at the
    filter's rate: with `timed`, one short pass timed here (a second or two; the first time
    also builds the compiled step that the run then finds), else the nominal rate)."""
    est = cfg.estimator
    ekf = est.method == "ekf"
    members = (est.ensemble_spec(cfg.seed).size if est.ensemble > 0 else 1) if ekf else 1
    samples = sum(e.n for e in train)
    peak = run_peak_bytes(samples=samples, longest=max(e.n for e in train),
                          n_theta=model.num_parameters, members=members)  # fmt: skip
    measured = _step_rate(cfg, model, train, members) if ekf and timed else None
    rate = measured or (nominal_rate(members) if ekf else None)
    seconds = (
        None
        if rate is None
        else run_seconds(samples=samples, passes=est.passes, members=members, rate=rate)
    )
    return RunEstimate(seconds, rate, measured is not None, members, peak, available_memory())
