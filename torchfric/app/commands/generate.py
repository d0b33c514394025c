"""``torchfric generate OUTDIR``: write the synthetic rig's data sets (CSV, truth.json,
truth_states.npz), simulated with the compiled LuGre integrator where a C compiler is there."""

from __future__ import annotations

import argparse

__all__ = ["cmd_generate"]


def cmd_generate(args: argparse.Namespace) -> int:
    from ...accel.native.lugre import lugre_integrator
    from ...data.rig import generate

    paths = generate(args.outdir, seed=args.seed, force=args.force, integrate=lugre_integrator())
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0
