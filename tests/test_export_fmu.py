"""FMU and C export (issue 35), checked by a client we did not write.

Every shipped checkpoint (and constructed models of the kinds no checkpoint has) is exported as
an FMI 2.0 FMU and as C99. FMPy — in a process where torch was never imported — validates each
FMU and simulates it as Co-Simulation and as Model Exchange (CVode); the results are compared
here with `torchfric.simulate`: Co-Simulation to 1e-9 relative on q (the same steps), Model
Exchange against a fine simulation to the solver's tolerance. The C sources compile with
``-std=c99 -Wall -Wextra -Werror`` and their friction and step are compared with the model's.
"""

from __future__ import annotations

import ctypes
import json
import pathlib
import subprocess
import sys
import zipfile

import numpy as np
import pytest
import torch

import torchfric
from torchfric.app.artifacts import checkpoint_config, checkpoint_model, read_checkpoint
from torchfric.app.cli import main
from torchfric.errors import TorchfricError
from torchfric.export import export_c, export_fmu
from torchfric.models import ArmModel
from torchfric.models.friction import make_friction

pytest.importorskip("fmpy")

ROOT = pathlib.Path(__file__).resolve().parents[1]
CHECKPOINTS = sorted((ROOT / "checkpoints").glob("*.pt"))
DT, N = 1e-3, 600
X0 = (0.1, 0.2)

# The client: FMPy only. It validates, simulates CS on the sample grid and ME with the input
# held (a repeated time is a step in FMPy's input table), and writes what it saw as JSON.
CLIENT = r"""
import json, sys
import numpy as np
from fmpy import simulate_fmu
from fmpy.validation import validate_fmu
jobs = json.load(open(sys.argv[1]))
out = {}
for job in jobs:
    t = np.array(job["t"]); u = np.array(job["u"])
    sig = np.array(list(zip(t, u)), dtype=[("time", float), ("u", float)])
    tt = np.repeat(t, 2)[1:]; uu = np.repeat(u, 2)[:-1]
    held = np.array(list(zip(tt, uu)), dtype=[("time", float), ("u", float)])
    start = job["start"]
    r = {"problems": [str(p) for p in validate_fmu(job["fmu"])]}
    cs = simulate_fmu(job["fmu"], fmi_type="CoSimulation", start_time=0.0, stop_time=t[-1],
                      output_interval=t[1] - t[0], input=sig, start_values=start,
                      output=["q", "qdot", "friction"])
    r["cs"] = {k: cs[k].tolist() for k in ("time", "q", "qdot", "friction")}
    me = simulate_fmu(job["fmu"], fmi_type="ModelExchange", solver="CVode",
                      relative_tolerance=1e-10, start_time=0.0, stop_time=t[-1],
                      output_interval=t[1] - t[0], input=held, start_values=start,
                      output=["q", "qdot"])
    keep = np.r_[True, me["time"][1:] != me["time"][:-1]]
    r["me_q"] = np.interp(t, me["time"][keep], me["q"][keep]).tolist()
    out[job["key"]] = r
out["torch_imported"] = "torch" in sys.modules
json.dump(out, open(sys.argv[2], "w"))
"""


def _input(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    t = torch.arange(N, dtype=torch.float64) * DT
    rng = np.random.default_rng(seed)
    u = 0.3 * np.sin(2 * np.pi * 1.5 * t.numpy()) + 0.05 * rng.standard_normal(N)
    return t, torch.tensor(u)


def _constructed() -> dict[str, tuple[ArmModel, str, int | str]]:
    """Kinds no shipped checkpoint has: every white-box term, c_m estimated, euler and midpoint
    solvers, a fixed sub-step count, LuGre around a polytopic curve, the baselines."""
    tanh = make_friction("tanh", 3, velocity_scale=5.0, torque_scale=0.1)
    everything = ArmModel(tanh, inertia=0.02, viscous=0.01, c_m=0.8, offset=0.003,
                          gravity=0.05, asymmetric=0.002, estimate_c_m=True)  # fmt: skip
    poly = make_friction("polytopic", 3, velocity_scale=4.0, torque_scale=0.05)
    lugre = ArmModel(poly, inertia=0.01, viscous=None, c_m=1.0, dynamic="lugre", sigma0=500.0,
                     sigma1=2.0, stick_velocity=0.05)  # fmt: skip
    coulomb = ArmModel(make_friction("coulomb", 1, fc=0.05, eps=0.02), inertia=0.02, viscous=0.01)
    stribeck = ArmModel(make_friction("stribeck", 1, fc=0.05, fs=0.08, vs=0.5, eps=0.02),
                        inertia=0.02, viscous=0.01)  # fmt: skip
    return {
        "all_terms_euler": (everything, "euler", "auto"),
        "all_terms_midpoint_fixed": (everything, "midpoint", 3),
        "lugre_polytopic": (lugre, "rk4", "auto"),
        "coulomb": (coulomb, "rk4", "auto"),
        "stribeck_fixed": (stribeck, "rk4", 2),
    }


def _cases() -> dict[str, tuple[ArmModel, str, int | str, str]]:
    cases = {}
    for ck in CHECKPOINTS:
        raw = read_checkpoint(ck)
        sim = checkpoint_config(raw).simulation
        cases[ck.stem] = (checkpoint_model(raw, ck), sim.method, sim.substeps, raw["name"])
    for key, (model, method, substeps) in _constructed().items():
        cases[key] = (model, method, substeps, key)
    return cases


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Every case exported as FMU and C, FMPy's view of every FMU (one client process, run on
    the second core while this one exports the C, compiles it and simulates the references)."""
    folder = tmp_path_factory.mktemp("export")
    cases = _cases()
    t, u = _input()
    jobs = []
    for key, (model, method, substeps, name) in cases.items():
        fmu = folder / f"{key}.fmu"
        export_fmu(model, fmu, name=name, method=method, substeps=substeps, dt=DT)
        jobs.append({"key": key, "fmu": str(fmu), "t": t.tolist(), "u": u.tolist(),
                     "start": {"q0": X0[0], "qdot0": X0[1]}})  # fmt: skip
    (folder / "jobs.json").write_text(json.dumps(jobs))
    (folder / "client.py").write_text(CLIENT)
    client = subprocess.Popen(
        [sys.executable, str(folder / "client.py"), str(folder / "jobs.json"), str(folder / "seen.json")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        built, reference = {}, {}
        for key, (model, method, substeps, _) in cases.items():
            export_c(model, folder / f"{key}.c", method=method, substeps=substeps)
            built[key] = _compile(folder, key)
            reference[key] = _reference(model, t, u, method, substeps, engine="compiled")
        _, err = client.communicate(timeout=600)
    finally:
        client.kill()
    assert client.returncode == 0, err[-2000:]
    seen = json.loads((folder / "seen.json").read_text())
    return {"folder": folder, "cases": cases, "seen": seen, "t": t, "u": u, "built": built,
            "reference": reference}  # fmt: skip


def test_every_shipped_checkpoint_is_covered(exported: dict) -> None:
    assert len(CHECKPOINTS) >= 18
    assert {ck.stem for ck in CHECKPOINTS} <= set(exported["seen"])
    kinds = {(m.friction.kind, m.dynamic) for m, *_ in exported["cases"].values()}
    assert {
        ("tanh", "none"),
        ("polytopic", "none"),
        ("tanh", "lugre"),
        ("polytopic", "lugre"),
    } <= kinds


def test_fmpy_validates_and_runs_without_torch(exported: dict) -> None:
    assert exported["seen"]["torch_imported"] is False
    for key in exported["cases"]:
        assert exported["seen"][key]["problems"] == [], key


def test_co_simulation_equals_simulate(exported: dict) -> None:
    """CS takes the simulator's own steps: q and qdot to 1e-9 relative (measured: 0 to 5e-15)."""
    t = exported["t"]
    for key in exported["cases"]:
        ref = exported["reference"][key]
        cs = exported["seen"][key]["cs"]
        assert np.allclose(cs["time"], t.numpy(), rtol=0, atol=1e-12), key
        for j, name in enumerate(("q", "qdot")):
            got = np.array(cs[name])
            scale = np.abs(ref[:, j]).max()
            assert np.abs(got - ref[:, j]).max() <= 1e-9 * scale, (key, name)


def test_friction_output_is_the_models_friction(exported: dict) -> None:
    """A static model's output ``friction`` is its curve at the simulated velocity."""
    for key, (model, _method, _substeps, _) in exported["cases"].items():
        if model.dynamic != "none":
            continue
        cs = exported["seen"][key]["cs"]
        with torch.no_grad():
            want = model.friction_torque(torch.tensor(cs["qdot"], dtype=torch.float64)).numpy()
        assert np.allclose(cs["friction"], want, rtol=1e-12, atol=1e-15), key


def test_model_exchange_agrees_to_the_solvers_tolerance(exported: dict) -> None:
    """ME: FMPy's CVode (rtol 1e-10) integrates the field; against `simulate` with 64 sub-steps
    (the compiled engine: the same rk4 steps as odeint's to rounding, 50× faster; measured on
    the rig's checkpoints: 3e-8 relative)."""
    t, u = exported["t"], exported["u"]
    for key, (model, _method, _substeps, _) in exported["cases"].items():
        fine = _reference(model, t, u, "rk4", 64, engine="compiled")
        got = np.array(exported["seen"][key]["me_q"])
        scale = np.abs(fine[:, 0]).max()
        assert np.abs(got - fine[:, 0]).max() <= 2e-6 * scale, key


def _reference(model: ArmModel, t, u, method: str, substeps, engine: str = "odeint") -> np.ndarray:  # type: ignore[no-untyped-def]
    with torch.no_grad():
        return torchfric.simulate(model, t, u, torch.tensor(X0, dtype=torch.float64),
                                  method=method, substeps=substeps, engine=engine).numpy()  # fmt: skip


def _compile(folder: pathlib.Path, key: str) -> str:
    """Compile NAME.c strictly into libNAME.so; the compiler's complaint if it failed."""
    flags = [
        "-std=c99",
        "-Wall",
        "-Wextra",
        "-Werror",
        "-O2",
        "-ffp-contract=off",
        "-fPIC",
        "-shared",
    ]
    run = subprocess.run(["cc", *flags, f"{key}.c", "-o", f"lib{key}.so", "-lm"], cwd=folder,
                         capture_output=True, text=True)  # fmt: skip
    return "" if run.returncode == 0 else run.stderr


def test_c_export_compiles_strict_and_matches(exported: dict) -> None:
    """NAME.c compiles with -Wall -Wextra -Werror; NAME_friction equals `friction_torque` and
    NAME_step, sample by sample, equals `simulate`."""
    folder, t, u = exported["folder"], exported["t"], exported["u"]
    v = torch.linspace(-20.0, 20.0, 401, dtype=torch.float64)
    for key, (model, _method, _substeps, _) in exported["cases"].items():
        assert exported["built"][key] == "", exported["built"][key]
        lib = ctypes.CDLL(str(folder / f"lib{key}.so"))
        fr = getattr(lib, f"{key}_friction")
        fr.restype, fr.argtypes = ctypes.c_double, [ctypes.c_double]
        with torch.no_grad():
            want = model.friction_torque(v).numpy()
        got = np.array([fr(float(a)) for a in v])
        assert np.allclose(got, want, rtol=1e-12, atol=1e-15), key
        step, init = getattr(lib, f"{key}_step"), getattr(lib, f"{key}_init")
        step.restype = ctypes.c_int
        step.argtypes = [ctypes.POINTER(ctypes.c_double), ctypes.c_double, ctypes.c_double]
        init.argtypes = [ctypes.POINTER(ctypes.c_double), ctypes.c_double, ctypes.c_double]
        state = (ctypes.c_double * model.state_size)()
        init(state, *X0)
        qs = [state[0]]
        for k in range(N - 1):
            assert step(state, float(u[k]), float(t[k + 1] - t[k])) >= 1
            qs.append(state[0])
        ref = exported["reference"][key]
        assert np.abs(np.array(qs) - ref[:, 0]).max() <= 1e-9 * np.abs(ref[:, 0]).max(), key


def test_description_carries_the_model(exported: dict) -> None:
    """Parameters are tunable with the identified values as start values; the GUID, the
    generation tool and the checkpoint's identity are in modelDescription.xml; the sources and
    buildDescription.xml are inside."""
    from xml.etree import ElementTree

    key = "arm_tanh_ekf"
    model = exported["cases"][key][0]
    with zipfile.ZipFile(exported["folder"] / f"{key}.fmu") as z:
        names = set(z.namelist())
        root = ElementTree.fromstring(z.read("modelDescription.xml"))
    assert {"sources/torchfric_fmu.c", "sources/torchfric_model.c",
            "sources/buildDescription.xml", f"binaries/linux64/{key}.so"} <= names  # fmt: skip
    assert root.get("generationTool", "").startswith("torchfric")
    by_name = {v.get("name"): v for v in root.iter("ScalarVariable")}
    for name, value in model.physical_parameters().items():
        var = by_name[name]
        assert var.get("causality") == "parameter" and var.get("variability") == "tunable"
        assert float(var.find("Real").get("start")) == value
    assert by_name["inertia"].find("Real").get("unit") == "kg.m2"
    assert by_name["u"].get("causality") == "input"
    assert {by_name[n].get("causality") for n in ("q", "qdot", "friction")} == {"output"}


def test_guid_changes_with_the_model(tmp_path: pathlib.Path) -> None:
    model = _constructed()["coulomb"][0]
    a = export_fmu(model, tmp_path / "a.fmu", name="m")
    b = export_fmu(model, tmp_path / "b.fmu", name="m")
    assert a.guid == b.guid  # the same model: the same GUID (the date is not part of it)
    other = ArmModel(make_friction("coulomb", 1, fc=0.06, eps=0.02), inertia=0.02, viscous=0.01)
    assert export_fmu(other, tmp_path / "c.fmu", name="m").guid != a.guid


def test_a_changed_parameter_changes_the_simulation(tmp_path: pathlib.Path) -> None:
    """Tunable parameters act: inertia × 2 through FMPy's start values equals `simulate` of the
    model with that inertia; a non-positive inertia is refused by the FMU with its reason."""
    model = _constructed()["coulomb"][0]
    fmu = tmp_path / "m.fmu"
    export_fmu(model, fmu, name="m")
    heavy = ArmModel(make_friction("coulomb", 1, fc=0.05, eps=0.02), inertia=0.04, viscous=0.01)
    t, u = _input(1)
    ref = _reference(heavy, t, u, "rk4", "auto")
    from fmpy import simulate_fmu

    sig = np.array(
        list(zip(t.numpy(), u.numpy(), strict=False)), dtype=[("time", float), ("u", float)]
    )
    common = dict(fmi_type="CoSimulation", start_time=0.0, stop_time=float(t[-1]),
                  output_interval=DT, input=sig, output=["q"])  # fmt: skip
    res = simulate_fmu(
        str(fmu), start_values={"q0": X0[0], "qdot0": X0[1], "inertia": 0.04}, **common
    )
    assert np.abs(res["q"] - ref[:, 0]).max() <= 1e-9 * np.abs(ref[:, 0]).max()
    from fmpy.fmi1 import FMICallException

    messages: list[str] = []
    with pytest.raises(FMICallException, match="fmi2ExitInitializationMode"):
        simulate_fmu(str(fmu), start_values={"inertia": -1.0},
                     logger=lambda *a: messages.append(a[-1].decode()), **common)  # fmt: skip
    assert messages == ["inertia must be positive, got -1"]


def test_cli_export_formats(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`export --out m.fmu` needs no other flag (the suffix names the format; so does .c, which
    writes NAME.c and NAME.h); a suffix that contradicts --format, an existing file and a bad
    --format are each one line, and replace nothing."""
    ck = str(CHECKPOINTS[0])
    assert main(["export", ck, "--out", str(tmp_path / "m.fmu")]) == 0
    assert zipfile.is_zipfile(tmp_path / "m.fmu")
    assert main(["export", ck, "--out", str(tmp_path / "ff.c")]) == 0
    assert (tmp_path / "ff.h").exists() and "ff_friction" in (tmp_path / "ff.h").read_text()
    assert main(["export", ck, "--out", str(tmp_path / "g.fmu"), "--format", "fmu"]) == 0
    capsys.readouterr()
    assert main(["export", ck, "--out", str(tmp_path / "h.ts"), "--format", "fmu"]) != 0
    assert "end --out in .fmu" in capsys.readouterr().err
    assert not (tmp_path / "h.ts").exists()
    before = (tmp_path / "m.fmu").read_bytes()
    assert main(["export", ck, "--out", str(tmp_path / "m.fmu"), "--format", "fmu"]) != 0
    assert (tmp_path / "m.fmu").read_bytes() == before
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(["export", ck, "--out", str(tmp_path / "x"), "--format", "zip"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "torchscript" in err and "fmu" in err and "'c'" in err


def test_no_compiler_is_one_line_and_writes_nothing(
    tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import torchfric.export.fmu as fmu_module

    monkeypatch.setattr(fmu_module, "compiler", lambda: None)
    model = _constructed()["coulomb"][0]
    with pytest.raises(TorchfricError, match="no C compiler"):
        export_fmu(model, tmp_path / "m.fmu", name="m")
    assert list(tmp_path.iterdir()) == []


def test_rebuilt_from_its_sources_by_fmpy(exported: dict, tmp_path: pathlib.Path) -> None:
    """Another platform's path: the archive without its binary, rebuilt by FMPy's own build
    (its buildDescription.xml through CMake), simulates as the shipped binary does."""
    if __import__("shutil").which("cmake") is None:
        pytest.skip("no cmake: FMPy's build needs it")
    from fmpy import extract, simulate_fmu
    from fmpy.build import build_platform_binary

    key = "arm_lugre_ekf"
    stripped = tmp_path / "nobin.fmu"
    with (
        zipfile.ZipFile(exported["folder"] / f"{key}.fmu") as z,
        zipfile.ZipFile(stripped, "w") as o,
    ):
        for item in z.infolist():
            if not item.filename.startswith("binaries/"):
                o.writestr(item, z.read(item))
    unzipped = extract(str(stripped), str((tmp_path / "unzipped").resolve()))
    build_platform_binary(unzipped)
    t, u = exported["t"], exported["u"]
    sig = np.array(
        list(zip(t.numpy(), u.numpy(), strict=True)), dtype=[("time", float), ("u", float)]
    )
    res = simulate_fmu(unzipped, fmi_type="CoSimulation", stop_time=float(t[-1]),
                       output_interval=DT, input=sig, start_values={"q0": X0[0], "qdot0": X0[1]},
                       output=["q"])  # fmt: skip
    assert np.array_equal(res["q"], np.array(exported["seen"][key]["cs"]["q"]))


@pytest.mark.parametrize(
    ("data", "unit"),
    [({"position_unit": "counts", "counts_per_m": 1e6}, "m"), ({"position_unit": "mm"}, "m"),
     ({"position_unit": "counts", "counts_per_rev": 4096.0}, "rad")],
)  # fmt: skip
def test_the_units_follow_the_datas_axis(tmp_path: pathlib.Path, data: dict, unit: str) -> None:
    """Encoder counts per metre are a linear axis (found by a user's walk: its FMU said rad)."""
    from fmpy import read_model_description

    raw = torch.load(CHECKPOINTS[0], weights_only=False)
    raw["config"]["data"].update(data)
    ck = tmp_path / "axis.pt"
    torch.save(raw, ck)
    assert main(["export", str(ck), "--out", str(tmp_path / "axis.fmu")]) == 0
    units = {
        v.name: v.unit for v in read_model_description(str(tmp_path / "axis.fmu")).modelVariables
    }
    assert units["q"] == unit and units["qdot"] == f"{unit}/s"
