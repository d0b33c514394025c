"""``torchfric export CHECKPOINT --out FILE``: the identified model as a TorchScript module
(`torchfric.models.export_model`), which loads with ``torch.jit.load`` and no torchfric."""

from __future__ import annotations

import argparse
import pathlib

from .evaluate import refuse_overwrite

__all__ = ["cmd_export"]


def cmd_export(args: argparse.Namespace) -> int:
    from ...models import export_model, save_exported
    from ..artifacts import checkpoint_config, checkpoint_model, read_checkpoint

    refuse_overwrite(pathlib.Path(args.out), [args.checkpoint], args.force)
    raw = read_checkpoint(args.checkpoint)
    model = checkpoint_model(raw, args.checkpoint)
    dt = args.dt
    if dt is None:
        dt = float(raw.get("metrics", {}).get("dt", 1e-3))
    cfg = checkpoint_config(raw)
    module = export_model(
        model, dt=dt, substeps=cfg.simulation.substeps, method=cfg.simulation.method
    )
    save_exported(module, args.out)
    print(
        f"wrote {args.out}: torch.jit.load(path).simulate(t, u, x0) -> (q, qdot) at any sample "
        "time; .friction(v), .field(x, u)"
    )
    return 0
