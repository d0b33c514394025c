"""``torchfric train CONFIG``: a run from a config, its summary (or JSON) on stdout.

The run itself is `torchfric.app.run.train`; this module turns the command's arguments into
it, names the command that resumes an interrupted run, and prints the result.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shlex
from typing import Any

from ...errors import RunInterrupted
from ...files import json_safe

__all__ = ["cmd_train", "print_result", "run_files"]


def cmd_train(args: argparse.Namespace) -> int:
    from ..config import Config
    from ..run import train_on_stderr

    cfg = Config.load(args.config, list(args.set or []))
    try:
        result = train_on_stderr(
            cfg, out=args.out, resume=args.resume, overwrite=args.overwrite,
            checkpoint=args.checkpoint, quiet=args.quiet, device=args.device,
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
    """A finished run on stdout: the human summary (`torchfric.app.run.summary_lines`), or
    with `as_json` its machine form (the metrics' headline keys and the files)."""
    from ..run import summary_lines

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
