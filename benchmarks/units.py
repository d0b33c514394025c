"""The same record in other units: do the physical parameters scale exactly?

    python benchmarks/units.py                 # 20 s records of the user-style axis, seed 5
    python benchmarks/units.py --seed 3 --duration 30 --set model.saturation=0

One identification and one validation record of `torchfric.data.axis.STRIBECK_AXIS` (an
independent simulator, not the built-in rig) are written four ways — q in rad, q in degrees,
q in encoder counts (rounded, as a drive logs them) and the record in rad with c_m given ×10 —
and each is trained as a user would (`torchfric.fit` on a config with data.train,
data.validation and model.c_m, every other key at its default). The table brings M and b
back to rad and the true c_m, and prints them with their σ, the validation FIT, the passes
and whether the run converged. Before issue 31 the same record gave b = 0.011, 0.0040 and
2.4e-5 in three units.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import torchfric
from torchfric.data.axis import STRIBECK_AXIS, axis_record

AXIS = STRIBECK_AXIS
VARIANTS = {  # name → (factor on q, factor on c_m, counts)
    "rad": (1.0, 1.0, False),
    "deg": (180.0 / math.pi, 1.0, False),
    "counts": (1.0 / AXIS.quantum, 1.0, True),
    "c_m ×10": (1.0, 10.0, False),
}


def write(folder: Path, records: dict, q_scale: float, c_m: float, counts: bool) -> Path:
    folder.mkdir(parents=True)
    for kind, r in records.items():
        q = r["q"] * q_scale
        q = np.round(q) if counts else q
        np.savetxt(folder / f"{kind}.csv", np.column_stack([r["t"], r["u"], q]), delimiter=",",
                   header="t,u,q", comments="", fmt=["%.6f", "%.10g", "%.12g"])  # fmt: skip
    cfg = folder / "cfg.toml"
    cfg.write_text(f'name = "axis"\n[data]\ntrain = ["identification.csv"]\n'
                   f'validation = ["validation.csv"]\n[model]\nc_m = {c_m!r}\n')  # fmt: skip
    return cfg


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    sets = {k: eval(v, {}) for k, v in (s.split("=", 1) for s in args.set)}  # noqa: S307
    records = {k: axis_record(AXIS, seed=args.seed, duration=args.duration, kind=k)
               for k in ("identification", "validation")}  # fmt: skip
    root = Path(tempfile.mkdtemp(prefix="torchfric-units-"))
    print("| data as | M [kg m²] | b [N m s/rad] | validation FIT q / q̇ | passes | converged |")
    print("|---|---|---|---|---|---|")
    for name, (q_scale, torque, counts) in VARIANTS.items():
        cfg = write(root / name.replace(" ", "_").replace("×", "x"), records, q_scale,
                    AXIS.c_m * torque, counts)  # fmt: skip
        t0 = time.perf_counter()
        m = torchfric.fit(str(cfg), out=str(cfg.parent / "run"), quiet=True, **sets).metrics
        back = q_scale / torque
        p = m["parameters"]
        fit = next(iter(m["validation"].values()))
        print(f"| {name} | {p['inertia']['value'] * back:.7g} ± {p['inertia']['std'] * back:.2g} "
              f"| {p['viscous']['value'] * back:.6g} ± {p['viscous']['std'] * back:.2g} "
              f"| {fit['fit_q']:.3f} / {fit['fit_qdot']:.3f} | {m['passes']} | {m['converged']} "
              f"({time.perf_counter() - t0:.0f} s) |")  # fmt: skip
    print(f"truth: M {AXIS.inertia}, b {AXIS.viscous}; runs in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
