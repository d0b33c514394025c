"""Run configuration: TOML → nested frozen dataclasses, dotted ``--set`` overrides, TOML out.

Each section is a frozen dataclass that owns its defaults and checks its own values on
construction (`__post_init__`), so a `Config` that exists is valid::

    name = "arm_tanh_ekf"          # top level: name, seed, out_dir
    [data]                         # DataConfig
    train = ["rig:identification"]
    [model]                        # ModelConfig
    friction = "tanh"
    [estimator]                    # EstimatorConfig
    passes = 10
    [simulation]                   # SimulationConfig

Rules the loader applies (`Config.load`):

- Unknown keys or sections, wrong types and out-of-range values raise `TorchfricError` naming
  the dotted key, the value, what is allowed and the fix. An int is accepted where a float is
  expected, a bool never where a number is; a single string is accepted for a list of paths.
- Data paths (``data.train``, ``data.validation``, ``data.test``) and a checkpoint path in
  ``model.init`` are relative to the config file's folder, or to the working directory when
  given with ``--set``; they are stored absolute. ``"rig:NAME"`` names a synthetic-rig
  experiment (`torchfric.rig.EXPERIMENTS`) and is not a file. ``out_dir`` stays as written
  (relative to the working directory of the run).
- The built-in rig's constants are defaults for rig data only: with rig data (every
  ``data.train`` entry a ``"rig:NAME"``) ``model.c_m`` defaults to the rig's 16 and
  ``data.validation`` to ``["rig:validation"]``; with a user's files ``model.c_m`` is required and
  ``data.validation`` defaults to none, and naming rig data beside them is an error.
- ``--set KEY=VALUE`` parses VALUE as a TOML value when it parses (``20``, ``1e-3``,
  ``[0.001, 0.01]``, ``true``, ``"x"``) and as a bare string otherwise (``tanh``,
  ``data/a.csv``); the same checks apply.

`Config.to_toml` writes the resolved config (``None`` values are omitted) and
``Config.loads(config.to_toml()) == config``.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import pathlib
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, NoReturn

from ..estimators.ekf import MEASUREMENTS
from ..estimators.ensemble import EnsembleSpec
from ..errors import TorchfricError, shorten
from ..models.friction import FRICTIONS
from ..estimators.identify import EKFTuning
from ..estimators.output_error import OETuning
from ..data.rig import EXPERIMENTS, RigParameters
from ..models.simulate import SOLVERS

__all__ = [
    "Config",
    "DataConfig",
    "ModelConfig",
    "EstimatorConfig",
    "SimulationConfig",
    "ESTIMATORS",
    "INIT_KEYWORDS",
    "POSITION_UNITS",
    "RIG_PREFIX",
    "SCHEMA",
    "VELOCITY_SOURCES",
    "apply_overrides",
    "to_toml",
]

RIG_PREFIX = "rig:"
"""A data path ``"rig:NAME"`` names the synthetic rig's experiment NAME instead of a file."""
RIG_VALIDATION: tuple[str, ...] = (RIG_PREFIX + "validation",)
"""``data.validation``'s default for rig data (a user's data has none by default)."""
MAX_PASSES = 1000
"""EKF passes above this are refused: the paper needs 10 and `tolerance` stops earlier."""
MAX_EPOCHS = 100_000
MAX_CONFIG_BYTES = 1_000_000
MAX_NAME = 100
"""Longest run name: it becomes a folder and a file name."""
ESTIMATORS: tuple[str, ...] = ("ekf", "output_error")
ENSEMBLE_KEYS: tuple[str, ...] = (
    "ensemble",
    "ensemble_spread",
    "ensemble_q_scales",
    "ensemble_r_scales",
)
INIT_KEYWORDS: tuple[str, ...] = ("prefit", "config")
VELOCITY_SOURCES: tuple[str, ...] = ("highpass", "zero_phase", "measured")
POSITION_UNITS: dict[str, float] = {"rad": 1.0, "deg": math.pi / 180.0, "m": 1.0, "mm": 1e-3}
"""Unit of q in the data files → factor to SI (rad or m) that the runner multiplies q by."""
COLUMN_NAMES: tuple[str, ...] = ("t", "u", "q", "qdot")
_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")


# --------------------------------------------------------------------------------------------
# Formatting and checking helpers
# --------------------------------------------------------------------------------------------


def _type_name(value: Any) -> str:
    if value is None:
        return "none"
    names = {bool: "boolean", int: "integer", float: "float", str: "string"}
    if type(value) in names:
        return names[type(value)]
    if isinstance(value, list | tuple):
        return "array"
    if isinstance(value, Mapping):
        return "table"
    return type(value).__name__


def _a(noun: str) -> str:
    return ("an " if noun[:1] in "aeiou" else "a ") + noun


def _show(value: Any) -> str:
    try:
        text = _toml_value(value)
    except (TorchfricError, RecursionError):
        text = repr(value)
    return shorten(text)


def _suggest(word: str, allowed: Sequence[str]) -> str:
    close = difflib.get_close_matches(word, list(allowed), n=1, cutoff=0.6)
    return f' (did you mean "{close[0]}"?)' if close else ""


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


class _Check:
    """Checks and normalises the fields of one (frozen) section in its `__post_init__`."""

    def __init__(self, obj: Any, section: str) -> None:
        self.obj = obj
        self.section = section
        self.defaults = {f.name: f for f in dataclasses.fields(obj)}

    def key(self, name: str) -> str:
        return f"{self.section}.{name}" if self.section else name

    def _hint(self, name: str, example: Any) -> str:
        f = self.defaults[name]
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if example is None:
            example = default
        return f"; write e.g. {self.key(name)} = {_show(example)}" if example is not None else ""

    def type_error(self, name: str, value: Any, expected: str, example: Any = None) -> NoReturn:
        raise TorchfricError(
            f"{self.key(name)} = {_show(value)} is {_a(_type_name(value))}, expected {expected}"
            + self._hint(name, example)
        )

    def range_error(self, name: str, value: Any, allowed: str) -> NoReturn:
        f = self.defaults[name]
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        tail = f" (the default is {_show(default)})" if default is not None else ""
        raise TorchfricError(
            f"{self.key(name)} = {_show(value)} is out of range; allowed: {allowed}{tail}"
        )

    def set(self, name: str, value: Any) -> None:
        object.__setattr__(self.obj, name, value)

    def number(
        self,
        name: str,
        *,
        gt: float | None = None,
        ge: float | None = None,
        optional: bool = False,
        example: Any = None,
    ) -> None:
        value = getattr(self.obj, name)
        if value is None and optional:
            return
        if not _is_number(value):
            self.type_error(name, value, "a number", example)
        value = float(value)
        if not math.isfinite(value):
            self.range_error(name, value, "a finite number")
        if gt is not None and not value > gt:
            self.range_error(name, value, f"a number > {gt:g}")
        if ge is not None and not value >= ge:
            self.range_error(name, value, f"a number >= {ge:g}")
        self.set(name, value)

    def integer(
        self, name: str, *, ge: int | None = None, optional: bool = False, example: Any = None
    ) -> None:
        value = getattr(self.obj, name)
        if value is None and optional:
            return
        if isinstance(value, bool) or not isinstance(value, int):
            self.type_error(name, value, "an integer", example)
        if ge is not None and value < ge:
            self.range_error(name, value, f"an integer >= {ge}")
        if not -(2**63) <= value < 2**63:
            self.range_error(name, value, "a 64-bit integer")
        self.set(name, int(value))

    def boolean(self, name: str) -> None:
        value = getattr(self.obj, name)
        if not isinstance(value, bool):
            self.type_error(name, value, "true or false")

    def string(self, name: str, *, choices: Sequence[str] | None = None) -> str:
        value = getattr(self.obj, name)
        listed = ", ".join(f'"{c}"' for c in choices or ())
        if not isinstance(value, str):
            self.type_error(name, value, "a string" if choices is None else f"one of {listed}")
        if choices is not None and value not in choices:
            raise TorchfricError(
                f"{self.key(name)} = {_show(value)} is not allowed; choose one of {listed}"
                + _suggest(value, choices)
            )
        if not value:
            self.range_error(name, value, "a non-empty string")
        return value

    def numbers(
        self, name: str, *, length: int | None = None, ge: float | None = None, scalar: bool = False
    ) -> None:
        """An array of finite numbers (or, with `scalar`, also one number) → tuple/float."""
        value = getattr(self.obj, name)
        if scalar and _is_number(value):
            self.number(name, ge=ge)
            return
        expected = "a number or an array of numbers" if scalar else "an array of numbers"
        if not isinstance(value, list | tuple) or not all(_is_number(v) for v in value):
            self.type_error(name, value, expected)
        out = tuple(float(v) for v in value)
        if length is not None and len(out) != length:
            self.range_error(name, value, f"exactly {length} numbers")
        if not out:
            self.range_error(name, value, "at least one number")
        if not all(math.isfinite(v) and (ge is None or v >= ge) for v in out):
            what = "finite numbers" + (f" >= {ge:g}" if ge is not None else "")
            self.range_error(name, value, what)
        self.set(name, out)

    def paths(self, name: str, *, nonempty: bool) -> None:
        """A path string or an array of them → tuple of strings; ``rig:`` names validated."""
        value = getattr(self.obj, name)
        if isinstance(value, str):
            value = (value,)
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            self.type_error(name, value, "a path string or an array of path strings")
        value = tuple(value)
        if nonempty and not value:
            self.range_error(name, list(value), "at least one path")
        rigs = [RIG_PREFIX + e for e in EXPERIMENTS]
        for i, p in enumerate(value):
            if not p:
                self.range_error(name, list(value), "non-empty path strings")
            if p.startswith(RIG_PREFIX) and p not in rigs:
                raise TorchfricError(
                    f"{self.key(name)}[{i}] = {_show(p)} is not a rig experiment"
                    f"{_suggest(p, rigs)}; choose one of {', '.join(rigs)}, or give a file path"
                )
        self.set(name, value)


# --------------------------------------------------------------------------------------------
# Sections
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DataConfig:
    """``[data]``: measurement files and how to read them.

    Attributes:
        train: identification records (paths or ``"rig:NAME"``); all are used in each pass.
        validation: records for the validation FIT after each pass and in ``metrics.json``;
            the default is ``["rig:validation"]`` for rig data and none for a user's files.
        test: extra held-out records evaluated once at the end.
        columns: our names (t, u, q, qdot) → names in the file, e.g. ``{u = "vir", q = "qm"}``.
        time_step: sample period [s] for files without a t column (checked against t otherwise).
        velocity: q̇ measurement for the estimators: "highpass" (the paper's causal
            differentiator), "zero_phase" (off-line) or "measured" (the file's qdot column).
        velocity_cutoff_hz: cut-off of the reconstruction; ``None`` = the method's default.
        position_unit: unit of q in the files (`POSITION_UNITS`); the runner converts to SI.
        start, stop: keep samples ``start <= k < stop`` of every file (``stop=None``: to the end).
        input_delay: whole samples by which the input acts late (`Experiment.delay_input`:
            sample k is driven by ``u[k − input_delay]``; the first ones are dropped). 0 = none.
    """

    train: tuple[str, ...] = (RIG_PREFIX + "identification",)
    validation: tuple[str, ...] | None = None
    test: tuple[str, ...] = ()
    columns: dict[str, str] = field(default_factory=dict)
    time_step: float | None = None
    velocity: str = "highpass"
    velocity_cutoff_hz: float | None = None
    position_unit: str = "rad"
    start: int = 0
    stop: int | None = None
    input_delay: int = 0

    PATH_KEYS: ClassVar[tuple[str, ...]] = ("train", "validation", "test")

    def __post_init__(self) -> None:
        c = _Check(self, "data")
        c.paths("train", nonempty=True)
        if self.validation is None:
            c.set("validation", RIG_VALIDATION if self.rig_only else ())
        c.paths("validation", nonempty=False)
        c.paths("test", nonempty=False)
        if not self.rig_only:
            for key in ("validation", "test"):
                rig = [p for p in getattr(self, key) if p.startswith(RIG_PREFIX)]
                if rig:
                    raise TorchfricError(
                        f"data.{key} = {_show(list(getattr(self, key)))} names the built-in "
                        f"rig's data ({rig[0]}) but data.train is your own data; the rig's "
                        f"records do not measure your machine: give your own files, or "
                        f"remove data.{key} (--set data.{key}=[])"
                    )
        cols = self.columns
        if not isinstance(cols, Mapping) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in cols.items()
        ):
            c.type_error("columns", cols, "a table of column names", {"u": "vir", "q": "qm"})
        for k, v in cols.items():
            if k not in COLUMN_NAMES:
                raise TorchfricError(
                    f'unknown key "data.columns.{k}"{_suggest(k, COLUMN_NAMES)}; allowed keys'
                    f" in [data.columns]: {', '.join(COLUMN_NAMES)} (each mapped to a name in the"
                    " file)"
                )
            if not v:
                raise TorchfricError(
                    f"data.columns.{k} is empty; give the column's name in the file"
                )
        c.set("columns", dict(cols))
        c.number("time_step", gt=0.0, optional=True, example=0.001)
        c.string("velocity", choices=VELOCITY_SOURCES)
        c.number("velocity_cutoff_hz", gt=0.0, optional=True, example=200.0)
        c.string("position_unit", choices=tuple(POSITION_UNITS))
        c.integer("start", ge=0)
        c.integer("stop", ge=1, optional=True, example=10000)
        if self.stop is not None and self.stop <= self.start:
            c.range_error("stop", self.stop, f"an integer > data.start = {self.start}, or omit it")
        c.integer("input_delay", ge=0)

    @property
    def rig_only(self) -> bool:
        """True when every identification record is the built-in rig's (``"rig:NAME"``)."""
        train = (self.train,) if isinstance(self.train, str) else self.train
        return all(isinstance(p, str) and p.startswith(RIG_PREFIX) for p in train)


@dataclass(frozen=True)
class ModelConfig:
    """``[model]``: the grey-box model and its initial guesses.

    Attributes:
        friction: black-box friction, a `torchfric.friction.FRICTIONS` name.
        size: neurons (tanh) or local models (polytopic, odd); ignored by the baselines.
        c_m: motor constant, torque (or force) per unit of input (known unless
            `estimate_c_m`). Required with a user's data; ``None`` takes the rig's 16 for rig
            data (`Config` resolves it).
        inertia, viscous: initial guesses of M and b (with ``init = "config"``, or as the
            fallback of the pre-fit). For "polytopic" the runner ignores `viscous`: the paper's
            polytopic model carries its own slopes and has no separate b.
        offset: ``None`` = no constant offset term; a number enables it with that initial guess.
        gravity: ``None`` = no ``g_c sin q`` term; a number (> 0) enables it.
        asymmetric: ``None`` = no even viscous term; a number enables ``a |q̇|`` with that
            initial guess (direction-dependent viscous slopes b ± a, `torchfric.arm.ArmModel`).
        estimate_c_m: put c_m in θ.
        log_positive: estimate positive parameters (M, b, variances…) as logarithms.
        velocity_scale, torque_scale: scales for the friction's initial shape; ``None`` = from
            the data.
        init: "prefit" (least-squares pre-fit on the training data), "config" (the values above)
            or the path of a checkpoint to warm-start from (stored absolute).
    """

    friction: str = "tanh"
    size: int = 3
    c_m: float | None = None
    inertia: float = 0.03
    viscous: float = 0.01
    offset: float | None = None
    gravity: float | None = None
    estimate_c_m: bool = False
    log_positive: bool = True
    velocity_scale: float | None = None
    torque_scale: float | None = None
    init: str = "prefit"
    asymmetric: float | None = None

    PATH_KEYS: ClassVar[tuple[str, ...]] = ("init",)

    def __post_init__(self) -> None:
        c = _Check(self, "model")
        c.string("friction", choices=tuple(FRICTIONS))
        c.integer("size", ge=1)
        if self.friction == "polytopic" and self.size % 2 == 0:
            raise TorchfricError(
                f'model.size = {self.size} is not allowed for model.friction = "polytopic": '
                f"it needs an odd number of local models (1, 3, 5, ...); use {self.size - 1} or "
                f"{self.size + 1}"
            )
        c.number("c_m", gt=0.0, optional=True, example=16.0)
        c.number("inertia", gt=0.0)
        c.number("viscous", ge=0.0)
        c.number("offset", optional=True, example=0.0)
        c.number("gravity", gt=0.0, optional=True, example=0.1)
        c.number("asymmetric", optional=True, example=0.0)
        c.boolean("estimate_c_m")
        c.boolean("log_positive")
        if self.viscous == 0.0 and self.log_positive and self.friction != "polytopic":
            raise TorchfricError(
                "model.viscous = 0.0 cannot be estimated with model.log_positive = true (b is "
                "stored as log b); give a small positive guess such as 1e-4, or set "
                "model.log_positive = false"
            )
        c.number("velocity_scale", gt=0.0, optional=True, example=10.0)
        c.number("torque_scale", gt=0.0, optional=True, example=1.0)
        c.string("init")


@dataclass(frozen=True)
class EstimatorConfig:
    """``[estimator]``: which estimator, and its tuning (EKF defaults are the paper's, §5).

    Attributes:
        method: "ekf" (augmented-state continuous–discrete EKF) or "output_error".
        passes, tolerance, p0_state, p0_theta, q_state, q_theta, r, measure, substeps,
            theta_bound: the EKF tuning, see `torchfric.identify.EKFTuning` (`ekf_tuning()`).
            p0_theta and q_theta are one number for every θ entry or one per entry.
        epochs, lr, window, batch: output-error training (``window = 0``: full length).
        learn_states, continuity: multiple shooting with learned window start states and a
            continuity penalty (output error, fixed window); see `torchfric.output_error`.
        ensemble: number of starts of an EKF ensemble (0: a single filter, the paper's
            method); start 0 is the initial θ itself, the others are random within
            ensemble_spread (×/÷ box around it). Every start runs under every tuning of the grid
            ensemble_q_scales × ensemble_r_scales (factors on Q and R), and the member with the
            best open-loop FIT is kept (on the validation data, else on the training data) —
            see `torchfric.ensemble.EnsembleSpec`. The default, 1 start × Q {÷10, 1, ×10} ×
            R {÷10, 1, ×10}, is 9 filters, so that a tuning off by up to ×/÷ 10 still ends at
            the physical model (measured on the rig, `benchmarks/robustness.py`: 180 of 180 runs
            for tanh(3) and for polytopic(3)). Output-error runs ignore the default;
            changing any ensemble key with method = "output_error" is an error.
    """

    method: str = "ekf"
    passes: int = 10
    tolerance: float = 1e-4
    p0_state: tuple[float, ...] = (0.0, 0.0)
    p0_theta: float | tuple[float, ...] = 1.0
    q_state: tuple[float, ...] = (0.0, 1e-3)
    q_theta: float | tuple[float, ...] = 0.0
    r: tuple[float, ...] = (1e-3, 1e-2)
    measure: str = "both"
    substeps: int = 1
    theta_bound: float = 1e6
    compile: bool = True
    p0_relative: bool = False
    rollback: bool = True
    epochs: int = 200
    lr: float = 0.01
    lr_final: float = 1e-4
    window: int = 200
    batch: int = 64
    weights: tuple[float, ...] = (1.0, 1.0)
    clip: float = 1.0
    lbfgs_steps: int = 0
    patience: int = 20
    eval_every: int = 10
    schedule: tuple[int, ...] = ()
    adjoint: bool = False
    learn_states: bool = False
    continuity: float = 1.0
    ensemble: int = 1
    ensemble_spread: float = 3.0
    ensemble_q_scales: tuple[float, ...] = (0.1, 1.0, 10.0)
    ensemble_r_scales: tuple[float, ...] = (0.1, 1.0, 10.0)

    PATH_KEYS: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        c = _Check(self, "estimator")
        c.string("method", choices=ESTIMATORS)
        c.integer("passes", ge=1)
        if self.passes > MAX_PASSES:
            c.range_error(
                "passes",
                self.passes,
                f"an integer from 1 to {MAX_PASSES} (estimator.tolerance stops earlier once θ "
                "settles; the paper uses 10)",
            )
        c.number("tolerance", ge=0.0)
        c.numbers("p0_state", length=2, ge=0.0)
        c.numbers("p0_theta", ge=0.0, scalar=True)
        c.numbers("q_state", length=2, ge=0.0)
        c.numbers("q_theta", ge=0.0, scalar=True)
        c.string("measure", choices=tuple(MEASUREMENTS))
        c.numbers("r")
        if not all(v > 0 for v in self.r):
            c.range_error("r", list(self.r), "measurement variances > 0")
        m = len(MEASUREMENTS[self.measure])
        if len(self.r) != m:
            example = _show([EstimatorConfig.r[i] for i in MEASUREMENTS[self.measure]])
            raise TorchfricError(
                f"estimator.r = {_show(list(self.r))} has {len(self.r)} value(s) but "
                f'estimator.measure = "{self.measure}" measures {m} channel(s); give {m}, '
                f"e.g. estimator.r = {example}"
            )
        c.integer("substeps", ge=1)
        c.number("theta_bound", gt=0.0)
        c.boolean("compile")
        c.boolean("p0_relative")
        c.boolean("rollback")
        c.integer("epochs", ge=0)
        if self.epochs > MAX_EPOCHS:
            c.range_error("epochs", self.epochs, f"an integer from 0 to {MAX_EPOCHS}")
        c.number("lr", gt=0.0)
        c.number("lr_final", gt=0.0)
        c.integer("window", ge=0)
        c.integer("batch", ge=1)
        c.numbers("weights", length=2, ge=0.0)
        c.number("clip", ge=0.0)
        c.integer("lbfgs_steps", ge=0)
        c.integer("patience", ge=1)
        c.integer("eval_every", ge=1)
        sched = self.schedule
        if not isinstance(sched, list | tuple) or not all(
            isinstance(v, int) and not isinstance(v, bool) and (v == 0 or v >= 2) for v in sched
        ):
            c.type_error(
                "schedule",
                sched,
                "an array of window lengths (0 or >= 2), short to long",
                [50, 200, 800],
            )
        c.set("schedule", tuple(int(v) for v in sched))
        c.boolean("adjoint")
        c.boolean("learn_states")
        c.number("continuity", ge=0.0)
        c.integer("ensemble", ge=0)
        c.number("ensemble_spread", ge=1.0)
        for key in ("ensemble_q_scales", "ensemble_r_scales"):
            c.numbers(key)
            if not getattr(self, key) or not all(v > 0 for v in getattr(self, key)):
                c.range_error(key, list(getattr(self, key)), "a non-empty list of factors > 0")
        if self.method != "ekf":
            for key in ENSEMBLE_KEYS:
                default = getattr(EstimatorConfig, key)
                if getattr(self, key) != default and not (key == "ensemble" and self.ensemble == 0):
                    raise TorchfricError(
                        f'estimator.{key} = {_show(getattr(self, key))} needs estimator.method = '
                        f'"ekf" (got "{self.method}"); remove it (output error runs no ensemble)'
                    )
        if self.method == "output_error":
            self.oe_tuning().check(1)  # the estimator's own cross-field rules (lr_final <= lr, ...)

    def oe_tuning(self, seed: int = 0) -> OETuning:
        """The output-error settings as `torchfric.output_error.OETuning`."""
        return OETuning(
            epochs=self.epochs,
            lr=self.lr,
            lr_final=self.lr_final,
            window=self.window,
            batch=self.batch,
            weights=self.weights,  # type: ignore[arg-type]
            clip=self.clip,
            lbfgs_steps=self.lbfgs_steps,
            patience=self.patience,
            eval_every=self.eval_every,
            seed=seed,
            substeps=self.substeps,
            schedule=self.schedule,
            adjoint=self.adjoint,
            learn_states=self.learn_states,
            continuity=self.continuity,
            compile=self.compile,
        )

    def ensemble_spec(self, seed: int = 0) -> EnsembleSpec:
        """The ensemble settings as `torchfric.ensemble.EnsembleSpec` (only when ensemble > 0)."""
        return EnsembleSpec(
            members=self.ensemble,
            spread=self.ensemble_spread,
            q_scales=tuple(self.ensemble_q_scales),
            r_scales=tuple(self.ensemble_r_scales),
            seed=seed,
        )

    def ekf_tuning(self) -> EKFTuning:
        """The EKF settings as `torchfric.identify.EKFTuning`."""
        return EKFTuning(
            p0_state=self.p0_state,  # type: ignore[arg-type]
            p0_theta=self.p0_theta,
            q_state=self.q_state,  # type: ignore[arg-type]
            q_theta=self.q_theta,
            r=self.r,
            measure=self.measure,
            passes=self.passes,
            tolerance=self.tolerance,
            substeps=self.substeps,
            theta_bound=self.theta_bound,
            compile=self.compile,
            p0_relative=self.p0_relative,
            rollback=self.rollback,
        )


@dataclass(frozen=True)
class SimulationConfig:
    """``[simulation]``: open-loop simulation for validation (`torchfric.simulate`).

    Attributes:
        method: fixed-grid solver, a `torchfric.simulate.SOLVERS` name.
        substeps: solver steps per sample interval, or "auto" (from the model's stiffness).
    """

    method: str = "rk4"
    substeps: int | str = "auto"

    PATH_KEYS: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        c = _Check(self, "simulation")
        c.string("method", choices=tuple(SOLVERS))
        if self.substeps != "auto":
            if isinstance(self.substeps, bool) or not isinstance(self.substeps, int):
                c.type_error("substeps", self.substeps, '"auto" or an integer >= 1', 4)
            c.integer("substeps", ge=1)


_SECTIONS: dict[str, type] = {
    "data": DataConfig,
    "model": ModelConfig,
    "estimator": EstimatorConfig,
    "simulation": SimulationConfig,
}


# --------------------------------------------------------------------------------------------
# The whole config
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Config:
    """A whole run.

    Attributes:
        name: run name: run directory ``out_dir/name`` (or ``name-2``, … when that exists;
            ``--out`` chooses another) and the final checkpoint ``<run directory>/name.pt``.
            Letters, digits, ``._+-``, at most `MAX_NAME` characters.
        seed: seeds torch/numpy (and the rig's noise for ``rig:`` data).
        out_dir: the folder that holds the run directories, relative to the working directory.

    Nothing a run writes goes outside its run directory: the final checkpoint is copied elsewhere
    only by the explicit ``torchfric train --checkpoint PATH``.
    """

    name: str = "run"
    seed: int = 0
    out_dir: str = "runs"
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    simulation: SimulationConfig = field(default_factory=SimulationConfig)

    def __post_init__(self) -> None:
        c = _Check(self, "")
        c.string("name")
        if len(self.name) > MAX_NAME:
            raise TorchfricError(
                f"name = {_show(self.name)} is {len(self.name)} characters long; a run name "
                f"becomes a folder and a file name: use at most {MAX_NAME}"
            )
        if not _NAME_RE.fullmatch(self.name):
            raise TorchfricError(
                f"name = {_show(self.name)} is not a usable run name; use letters, digits and "
                '"._+-" (not starting with "." or "-"), e.g. name = "arm_tanh_ekf"'
            )
        c.integer("seed", ge=0)
        c.string("out_dir")
        for section, cls in _SECTIONS.items():
            if not isinstance(getattr(self, section), cls):
                raise TorchfricError(
                    f"Config.{section} must be a {cls.__name__}, got "
                    f"{type(getattr(self, section)).__name__}; use Config.from_dict for tables"
                )
        if self.model.c_m is None:
            if not self.data.rig_only:
                raise TorchfricError(
                    "model.c_m is required with your own data (the built-in rig's c_m = 16 "
                    "applies to rig data only): add the line `c_m = VALUE` (your motor constant: "
                    "torque or force per unit of input) to the [model] section, or pass "
                    "--set model.c_m=VALUE"
                )
            c.set("model", dataclasses.replace(self.model, c_m=RigParameters.c_m))

    # -- building -------------------------------------------------------------------------------
    @classmethod
    def from_dict(
        cls,
        d: Mapping[str, Any],
        *,
        base_dir: str | os.PathLike[str] | None = None,
        check_files: bool = True,
    ) -> Config:
        """Build and validate from nested tables (a parsed TOML file or `to_dict` output).

        Relative data paths and a ``model.init`` checkpoint path are resolved against
        `base_dir` (default: the working directory). With `check_files`, those files must exist.
        """
        if not isinstance(d, Mapping):
            raise TorchfricError(f"a config must be a table of keys, got {type(d).__name__}")
        base = pathlib.Path(os.getcwd() if base_dir is None else base_dir).absolute()
        top: dict[str, Any] = {}
        sections: dict[str, Any] = {}
        for key, value in d.items():
            if key in _SECTIONS:
                if not isinstance(value, Mapping):
                    raise TorchfricError(
                        f"{key} = {_show(value)} must be a table: write it as a [{key}] section"
                    )
                _check_keys(key, value)
                sections[key] = _SECTIONS[key](**_resolve_paths(key, value, base))
            elif key in _TOP_KEYS:
                top[key] = value
            else:
                _unknown_key(str(key), "", value)
        config = cls(**top, **sections)
        if check_files:
            config.check_files()
        return config

    @classmethod
    def loads(
        cls,
        text: str,
        overrides: Sequence[str] = (),
        *,
        base_dir: str | os.PathLike[str] | None = None,
        check_files: bool = True,
        source: str = "<config>",
    ) -> Config:
        """Parse TOML `text`; paths in it are relative to `base_dir`, `--set` ones to the cwd."""
        try:
            raw = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise TorchfricError(
                f"{source}: invalid TOML: {shorten(str(exc))}; fix the syntax there"
            ) from None
        except RecursionError:
            raise TorchfricError(
                f"{source}: the TOML is nested too deeply to read; a config needs tables one "
                "level deep ([data], [model], ...)"
            ) from None
        raw = apply_overrides(raw, overrides)
        return cls.from_dict(raw, base_dir=base_dir, check_files=check_files)

    @classmethod
    def load(
        cls,
        path: str | os.PathLike[str],
        overrides: Sequence[str] = (),
        *,
        check_files: bool = True,
    ) -> Config:
        """Read a TOML config file and apply ``--set`` overrides ("dotted.key=value")."""
        p = pathlib.Path(path)
        if not p.is_file():
            what = (
                "is a directory"
                if p.is_dir()
                else "is not a regular file"
                if p.exists()
                else "not found"
            )
            raise TorchfricError(
                f"config file {shorten(repr(str(p)))} {what} (working directory {os.getcwd()}); "
                "give the path of a .toml file"
            )
        if p.stat().st_size > MAX_CONFIG_BYTES:
            raise TorchfricError(
                f"config file {shorten(str(p))} is {p.stat().st_size:,} bytes; a config is a few "
                f"hundred bytes (at most {MAX_CONFIG_BYTES:,}): give the .toml config, not a data "
                "file"
            )
        try:
            text = p.read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise TorchfricError(
                f"{p}: not a UTF-8 text file ({exc.reason}); save it as UTF-8"
            ) from None
        return cls.loads(
            text, overrides, base_dir=p.parent.absolute(), check_files=check_files, source=str(p)
        )

    def with_overrides(self, overrides: Sequence[str], *, check_files: bool = True) -> Config:
        """This config with ``--set`` overrides applied (their paths relative to the cwd)."""
        raw = apply_overrides(self.to_dict(), overrides)
        return Config.from_dict(raw, check_files=check_files)

    def check_files(self) -> None:
        """Raise if a data file or the ``model.init`` checkpoint does not exist."""
        for key in DataConfig.PATH_KEYS:
            for i, p in enumerate(getattr(self.data, key)):
                if not p.startswith(RIG_PREFIX) and os.path.exists(p) and not os.path.isfile(p):
                    raise TorchfricError(
                        f"data.{key}[{i}] = {_show(p)} is not a regular file (a directory, FIFO "
                        "or device); give the path of a CSV, NPZ or MAT data file"
                    )
                if not p.startswith(RIG_PREFIX) and not os.path.isfile(p):
                    raise TorchfricError(
                        f"data.{key}[{i}] = {_show(p)}: no such file; fix the path (relative to "
                        "the config file's folder, or to the working directory with --set) or "
                        'use a rig experiment such as "rig:identification"'
                    )
        init = self.model.init
        if init not in INIT_KEYWORDS and not os.path.isfile(init):
            raise TorchfricError(
                f'model.init = {_show(init)}: no such checkpoint file; give "prefit", '
                '"config" or the path of an existing checkpoint (relative to the config file\'s '
                "folder, or to the working directory with --set)"
            )

    # -- writing --------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Nested plain dict (lists, not tuples; ``None`` kept) — checkpoint-safe."""
        return _plain(self)

    def to_toml(self) -> str:
        """The config as TOML text (``None`` values omitted); `loads` gives it back."""
        return to_toml(self.to_dict())


_TOP_KEYS: tuple[str, ...] = tuple(
    f.name for f in dataclasses.fields(Config) if f.name not in _SECTIONS
)
SCHEMA: dict[str, tuple[str, ...]] = {
    "": _TOP_KEYS,
    **{name: tuple(f.name for f in dataclasses.fields(cls)) for name, cls in _SECTIONS.items()},
}
"""The keys a config may hold: top-level ones under "", each section's under its name."""


def _fields(cls: type) -> dict[str, dataclasses.Field[Any]]:
    return {f.name: f for f in dataclasses.fields(cls)}


def _unknown_key(dotted: str, section: str, value: Any = None) -> NoReturn:
    """Raise for an unknown `dotted` key (in `section`, "" = top level)."""
    if section:
        allowed = list(_fields(_SECTIONS[section]))
        dotted_allowed = [f"{section}.{k}" for k in allowed]
        raise TorchfricError(
            f'unknown key "{dotted}"{_suggest(dotted, dotted_allowed)}; allowed keys '
            f"in [{section}]: {', '.join(allowed)}"
        )
    sections = ", ".join(f"[{s}]" for s in _SECTIONS)
    if dotted == "checkpoint_dir":
        raise TorchfricError(
            "checkpoint_dir was removed: a run writes its checkpoint inside its run directory "
            "only; delete the key, and copy the final checkpoint elsewhere with "
            "`torchfric train CONFIG --checkpoint PATH`"
        )
    if isinstance(value, Mapping):
        raise TorchfricError(
            f"unknown section [{dotted}]{_suggest(dotted, list(_SECTIONS))}; allowed sections: "
            f"{sections}; top-level keys: {', '.join(_TOP_KEYS)}"
        )
    raise TorchfricError(
        f'unknown key "{dotted}"{_suggest(dotted, list(_TOP_KEYS) + list(_SECTIONS))}; allowed '
        f"top-level keys: {', '.join(_TOP_KEYS)}; sections: {sections}"
    )


def _check_keys(section: str, table: Mapping[str, Any]) -> None:
    allowed = _fields(_SECTIONS[section])
    for key in table:
        if key not in allowed:
            _unknown_key(f"{section}.{key}", section)


def _resolve(path: str, base: pathlib.Path) -> str:
    p = pathlib.Path(path).expanduser()
    return os.path.normpath(p if p.is_absolute() else base / p)


def _resolve_paths(section: str, table: Mapping[str, Any], base: pathlib.Path) -> dict[str, Any]:
    """Copy of `table` with its path keys made absolute against `base` (bad types left alone)."""
    out = dict(table)
    for key in _SECTIONS[section].PATH_KEYS:  # type: ignore[attr-defined]
        value = out.get(key)
        if key == "init":
            if isinstance(value, str) and value and value not in INIT_KEYWORDS:
                out[key] = _resolve(value, base)
            continue
        single = isinstance(value, str)
        items = [value] if single else value
        if isinstance(items, list | tuple) and all(isinstance(v, str) for v in items):
            items = [v if v.startswith(RIG_PREFIX) or not v else _resolve(v, base) for v in items]
            out[key] = items[0] if single else items
    return out


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    return value


# --------------------------------------------------------------------------------------------
# --set overrides
# --------------------------------------------------------------------------------------------


def _parse_value(text: str, string_field: bool) -> Any:
    """A TOML value when `text` parses as one, else the bare string."""
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text
    if string_field and not isinstance(value, str | list | dict):
        return text  # name=2024 or a path like 12 stays a string
    return value


def apply_overrides(raw: Mapping[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Apply ``--set`` strings ("dotted.key=value") to nested tables `raw`; returns a copy.

    Keys are checked here (unknown → error naming the key); values by `Config.from_dict`.
    Path values are made absolute against the working directory.
    """
    if isinstance(overrides, str):
        overrides = [overrides]
    out: dict[str, Any] = {k: dict(v) if isinstance(v, Mapping) else v for k, v in raw.items()}
    cwd = pathlib.Path.cwd()
    for item in overrides:
        if not isinstance(item, str) or "=" not in item:
            raise TorchfricError(
                f"--set {item!r}: expected KEY=VALUE with a dotted key, e.g. "
                "--set estimator.passes=20 or --set model.friction=polytopic"
            )
        key, _, text = item.partition("=")
        key, text = key.strip(), text.strip()
        parts = key.split(".")
        if len(parts) == 1:
            if parts[0] in _SECTIONS:
                first = next(iter(_fields(_SECTIONS[parts[0]])))
                raise TorchfricError(
                    f"--set {item!r}: [{parts[0]}] is a section; set one of its keys, e.g. "
                    f"--set {parts[0]}.{first}=..."
                )
            if parts[0] not in _TOP_KEYS:
                _unknown_key(key, "")
            out[key] = _parse_value(text, _fields(Config)[key].type == "str")
            continue
        section, name = parts[0], parts[1]
        if section not in _SECTIONS:
            _unknown_key(section, "", {})
        fields = _fields(_SECTIONS[section])
        if name not in fields or (len(parts) > 2 and name != "columns") or len(parts) > 3:
            _unknown_key(key, section)
        table = out.get(section)
        if not isinstance(table, dict):
            table = out[section] = {}
        if len(parts) == 3:  # data.columns.q=qm
            if parts[2] not in COLUMN_NAMES:
                raise TorchfricError(
                    f'unknown key "{key}"{_suggest(parts[2], COLUMN_NAMES)}; allowed keys in '
                    f"[data.columns]: {', '.join(COLUMN_NAMES)}"
                )
            columns = table.get("columns")
            columns = dict(columns) if isinstance(columns, Mapping) else {}
            columns[parts[2]] = _parse_value(text, True)
            table["columns"] = columns
            continue
        string_field = fields[name].type in ("str", "tuple[str, ...]")
        value = _parse_value(text, string_field)
        if name in _SECTIONS[section].PATH_KEYS:  # type: ignore[attr-defined]
            value = _resolve_paths(section, {name: value}, cwd)[name]
        table[name] = value
    return out


# --------------------------------------------------------------------------------------------
# A small TOML writer (str, int, float, bool, arrays, nested tables; None omitted)
# --------------------------------------------------------------------------------------------

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
_ESCAPES = {'"': '\\"', "\\": "\\\\", "\n": "\\n", "\t": "\\t", "\r": "\\r", "\b": "\\b"}


def _toml_string(s: str) -> str:
    out = []
    for ch in s:
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _toml_key(key: Any) -> str:
    if not isinstance(key, str):
        raise TorchfricError(f"TOML keys must be strings, got {key!r}")
    return key if _BARE_KEY.fullmatch(key) else _toml_string(key)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return _toml_string(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value if v is not None) + "]"
    if isinstance(value, Mapping):
        items = [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items() if v is not None]
        return "{ " + ", ".join(items) + " }" if items else "{}"
    raise TorchfricError(f"cannot write {value!r} ({type(value).__name__}) as a TOML value")


def to_toml(data: Mapping[str, Any]) -> str:
    """Nested tables → TOML text: top-level keys, then one ``[section]`` per top-level table;
    tables inside sections are written inline (``columns = { q = "qm" }``)."""
    lines = [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in data.items() if _scalar(v)]
    for k, v in data.items():
        if isinstance(v, Mapping):
            lines += ["", f"[{_toml_key(k)}]"] if lines else [f"[{_toml_key(k)}]"]
            lines += [
                f"{_toml_key(kk)} = {_toml_value(vv)}" for kk, vv in v.items() if vv is not None
            ]
    return "\n".join(lines) + "\n"


def _scalar(value: Any) -> bool:
    return value is not None and not isinstance(value, Mapping)
