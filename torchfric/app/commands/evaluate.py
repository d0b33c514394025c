"""``torchfric evaluate | simulate | export``: using a checkpoint on a record.

`load_for_eval` reads the record as the run read its records (the checkpoint's data config,
with ``--column`` and ``--position-unit`` in place of its columns and unit); `evaluate` scores
it as the run scored its validation records (the same engine, so the same FIT as
``metrics.json``). Nothing here imports torch at module level: the CLI imports this module for
``--help``.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import pathlib
import sys
from collections.abc import Sequence

from ...errors import MissingColumn, TorchfricError
from ...files import atomic_write_text, json_safe

__all__ = ["cmd_evaluate", "cmd_simulate", "load_for_eval", "refuse_overwrite"]


def refuse_overwrite(out: pathlib.Path, inputs: Sequence[str], force: bool) -> None:
    """An output path never names an input; an existing file is replaced only with --force."""
    target = out.resolve()
    for p in inputs:
        if not p.startswith("rig:") and pathlib.Path(p).resolve() == target:
            raise TorchfricError(f"--out {out} is an input of this command; give another file name")
    if out.is_dir():
        raise TorchfricError(f"--out {out} is a directory; give a file name")
    if out.exists() and not force:
        raise TorchfricError(f"--out {out} exists; give a new file name, or --force to replace it")


def load_for_eval(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    """(model, config, experiment, unit, the checkpoint as read) for ``evaluate`` and ``simulate``: the record
    ``args.data`` read as the run read its records — the checkpoint's data config with
    ``--column`` and ``--position-unit`` in place of its columns and unit, the input delay
    applied — and the SI unit of its q. The training's sample range does not apply. A warning
    on stderr when the model's axis (linear or rotary) is not the record's."""
    from ..artifacts import checkpoint_config, checkpoint_model, read_checkpoint
    from ..config import RIG_PREFIX
    from ..run import load_record
    from .columns import parse_columns

    columns = parse_columns(args.column) if args.column else None
    rig = args.data.startswith(RIG_PREFIX)
    if rig and (columns is not None or args.position_unit):
        flag = "--column" if columns is not None else "--position-unit"
        raise TorchfricError(
            f"{flag} is for a data file; {args.data} is the built-in rig's record (q in rad), "
            f"read as it is: leave {flag} out"
        )
    raw = read_checkpoint(args.checkpoint)
    model, cfg = checkpoint_model(raw, args.checkpoint), checkpoint_config(raw)
    trained_in, trained_axis = cfg.data.position_unit, cfg.data.axis_unit
    data = dataclasses.replace(
        cfg.data,
        start=0,
        stop=None,
        columns=cfg.data.columns if columns is None else columns,
        position_unit=args.position_unit or trained_in,
    )
    cfg = dataclasses.replace(cfg, data=data)
    unit = "rad" if rig else data.axis_unit
    if unit != trained_axis:
        axis = {"m": "a linear axis", "rad": "a rotary axis"}
        read = "the rig's arm" if rig else f"--position-unit {data.position_unit}"
        sys.stderr.write(
            f"warning: the model was identified on {axis[trained_axis]} (data.position_unit"
            f" = {trained_in!r}, q in {trained_axis}) but {args.data} is {axis[unit]} "
            f"({read}, q in {unit}); the scores compare unlike quantities\n"
        )
    try:
        exp, _ = load_record(cfg, args.data)
    except MissingColumn as err:  # it speaks of data.columns: here the fix is --column
        raise TorchfricError(
            f"{err}; here: --column {err.role}=NAME (repeatable; it replaces the checkpoint's "
            "data.columns, so map every column the file names differently)"
        ) from None
    return model, cfg, exp, unit, raw


def cmd_evaluate(args: argparse.Namespace) -> int:
    from ..run import evaluate_model, parameter_lines, parameter_table

    model, cfg, exp, unit, raw = load_for_eval(args)
    # Scored as the run scored its validation records (the same engine and solver), so a run's
    # own validation record gives the FIT in its metrics.json.
    (score,) = evaluate_model(model, [exp], cfg).values()
    state = raw.get("estimator", {}).get("state", {})
    out = {
        "data": args.data,
        "samples": exp.n,
        **score.to_dict(),
        "unit": {"q": unit, "qdot": f"{unit}/s"},  # of rms_q and rms_qdot (SI)
        # ± σ from the checkpoint's P_θθ: the run's covariance (docs/estimators.md, Uncertainty)
        "parameters": parameter_table(model, state.get("P_theta")),
        "sigma": ((raw.get("metrics") or {}).get("covariance") or {}).get("method") or "filter",
    }
    if args.json:
        print(json.dumps(json_safe(out)[0], indent=2, allow_nan=False))
    else:
        print(f"{'metric':<18}{'q':>14}{'qdot':>14}")
        print(f"{'FIT %':<18}{score.fit_q:>14.3f}{score.fit_qdot:>14.3f}")
        print(f"{f'RMS [{unit}, {unit}/s]':<18}{score.rms_q:>14.6g}{score.rms_qdot:>14.6g}")
        print()
        print("parameters (value ± σ):")
        print("\n".join(parameter_lines(out["parameters"], limit=len(out["parameters"]))))
        print(_sigma_line(out["sigma"]))
    return 0


def _sigma_line(method: str) -> str:
    """Where evaluate's σ come from, by the checkpoint's metrics ``covariance.method``."""
    from ...estimators.uncertainty import SIGMA_SOURCES

    method = method if method in SIGMA_SOURCES else "filter"
    line = f"σ: {SIGMA_SOURCES[method]}"
    if method == "filter":
        line += ": this checkpoint holds no covariance of its run (written before torchfric "
        line += "computed one, or the run could not); train it again for σ that cover the truth"
    return line


def cmd_simulate(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    from ...models.simulate import simulate
    from ..run import scoring_engine

    out = pathlib.Path(args.out)
    refuse_overwrite(out, [args.checkpoint, args.data], args.force)
    model, cfg, exp, unit, _ = load_for_eval(args)
    x0 = torch.stack([exp.q[0], exp.qdot[0] if exp.qdot is not None else exp.q.new_zeros(())])
    with torch.no_grad():
        states = simulate(
            model,
            exp.t,
            exp.u,
            x0,
            method=cfg.simulation.method,
            substeps=cfg.simulation.substeps,
            engine=scoring_engine(cfg),  # the engine the run scores with
        )
    table = np.column_stack(
        [exp.t.numpy(), exp.u.numpy(), states[:, 0].numpy(), states[:, 1].numpy()]
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    text = io.StringIO()
    np.savetxt(text, table, delimiter=",", header="t,u,q,qdot", comments="", fmt="%.17g")
    atomic_write_text(out, text.getvalue())
    print(f"wrote {out} ({exp.n} samples; q in {unit}, qdot in {unit}/s)")
    return 0
