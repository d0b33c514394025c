"""``torchfric sweep --backend ray``: the trials on Ray, through Ray Tune with Optuna searching.

Ray Tune schedules the trials (one CPU each) and `ray.tune.search.optuna.OptunaSearch` draws
their values from the same Optuna study (storage and name) as the local backend, so a sweep
can be started with one backend and continued with the other, and the outputs are the same.
Without ``RAY_ADDRESS`` (Ray's own variable) a local Ray is started with ``--jobs`` CPUs and
stopped afterwards; with it, the trials go to that cluster, ``--jobs`` of them at once (every
node needs torchfric installed and the data and ``--out`` at the same paths).

Ray's trials are not pruned: a run reports its score once, at its end (Ray stops trials early
through its own schedulers, which a sweep does not configure). A trial whose run fails with a
`TorchfricError` is recorded as FAIL with its message, as locally.
"""

from __future__ import annotations

import contextlib
import math
import os
import pathlib
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ...errors import RunInterrupted, TorchfricError, shorten
from .study import open_storage, sampler

if TYPE_CHECKING:
    from .trial import SweepSpec

__all__ = ["import_ray", "run_ray"]

# The config keys that carry a Ray trial's Optuna trial number and id to the trial.
_NUMBER, _ID = "torchfric_trial_number", "torchfric_trial_id"


def import_ray() -> None:
    """Raise a `TorchfricError` naming the install when Ray Tune cannot be imported."""
    try:
        import ray  # noqa: F401
        from ray.tune.search.optuna import OptunaSearch  # noqa: F401
    except ImportError as exc:
        raise TorchfricError(
            f"--backend ray needs Ray Tune ({shorten(str(exc), 120)}): pip install "
            '"torchfric[ray]" (in a checkout: pip install -e ".[ray]"), or use --backend optuna'
        ) from None


def _numbered_search(**kwargs: Any) -> Any:
    """An `OptunaSearch` that also hands each trial its Optuna trial number and id (the trial's
    folder is named by the number, and its error or folder are recorded by the id)."""
    from ray.tune.search.optuna import OptunaSearch

    class NumberedSearch(OptunaSearch):
        def suggest(self, trial_id: str) -> dict[str, Any] | None:
            params = super().suggest(trial_id)
            ot = self._ot_trials.get(trial_id)
            if isinstance(params, dict) and ot is not None:
                params = {**params, _NUMBER: ot.number, _ID: ot._trial_id}
            return params

    return NumberedSearch(**kwargs)


def _ray_trial(config: dict[str, Any], spec: SweepSpec) -> dict[str, float]:
    """One Ray trial: the run of `spec`'s config with the trial's values; its score, or NaN
    (Optuna records the trial as FAIL) with the run's error in the study."""
    from .trial import run_trial, trial_dir

    number, trial_id = int(config[_NUMBER]), int(config[_ID])
    values = {p.key: p.value(config[p.key]) for p in spec.params}
    storage = open_storage(spec.storage)
    storage.set_trial_user_attr(trial_id, "run_dir", str(trial_dir(spec.out, number)))
    try:
        score, _, _ = run_trial(spec, number, values, lambda value, step: False)
    except RunInterrupted:
        raise
    except TorchfricError as err:
        storage.set_trial_user_attr(trial_id, "error", shorten(str(err), 1000))
        return {"score": math.nan}
    return {"score": float(score)}


def run_ray(spec: SweepSpec, n: int, jobs: int, say: Callable[[str], None]) -> None:
    """`n` trials of `spec`'s study on Ray (local with `jobs` CPUs, or ``RAY_ADDRESS``'s)."""
    import ray
    from ray import tune

    started = not ray.is_initialized()
    if started and os.environ.get("RAY_ADDRESS"):
        say(f"  ray: connecting to {os.environ['RAY_ADDRESS']} (RAY_ADDRESS)")
        ray.init(log_to_driver=False)
    elif started:
        say(f"  ray: starting a local Ray with {jobs} CPU(s)")
        ray.init(num_cpus=jobs, include_dashboard=False, log_to_driver=False)
    try:
        import optuna

        storage = open_storage(spec.storage)
        count = len(optuna.load_study(study_name=spec.study, storage=storage).trials)
        search = _numbered_search(
            space={p.key: p.distribution() for p in spec.params}, metric="score", mode="max",
            study_name=spec.study, storage=storage,
            sampler=sampler(int(spec.config.get("seed", 0)), count, 0),
        )  # fmt: skip
        trainable = tune.with_resources(tune.with_parameters(_ray_trial, spec=spec), {"cpu": 1})
        tuner = tune.Tuner(
            trainable,
            tune_config=tune.TuneConfig(
                search_alg=search, num_samples=n, max_concurrent_trials=jobs
            ),
            run_config=tune.RunConfig(
                name="tune", storage_path=str(pathlib.Path(spec.out) / "ray"), verbose=0
            ),
        )
        with contextlib.redirect_stdout(sys.stderr):  # Ray's tables: progress, not the result
            tuner.fit()
    finally:
        if started:
            ray.shutdown()
