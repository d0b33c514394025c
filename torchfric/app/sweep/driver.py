"""`torchfric sweep`: many training runs over a search space, with Optuna as the engine.

    torchfric sweep CONFIG --space SPACE.toml --trials N --out DIR [--jobs J] [--storage URL]
                    [--backend optuna|ray] [--set KEY=VALUE ...]

Each trial is an ordinary run of CONFIG (`torchfric.app.run.runner.train`) with the trial's values
of the ``[space]`` keys (`torchfric.app.sweep.space`), in its own run directory
``DIR/trials/NNNN`` (NNNN: the trial's number in the study), so its checkpoint, metrics.json
and report.html are there to look at. The study is named after the config's ``name`` and lives
in ``--storage`` (default ``sqlite:///DIR/study.db``); the same command again continues it until
N trials have finished (complete, pruned or failed) in all. On a cluster, the same command on
several machines with one shared ``--storage`` (PostgreSQL, MySQL) works on one study; or
``--backend ray`` runs the trials through Ray Tune (`torchfric.app.sweep.ray_tune`).

The objective, maximised, is the score a run keeps its best pass by
(`torchfric.app.run.outcome.keep_best`): the validation FIT (the mean over the validation records of
(FIT q + FIT q̇)/2, in %) when the config has validation data, else the identification
log-likelihood of the kept pass (output error: its identification FIT). Every pass (epoch) of a
trial reports its own score of that kind (`PassReports`; an ensemble: its best member's
log-likelihood), and the study's pruner (median by default) stops a trial that falls behind:
the run ends after that pass as a finished run, and the trial is recorded as PRUNED. A run that
fails with a `TorchfricError` (a diverged filter, a config the trial's values make invalid) is
recorded as FAIL with its message, and the sweep goes on.

Outputs (`torchfric.app.sweep.outputs`): ``DIR/trials.csv``, ``DIR/best.toml`` (the best trial's
whole config, for ``torchfric train``), ``DIR/sweep.png`` (score against each parameter) and
``DIR/sweep.json`` (what this folder sweeps: a later run must sweep the same).
"""

from __future__ import annotations

import json
import multiprocessing
import os
import pathlib
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from ...errors import RunInterrupted, TorchfricError, shorten
from ...files import atomic_write_text
from ..config import Config
from .outputs import SweepResult
from .space import read_space, space_table
from .study import finished, hide_password, open_study, quiet_optuna
from .trial import OBJECTIVES, SweepSpec, objective_kind, run_trial, trial_dir, values_text

__all__ = ["BACKENDS", "SPEC_FILE", "run_sweep", "shares"]

BACKENDS = ("optuna", "ray")
MAX_TRIALS = 100_000
MAX_JOBS = 1024
SPEC_FILE = "sweep.json"


class _TrialFailed(Exception):
    """A trial's run failed with a `TorchfricError` (its message is the trial's ``error``)."""


class _Objective:
    """The Optuna objective: one trial = one run (`run_trial`)."""

    def __init__(self, spec: SweepSpec, say: Callable[[str], None]) -> None:
        self.spec, self.say = spec, say

    def __call__(self, trial: Any) -> float:
        import optuna

        values = {p.key: p.suggest(trial) for p in self.spec.params}
        n = trial.number
        trial.set_user_attr("run_dir", str(trial_dir(self.spec.out, n)))
        t0 = time.perf_counter()

        def report(value: float, step: int) -> bool:
            trial.report(value, step)
            return trial.should_prune()

        try:
            score, reports, _ = run_trial(self.spec, n, values, report)
        except RunInterrupted:
            raise
        except TorchfricError as err:
            trial.set_user_attr("error", shorten(str(err), 1000))
            self.say(f"  trial {n}: failed: {err}")
            raise _TrialFailed(str(err)) from None
        took = time.perf_counter() - t0
        if reports.pruned_at is not None:
            trial.set_user_attr("pruned_at", reports.pruned_at)
            self.say(
                f"  trial {n}: pruned after pass {reports.pruned_at} (reported "
                f"{reports.last:.6g}; {took:.1f} s): {values_text(values)}"
            )
            raise optuna.TrialPruned(f"pruned after pass {reports.pruned_at}")
        self.say(f"  trial {n}: {score:.6g} ({took:.1f} s): {values_text(values)}")
        return float(score)


def _optimize(spec: SweepSpec, n: int, worker: int, say: Callable[[str], None]) -> None:
    """`n` trials of the study in this process."""
    with quiet_optuna():
        study = open_study(spec, worker)
        study.optimize(_Objective(spec, say), n_trials=n, catch=(_TrialFailed,))


def _worker_main(spec: SweepSpec, n: int, worker: int) -> None:
    """A `--jobs` worker process (spawned): `n` trials, progress on stderr."""
    from ..run import progress_printer

    try:
        _optimize(spec, n, worker, progress_printer(False))
    except KeyboardInterrupt:
        sys.exit(130)
    except TorchfricError as err:
        sys.stderr.write(f"\nerror: worker {worker}: {err}\n")
        sys.exit(2)


def shares(n: int, jobs: int) -> list[int]:
    """`n` trials split over `jobs` workers as evenly as possible (no worker with none)."""
    return [n // jobs + (1 if i < n % jobs else 0) for i in range(min(jobs, n))]


def _run_local(spec: SweepSpec, n: int, jobs: int, say: Callable[[str], None]) -> None:
    """`n` trials with Optuna in `jobs` processes on this machine (this one when jobs = 1)."""
    if jobs == 1:
        _optimize(spec, n, 0, say)
        return
    ctx = multiprocessing.get_context("spawn")  # no forked torch state in the workers
    procs = [
        ctx.Process(target=_worker_main, args=(spec, k, i), name=f"torchfric-sweep-{i}")
        for i, k in enumerate(shares(n, jobs))
    ]
    for p in procs:
        p.start()
    try:
        for p in procs:
            p.join()
    except KeyboardInterrupt:
        for p in procs:
            p.join(timeout=30)
        raise
    bad = [p.exitcode for p in procs if p.exitcode]
    if bad:
        raise TorchfricError(
            f"{len(bad)} of {len(procs)} sweep workers stopped (exit status "
            f"{', '.join(map(str, bad))}; their messages are above); the study keeps every "
            "finished trial: run the same command again to continue"
        )


def _check_args(trials: int, jobs: int, backend: str) -> None:
    if isinstance(trials, bool) or not isinstance(trials, int) or not 1 <= trials <= MAX_TRIALS:
        raise TorchfricError(
            f"--trials {trials!r}: give the number of trials in all, 1 to {MAX_TRIALS}"
        )
    if isinstance(jobs, bool) or not isinstance(jobs, int) or not 1 <= jobs <= MAX_JOBS:
        raise TorchfricError(
            f"--jobs {jobs!r}: give the number of trials run at once, 1 to {MAX_JOBS} "
            f"(this machine has {os.cpu_count()} cores)"
        )
    if backend not in BACKENDS:
        raise TorchfricError(f"--backend {backend!r}: use one of {', '.join(BACKENDS)}")


def _import_engine(backend: str) -> None:
    try:
        import optuna  # noqa: F401
    except ImportError:
        raise TorchfricError(
            'torchfric sweep needs Optuna: pip install "torchfric[sweep]" (or, in a checkout, '
            'pip install -e ".[sweep]")'
        ) from None
    if backend == "ray":
        from .ray_tune import import_ray

        import_ray()


def _claim_out(out: pathlib.Path, doc: dict[str, Any]) -> bool:
    """Check that `out` is new, empty, or this same sweep's folder (True: it holds one).
    Writes nothing."""
    if out.exists() and not out.is_dir():
        raise TorchfricError(f"--out {out} is a file; give a folder for the sweep")
    if not out.is_dir() or not any(out.iterdir()):
        return False
    spec = out / SPEC_FILE
    try:
        old = json.loads(spec.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        raise TorchfricError(
            f"--out {out} holds files that are not a torchfric sweep (no readable {SPEC_FILE}); "
            "give a new or empty folder"
        ) from None
    for key, what in (("config", "config (or --set)"), ("space", "space")):
        if old.get(key) != doc[key]:
            raise TorchfricError(
                f"--out {out} holds a sweep of another {what}; continue it with the same "
                "config, --set and space, or give a new --out"
            )
    return True


def run_sweep(
    config: str | os.PathLike[str] | Config,
    space: str | os.PathLike[str],
    trials: int,
    *,
    out: str | os.PathLike[str],
    jobs: int = 1,
    storage: str | None = None,
    backend: str = "optuna",
    sets: Sequence[str] = (),
    say: Callable[[str], None] | None = None,
    pruner: Any = None,
) -> SweepResult:
    """Run the sweep until the study has `trials` finished trials; write its outputs.

    Everything (arguments, config, space, ``--out``, the storage and its study) is checked
    before anything is written. `say` prints progress (default: stderr); `pruner` replaces
    the default `optuna.pruners.MedianPruner` (4 trials before any pruning, none at pass 1).
    """
    from ..run import progress_printer
    from .outputs import write_outputs

    say = say or progress_printer(False)
    _check_args(trials, jobs, backend)
    if isinstance(config, Config):
        cfg = config.with_overrides(list(sets)) if sets else config
    else:
        cfg = Config.load(config, list(sets))
    params = tuple(read_space(space, cfg))
    _import_engine(backend)
    out = pathlib.Path(out).absolute()
    kind = objective_kind(cfg)
    doc = json.loads(json.dumps({
        "torchfric_sweep": 1, "study": cfg.name, "objective": kind,
        "space": space_table(list(params)), "config": cfg.to_dict(),
    }))  # fmt: skip
    resuming = _claim_out(out, doc)
    url = storage or f"sqlite:///{out / 'study.db'}"
    spec = SweepSpec(doc["config"], params, str(out), url, cfg.name, kind, pruner)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        with quiet_optuna():
            study = open_study(spec)
    except BaseException:
        if created and not any(out.iterdir()):
            out.rmdir()
        raise
    if not resuming:
        atomic_write_text(out / SPEC_FILE, json.dumps(doc, indent=2) + "\n")
    done = finished(study)
    todo = max(0, trials - done)
    say(
        f"torchfric sweep: study {cfg.name} ({hide_password(url)}): {done} finished trial(s), "
        f"{todo} to run" + (f" with {jobs} jobs" if todo and jobs > 1 else "")
        + f" ({backend}); objective: {OBJECTIVES[kind].split(':')[0]}"
    )  # fmt: skip
    t0 = time.perf_counter()
    if todo and backend == "ray":
        from .ray_tune import run_ray

        run_ray(spec, todo, jobs, say)
    elif todo:
        _run_local(spec, todo, jobs, say)
    seconds = time.perf_counter() - t0
    with quiet_optuna():
        study = open_study(spec)
    rows, best, files = write_outputs(study, spec)
    added = finished(study) - done
    return SweepResult(out, cfg.name, url, kind, params, rows, best, added, seconds, files)
