"""Command line: ``torchfric init | check | train | evaluate | simulate | export | track | sweep | generate``.

User errors (bad config, data, checkpoints, a diverging filter) print one line
``error: <message>`` and exit with status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import atexit
import os
import sys
import warnings
from collections.abc import Callable, Sequence
from typing import NoReturn

# Nothing here imports torch at module level: `--help`, `--version` and argument errors answer
# without it (a third of a second instead of two); each command imports what it needs.
from ..errors import RunInterrupted, TorchfricError
from ..version import __version__

# torchfric.data.units.POSITION_UNITS (a test keeps them equal): importing it here would import
# torch for every --help
POSITION_UNIT_CHOICES = ("rad", "deg", "rev", "m", "mm", "um", "counts")

__all__ = ["COMMANDS", "build_parser", "main"]


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
    p.add_argument(
        "--device",
        default=None,
        metavar="DEVICE",
        help='cuda (or cuda:N): filter ensembles and model.size = "auto" on that GPU, one '
        "member per GPU thread, for big batches; default: the CPU",
    )


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
        choices=POSITION_UNIT_CHOICES,
        default=None,
        help="unit of q in this file (default: the checkpoint's data.position_unit)",
    )


def _add_export(sub: argparse._SubParsersAction) -> None:
    """``torchfric export CHECKPOINT --out FILE [--format torchscript|fmu|c]``."""
    p = sub.add_parser(
        "export",
        help="export a checkpoint as TorchScript, an FMI 2.0 FMU or C99 sources",
        description=(
            "Export a checkpoint: a TorchScript module (loads with torch.jit.load, no torchfric "
            "needed), an FMI 2.0 FMU (Model Exchange and Co-Simulation, self-contained C with "
            "its binary for this platform), or C99 sources NAME.c and NAME.h (friction "
            "feed-forward and the model's step)."
        ),
    )
    p.add_argument("checkpoint")
    p.add_argument(
        "--out",
        required=True,
        help="output file: arm.ts (torchscript), arm.fmu (fmu), arm.c (c; arm.h beside it)",
    )
    p.add_argument(
        "--format",
        choices=("torchscript", "fmu", "c"),
        default=None,
        help="torchscript, fmu or c (default: from --out: .fmu an FMU, .c C sources, else TorchScript)",
    )
    p.add_argument(
        "--dt",
        type=float,
        default=None,
        help="nominal sample time stored with the module (metadata: it simulates at the sample time of the t it is given; default: the training data's)",
    )
    p.add_argument("--force", action="store_true", help="replace --out if it exists")


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
    p.add_argument(
        "--counts-per-rev",
        metavar="N",
        default=None,
        help="q is in encoder counts, N per revolution (a rotary axis; q becomes rad)",
    )
    p.add_argument(
        "--counts-per-m",
        metavar="N",
        default=None,
        help="q is in encoder counts, N per metre (a linear axis; q becomes m)",
    )
    p.add_argument(
        "--position-unit",
        choices=POSITION_UNIT_CHOICES,
        default=None,
        help="unit of q where its column name states none (or one torchfric does not read)",
    )


def _add_check(sub: argparse._SubParsersAction) -> None:
    """``torchfric check CONFIG``: validate config and data; say what would run."""
    p = sub.add_parser(
        "check",
        help="validate a config and its data, and show what train would run",
        description="Check a config and its data as train does before it starts (data, "
        "memory, the pre-fit) and show what would run. Writes nothing.",
    )
    _add_config_and_sets(p)


def _add_track(sub: argparse._SubParsersAction) -> None:
    """``torchfric track CHECKPOINT DATA --out DIR``: the recursive EKF over a record."""
    p = sub.add_parser("track", help="follow a machine on-line from a checkpoint (recursive EKF)")
    p.add_argument("checkpoint", help="a checkpoint (torchfric train's NAME.pt)")
    p.add_argument("data", help="a record (file, or rig:NAME), read as the run read its records")
    p.add_argument("--out", required=True, help="a new (or empty) directory for the outputs")
    p.add_argument("--every", type=int, default=100, help="samples per row of track.csv (100)")
    p.add_argument("--follow", action="store_true", help="keep reading a file that grows")
    p.add_argument("--idle", type=float, default=30.0,
                   help="with --follow: stop after this many seconds without new rows (30)")  # fmt: skip
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a config key of the checkpoint's run, e.g. track.q_theta=1e-5")  # fmt: skip
    p.add_argument("--column", action="append", metavar="ROLE=NAME",
                   help="the file's column for t, u, q or qdot (as evaluate's --column)")  # fmt: skip
    p.add_argument("--position-unit", help="the file's unit of q (as evaluate's)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")


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
    for add, _ in COMMANDS.values():
        add(sub)
    return parser


COMMANDS: dict[str, tuple[Callable[[argparse._SubParsersAction], None], str]] = {
    "init": (_add_init, "cmd_init"),
    "check": (_add_check, "cmd_check"),
    "train": (_add_train, "cmd_train"),
    "evaluate": (_add_evaluate, "cmd_evaluate"),
    "simulate": (_add_simulate, "cmd_simulate"),
    "export": (_add_export, "cmd_export"),
    "track": (_add_track, "cmd_track"),
    "sweep": (_add_sweep, "cmd_sweep"),
    "generate": (_add_generate, "cmd_generate"),
}
"""Each command (in ``--help``'s order) → the function that adds its arguments to the parser
and the name of its handler in `torchfric.app.commands` (the parsed arguments → the exit
status), imported only when that command runs."""


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        from . import commands
        from .run import torch_settings

        handler = getattr(commands, COMMANDS[args.command][1])
        # float64, and one thread by default: the filter's tensors are tiny, a thread pool only
        # adds overhead, and with a busy second core it made small operations several times
        # slower here. TORCHFRIC_THREADS overrides.
        with torch_settings(), warnings.catch_warnings():
            warnings.simplefilter("default")
            warnings.showwarning = _show_warning
            return int(handler(args) or 0)
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


def run() -> NoReturn:
    """The ``torchfric`` program: `main` on the command line's arguments, then the exit without
    the interpreter's teardown. Once a command has returned, every file it wrote is closed;
    what is left is tearing down torch and every module one by one (0.5–1 s of a 5-s quick
    start, measured). Its output is flushed and every exit handler runs (`atexit`: the private
    build folder's removal, the painter's end, logging's flush) before `os._exit` with
    `main`'s status. An error escaping `main` takes Python's usual way out."""
    code = main()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (BrokenPipeError, ValueError, OSError):  # the reader left, or a closed stream
            pass
    atexit._run_exitfuncs()
    os._exit(code)


def _show_warning(message, category, filename, lineno, file=None, line=None):  # type: ignore[no-untyped-def]
    """Library warnings (a slow fallback, a refused cache) as one line, without source lines."""
    sys.stderr.write(f"warning: {message}\n")


if __name__ == "__main__":  # pragma: no cover
    run()
