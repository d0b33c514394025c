"""Command line: ``torchfric train | evaluate | simulate | export | generate``.

User errors (bad config, data, checkpoints, a diverging filter) print one line
``error: <message>`` and exit with status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import sys
from collections.abc import Sequence

import torch

from .errors import TorchfricError

__all__ = ["main"]


def _say_factory(quiet: bool):  # type: ignore[no-untyped-def]
    def say(msg: str) -> None:
        if quiet:
            return
        if msg.startswith("\r"):
            if sys.stderr.isatty():
                sys.stderr.write(msg)
                sys.stderr.flush()
                return
            if not msg.endswith("\n"):
                return  # in-pass progress only on a terminal
            msg = msg[1:]
        sys.stderr.write(msg if msg.endswith("\n") else msg + "\n")
        sys.stderr.flush()

    return say


def _cmd_train(args: argparse.Namespace) -> int:
    from .config import Config
    from .runner import train

    cfg = Config.load(args.config, list(args.set or []))
    if args.resume is not None:
        run_dir = args.resume
    else:
        run_dir = args.out
    result = train(
        cfg, run_dir=run_dir, resume=args.resume is not None, say=_say_factory(args.quiet)
    )
    if not args.quiet:
        print(
            json.dumps(
                {
                    "checkpoint": str(result.checkpoint),
                    "run_dir": str(result.run_dir),
                    "inertia": result.metrics["inertia"],
                    "validation": result.metrics["validation"],
                },
                indent=2,
            )
        )
    return 0


def _load_for_eval(checkpoint: str, data: str):  # type: ignore[no-untyped-def]
    from .checkpoint import load_checkpoint, read_checkpoint
    from .config import Config
    from .runner import _load_one

    model = load_checkpoint(checkpoint)
    raw = read_checkpoint(checkpoint)
    cfg = Config.from_dict(raw["config"], check_files=False) if raw.get("config") else Config()
    # The training's sample range does not apply to the file being evaluated.
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, start=0, stop=None))
    exp, _ = _load_one(cfg, data)
    return model, cfg, exp


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from .metrics import score_simulation

    model, cfg, exp = _load_for_eval(args.checkpoint, args.data)
    score = score_simulation(
        model, exp, method=cfg.simulation.method, substeps=cfg.simulation.substeps
    )
    out = {
        "data": args.data,
        "samples": exp.n,
        **score.to_dict(),
        "parameters": model.physical_parameters(),
    }
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"{'metric':<12}{'q':>14}{'qdot':>14}")
        print(f"{'FIT %':<12}{score.fit_q:>14.3f}{score.fit_qdot:>14.3f}")
        print(f"{'RMS':<12}{score.rms_q:>14.6g}{score.rms_qdot:>14.6g}")
        print()
        print(f"{'parameter':<14}{'value':>16}")
        for name, value in out["parameters"].items():
            print(f"{name:<14}{value:>16.6g}")
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    import numpy as np

    from .simulate import simulate

    model, cfg, exp = _load_for_eval(args.checkpoint, args.data)
    x0 = torch.stack([exp.q[0], exp.qdot[0] if exp.qdot is not None else exp.q.new_zeros(())])
    with torch.no_grad():
        states = simulate(
            model, exp.t, exp.u, x0, method=cfg.simulation.method, substeps=cfg.simulation.substeps
        )
    table = np.column_stack(
        [exp.t.numpy(), exp.u.numpy(), states[:, 0].numpy(), states[:, 1].numpy()]
    )
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    np.savetxt(tmp, table, delimiter=",", header="t,u,q,qdot", comments="", fmt="%.17g")
    tmp.replace(out)
    print(f"wrote {out} ({exp.n} samples)")
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from .checkpoint import load_checkpoint, read_checkpoint
    from .export import export_model, save_exported

    model = load_checkpoint(args.checkpoint)
    raw = read_checkpoint(args.checkpoint)
    dt = args.dt
    if dt is None:
        dt = float(raw.get("metrics", {}).get("dt", 1e-3))
    substeps = raw.get("config", {}).get("simulation", {}).get("substeps", "auto")
    module = export_model(model, dt=dt, substeps=substeps)
    save_exported(module, args.out)
    print(f"wrote {args.out}: torch.jit.load(path).simulate(t, u, x0) -> (q, qdot); .friction(v)")
    return 0


def _cmd_generate(args: argparse.Namespace) -> int:
    from .rig import generate

    paths = generate(args.outdir, seed=args.seed)
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchfric",
        description="Grey-box identification of machines with friction (Hensen et al.): "
        "augmented-state EKF, odd-by-construction friction models, config-to-checkpoint runs.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser(
        "train",
        help="identify a model from a TOML config",
        description="Identify a model from a TOML config.",
    )
    p.add_argument("config", help="TOML config file (see experiments/configs/)")
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a config key, e.g. --set estimator.passes=20 (repeatable)",
    )
    p.add_argument("--out", default=None, help="run directory (default: <out_dir>/<name>)")
    p.add_argument(
        "--resume",
        metavar="RUN_DIR",
        default=None,
        help="continue an interrupted run from its last completed pass",
    )
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser(
        "evaluate",
        help="open-loop simulation scores of a checkpoint on data",
        description="Open-loop simulation scores (FIT, RMS) of a checkpoint on a data file.",
    )
    p.add_argument("checkpoint")
    p.add_argument(
        "data", help="CSV/NPZ/MAT file (columns per the checkpoint's config) or rig:NAME"
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser(
        "simulate",
        help="simulate a checkpoint on a data file's input",
        description="Simulate a checkpoint open loop on a data file's input; writes CSV t,u,q,qdot.",
    )
    p.add_argument("checkpoint")
    p.add_argument("data")
    p.add_argument("--out", required=True, help="output CSV (columns t,u,q,qdot)")
    p.set_defaults(func=_cmd_simulate)

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
        help="sample time the module will simulate at (default: the training data's)",
    )
    p.set_defaults(func=_cmd_export)

    p = sub.add_parser(
        "generate",
        help="write the synthetic rig's data sets",
        description="Write the synthetic rig's experiments (CSV), truth.json and truth_states.npz.",
    )
    p.add_argument("outdir")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_generate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    torch.set_default_dtype(torch.float64)
    # The filter's tensors are tiny: a thread pool only adds overhead, and with a busy second
    # core it made small operations several times slower here. TORCHFRIC_THREADS overrides.
    torch.set_num_threads(int(os.environ.get("TORCHFRIC_THREADS", "1")))
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except TorchfricError as err:
        sys.stderr.write(f"\nerror: {err}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write(
            "\ninterrupted: completed passes are saved; continue with --resume RUN_DIR\n"
        )
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
