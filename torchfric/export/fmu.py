"""An identified model as an FMI 2.0 FMU: Model Exchange and Co-Simulation in one archive.

The archive holds ``modelDescription.xml``, the C sources with a ``buildDescription.xml`` (so an
importer on another platform can rebuild it), and the binary for this platform built with the
system C compiler. The C is the model's own torch code written out (`torchfric.export.program`)
around a hand-written FMI layer (``c/torchfric_fmu.c``); the binary needs no Python, torch or
torchfric.

- Input ``u``; outputs ``q``, ``qdot`` and ``friction`` (the friction torque at the state);
  LuGre's bristle deflection ``z`` is a local state.
- Co-Simulation: each communication step is the simulator's sub-steps (`torchfric.simulate`'s
  solver and sub-step rule, u held), so a CS run on the sample grid equals `simulate`.
- Model Exchange: ``der(q)``, ``der(qdot)`` (and ``der(z)``) from the model's vector field for
  the importer's solver.
- Parameters: every identified value (tunable, with its unit where it has one), the initial
  state ``q0``, ``qdot0`` (fixed; a LuGre model starts with its bristles at the steady
  deflection of qdot0).
- The GUID is a hash of the generated sources and the description: another model, another GUID.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import io
import pathlib
import re
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass, field
from typing import Any
from xml.sax.saxutils import quoteattr

import torch

from ..accel.native import compiler
from ..errors import TorchfricError
from ..files import atomic_write_bytes
from ..models import ArmModel
from ..version import __version__
from .program import Program, model_program, model_source

__all__ = ["FMUInfo", "export_fmu", "model_identifier", "platform_folder"]

_C_DIR = pathlib.Path(__file__).with_name("c")
_FMU_C = "torchfric_fmu.c"
_SOURCES = ("torchfric_fmi2.h", _FMU_C)

# Units by kind, for an axis whose q is in rad (rotary) or m (linear): (name, base exponents).
_UNITS = {
    False: {"position": ("rad", {"rad": 1}), "velocity": ("rad/s", {"rad": 1, "s": -1}),
            "acceleration": ("rad/s2", {"rad": 1, "s": -2}),
            "torque": ("N.m", {"kg": 1, "m": 2, "s": -2}),
            "inertia": ("kg.m2", {"kg": 1, "m": 2}),
            "torque/velocity": ("N.m.s/rad", {"kg": 1, "m": 2, "s": -1, "rad": -1}),
            "torque/position": ("N.m/rad", {"kg": 1, "m": 2, "s": -2, "rad": -1})},
    True: {"position": ("m", {"m": 1}), "velocity": ("m/s", {"m": 1, "s": -1}),
           "acceleration": ("m/s2", {"m": 1, "s": -2}),
           "torque": ("N", {"kg": 1, "m": 1, "s": -2}), "inertia": ("kg", {"kg": 1}),
           "torque/velocity": ("N.s/m", {"kg": 1, "s": -1}),
           "torque/position": ("N/m", {"kg": 1, "s": -2})},
}  # fmt: skip


@dataclass
class FMUInfo:
    """What `export_fmu` wrote: the file, its GUID, model identifier, size in bytes, the
    platform folder of its binary, and its variables' names."""

    path: pathlib.Path
    guid: str
    identifier: str
    size: int
    platform: str
    variables: list[str] = field(default_factory=list)


def model_identifier(name: str) -> str:
    """A C identifier from a run's name (the FMU's modelIdentifier and binary's name)."""
    ident = re.sub(r"[^A-Za-z0-9_]", "_", name) or "model"
    return ident if not ident[0].isdigit() else f"m_{ident}"


def platform_folder() -> str:
    """The FMI 2.0 platform folder of this machine's binaries (linux64, darwin64, win64)."""
    bits = "64" if sys.maxsize > 2**32 else "32"
    if sys.platform.startswith("linux"):
        return f"linux{bits}"
    if sys.platform == "darwin":
        return f"darwin{bits}"
    if sys.platform.startswith("win"):
        return f"win{bits}"
    raise TorchfricError(f"no FMI platform folder for {sys.platform!r}; build from the sources")


def _suffix() -> str:
    return {"darwin": ".dylib", "win32": ".dll"}.get(sys.platform, ".so")


def _variables(program: Program, linear: bool) -> list[dict[str, Any]]:
    """The model variables in order (index i + 1), each a dict of its XML attributes."""
    unit = {k: v[0] for k, v in _UNITS[linear].items()}
    dyn = program.dynamic
    out: list[dict[str, Any]] = [
        {"name": "u", "vr": 0, "causality": "input", "variability": "continuous", "start": 0.0,
         "description": "input (current, voltage, ...): torque c_m*u, held over a communication step"},
        {"name": "q", "vr": 1, "causality": "output", "initial": "calculated",
         "unit": unit["position"], "description": "position", "state": 0},
        {"name": "qdot", "vr": 2, "causality": "output", "initial": "calculated",
         "unit": unit["velocity"], "description": "velocity", "state": 1},
        {"name": "friction", "vr": 3, "causality": "output", "initial": "calculated",
         "unit": unit["torque"], "description": "friction torque (force) at the state"},
        {"name": "der(q)", "vr": 4, "causality": "local", "initial": "calculated",
         "unit": unit["velocity"], "derivative_of": "q"},
        {"name": "der(qdot)", "vr": 5, "causality": "local", "initial": "calculated",
         "unit": unit["acceleration"], "derivative_of": "qdot"},
    ]  # fmt: skip
    if dyn:
        out += [
            {"name": "z", "vr": 6, "causality": "local", "initial": "calculated",
             "unit": unit["position"], "description": "LuGre bristle deflection", "state": 2},
            {"name": "der(z)", "vr": 7, "causality": "local", "initial": "calculated",
             "unit": unit["velocity"], "derivative_of": "z"},
        ]  # fmt: skip
    out += [
        {"name": "q0", "vr": 8, "causality": "parameter", "variability": "fixed",
         "initial": "exact", "start": 0.0, "unit": unit["position"],
         "description": "initial position"},
        {"name": "qdot0", "vr": 9, "causality": "parameter", "variability": "fixed",
         "initial": "exact", "start": 0.0, "unit": unit["velocity"],
         "description": "initial velocity" + (" (bristles start at its steady deflection)" if dyn else "")},
    ]  # fmt: skip
    for i, p in enumerate(program.parameters):
        var = {"name": p.name, "vr": 10 + i, "causality": "parameter", "variability": "tunable",
               "initial": "exact", "start": p.value, "description": p.description}  # fmt: skip
        if p.unit in unit:
            var["unit"] = unit[p.unit]
        out.append(var)
    return out


def _scalar_xml(var: dict[str, Any], index: dict[str, int]) -> str:
    attrs = f'name={quoteattr(var["name"])} valueReference="{var["vr"]}"'
    if "description" in var:
        attrs += f" description={quoteattr(var['description'])}"
    attrs += f' causality="{var["causality"]}"'
    attrs += f' variability="{var.get("variability", "continuous")}"'
    if "initial" in var:
        attrs += f' initial="{var["initial"]}"'
    real = ""
    if "unit" in var:
        real += f" unit={quoteattr(var['unit'])}"
    if "derivative_of" in var:
        real += f' derivative="{index[var["derivative_of"]]}"'
    if "start" in var:
        real += f' start="{float(var["start"])!r}"'
    return f"    <ScalarVariable {attrs}>\n      <Real{real}/>\n    </ScalarVariable>"


def _description_xml(
    program: Program, *, guid: str, ident: str, name: str, linear: bool, dt: float,
    meta: dict[str, Any], when: str,
) -> str:  # fmt: skip
    variables = _variables(program, linear)
    index = {v["name"]: i + 1 for i, v in enumerate(variables)}
    used = {v["unit"] for v in variables if "unit" in v}
    units = []
    for uname, base in _UNITS[linear].values():
        if uname in used:
            exps = " ".join(f'{k}="{e}"' for k, e in base.items())
            units.append(f'    <Unit name="{uname}">\n      <BaseUnit {exps}/>\n    </Unit>')
    outputs = [index[n] for n in ("q", "qdot", "friction")]
    derivs = [index[v["name"]] for v in variables if "derivative_of" in v]
    states = [index[v["name"]] for v in variables if "state" in v and v["causality"] == "local"]
    initial = sorted(set(outputs + derivs + states))
    meta_xml = " ".join(f"{k}={quoteattr(str(v))}" for k, v in meta.items())
    sources = f'      <File name="{_FMU_C}"/>'
    desc = (
        f"{'LuGre' if program.dynamic else 'static'} friction model identified by torchfric "
        f"(run {name}); u in, q, qdot and the friction torque out"
    )
    caps = 'canNotUseMemoryManagementFunctions="false" canGetAndSetFMUstate="false" canSerializeFMUstate="false" providesDirectionalDerivative="false"'
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<fmiModelDescription fmiVersion="2.0" modelName={quoteattr(name)} guid="{guid}"',
        f"  description={quoteattr(desc)}",
        f'  generationTool="torchfric {__version__}" generationDateAndTime="{when}"',
        '  variableNamingConvention="flat" numberOfEventIndicators="0">',
        f'  <ModelExchange modelIdentifier="{ident}" {caps}>',
        f"    <SourceFiles>\n{sources}\n    </SourceFiles>",
        "  </ModelExchange>",
        f'  <CoSimulation modelIdentifier="{ident}" canHandleVariableCommunicationStepSize="true" {caps}>',
        f"    <SourceFiles>\n{sources}\n    </SourceFiles>",
        "  </CoSimulation>",
        "  <UnitDefinitions>", *units, "  </UnitDefinitions>",
        '  <LogCategories>\n    <Category name="logStatusError"/>\n  </LogCategories>',
        f'  <DefaultExperiment startTime="0.0" stepSize="{dt!r}"/>',
        '  <VendorAnnotations>\n    <Tool name="torchfric">',
        f"      <Checkpoint {meta_xml}/>",
        "    </Tool>\n  </VendorAnnotations>",
        "  <ModelVariables>", *(_scalar_xml(v, index) for v in variables), "  </ModelVariables>",
        "  <ModelStructure>",
        "    <Outputs>", *(f'      <Unknown index="{i}"/>' for i in outputs), "    </Outputs>",
        "    <Derivatives>", *(f'      <Unknown index="{i}"/>' for i in derivs), "    </Derivatives>",
        "    <InitialUnknowns>", *(f'      <Unknown index="{i}"/>' for i in initial),
        "    </InitialUnknowns>",
        "  </ModelStructure>",
        "</fmiModelDescription>",
        "",
    ]  # fmt: skip
    return "\n".join(lines)


def _build_xml(ident: str) -> str:
    return "\n".join([
        '<?xml version="1.0" encoding="UTF-8"?>',
        '<fmiBuildDescription fmiVersion="3.0">',
        f'  <BuildConfiguration modelIdentifier="{ident}" description="cc -std=c99 -O2 -ffp-contract=off -fPIC -shared -fvisibility=hidden {_FMU_C} -lm">',
        '    <SourceFileSet language="C99">',
        f'      <SourceFile name="{_FMU_C}"/>',
        "    </SourceFileSet>",
        '    <Library name="m"/>',
        "  </BuildConfiguration>",
        "</fmiBuildDescription>",
        "",
    ])  # fmt: skip


def _nominals(model: ArmModel) -> list[float]:
    """Nominal sizes of the states for the importer's error control: 1 for q and q̇; for the
    bristles, their steady deflection at unit speed."""
    if model.state_size == 2:
        return [1.0, 1.0]
    from ..models.simulate import steady_bristles

    fric, arm = model.split(model.get_theta())
    z = float(steady_bristles(model, torch.ones((), dtype=torch.float64), fric, arm).abs())
    return [1.0, 1.0, z if z > 0 else 1e-6]


def _compile(sources: dict[str, str], ident: str) -> bytes:
    cc = compiler()
    if cc is None:
        raise TorchfricError(
            "no C compiler found to build the FMU's binary: install gcc or clang (or set CC)"
        )
    with tempfile.TemporaryDirectory(prefix="torchfric-fmu-") as tmp:
        folder = pathlib.Path(tmp)
        for fname, text in sources.items():
            (folder / fname).write_text(text, encoding="utf-8")
        lib = folder / f"{ident}{_suffix()}"
        cmd = [cc, "-std=c99", "-O2", "-fno-fast-math", "-ffp-contract=off", "-fPIC", "-shared",
               "-fvisibility=hidden", _FMU_C, "-o", lib.name, "-lm"]  # fmt: skip
        run = subprocess.run(cmd, cwd=folder, capture_output=True, text=True, timeout=600)
        if run.returncode != 0:
            first = (run.stderr.strip().splitlines() or [f"exit {run.returncode}"])[0]
            raise TorchfricError(f"the C compiler ({cc}) could not build the FMU: {first}")
        return lib.read_bytes()


def export_fmu(
    model: ArmModel,
    out: str | pathlib.Path,
    *,
    name: str = "model",
    method: str = "rk4",
    substeps: int | str = "auto",
    dt: float = 1e-3,
    linear: bool = False,
    meta: dict[str, Any] | None = None,
) -> FMUInfo:
    """Write `model` as an FMI 2.0 FMU (ME and CS) to `out`, atomically.

    Args:
        model: the identified arm.
        out: the ``.fmu`` file to write (replaced if it exists: the caller decides).
        name: the model's name (the run's); its identifier names the binary.
        method, substeps: the run's `simulation.method` and `simulation.substeps`, which
            Co-Simulation steps with.
        dt: the default experiment's step size (the data's sample time).
        linear: q in m (a linear axis) rather than rad, for the units.
        meta: the checkpoint's identity (name, date, file hash …), written as attributes of
            the vendor annotation.
    """
    program = model_program(model, method=method, substeps=substeps)
    ident = model_identifier(name)
    when = _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat().replace("+00:00", "Z")
    meta = {"name": name, **(meta or {})}
    # The GUID hashes everything that defines the model and the interface, not the date.
    body = model_source(program, guid="{GUID}", nominals=_nominals(model), title=name)
    probe = _description_xml(program, guid="{GUID}", ident=ident, name=name, linear=linear,
                             dt=dt, meta=meta, when="")  # fmt: skip
    sources = {f: (_C_DIR / f).read_text(encoding="utf-8") for f in _SOURCES}
    digest = hashlib.sha256((body + probe + sources[_FMU_C]).encode()).hexdigest()
    guid = (
        "{" + f"{digest[:8]}-{digest[8:12]}-{digest[12:16]}-{digest[16:20]}-{digest[20:32]}" + "}"
    )
    description = _description_xml(program, guid=guid, ident=ident, name=name, linear=linear,
                                   dt=dt, meta=meta, when=when)  # fmt: skip
    sources["torchfric_model.c"] = body.replace("{GUID}", guid)
    binary = _compile(sources, ident)
    plat = platform_folder()
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("modelDescription.xml", description)
        for fname, text in sources.items():
            z.writestr(f"sources/{fname}", text)
        z.writestr("sources/buildDescription.xml", _build_xml(ident))
        z.writestr(f"binaries/{plat}/{ident}{_suffix()}", binary)
    data = buf.getvalue()
    path = pathlib.Path(out)
    atomic_write_bytes(path, data, what="FMU")
    names = [v["name"] for v in _variables(program, linear)]
    return FMUInfo(path, guid, ident, len(data), plat, names)
