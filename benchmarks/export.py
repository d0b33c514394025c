"""FMU and C export of every shipped checkpoint: size, export time, and agreement with
`torchfric.simulate` as FMPy (a client we did not write, in a process without torch) runs it.

    python benchmarks/export.py [--samples 2000]

Per checkpoint: the FMU's size, the time of `export_fmu` and `export_c` (tracing, C, the
compiler), FMPy's validation problems, Co-Simulation's largest |q − simulate| relative to
max |q| (the same steps: rounding), Model Exchange's under CVode at rtol 1e-10 against a fine
simulation (64 rk4 sub-steps per sample), and the C export's friction against
`friction_torque` over ±20 velocity units.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torchfric  # noqa: E402
from torchfric.app.artifacts import checkpoint_config, checkpoint_model, read_checkpoint  # noqa: E402
from torchfric.export import export_c, export_fmu  # noqa: E402

CLIENT = r"""
import json, sys, time
import numpy as np
from fmpy import simulate_fmu
from fmpy.validation import validate_fmu
out = {}
for job in json.load(open(sys.argv[1])):
    t = np.array(job["t"]); u = np.array(job["u"])
    sig = np.array(list(zip(t, u)), dtype=[("time", float), ("u", float)])
    held = np.array(list(zip(np.repeat(t, 2)[1:], np.repeat(u, 2)[:-1])), dtype=sig.dtype)
    r = {"problems": len(validate_fmu(job["fmu"]))}
    a = time.perf_counter()
    cs = simulate_fmu(job["fmu"], fmi_type="CoSimulation", stop_time=t[-1], output_interval=t[1] - t[0],
                      input=sig, start_values=job["start"], output=["q"])
    b = time.perf_counter()
    me = simulate_fmu(job["fmu"], fmi_type="ModelExchange", solver="CVode", relative_tolerance=1e-10,
                      stop_time=t[-1], output_interval=t[1] - t[0], input=held,
                      start_values=job["start"], output=["q"])
    c = time.perf_counter()
    keep = np.r_[True, me["time"][1:] != me["time"][:-1]]
    r.update(cs=cs["q"].tolist(), me=np.interp(t, me["time"][keep], me["q"][keep]).tolist(),
             cs_s=b - a, me_s=c - b)
    out[job["key"]] = r
out["torch"] = "torch" in sys.modules
json.dump(out, open(sys.argv[2], "w"))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=2000)
    args = ap.parse_args()
    dt, n = 1e-3, args.samples
    t = torch.arange(n, dtype=torch.float64) * dt
    rng = np.random.default_rng(0)
    u = torch.tensor(0.3 * np.sin(2 * np.pi * 1.5 * t.numpy()) + 0.05 * rng.standard_normal(n))
    x0 = torch.tensor([0.1, 0.2], dtype=torch.float64)
    rows, jobs, refs = {}, [], {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = pathlib.Path(tmp)
        for ck in sorted((ROOT / "checkpoints").glob("*.pt")):
            raw = read_checkpoint(ck)
            model, sim = checkpoint_model(raw, ck), checkpoint_config(raw).simulation
            a = time.perf_counter()
            info = export_fmu(model, folder / f"{ck.stem}.fmu", name=raw["name"], method=sim.method,
                              substeps=sim.substeps, dt=dt)  # fmt: skip
            b = time.perf_counter()
            export_c(model, folder / f"{ck.stem}.c", method=sim.method, substeps=sim.substeps)
            c = time.perf_counter()
            lib = folder / f"lib{ck.stem}.so"
            subprocess.run(["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", "-fPIC", "-shared",
                            "-ffp-contract=off", f"{ck.stem}.c", "-o", lib.name, "-lm"], cwd=folder,
                           check=True)  # fmt: skip
            import ctypes

            fr = getattr(ctypes.CDLL(str(lib)), f"{ck.stem}_friction")
            fr.restype, fr.argtypes = ctypes.c_double, [ctypes.c_double]
            v = torch.linspace(-20.0, 20.0, 401, dtype=torch.float64)
            with torch.no_grad():
                want = model.friction_torque(v).numpy()
                refs[ck.stem] = (
                    torchfric.simulate(model, t, u, x0, method=sim.method, substeps=sim.substeps).numpy()[:, 0],
                    torchfric.simulate(model, t, u, x0, substeps=64, engine="compiled").numpy()[:, 0],
                )  # fmt: skip
            got = np.array([fr(float(a)) for a in v])
            kind = f"{model.friction.kind}{' LuGre' if model.dynamic == 'lugre' else ''}"
            rows[ck.stem] = {"kind": kind, "kib": info.size / 1024, "fmu_s": b - a, "c_s": c - b,
                             "c_fric": float(np.abs(got - want).max() / np.abs(want).max())}  # fmt: skip
            jobs.append({"key": ck.stem, "fmu": str(info.path), "t": t.tolist(), "u": u.tolist(),
                         "start": {"q0": 0.1, "qdot0": 0.2}})  # fmt: skip
        (folder / "jobs.json").write_text(json.dumps(jobs))
        (folder / "client.py").write_text(CLIENT)
        subprocess.run(
            [sys.executable, "client.py", "jobs.json", "seen.json"], cwd=folder, check=True
        )
        seen = json.loads((folder / "seen.json").read_text())
    print(
        f"{len(rows)} checkpoints, {n} samples at {dt * 1e3:g} ms; FMPy's process imported torch: {seen['torch']}"
    )
    print(
        "| checkpoint | model | FMU KiB | export FMU s | export C s | FMPy problems | CS: max rel q err "
        "| ME (CVode 1e-10): max rel q err | CS / ME run s | C friction rel err |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for key, r in rows.items():
        s, (ref, fine) = seen[key], refs[key]
        cs = np.abs(np.array(s["cs"]) - ref).max() / np.abs(ref).max()
        me = np.abs(np.array(s["me"]) - fine).max() / np.abs(fine).max()
        print(f"| {key} | {r['kind']} | {r['kib']:.0f} | {r['fmu_s']:.2f} | {r['c_s']:.2f} | "
              f"{s['problems']} | {cs:.1e} | {me:.1e} | {s['cs_s']:.2f} / {s['me_s']:.2f} | "
              f"{r['c_fric']:.1e} |")  # fmt: skip


if __name__ == "__main__":
    main()
