"""The ``[data]``, ``[model]``, ``[simulation]`` and ``[log]`` sections of a run config.

Each is a frozen dataclass whose fields are its TOML keys: it owns its defaults and checks its
own values on construction (`__post_init__`, with `torchfric.app.config.schema.Check`), so a section
that exists is valid. The ``[estimator]`` section is `torchfric.app.config.estimator`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar

from ...data.units import COLUMN_NAMES, POSITION_UNITS, TIME_UNITS, position_factor, si_unit
from ...errors import TorchfricError
from ...estimators.tracking import TrackSettings
from ...models.friction import FRICTIONS
from ...models.lugre import DYNAMICS
from ...models.simulate import SOLVERS
from .schema import (
    INIT_KEYWORDS,
    RIG_PREFIX,
    RIG_VALIDATION,
    VELOCITY_SOURCES,
    Check,
    TableSection,
    show,
    suggest,
)

__all__ = [
    "AUTO_SIZES",
    "DataConfig",
    "LogConfig",
    "ModelConfig",
    "SimulationConfig",
    "TrackConfig",
]

AUTO_SIZES: dict[str, tuple[int, ...]] = {"tanh": (1, 2, 3, 4, 5, 6, 7), "polytopic": (3, 5, 7, 9)}
"""The sizes ``model.size = "auto"`` tries without ``model.sizes``, for the frictions that have
a size (`torchfric.app.run.autosize`)."""

DYNAMIC_CHOICES = (*DYNAMICS, "auto")
"""``model.dynamic``: the model's classes, or "auto" (chosen from the data, `torchfric.app.run.autosize`)."""


@dataclass(frozen=True)
class DataConfig(TableSection):
    """``[data]``: measurement files and how to read them.

    Attributes:
        train: identification records (paths or ``"rig:NAME"``); all are used in each pass.
        validation: records for the validation FIT after each pass and in ``metrics.json``;
            the default is ``["rig:validation"]`` for rig data and none for a user's files.
        test: extra held-out records evaluated once at the end.
        columns: our names (t, u, q, qdot) → names in the file, e.g. ``{u = "vir", q = "qm"}``;
            a name ``"A:k"`` selects column k of a 2-D array A (NPZ and MAT files). Unmapped
            names are looked up as themselves.
        columns.t: the file's time column, in seconds (default: the column named t); a file
            without one needs `time_step`.
        columns.u: the file's input column (default: u), the signal that ``model.c_m`` turns into
            torque or force.
        columns.q: the file's position column (default: q), in `position_unit`.
        columns.qdot: the file's measured velocity column (default: qdot, read when the file
            has it), in `position_unit` per second; the estimators use it with
            ``velocity = "measured"``.
        time_step: sample period [s] for files without a t column (checked against t otherwise);
            t is then the file's sample counter (a column named Index, Sample, Nr …) times it
            where there is one, so that samples a logger dropped stay gaps.
        velocity: q̇ measurement for the estimators: "highpass" (the paper's causal
            differentiator, started at the record's first-step speed, so a record may start
            in motion), "zero_phase" (off-line) or "measured" (the file's qdot column).
        velocity_cutoff_hz: cut-off of the reconstruction [Hz], below the Nyquist frequency
            1/(2·time step); ``None`` = the method's default (`DEFAULT_CUTOFF_HZ`: 200 Hz for
            "highpass", 50 Hz for "zero_phase"; a file sampled at 400 Hz or slower needs a
            lower one with "highpass").
        time_unit: unit of t in the files (`TIME_UNITS`: "s", "ms", "us"); the loader converts
            to s. A header that states the unit (``Zeit [ms]``) must agree.
        position_unit: unit of q in the files (`POSITION_UNITS`); the loader converts to SI.
            "counts" needs `counts_per_rev` (rotary) or `counts_per_m` (linear). A header that
            states the unit (``Winkel [deg]``) must agree.
        counts_per_rev: encoder counts per revolution, for ``position_unit = "counts"`` on a
            rotary axis (q becomes rad: × 2π / counts_per_rev).
        counts_per_m: encoder counts per metre, for ``position_unit = "counts"`` on a linear
            axis (q becomes m).
        wrap_period: the period at which q wraps, in `position_unit` (4096 for a single-turn
            count of 4096, 360 for degrees in 0 … 360); each segment is unwrapped at load.
            ``None``: q does not wrap, and a record whose q jumps by about a period between
            samples is refused.
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
    time_unit: str = "s"
    counts_per_rev: float | None = None
    counts_per_m: float | None = None
    wrap_period: float | None = None

    PATH_KEYS: ClassVar[tuple[str, ...]] = ("train", "validation", "test")

    @property
    def axis_unit(self) -> str:
        """The SI unit q is converted to: "m" (a linear axis) or "rad" (a rotary one)."""
        return si_unit(self.position_unit, self.counts_per_m)

    def __post_init__(self) -> None:
        c = Check(self, "data")
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
                        f"data.{key} = {show(list(getattr(self, key)))} names the built-in "
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
                    f'unknown key "data.columns.{k}"{suggest(k, COLUMN_NAMES)}; allowed keys'
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
        c.string("time_unit", choices=tuple(TIME_UNITS))
        c.number("counts_per_rev", gt=0.0, optional=True, example=4096.0)
        c.number("counts_per_m", gt=0.0, optional=True, example=1e6)
        c.number("wrap_period", gt=0.0, optional=True, example=4096.0)
        per = [k for k in ("counts_per_rev", "counts_per_m") if getattr(self, k) is not None]
        if self.position_unit == "counts" and len(per) != 1:
            raise TorchfricError(
                'data.position_unit = "counts" needs exactly one of data.counts_per_rev (a '
                "rotary axis: counts per revolution) and data.counts_per_m (a linear axis), "
                f"{'not both' if per else 'none is set'}; e.g. data.counts_per_rev = 4096"
            )
        if self.position_unit != "counts" and per:
            raise TorchfricError(
                f"data.{per[0]} is set but data.position_unit = {self.position_unit!r}; set "
                'data.position_unit = "counts" (q in encoder counts), or remove it'
            )

    @property
    def position_factor(self) -> float:
        """The factor that turns q in `position_unit` into SI (rad or m)."""
        return position_factor(self.position_unit, self.counts_per_rev, self.counts_per_m)

    @property
    def rig_only(self) -> bool:
        """True when every identification record is the built-in rig's (``"rig:NAME"``)."""
        train = (self.train,) if isinstance(self.train, str) else self.train
        return all(isinstance(p, str) and p.startswith(RIG_PREFIX) for p in train)


@dataclass(frozen=True)
class ModelConfig(TableSection):
    """``[model]``: the grey-box model and its initial guesses.

    Attributes:
        friction: black-box friction, a `torchfric.friction.FRICTIONS` name.
        size: neurons (tanh) or local models (polytopic, odd); ignored by the baselines.
            "auto" chooses it from the data (tanh or polytopic): every size of `sizes` is
            identified and the one with the lowest BIC on the identification data's fixed-θ
            EKF innovations is kept (`torchfric.estimators.sizing`; the table of sizes is in
            ``metrics.json`` and the report).
        sizes: the sizes that ``size = "auto"`` tries; empty = tanh 1–7, polytopic 3, 5, 7, 9.
        c_m: motor constant, torque (or force) per unit of input (known unless
            `estimate_c_m`). Required with a user's data; ``None`` takes the rig's 16 for rig
            data (`Config` resolves it).
        inertia, viscous: initial guesses of M and b (with ``init = "config"``, or as the
            fallback of the pre-fit). For "polytopic" the runner ignores `viscous`: the paper's
            polytopic model carries its own slopes and has no separate b.
        offset: ``None`` = no constant offset term; a number enables it with that initial guess.
            It is subtracted from the motor's force: ``M q̈ = c_m u − friction − offset``, so a
            load pulling towards negative q (gravity on a vertical axis whose q points up) has
            a positive offset, m·g.
        gravity: ``None`` = no ``g_c sin q`` term; a number (> 0) enables it.
        asymmetric: ``None`` = no even viscous term; a number enables ``a |q̇|`` with that
            initial guess (direction-dependent viscous slopes b ± a, `torchfric.arm.ArmModel`).
        estimate_c_m: put c_m in θ.
        log_positive: estimate positive parameters (M, b, variances…) as logarithms.
        velocity_scale, torque_scale: scales for the friction's initial shape; ``None`` = from
            the data.
        saturation: tanh only: every neuron's input weight is bounded below by ``saturation /
            velocity scale`` (`OddTanhFriction.min_slope`), so each neuron is saturated to
            within ``1 − tanh(saturation)`` at the data's 95th-percentile speed: none can stay
            linear over the whole data. A neuron at the bound still rises between the median
            and that speed, though, and takes part of b's slope there (one of 12 fits of a
            rotary axis: b 47 σ off, 1.2 σ with 6); the run checks every neuron and warns
            ("viscous and neuron j … are not separately identifiable"): raise it (6, say)
            then. 0 = the paper's unbounded weights. "auto" (what ``torchfric init`` writes):
            6 for a static model (every neuron saturated by half of v95: on machines that
            stick, a static curve otherwise recruits a slow neuron for the steep part near
            rest, which takes b's slope), 3 for LuGre, whose bristles hold the stick (measured
            over 20 seeds on four machines: docs/results.md, "Parameters you can trust");
            the shipped configs keep 3.
        init: "prefit" (least-squares pre-fit on the training data), "config" (the values above)
            or the path of a checkpoint to warm-start from (stored absolute).
        dynamic: "none" (static friction), "lugre": a bristle state z with ``ż = q̇ − σ0 |q̇|
            z / g(q̇)``, ``F = σ0 z + σ1 ż + b q̇``, whose sliding curve g is the friction
            module's (`torchfric.models.lugre`); σ0 and σ1 are estimated (in log space), or
            "auto" (what ``init`` writes): both are identified on the first 70 % of every
            identification record and each predicts the last 30 % in 0.05-s open-loop windows
            from its own filter; "lugre" is kept only when its windows' mean squared position
            error is lower by more than 2 standard errors of the paired difference and its
            bristles travel at least one position step through a reversal (2 g(0)/σ0; a
            stiffer σ0 is, for this record, σ0 → ∞: a static model that sticks) and less
            than the records' position span (a softer one never slides: σ0 → 0), and the
            axis stuck on them settles slowly enough for the samples to see it (its faster
            rate × the sample time ≤ 1; faster is σ0 → ∞ in time), else the static model
            (`torchfric.app.run.autosize`; the comparison is in metrics.json's ``dynamics``,
            the summary and report.html). The validation and test records are
            not read. A run then trains the chosen class on all the data (about 2.4× the time
            of a run of one class). Beyond 100,000 samples in all, both classes are
            identified on four excerpts of each record's first 70 % (70,000 samples in all)
            and scored on the whole held-out 30 % (`comparison_heads`; ``dynamics.excerpts``).
        sigma0: initial bristle stiffness σ0 [torque per unit of q] of "lugre"; ``None`` = from
            the data: the pre-sliding range starts at one position step (encoder count) of the
            identification records, ``σ0 = |F(v_s)| / Δq`` with F the starting model's static
            friction at the stick velocity and Δq the records' smallest position step
            (`torchfric.data.position_step`), so the start scales with the data's
            units as the machine does.
        sigma1: initial bristle damping σ1 [torque per unit of q̇]; ``None`` = critically damped
            from σ0 and the starting inertia (the pre-fit's, with ``init = "prefit"``),
            ``2 sqrt(σ0 M)``.
        stick_velocity: initial stick velocity v_s of "lugre" [unit of q̇]: below it the sliding
            curve is held at its value there, the static friction; ``None`` = 1 % of the
            velocity scale.
    """

    friction: str = "tanh"
    size: int | str = 3
    sizes: tuple[int, ...] = ()
    c_m: float | None = None
    inertia: float = 0.03
    viscous: float = 0.01
    offset: float | None = None
    gravity: float | None = None
    estimate_c_m: bool = False
    log_positive: bool = True
    velocity_scale: float | None = None
    torque_scale: float | None = None
    saturation: float | str = 3.0
    init: str = "prefit"
    asymmetric: float | None = None
    dynamic: str = "none"
    sigma0: float | None = None
    sigma1: float | None = None
    stick_velocity: float | None = None

    PATH_KEYS: ClassVar[tuple[str, ...]] = ("init",)

    def __post_init__(self) -> None:
        c = Check(self, "model")
        c.string("friction", choices=tuple(FRICTIONS))
        c.auto_or_integer("size", ge=1, example=3)
        if self.friction == "polytopic" and self.size != "auto" and self.size % 2 == 0:
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
        c.auto_or_number("saturation", ge=0.0, example=6.0)
        c.string("init")
        _check_sizes(c, self)
        c.string("dynamic", choices=DYNAMIC_CHOICES)
        c.number("sigma0", gt=0.0, optional=True, example=1000.0)
        c.number("sigma1", gt=0.0, optional=True, example=10.0)
        c.number("stick_velocity", gt=0.0, optional=True, example=0.05)


def _check_sizes(c: Check, m: ModelConfig) -> None:
    """``model.sizes``: integers >= 1 (odd for polytopic), only with ``model.size = "auto"``,
    which needs a friction with a size and a start of its own (not a checkpoint)."""
    sizes = m.sizes
    if not isinstance(sizes, list | tuple) or not all(
        isinstance(s, int) and not isinstance(s, bool) and s >= 1 for s in sizes
    ):
        c.type_error("sizes", sizes, "an array of integers >= 1", [1, 2, 3, 4])
    c.set("sizes", tuple(sorted(set(sizes))))
    if m.size != "auto":
        if sizes:
            raise TorchfricError(
                f'model.sizes = {show(list(sizes))} lists the sizes that model.size = "auto" '
                f'tries, but model.size = {show(m.size)}; set model.size = "auto", or remove '
                "model.sizes"
            )
        return
    if m.friction not in AUTO_SIZES:
        raise TorchfricError(
            f'model.size = "auto" chooses the size of a tanh or polytopic friction, but '
            f'model.friction = "{m.friction}" has no size; give model.size an integer (it is '
            "ignored) or choose a sized friction"
        )
    even = [s for s in m.sizes if s % 2 == 0]
    if m.friction == "polytopic" and even:
        raise TorchfricError(
            f"model.sizes = {show(list(m.sizes))} holds even sizes ({show(even)}); "
            '"polytopic" needs an odd number of local models: use e.g. [3, 5, 7, 9]'
        )
    if m.init not in INIT_KEYWORDS:
        raise TorchfricError(
            f'model.size = "auto" builds each size from model.init = "prefit" or "config", but '
            f"model.init is a checkpoint ({m.init}) of one size; give model.size that "
            'checkpoint\'s size, or set model.init = "prefit"'
        )


@dataclass(frozen=True)
class SimulationConfig(TableSection):
    """``[simulation]``: open-loop simulation for validation (`torchfric.simulate`).

    Attributes:
        method: fixed-grid solver, a `torchfric.simulate.SOLVERS` name.
        substeps: solver steps per sample interval, or "auto" (from the model's stiffness).
    """

    method: str = "rk4"
    substeps: int | str = "auto"

    def __post_init__(self) -> None:
        c = Check(self, "simulation")
        c.string("method", choices=tuple(SOLVERS))
        c.auto_or_integer("substeps", ge=1, example=4)


@dataclass(frozen=True)
class LogConfig(TableSection):
    """``[log]``: what a run draws into TensorBoard besides its scalars (which are every pass).

    Attributes:
        figure_every: the friction curve and the validation responses. Always drawn for the
            starting model (step 0) and the final one, when the run ends; in between, every N
            passes or epochs for an integer N >= 1, never for 0, and for "auto" (the default)
            at most once a minute, so that a run under a minute draws only those two.
    """

    figure_every: int | str = "auto"

    def __post_init__(self) -> None:
        Check(self, "log").auto_or_integer("figure_every", ge=0, example=5)


@dataclass(frozen=True)
class TrackConfig(TrackSettings, TableSection):
    """``[track]``: ``torchfric track``, the EKF run on-line from a checkpoint
    (`torchfric.estimators.tracking`; times in seconds).

    Attributes:
        q_theta: random-walk intensity of θ (estimation coordinates² per second; log-stored
            parameters such as M: relative).
        forgetting: forgetting factor λ in (0, 1]; ``P_θθ`` is divided by λ every sample
            (1 = off).
        block: the change detector averages the normalised innovations (NIS) over blocks this
            long.
        calibrate: how long the detector measures its baseline, at the start and after a
            change's hold-off (the machine is assumed unchanged then).
        holdoff: after a change, how long detection pauses while θ re-converges.
        false_alarm_hours: the mean time between false alarms on unchanged data that the
            detector's threshold is designed for (a CUSUM on the NIS block means, each scored by
            the smaller of its standardised value and its rarity in the calibration).
        reopen: the variance added to each θ entry's ``P_θθ`` after a change, so that θ
            converges to the changed machine quickly.
        detect: run the change detector.

    The fields and defaults are `torchfric.estimators.tracking.TrackSettings`' (this section is
    those settings, checked), so the tracker takes the section as it is.
    """

    def __post_init__(self) -> None:
        c = Check(self, "track")
        c.number("q_theta", ge=0.0)
        c.number("forgetting", gt=0.0)
        if self.forgetting > 1.0:
            c.range_error("forgetting", self.forgetting, "a number in (0, 1]")
        c.number("block", gt=0.0)
        c.number("calibrate", gt=0.0)
        c.number("holdoff", ge=0.0)
        c.number("false_alarm_hours", gt=0.0)
        c.number("reopen", ge=0.0)
        c.boolean("detect")
