"""Command line: ``torchfric init | check | train | evaluate | simulate | export | track | sweep | generate``.

User errors (bad config, data, checkpoints, a diverging filter) print one line
``error: <message>`` and exit with status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shlex
import sys
import warnings
from collections.abc import Sequence
from typing import Any

# Nothing here imports torch at module level: `--help`, `--version` and argument errors answer
# without it (a third of a second instead of two); each command imports what it needs.
from ..errors import RunInterrupted, TorchfricError
from ..files import json_safe
from ..version import __version__
from .api import torch_settings, train_on_stderr
from .track import add_track_parser
from .use import cmd_evaluate, cmd_export, cmd_simulate

__all__ = ["main"]


def _cmd_train(args: argparse.Namespace) -> int:
    from .config import Config

    cfg = Config.load(args.config, list(args.set or []))
    try:
        result = train_on_stderr(
            cfg, out=args.out, resume=args.resume, overwrite=args.overwrite,
            checkpoint=args.checkpoint, quiet=args.quiet,
        )  # fmt: skip
    except RunInterrupted as stop:
        if stop.run_dir is not None:
            sets = "".join(f" --set {shlex.quote(s)}" for s in args.set or [])
            stop.args = (
                f"{stop}; continue with: torchfric train {shlex.quote(args.config)}{sets} "
                f"--resume {shlex.quote(str(stop.run_dir))}",
            )
        raise
    print_result(result, as_json=args.json, copied=args.checkpoint)
    return 0


def run_files(result: Any, copied: str | None = None) -> dict[str, str]:
    """The files a finished run wrote, by label (the summary's last lines, ``files`` in JSON)."""
    run = pathlib.Path(result.run_dir)
    files = {"checkpoint": str(result.checkpoint)}
    if copied:
        files["copied to"] = str(copied)
    for label, name in (("metrics", "metrics.json"), ("report", "report.html")):
        if (run / name).exists():
            files[label] = str(run / name)
    files["tensorboard"] = f"tensorboard --logdir {shlex.quote(str(run))}"
    files["run"] = str(run)
    return files


def print_result(result: Any, *, as_json: bool = False, copied: str | None = None) -> None:
    """A finished run on stdout: the human summary (`torchfric.app.outcome.summary_lines`), or
    with `as_json` its machine form (the metrics' headline keys and the files)."""
    from .outcome import summary_lines

    m = result.metrics
    files = run_files(result, copied)
    if as_json:
        keys = ("name", "estimator", "inertia", "parameters", "best_pass", "converged",
                "stopped", "validation", "test", "identification", "warnings", "seconds")  # fmt: skip
        out = {
            "checkpoint": str(result.checkpoint),
            "run_dir": str(result.run_dir),
            **{k: m[k] for k in keys if k in m},
            "files": files,
        }
        print(json.dumps(json_safe(out)[0], indent=2, allow_nan=False))
        return
    print("\n".join(summary_lines(m, files)))


def _cmd_generate(args: argparse.Namespace) -> int:
    from ..accel.native.lugre import lugre_integrator
    from ..data.rig import generate

    paths = generate(args.outdir, seed=args.seed, force=args.force, integrate=lugre_integrator())
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0


def _cmd_init(args: argparse.Namespace) -> int:
    from .starter import write_starter

    lines = write_starter(
        args.data,
        c_m=args.c_m,
        out=args.out,
        force=args.force,
        split=args.split,
        columns=args.column or (),
        time_step=args.time_step,
    )
    print("\n".join(lines))
    return 0


def _cmd_check(args: argparse.Namespace) -> int:
    from .check import check_run
    from .config import Config

    cfg = Config.load(args.config, list(args.set or []))
    print(check_run(cfg))
    sets = "".join(f" --set {shlex.quote(s)}" for s in args.set or [])
    train = f"torchfric train {shlex.quote(args.config)}{sets}"
    print(f"ok          nothing written; train with: {train}")
    return 0


def _add_train(sub: argparse._SubParsersAction) -> None:
    """``torchfric train CONFIG``: identify a model from a TOML config."""
    p = sub.add_parser(
        "train",
        help="identify a model from a TOML config",
        description="Identify a model from a TOML config. Progress goes to stderr (bars on a "
        "terminal); the summary (parameters ± σ, the kept pass, validation FIT, convergence, "
        "warnings, the files written) to stdout.",
    )
    _add_config_and_sets(p)
    p.add_argument(
        "--out",
        default=None,
        help="run directory (default: <out_dir>/<name>, or <name>-2, ... when that exists); "
        "must be new or empty, or an earlier run with --overwrite",
    )
    p.add_argument(
        "--resume",
        metavar="RUN_DIR",
        default=None,
        help="continue an interrupted run from its last completed pass",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the earlier run in --out (only once the new run has finished)",
    )
    p.add_argument(
        "--checkpoint",
        metavar="PATH",
        default=None,
        help="also copy the final checkpoint to PATH (replaces only a torchfric checkpoint); "
        "the one explicit way to update checkpoints/",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="print the result as JSON (parameters with σ, kept pass, convergence, FITs, "
        "warnings, files) instead of the summary",
    )
    p.add_argument(
        "--quiet", action="store_true", help="no progress on stderr (the result still prints)"
    )
    p.set_defaults(func=_cmd_train)


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    """``torchfric evaluate CHECKPOINT DATA``: open-loop scores on a data file."""
    p = sub.add_parser(
        "evaluate",
        help="open-loop simulation scores of a checkpoint on data",
        description="Open-loop simulation scores (FIT, RMS) of a checkpoint on a data file, "
        "simulated as the run scored its validation records. RMS is in SI units: rad and rad/s "
        "(rotary), m and m/s (linear), after data.position_unit's conversion.",
    )
    p.add_argument("checkpoint")
    p.add_argument(
        "data", help="CSV/NPZ/MAT file (columns per the checkpoint's config) or rig:NAME"
    )
    _add_record_options(p)
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=cmd_evaluate)


def _add_simulate(sub: argparse._SubParsersAction) -> None:
    """``torchfric simulate CHECKPOINT DATA --out CSV``."""
    p = sub.add_parser(
        "simulate",
        help="simulate a checkpoint on a data file's input",
        description="Simulate a checkpoint open loop on a data file's input; writes CSV "
        "t,u,q,qdot with t in s, u as in the file, q and qdot in SI units (rad, rad/s or m, "
        "m/s).",
    )
    p.add_argument("checkpoint")
    p.add_argument(
        "data", help="CSV/NPZ/MAT file (columns per the checkpoint's config) or rig:NAME"
    )
    _add_record_options(p)
    p.add_argument(
        "--out", required=True, help="output CSV (columns t,u,q,qdot; q in rad or m, SI)"
    )
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.set_defaults(func=cmd_simulate)


def _add_record_options(p: argparse.ArgumentParser) -> None:
    """``--column`` and ``--position-unit``, which ``evaluate`` and ``simulate`` share."""
    p.add_argument(
        "--column",
        action="append",
        metavar="OURS=NAME",
        help="read our column t, u, q or qdot from the file's column NAME (repeatable); replaces "
        "the checkpoint's data.columns for this file",
    )
    p.add_argument(
        "--position-unit",
        # torchfric.app.schema.POSITION_UNITS (a test keeps them equal): importing it here would
        # import torch for every --help
        choices=("rad", "deg", "m", "mm"),
        default=None,
        help="unit of q in this file (default: the checkpoint's data.position_unit)",
    )


def _add_export(sub: argparse._SubParsersAction) -> None:
    """``torchfric export CHECKPOINT --out FILE``: a TorchScript module."""
    p = sub.add_parser(
        "export",
        help="export a checkpoint as TorchScript",
        description="Export a checkpoint as a TorchScript module (loads with torch.jit.load, no torchfric needed).",
    )
    p.add_argument("checkpoint")
    p.add_argument("--out", required=True, help="output file, e.g. arm_tanh.ts")
    p.add_argument(
        "--dt",
        type=float,
        default=None,
        help="nominal sample time stored with the module (metadata: it simulates at the sample time of the t it is given; default: the training data's)",
    )
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.set_defaults(func=cmd_export)


def _add_generate(sub: argparse._SubParsersAction) -> None:
    """``torchfric generate OUTDIR``: the synthetic rig's data sets."""
    p = sub.add_parser(
        "generate",
        help="write the synthetic rig's data sets",
        description="Write the synthetic rig's experiments (CSV), truth.json and truth_states.npz.",
    )
    p.add_argument("outdir")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--force", action="store_true", help="replace the rig's files in OUTDIR")
    p.set_defaults(func=_cmd_generate)


def _add_init(sub: argparse._SubParsersAction) -> None:
    """``torchfric init DATA --c-m VALUE``: a starter config for the user's file."""
    p = sub.add_parser(
        "init",
        help="write a commented starter config for your data file",
        description="Write a commented starter config for a data file: columns from its "
        "header, sample time and units checked, a validation record proposed. The config "
        "passes `torchfric check` before it is written; nothing is replaced.",
    )
    p.add_argument("data", help="your record: a CSV with a header line (t, u, q, ...)")
    p.add_argument(
        "--c-m",
        metavar="VALUE",
        default=None,
        help="motor constant: torque or force per unit of u (required; not estimated)",
    )
    p.add_argument("--out", default=None, help="config file (default: <data stem>.toml here)")
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.add_argument(
        "--column",
        action="append",
        metavar="OURS=NAME",
        help="map one of t, u, q, qdot to the file's column NAME when the header does not tell "
        "(repeatable)",
    )
    p.add_argument(
        "--time-step",
        type=float,
        metavar="SECONDS",
        default=None,
        help="sample time of a file without a t column",
    )
    p.add_argument(
        "--split",
        metavar="FRACTION",
        default=None,
        help="write the first FRACTION of the file and the rest as two new CSV files beside "
        "the config, for identification and validation (e.g. 0.7)",
    )
    p.set_defaults(func=_cmd_init)


def _add_check(sub: argparse._SubParsersAction) -> None:
    """``torchfric check CONFIG``: validate config and data; say what would run."""
    p = sub.add_parser(
        "check",
        help="validate a config and its data, and show what train would run",
        description="Check a config and its data as train does before it starts (data, "
        "memory, the pre-fit) and show what would run. Writes nothing.",
    )
    _add_config_and_sets(p)
    p.set_defaults(func=_cmd_check)


def _cmd_sweep(args: argparse.Namespace) -> int:
    from .sweep import run_sweep
    from .sweep_out import summary_lines

    result = run_sweep(
        args.config, args.space, args.trials, out=args.out, jobs=args.jobs,
        storage=args.storage, backend=args.backend, sets=list(args.set or []),
    )  # fmt: skip
    print("\n".join(summary_lines(result)))
    return 0


def _add_sweep(sub: argparse._SubParsersAction) -> None:
    """``torchfric sweep CONFIG --space SPACE --trials N --out DIR``: many runs, the best kept."""
    p = sub.add_parser(
        "sweep",
        help="train over a search space (Optuna) and keep the best config",
        description="Train CONFIG once per trial with values drawn from SPACE.toml's [space] "
        "table (Optuna), each run in DIR/trials/NNNN; prune trials that fall behind; write "
        "DIR/trials.csv, DIR/best.toml and DIR/sweep.png. The same command again continues the "
        "study until N trials have finished. Progress goes to stderr, the summary to stdout.",
    )
    _add_config_and_sets(p)
    p.add_argument(
        "--space", required=True, metavar="SPACE.toml",
        help='search space: a [space] table of config keys, e.g. "model.size" = '
        "{ choices = [2, 3, 4] } (see docs/cli.md)",
    )  # fmt: skip
    p.add_argument(
        "--trials", required=True, type=int, metavar="N",
        help="trials in the study in all (finished: complete, pruned or failed)",
    )  # fmt: skip
    p.add_argument("--out", required=True, metavar="DIR", help="the sweep's folder")
    p.add_argument(
        "--jobs", type=int, default=1, metavar="J",
        help="trials at once: worker processes on this machine (Ray: CPUs; default 1)",
    )  # fmt: skip
    p.add_argument(
        "--storage", default=None, metavar="URL",
        help="the study's database (default sqlite:///DIR/study.db); a shared PostgreSQL or "
        "MySQL URL lets several machines work on one study",
    )  # fmt: skip
    p.add_argument(
        "--backend", choices=("optuna", "ray"), default="optuna",
        help="optuna: trials in local processes (default); ray: through Ray Tune, on a local "
        "Ray or the cluster of RAY_ADDRESS",
    )  # fmt: skip
    p.set_defaults(func=_cmd_sweep)


def _add_config_and_sets(p: argparse.ArgumentParser) -> None:
    """The CONFIG argument and ``--set`` overrides that ``train`` and ``check`` share."""
    p.add_argument("config", help="TOML config file (see experiments/configs/)")
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a config key, e.g. --set estimator.passes=20 (repeatable)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The ``torchfric`` argument parser with its subcommands."""
    parser = argparse.ArgumentParser(
        prog="torchfric",
        description="Grey-box identification of machines with friction (Hensen et al.): "
        "augmented-state EKF, odd-by-construction friction models, config-to-checkpoint runs.",
    )
    parser.add_argument("--version", action="version", version=f"torchfric {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (
        _add_init,
        _add_check,
        _add_train,
        _add_evaluate,
        _add_simulate,
        _add_export,
        add_track_parser,
        _add_sweep,
        _add_generate,
    ):
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        # float64, and one thread by default: the filter's tensors are tiny, a thread pool only
        # adds overhead, and with a busy second core it made small operations several times
        # slower here. TORCHFRIC_THREADS overrides.
        with torch_settings(), warnings.catch_warnings():
            warnings.simplefilter("default")
            warnings.showwarning = _show_warning
            return int(args.func(args) or 0)
    except RunInterrupted as stop:
        sys.stderr.write(f"\n{stop}\n")
        return 130
    except TorchfricError as err:
        sys.stderr.write(f"\nerror: {err}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write("\ninterrupted; nothing was left half-written\n")
        return 130
    except BrokenPipeError:  # `torchfric evaluate ... | head`: the reader has what it wanted
        # Point stdout at /dev/null so that Python's final flush does not raise again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141


def _show_warning(message, category, filename, lineno, file=None, line=None):  # type: ignore[no-untyped-def]
    """Library warnings (a slow fallback, a refused cache) as one line, without source lines."""
    sys.stderr.write(f"warning: {message}\n")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
