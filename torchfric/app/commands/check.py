"""``torchfric check CONFIG``: everything `train` checks before it starts, and what would run.

`check_run` does what a run does before it claims its directory (`torchfric.app.run.runner.train`,
``_Run.prepare``): it loads and checks every data file, builds the configured model, checks
the machine's memory for it and computes the starting point (the pre-fit, about a second). Then
it describes the run: its name and the run directory it would claim (`next_run_dir`), the data,
the model and the estimator. It writes nothing: no run directory, no file. (As in a run, the
pre-fit's compiled code may be added to the compiled-code cache, ``TORCHFRIC_CACHE``.)
"""

from __future__ import annotations

import argparse
import os
import pathlib
import shlex
import time

import torch

from ...data import DEFAULT_CUTOFF_HZ, Experiment
from ...data.units import si_unit
from ...data.velocity import settling_samples
from ...errors import TorchfricError
from ...estimators.sizing import HOLDOUT
from ...models.arm import ArmModel
from ...resources import fewest_passes, format_bytes
from ..artifacts import next_run_dir
from ..config import Config
from ..run import (
    RunEstimate,
    auto_estimate,
    candidate_sizes,
    check_resources,
    config_model,
    estimate_run,
    initial_model,
    load_data,
    missing_terms,
    with_dynamic,
)
from ..run import sized as with_size
from .columns import rpm

__all__ = ["check_run", "cmd_check"]

_W = 12  # width of the label column, as in the train summary


def _line(label: str, text: str) -> str:
    return f"{label:<{_W}}{text}"


def _run_dir(cfg: Config) -> pathlib.Path:
    """The run directory a plain ``torchfric train`` would claim; refuses an ``out_dir`` that
    cannot hold one (a file on the way), as the claim itself would."""
    default = pathlib.Path(cfg.out_dir) / cfg.name
    for folder in (default.parent, *default.parent.parents):
        if folder.exists():
            if not folder.is_dir():
                raise TorchfricError(
                    f"out_dir = {cfg.out_dir!r}: {folder} is a file, not a folder, so no run "
                    "directory can be made there; set out_dir to a folder (or pass --out DIR "
                    "to train)"
                )
            break
    return next_run_dir(default)


def _velocity(cfg: Config) -> str:
    d = cfg.data
    if d.velocity == "measured":
        return "measured (the files' qdot column)"
    cutoff = DEFAULT_CUTOFF_HZ[d.velocity] if d.velocity_cutoff_hz is None else d.velocity_cutoff_hz
    kind = "causal high-pass differentiator" if d.velocity == "highpass" else "off-line, zero-phase"
    return f"{d.velocity} ({kind}, cut-off {cutoff:g} Hz)"


def _shown(path: str) -> str:
    """`path` relative to the working directory when it lies below it (paths are absolute)."""
    try:
        rel = os.path.relpath(path)
    except ValueError:  # another drive
        return path
    return path if rel.startswith("..") else rel


def _records(
    label: str, exps: list[Experiment], paths: tuple[str, ...], settle: int = 0
) -> list[str]:
    """One line per record: file, samples, sample time and rate, duration (and its segments,
    ``NAME#1``, ``NAME#2``, … where gaps cut it, each without its first `settle` samples: the
    velocity filter's start transient, which `init`'s count of the file's rows includes)."""
    if not exps:
        return [_line(label, "none")]
    lines, rest = [], list(exps)
    for i, path in enumerate(paths):
        stem = pathlib.Path(path).stem if not path.startswith("rig:") else path[4:]
        part = [rest.pop(0)] if rest else []
        while rest and part[0].name.startswith(f"{stem}#") and rest[0].name.startswith(f"{stem}#"):
            part.append(rest.pop(0))
        n, dt = sum(e.n for e in part), part[0].dt
        cut = f" in {len(part)} segments" if len(part) > 1 else ""
        if cut and settle:
            cut += f" (each without its first {settle}: the velocity filter settling)"
        text = (
            f"{_shown(path)}: {n} samples{cut}, dt {dt:.6g} s ({1.0 / dt:.6g} Hz), "
            f"{sum(e.duration for e in part):.6g} s"
        )
        lines.append(_line(label if i == 0 else "", text))
    return lines


def _model_lines(cfg: Config, base: ArmModel, start: ArmModel, init_kind: str) -> list[str]:
    m = cfg.model
    terms = [
        name
        for name, on in (
            ("offset", m.offset is not None),
            ("gravity", m.gravity is not None),
            ("asymmetric viscous", m.asymmetric is not None),
        )
        if on
    ]
    c_m = f"c_m {m.c_m:g}" + (" (estimated)" if m.estimate_c_m else " (known, fixed)")
    sized = m.friction in ("tanh", "polytopic")
    tries = ", ".join(map(str, candidate_sizes(cfg))) if m.size == "auto" else ""
    size = f"auto (tries {tries}; the largest is started here)" if tries else m.size
    what = f"{m.friction} friction" + (f", size {size}" if sized else "")
    if m.dynamic == "auto":
        what += (
            f", friction class auto (static and LuGre identified on the first {1 - HOLDOUT:.0%} "
            f"of the records, LuGre kept if it predicts the last {HOLDOUT:.0%} better and its "
            "bristles move the encoder; LuGre shown here)"
        )
    if base.state_size != 2:
        # the values the run starts from (a checkpoint's, when model.init names one)
        bristles = {k: v for k, v in start.physical_parameters().items() if k.startswith("lugre")}
        what += (
            " with LuGre bristles ("
            + ", ".join(f"{k.removeprefix('lugre_')} {v:.4g}" for k, v in bristles.items())
            + " to start)"
        )
    lines = [
        _line(
            "model",
            f"{what}, {base.num_parameters} parameters, {c_m}"
            + (f"; terms: {', '.join(terms)}" if terms else ""),
        )
    ]
    source = {"prefit": "pre-fit on the identification data", "config": "the config's values"}
    where = source.get(init_kind, init_kind.replace("checkpoint:", "checkpoint "))
    values = f"inertia {float(start.inertia.detach()):.6g}"
    if m.friction != "polytopic":
        values += f", viscous {float(start.viscous.detach()):.6g}"
    lines.append(_line("start", f"{where}: {values}"))
    return lines


def _kept_line(cfg: Config) -> str:
    """What chooses the model a run keeps (``estimator.select``)."""
    est = cfg.estimator
    unit = "pass and member" if est.ensemble else "pass"
    if est.method == "output_error":
        what = "the last epoch" if est.select == "identification" or not cfg.data.validation else (
            "the best-validating epoch, so the validation FIT is not held out")  # fmt: skip
        return _line("kept", what)
    if est.select == "identification":
        return _line("kept", f"the {unit} best simulating the identification records; "
                     "validation chooses nothing (a held-out score)")  # fmt: skip
    if cfg.data.validation:
        return _line("kept", f"the best-validating {unit}, so the validation FIT is not held "
                     'out (estimator.select = "identification" holds it out)')  # fmt: skip
    return _line("kept", "the likeliest pass (no validation records)")


def _estimator_lines(cfg: Config, samples: int) -> list[str]:
    est = cfg.estimator
    if est.method == "output_error":
        window = "full length" if est.window == 0 else f"windows of {est.window} samples"
        return [
            _line(
                "estimator",
                f"output_error: up to {est.epochs} epochs, lr {est.lr:g} → {est.lr_final:g}, "
                f"{window}, batch {est.batch}, early stop after {est.patience} evaluations "
                "without improvement",
            ),
            _kept_line(cfg),
            _line("work", f"{samples} samples × up to {est.epochs} epochs"),
        ]
    stop = f"tolerance {est.tolerance:g}" if est.tolerance > 0 else "no early stop"
    if est.ensemble > 0:
        spec = est.ensemble_spec(cfg.seed)
        filters = spec.size
        how = (
            f"ensemble of {filters} filters ({spec.members} start(s) × {len(spec.q_scales)} Q × "
            f"{len(spec.r_scales)} R scales; the best by open-loop FIT is kept)"
        )
    else:
        filters, how = 1, "one filter"
    steps = samples * est.passes * filters
    if est.substeps == "auto":
        how += '; RK4 sub-steps from the model\'s friction (estimator.substeps = "auto")'
    elif est.substeps > 1:
        how += f"; {est.substeps} RK4 sub-steps a sample"
    return [
        _line("estimator", f"ekf: up to {est.passes} passes ({stop}), {how}"),
        _kept_line(cfg),
        _line(
            "work",
            f"{samples} samples × {est.passes} passes × {filters} filter(s) = "
            f"{steps:,} filter steps at most",
        ),
    ]


def check_run(cfg: Config, warnings: list[str] | None = None, *, timed: bool = False) -> str:
    """Check `cfg` as `train` does before it starts, writing nothing; what would run, as text,
    with the run's time and peak memory (`timed`: the filter's rate timed here, as ``check``
    does; else its nominal rate).

    Raises `TorchfricError` (one line naming the problem and its fix) for bad data, a model too
    large for this machine, a failing pre-fit or an ``out_dir`` that cannot hold a run. The
    data's warnings (`torchfric.data.data_warnings`) are in the text and appended to `warnings`.
    """
    torch.manual_seed(cfg.seed)  # as train does: the same starting point
    found: list[str] = []
    train, val, test, _ = load_data(cfg, warnings=found)
    # model.size = "auto": the largest size tried is the one checked and started here
    one = with_size(cfg, max(candidate_sizes(cfg))) if cfg.model.size == "auto" else cfg
    # model.dynamic = "auto": the LuGre model (the larger) is checked and started here
    one = with_dynamic(one, "lugre") if cfg.model.dynamic == "auto" else one
    base = config_model(one, train)
    check_resources(one, train, base)
    found += missing_terms(cfg, base, train)
    t_start = time.perf_counter()
    start, init_kind = initial_model(one, train, base)
    t_start = time.perf_counter() - t_start
    run = _run_dir(cfg)
    d = cfg.data
    settle = settling_samples(d.velocity, train[0].dt, d.velocity_cutoff_hz) if train else 0
    lines = [
        _line("run", f"{cfg.name} → {run} (train claims it; check creates nothing)"),
        *_records("train", train, d.train, settle),
        *_records("validation", val, d.validation, settle),
    ]
    if not val:
        lines.append(
            _line(
                "",
                "(scored on the identification data only; add held-out records as data.validation)",
            )  # fmt: skip
        )
    if test:
        lines += _records("test", test, d.test, settle)
    lines.append(_line("velocity", _velocity(cfg)))
    lines.append(_line("units", _units(cfg, train)))
    if d.position_unit != "rad" or d.start or d.stop is not None or d.input_delay:
        span = f"samples {d.start} … {'end' if d.stop is None else d.stop - 1}"
        lines.append(_line("reading", f"q in {_q_unit(cfg)}, {span}, input delay {d.input_delay}"))
    lines += _model_lines(cfg, base, start, init_kind)
    lines += _estimator_lines(cfg, sum(e.n for e in train))
    estimate = estimate_run(one, train, start, timed=timed)
    if cfg.model.dynamic == "auto":  # both classes compared first, then the kept one
        estimate = auto_estimate(cfg, train, estimate, timed=timed)
    auto = cfg.estimator.method == "ekf" and cfg.estimator.substeps == "auto"
    lines += _estimate_lines(estimate, t_start, init_kind, cfg.estimator.passes, auto)
    lines += [_line("warning", w) for w in found]
    if warnings is not None:
        warnings.extend(found)
    return "\n".join(lines)


def _minutes(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"


def _estimate_lines(
    est: RunEstimate, start_s: float, init_kind: str, passes: int, auto_steps: bool = False
) -> list[str]:
    """The run's time (the starting point as measured here, the filter at a rate timed here)
    and its peak memory (`torchfric.resources.run_peak_bytes`)."""
    start = f"{'pre-fit' if init_kind == 'prefit' else 'start'} {_minutes(start_s)}"
    if est.seconds is None or est.rate is None:
        time_text = f"not estimated for this estimator; the {start}"
    else:
        low, high = est.seconds
        fewest, rate = fewest_passes(passes), f"{est.rate / 1e6:.2g} M"
        ends, first = (f"{fewest} pass{'es' if fewest > 1 else ''}", "every pass"), ""
        if est.static_rate is not None:  # model.dynamic = "auto" (`auto_estimate`)
            ends = (f"static, {ends[0]}", f"LuGre, {ends[1]}")
            rate = f"{est.static_rate / 1e6:.2g} M (static) and {rate} (LuGre)"
            first = f"both classes on {est.compared:,} samples, then the kept one's "
        time_text = (
            f"about {_minutes(start_s + low)} ({ends[0]}) to {_minutes(start_s + high)} "
            f"({ends[1]}): the {start} as here, then {first}passes at {rate} filter steps/s "
            f"({'timed here' if est.timed else 'nominal'}) and the covariance"
        )
        if auto_steps:  # estimator.substeps = "auto"
            time_text += (" (at the start's RK4 sub-steps; each pass costs as many times more "
                          "as the passes raise them, up to 16, on friction that steepens)")  # fmt: skip
    free = "" if est.available is None else f"; {format_bytes(est.available)} available"
    return [
        _line("time", time_text),
        _line("memory", f"about {format_bytes(est.peak)} at peak{free}"),
    ]


def _q_unit(cfg: Config) -> str:
    """The unit q is read in: ``deg``, ``counts (4096 per rev)``, with its wrap."""
    d = cfg.data
    unit = d.position_unit
    if unit == "counts":
        unit += (
            f" ({d.counts_per_rev:g} per rev)"
            if d.counts_per_rev
            else f" ({d.counts_per_m:g} per m)"
        )
    return unit + (f", unwrapped at {d.wrap_period:g}" if d.wrap_period else "")


def _units(cfg: Config, train: list[Experiment]) -> str:
    """The units the data are read in, with the identification data's top speed in them: the
    number that shows a position in degrees (or mm) read as rad (or m) at a glance."""
    d = cfg.data
    si = si_unit(d.position_unit, d.counts_per_m)
    t = "t in s" if d.time_unit == "s" else f"t in {d.time_unit} (converted to s)"
    speeds = [float(e.qdot.abs().max()) for e in train if e.qdot is not None and e.n]
    if not speeds:
        return f"{t}, q in {_q_unit(cfg)} (converted to {si})"
    v = max(speeds)
    turns = f" = {rpm(v):,.0f} rpm" if si == "rad" else ""
    return (
        f"{t}, q in {_q_unit(cfg)}: |q̇| reaches {v:.3g} {si}/s{turns} in the identification "
        "data; if your machine never moves that fast, set data.position_unit"
    )


def cmd_check(args: argparse.Namespace) -> int:
    from ..config import Config

    cfg = Config.load(args.config, list(args.set or []))
    print(check_run(cfg, timed=True))
    sets = "".join(f" --set {shlex.quote(s)}" for s in args.set or [])
    train = f"torchfric train {shlex.quote(args.config)}{sets}"
    print(f"ok          nothing written; train with: {train}")
    return 0
