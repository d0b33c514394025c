"""The ``[estimator]`` section: which estimator, and the estimators' own settings.

The section is flat in TOML (``passes = 10``, ``lr = 0.01``, ``ensemble = 1``, ...), but
`EstimatorConfig` holds the very dataclasses the estimators take
(`torchfric.estimators.settings`): `EKFTuning` for ``identify_ekf`` (and every ensemble member),
`OETuning` for ``identify_output_error`` and `EnsembleSpec` for ``identify_ekf_ensemble``.
`ESTIMATOR_KEYS` routes each flat key to the one dataclass field that owns it, in the order the
keys are written; the defaults are those dataclasses' own (the ensemble's: `RUN_ENSEMBLE`), so no
default is restated here.

Two keys are shared: ``substeps`` and ``compile`` mean the same to both estimators, so one value
goes into `EKFTuning` and `OETuning` alike (each estimator's settings are complete by
themselves), reading one gives the EKF's, and the two must agree.

The config's own checks give the messages users see from a config (the dotted key, the value,
what is allowed, an example); the output-error settings' cross-field rules (``lr_final <= lr``,
``learn_states`` needs a fixed window, ...) are `OETuning.check`'s, stated there once.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

from ...errors import TorchfricError
from ...estimators.ekf import MEASUREMENTS
from ...estimators.settings import RUN_ENSEMBLE, TUNING_UNITS, EKFTuning, EnsembleSpec, OETuning
from .schema import Check, TableSection, show, unknown_section_key

__all__ = [
    "ENSEMBLE_KEYS",
    "ESTIMATORS",
    "ESTIMATOR_KEYS",
    "MAX_EPOCHS",
    "MAX_PASSES",
    "SELECT_RULES",
    "EstimatorConfig",
]

ESTIMATORS: tuple[str, ...] = ("ekf", "output_error")
SELECT_RULES: tuple[str, ...] = ("validation", "identification")
"""What chooses the kept pass, member, polish and epoch (`EstimatorConfig.select`)."""
MAX_PASSES = 1000
"""EKF passes above this are refused: the paper needs 10 and `tolerance` stops earlier."""
MAX_EPOCHS = 100_000
ENSEMBLE_KEYS: tuple[str, ...] = (
    "ensemble",
    "ensemble_spread",
    "ensemble_q_scales",
    "ensemble_r_scales",
)

_SETTINGS: dict[str, type] = {
    "ekf": EKFTuning,
    "output_error": OETuning,
    "ekf_ensemble": EnsembleSpec,
}
"""`EstimatorConfig`'s fields that hold an estimator's settings → their dataclass."""


def _own(holder: str, *names: str) -> dict[str, tuple[tuple[str, str], ...]]:
    return {name: ((holder, name),) for name in names}


ESTIMATOR_KEYS: dict[str, tuple[tuple[str, str], ...]] = {
    "method": (("", "method"),),
    **_own("ekf", "passes", "tolerance", "p0_state", "p0_theta", "q_state", "q_theta", "r"),
    **_own("ekf", "measure"),
    "substeps": (("ekf", "substeps"), ("output_error", "substeps")),
    **_own("ekf", "theta_bound"),
    "compile": (("ekf", "compile"), ("output_error", "compile")),
    **_own("ekf", "p0_relative", "rollback", "units"),
    **_own("output_error", "epochs", "lr", "lr_final", "window", "batch", "weights", "clip"),
    **_own("output_error", "lbfgs_steps", "patience", "eval_every", "schedule", "adjoint"),
    **_own("output_error", "learn_states", "continuity"),
    "ensemble": (("ekf_ensemble", "members"),),
    "ensemble_spread": (("ekf_ensemble", "spread"),),
    "ensemble_q_scales": (("ekf_ensemble", "q_scales"),),
    "ensemble_r_scales": (("ekf_ensemble", "r_scales"),),
    "select": (("", "select"),),
}
"""Each flat ``[estimator]`` key, in TOML order → the ``(holder, field)`` it sets: holder "" is
`EstimatorConfig` itself, else one of its settings fields. A shared key names two; it is read
from the first."""


@dataclass(frozen=True)
class EstimatorConfig(TableSection):
    """``[estimator]``: which estimator, and its settings (EKF defaults are the paper's, §5).

    Attributes:
        method: "ekf" (augmented-state continuous–discrete EKF) or "output_error".
        select: what chooses the model a run keeps — the EKF's pass, the ensemble's member,
            whether the prediction-error polish is kept, output error's epoch.
            "validation": the validation records' open-loop FIT (the ensemble's member by
            validation and identification FIT, weighted equally; without validation data the
            passes by the innovation likelihood, the member by the identification FIT, output
            error its last epoch); the validation FIT reported is then not a held-out score.
            "identification": the identification records' full-length open-loop FIT (mean of q
            and q̇) alone, the rule that predicted held-out error best on EMPS; output error
            keeps its last epoch; validation records choose nothing and their FIT is held out.
            Judged on a third record, neither rule wins everywhere (25 records of nine machines:
            median FIT q 91.8 against the validation rule's 92.8 %; ten seeds of a conveyor:
            92.6 against 86.6 %; docs/results.md, "Which records choose the kept model"), so
            "validation" stays the default and ``torchfric init`` writes it.
        ekf: the EKF tuning (`EKFTuning`; keys passes, tolerance, p0_state, p0_theta, q_state,
            q_theta, r, measure, substeps, theta_bound, compile, p0_relative, rollback, units).
            p0_theta and q_theta are one number for every θ entry or one per entry.
        output_error: output-error training (`OETuning`; keys epochs, lr, lr_final, window
            (0: full length), batch, weights, clip, lbfgs_steps, patience, eval_every, schedule,
            adjoint, learn_states, continuity — multiple shooting with learned window start
            states and a continuity penalty — and the shared substeps and compile). Its
            ``seed`` is the run's top-level ``seed`` (`oe_tuning`), not a key.
        ekf_ensemble: the EKF ensemble (`EnsembleSpec`; keys ensemble → members,
            ensemble_spread → spread, ensemble_q_scales → q_scales, ensemble_r_scales →
            r_scales; its ``seed`` is the run's, `ensemble_spec`); default `RUN_ENSEMBLE`.
        substeps: RK4 steps per sample interval, one value for both estimators: the EKF's
            prediction (`EKFTuning.substeps`) and the output-error simulations
            (`OETuning.substeps`). "auto": the EKF takes the fewest that keep RK4 stable on
            the model's stiffest mode (`filter_substeps`: a friction slope λ needs ⌈λ·dt / 2⌉),
            from the start and raised between passes as the leading member's friction steepens
            (at most 16; 1 for LuGre, whose step is stable at any stiffness); the covariance
            stage takes the kept θ's; output error re-chooses them every epoch
            (`auto_substeps`). The default 1 is the paper's; ``torchfric init`` writes "auto".
            A run warns when the kept model needs more than its filter's last pass took.
        ensemble: number of starts of the EKF ensemble (`EnsembleSpec.members`); 0 runs a
            single filter, the paper's method. Start 0 is the initial θ itself, the others are
            random within ensemble_spread (×/÷ box around it). Every start runs under every
            tuning of the grid ensemble_q_scales × ensemble_r_scales (factors on Q and R), and
            the member with the best open-loop FIT is kept (on the validation data, else on
            the training data). The default is `RUN_ENSEMBLE`: 1 start × Q {÷10, 1, ×10} × R
            {÷10, 1, ×10}, 9 filters. Output-error runs ignore the default; changing any
            ensemble key with method = "output_error" is an error.

    Every flat key reads as an attribute too (``config.estimator.passes``), and
    `from_table`/`to_table` convert from and to the flat TOML table.
    """

    method: str = "ekf"
    select: str = "validation"
    ekf: EKFTuning = field(default_factory=EKFTuning)
    output_error: OETuning = field(default_factory=OETuning)
    ekf_ensemble: EnsembleSpec = field(default_factory=lambda: RUN_ENSEMBLE)

    def __post_init__(self) -> None:
        self._check_settings()
        values = SimpleNamespace(**self.to_table())
        c = Check(values, "estimator", _default_table())
        c.string("method", choices=ESTIMATORS)
        c.string("select", choices=SELECT_RULES)
        _check_ekf_keys(c, values)
        _check_output_error_keys(c, values)
        _check_ensemble_keys(c, values)
        self._store(vars(values))
        if self.method == "output_error":
            # the estimator's own cross-field rules (lr_final <= lr, ...), stated there once;
            # each message starts with the field, which is the [estimator] key of that name
            try:
                self.output_error.check(1)
            except TorchfricError as err:
                raise TorchfricError(f"estimator.{err}") from None

    def __getattr__(self, name: str) -> Any:
        """A flat key's value (``estimator.passes`` → ``self.ekf.passes``)."""
        routes = ESTIMATOR_KEYS.get(name)
        if routes is None or name.startswith("_"):
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        holder, key = routes[0]
        return getattr(object.__getattribute__(self, holder), key)

    # -- the flat table ---------------------------------------------------------------------------
    @classmethod
    def toml_keys(cls) -> dict[str, str]:
        """The flat keys in TOML order → the annotation of the field that owns each."""
        owners: dict[str, type] = {"": cls, **_SETTINGS}
        out = {}
        for key, ((holder, name), *_) in ESTIMATOR_KEYS.items():
            out[key] = str(
                next(f.type for f in dataclasses.fields(owners[holder]) if f.name == name)
            )
        return out

    @classmethod
    def from_table(cls, table: Mapping[str, Any]) -> EstimatorConfig:
        """Build (and validate) from a flat ``[estimator]`` table; missing keys take defaults."""
        for key in table:
            if key not in ESTIMATOR_KEYS:
                raise unknown_section_key(f"estimator.{key}", "estimator", list(ESTIMATOR_KEYS))
        values = {**_default_table(), **table}
        settings = {holder: kind(**_routed(values, holder)) for holder, kind in _SETTINGS.items()}
        return cls(method=values["method"], select=values["select"], **settings)

    def to_table(self) -> dict[str, Any]:
        """The flat ``[estimator]`` table, in TOML order."""
        return {key: getattr(self, key) for key in ESTIMATOR_KEYS}

    # -- the estimators' settings ---------------------------------------------------------------
    def ekf_tuning(self) -> EKFTuning:
        """The EKF settings (`torchfric.estimators.settings.EKFTuning`)."""
        return self.ekf

    def oe_tuning(self, seed: int = 0) -> OETuning:
        """The output-error settings with the run's `seed` (`OETuning`)."""
        return dataclasses.replace(self.output_error, seed=seed)

    def ensemble_spec(self, seed: int = 0) -> EnsembleSpec:
        """The ensemble settings with the run's `seed` (`EnsembleSpec`; only when ensemble > 0)."""
        return dataclasses.replace(self.ekf_ensemble, seed=seed)

    # -- internals ------------------------------------------------------------------------------
    def _check_settings(self) -> None:
        """The settings fields hold their dataclasses, without a seed, and shared keys agree."""
        for holder, kind in _SETTINGS.items():
            value = getattr(self, holder)
            if not isinstance(value, kind):
                raise TorchfricError(
                    f"EstimatorConfig.{holder} must be an {kind.__name__}, got "
                    f"{type(value).__name__}; use EstimatorConfig.from_table for a flat table"
                )
            if getattr(value, "seed", 0) != 0:
                raise TorchfricError(
                    f"EstimatorConfig.{holder}.seed = {value.seed!r}: the run's top-level seed "
                    "seeds the estimators; leave it 0"
                )
        for key, routes in ESTIMATOR_KEYS.items():
            (first, name), *others = routes
            for holder, _ in others:
                a, b = getattr(getattr(self, first), name), getattr(getattr(self, holder), name)
                if a is not b and a != b:  # (the same object: one value, NaN included)
                    raise TorchfricError(
                        f"estimator.{key} is {show(a)} in EstimatorConfig.{first} but {show(b)} "
                        f"in EstimatorConfig.{holder}; [estimator] holds one {key} for both "
                        "estimators: give both the same"
                    )

    def _store(self, values: Mapping[str, Any]) -> None:
        """Put the checked, normalised flat `values` back into the held dataclasses."""
        object.__setattr__(self, "method", values["method"])
        object.__setattr__(self, "select", values["select"])
        for holder in _SETTINGS:
            held = dataclasses.replace(getattr(self, holder), **_routed(values, holder))
            object.__setattr__(self, holder, held)


def _routed(values: Mapping[str, Any], holder: str) -> dict[str, Any]:
    """The fields of settings `holder` → their values from the flat table `values`."""
    return {
        name: values[key]
        for key, routes in ESTIMATOR_KEYS.items()
        for owner, name in routes
        if owner == holder
    }


@functools.cache
def _default_table() -> Mapping[str, Any]:
    """Every flat key's default, read from the settings dataclasses' own defaults."""
    fields = {f.name: f for f in dataclasses.fields(EstimatorConfig)}
    own = {name: fields[name].default for name in ("method", "select")}
    holders: dict[str, Any] = {"": SimpleNamespace(**own)}
    holders.update({name: fields[name].default_factory() for name in _SETTINGS})  # type: ignore[misc]
    return {key: getattr(holders[h], name) for key, ((h, name), *_) in ESTIMATOR_KEYS.items()}


def _check_ekf_keys(c: Check, v: SimpleNamespace) -> None:
    """The EKF keys (and the shared substeps and compile), in TOML order."""
    c.integer("passes", ge=1)
    if v.passes > MAX_PASSES:
        c.range_error(
            "passes",
            v.passes,
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
    if not all(x > 0 for x in v.r):
        c.range_error("r", list(v.r), "measurement variances > 0")
    m = len(MEASUREMENTS[v.measure])
    if len(v.r) != m:
        example = show([c.defaults["r"][i] for i in MEASUREMENTS[v.measure]])
        raise TorchfricError(
            f"estimator.r = {show(list(v.r))} has {len(v.r)} value(s) but "
            f'estimator.measure = "{v.measure}" measures {m} channel(s); give {m}, '
            f"e.g. estimator.r = {example}"
        )
    c.auto_or_integer("substeps", ge=1, example=4)
    c.number("theta_bound", gt=0.0)
    c.boolean("compile")
    c.boolean("p0_relative")
    c.boolean("rollback")
    c.string("units", choices=TUNING_UNITS)


def _check_output_error_keys(c: Check, v: SimpleNamespace) -> None:
    """The output-error keys, in TOML order."""
    c.integer("epochs", ge=0)
    if v.epochs > MAX_EPOCHS:
        c.range_error("epochs", v.epochs, f"an integer from 0 to {MAX_EPOCHS}")
    c.number("lr", gt=0.0)
    c.number("lr_final", gt=0.0)
    c.integer("window", ge=0)
    c.integer("batch", ge=1)
    c.numbers("weights", length=2, ge=0.0)
    c.number("clip", ge=0.0)
    c.integer("lbfgs_steps", ge=0)
    c.integer("patience", ge=1)
    c.integer("eval_every", ge=1)
    sched = v.schedule
    if not isinstance(sched, list | tuple) or not all(
        isinstance(x, int) and not isinstance(x, bool) and (x == 0 or x >= 2) for x in sched
    ):
        c.type_error(
            "schedule",
            sched,
            "an array of window lengths (0 or >= 2), short to long",
            [50, 200, 800],
        )
    c.set("schedule", tuple(int(x) for x in sched))
    c.boolean("adjoint")
    c.boolean("learn_states")
    c.number("continuity", ge=0.0)


def _check_ensemble_keys(c: Check, v: SimpleNamespace) -> None:
    """The ensemble keys; with a method other than "ekf", only their defaults (or ensemble 0)."""
    c.integer("ensemble", ge=0)
    c.number("ensemble_spread", ge=1.0)
    for key in ("ensemble_q_scales", "ensemble_r_scales"):
        c.numbers(key)
        if not getattr(v, key) or not all(x > 0 for x in getattr(v, key)):
            c.range_error(key, list(getattr(v, key)), "a non-empty list of factors > 0")
    if v.method != "ekf":
        for key in ENSEMBLE_KEYS:
            if getattr(v, key) != c.defaults[key] and not (key == "ensemble" and v.ensemble == 0):
                raise TorchfricError(
                    f"estimator.{key} = {show(getattr(v, key))} needs estimator.method = "
                    f'"ekf" (got "{v.method}"); remove it (output error runs no ensemble)'
                )
