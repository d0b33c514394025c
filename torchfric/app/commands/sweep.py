"""``torchfric sweep CONFIG --space SPACE --trials N --out DIR``: the command over
`torchfric.app.sweep.run_sweep`; its summary goes to stdout."""

from __future__ import annotations

import argparse

__all__ = ["cmd_sweep"]


def cmd_sweep(args: argparse.Namespace) -> int:
    from ..sweep import run_sweep, summary_lines

    result = run_sweep(
        args.config, args.space, args.trials, out=args.out, jobs=args.jobs,
        storage=args.storage, backend=args.backend, sets=list(args.set or []),
    )  # fmt: skip
    print("\n".join(summary_lines(result)))
    return 0
