"""A sweep's Optuna study: its storage, its sampler and pruner, and the checks that a study
being continued sweeps the same space for the same objective.

The study's user attributes ``torchfric_space`` and ``torchfric_objective`` record what it
sweeps; a study by the same name that sweeps something else is refused, never mixed.
"""

from __future__ import annotations

import contextlib
import json
import warnings
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from ...errors import TorchfricError, shorten
from .space import space_table

if TYPE_CHECKING:
    from .trial import SweepSpec

__all__ = ["finished", "hide_password", "open_storage", "open_study", "quiet_optuna", "sampler"]


@contextlib.contextmanager
def quiet_optuna() -> Iterator[None]:
    """Optuna's own log lines (one per trial) and experimental-feature warnings off; the
    sweep says what happened. Restored afterwards."""
    import optuna

    level = optuna.logging.get_verbosity()
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            yield
    finally:
        optuna.logging.set_verbosity(level)


def hide_password(url: str) -> str:
    """`url` with its password (if any) as ***: for messages and the summary."""
    try:
        from sqlalchemy.engine import make_url

        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # noqa: BLE001 - a URL SQLAlchemy cannot parse is shown as it is
        return url


def open_storage(url: str) -> Any:
    """Optuna's RDB storage at SQLAlchemy `url` (SQLite waits up to a minute for a lock that
    another worker holds)."""
    import optuna

    kwargs = {"connect_args": {"timeout": 60}} if url.startswith("sqlite") else {}
    try:
        return optuna.storages.RDBStorage(url, engine_kwargs=kwargs)
    except Exception as exc:  # noqa: BLE001 - SQLAlchemy's and the drivers' errors vary
        raise TorchfricError(
            f"--storage {hide_password(url)}: cannot open the study database "
            f"({shorten(str(exc))}); give an SQLAlchemy URL such as sqlite:///DIR/study.db or "
            "postgresql://USER@HOST/DB (its driver installed)"
        ) from None


def sampler(seed: int, trials: int, worker: int) -> Any:
    """A TPE sampler whose seed differs per worker and per restart (a resumed sweep must not
    draw its first points again), with the constant liar for parallel workers."""
    import numpy as np
    import optuna

    state = int(np.random.SeedSequence([seed, trials, worker]).generate_state(1)[0])
    return optuna.samplers.TPESampler(seed=state, constant_liar=True)


def open_study(spec: SweepSpec, worker: int = 0) -> Any:
    """The study named `spec.study` in `spec.storage` (created when new), checked to sweep the
    same space for the same objective."""
    import optuna

    storage = open_storage(spec.storage)
    seed = int(spec.config.get("seed", 0))
    existing = {s.study_name: s for s in optuna.get_all_study_summaries(storage)}
    count = existing[spec.study].n_trials if spec.study in existing else 0
    pruner = spec.pruner if spec.pruner is not None else optuna.pruners.MedianPruner(
        n_startup_trials=4, n_warmup_steps=1
    )  # fmt: skip
    study = optuna.create_study(
        study_name=spec.study, storage=storage, direction="maximize",
        sampler=sampler(seed, count, worker), pruner=pruner, load_if_exists=True,
    )  # fmt: skip
    mine = {"torchfric_space": json.loads(json.dumps(space_table(list(spec.params)))),
            "torchfric_objective": spec.kind}  # fmt: skip
    attrs = study.user_attrs
    if "torchfric_space" not in attrs and study.trials:
        raise TorchfricError(
            f"study {spec.study} in {hide_password(spec.storage)} holds trials that torchfric "
            "sweep did not make; give another --storage, or another config name"
        )
    for key, value in mine.items():
        if key not in attrs:
            study.set_user_attr(key, value)
        elif attrs[key] != value:
            what = "space" if key == "torchfric_space" else "objective"
            raise TorchfricError(
                f"study {spec.study} in {hide_password(spec.storage)} sweeps another {what} "
                f"({shorten(json.dumps(attrs[key]), 120)}); continue it with that, or start "
                "another study: another --storage or another config name (--set name=...)"
            )
    return study


def finished(study: Any) -> int:
    """The study's finished trials: complete, pruned or failed."""
    from optuna.trial import TrialState

    states = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)
    return len(study.get_trials(deepcopy=False, states=states))
