"""``torchfric export CHECKPOINT --out FILE [--format torchscript|fmu|c]``: the identified model
as a TorchScript module (`torchfric.models.export_model`, loads with ``torch.jit.load`` and no
torchfric), an FMI 2.0 FMU or C99 sources (`torchfric.export`)."""

from __future__ import annotations

import argparse
import pathlib

from ...errors import TorchfricError
from .evaluate import refuse_overwrite

__all__ = ["cmd_export"]


def cmd_export(args: argparse.Namespace) -> int:
    from ..artifacts import checkpoint_config, checkpoint_model, read_checkpoint, sha256_file

    out = pathlib.Path(args.out)
    fmt = _format(getattr(args, "format", None), out)
    targets = [out, out.with_suffix(".h")] if fmt == "c" else [out]
    for target in targets:
        refuse_overwrite(target, [args.checkpoint], args.force)
    raw = read_checkpoint(args.checkpoint)
    model = checkpoint_model(raw, args.checkpoint)
    dt = args.dt
    if dt is None:
        dt = float(raw.get("metrics", {}).get("dt", 1e-3))
    cfg = checkpoint_config(raw)
    sim = cfg.simulation
    if fmt == "torchscript":
        return _torchscript(model, args.out, dt, sim)
    from ...export import export_c, export_fmu

    name = str(raw.get("name") or pathlib.Path(args.checkpoint).stem)
    digest = sha256_file(args.checkpoint)
    meta = {"checkpoint": pathlib.Path(args.checkpoint).name, "created": raw.get("created", ""),
            "sha256": digest, "torchfric_version": raw.get("torchfric_version", "")}  # fmt: skip
    if fmt == "c":
        c_path, h_path = export_c(model, out, method=sim.method, substeps=sim.substeps,
                                  meta={"run": name, **meta})  # fmt: skip
        stem = c_path.stem
        print(f"wrote {c_path} and {h_path}: {stem}_friction(v), {stem}_step(state, u, dt), "
              f"{stem}_init(state, q0, qdot0)")  # fmt: skip
        return 0
    linear = cfg.data.axis_unit == "m"  # counts per metre too
    info = export_fmu(model, out, name=name, method=sim.method, substeps=sim.substeps, dt=dt,
                      linear=linear, meta=meta)  # fmt: skip
    print(f"wrote {info.path} ({info.size / 1024:.0f} KiB, FMI 2.0 Model Exchange and "
          f"Co-Simulation, binary {info.platform}, sources inside): input u; outputs q, qdot, "
          "friction; parameters q0, qdot0 and the identified values")  # fmt: skip
    return 0


_SUFFIX = {".fmu": "fmu", ".c": "c"}


def _format(asked: str | None, out: pathlib.Path) -> str:
    """The format: `asked`, else the one --out's suffix names (.fmu, .c; anything else
    TorchScript); a suffix that names another format than `asked` is a one-line error."""
    implied = _SUFFIX.get(out.suffix.lower(), "torchscript")
    if asked is None or asked == implied:
        return implied
    want = {v: k for k, v in _SUFFIX.items()}.get(asked)
    fix = f"end --out in {want}" if want else "give --out a name not ending in .fmu or .c"
    raise TorchfricError(f"--out {out} does not fit --format {asked}: {fix}")


def _torchscript(model, out: str, dt: float, sim) -> int:  # type: ignore[no-untyped-def]
    from ...models import export_model, save_exported

    module = export_model(model, dt=dt, substeps=sim.substeps, method=sim.method)
    save_exported(module, out)
    print(
        f"wrote {out}: torch.jit.load(path).simulate(t, u, x0) -> (q, qdot) at any sample "
        "time; .friction(v), .field(x, u)"
    )
    return 0
