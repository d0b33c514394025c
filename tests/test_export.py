"""TorchScript export (`torchfric.models.torchscript`): every model option simulates as `torchfric.models.simulate`
does, after a save + ``torch.jit.load`` round trip, at the training sample time and at others.

The export shares the physics with `ArmModel` (`torchfric.models.arm.arm_field` / `arm_friction`, the
friction's own `evaluate` traced), so these comparisons are to rounding; the tolerance asked of
them is a relative 1e-6 of each channel's range.
"""

from __future__ import annotations

import math
import pathlib
import subprocess
import sys
import textwrap
import warnings

import pytest
import torch

from torchfric.errors import TorchfricError
from torchfric.models.arm import ArmModel
from torchfric.models.friction import FRICTIONS, make_friction
from torchfric.models.simulate import SOLVERS, auto_substeps, simulate
from torchfric.models.torchscript import export_model, save_exported

RTOL = 1e-6


def rel_diff(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a − b| over max |b|, per channel (last axis), the worse channel."""
    a, b = a.detach(), b.detach()
    worst = 0.0
    for i in range(b.shape[-1]):
        scale = float(b[..., i].abs().max())
        diff = float((a[..., i] - b[..., i]).abs().max())
        worst = max(worst, diff / scale if scale > 0 else diff)
    return worst


def round_trip(module: torch.jit.ScriptModule, tmp_path: pathlib.Path, name: str = "m.pt"):  # type: ignore[no-untyped-def]
    path = tmp_path / name
    save_exported(module, path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # TorchScript is deprecated upstream
        return torch.jit.load(str(path))


def excitation(n: int, dt: float, amplitude: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Sines and steps: both directions, stops and reversals."""
    t = torch.arange(n, dtype=torch.float64) * dt
    span = n * dt
    u = amplitude * (
        0.6 * torch.sin(2 * math.pi * 3.0 * t / span)
        + 0.3 * torch.sign(torch.sin(2 * math.pi * 5.0 * t / span))
        + 0.2 * torch.sin(2 * math.pi * 11.0 * t / span)
    )
    return t, u


def make_arm(
    kind: str,
    *,
    viscous: bool = True,
    offset: bool = False,
    gravity: bool = False,
    asymmetric: bool = False,
    estimate_c_m: bool = False,
    log_positive: bool = True,
) -> ArmModel:
    size = 3 if kind in ("tanh", "polytopic") else 1
    friction = make_friction(kind, size, log_positive=log_positive)
    model = ArmModel(
        friction,
        inertia=0.03,
        viscous=0.01 if viscous else None,
        c_m=2.0,
        offset=-0.02 if offset else None,
        gravity=0.15 if gravity else None,
        asymmetric=0.004 if asymmetric else None,
        estimate_c_m=estimate_c_m,
        log_positive=log_positive,
    )
    # θ away from the constructor's defaults, as after identification.
    gen = torch.Generator().manual_seed(3)
    theta = model.get_theta()
    return model.set_theta(theta + 0.05 * torch.randn(theta.shape, generator=gen))


# The friction curve and the white-box terms are separate parts of the exported field: every
# kind with no term, with all of them, with c_m estimated (θ's layout shifts) and with linear
# parameters (the friction's own parametrisation changes); each term alone on one kind.
EVERY_KIND = [
    ("plain", {}),
    ("all_terms", {"offset": True, "gravity": True, "asymmetric": True}),
    ("estimate_c_m", {"estimate_c_m": True, "offset": True, "asymmetric": True}),
    ("linear_params", {"log_positive": False, "offset": True, "gravity": True}),
]
ONE_TERM = [
    ("no_viscous", {"viscous": False}),
    ("asymmetric", {"asymmetric": True}),
    ("offset", {"offset": True}),
    ("gravity", {"gravity": True}),
]
OPTIONS = [
    pytest.param(kind, opts, id=f"{kind}-{label}")
    for kind in sorted(FRICTIONS)
    for label, opts in EVERY_KIND + (ONE_TERM if kind == "tanh" else [])
]


@pytest.mark.parametrize(("kind", "opts"), OPTIONS)
def test_export_matches_simulate_for_every_option(
    kind: str, opts: dict[str, bool], tmp_path: pathlib.Path
) -> None:
    model = make_arm(kind, **opts)
    module = round_trip(export_model(model, dt=1e-3), tmp_path)
    t, u = excitation(600, 1e-3, 0.2)
    x0 = torch.tensor([0.1, -0.5], dtype=torch.float64)
    with torch.no_grad():
        ref = simulate(model, t, u, x0)
    q, qd = module.simulate(t, u, x0)
    sim = torch.stack([q, qd], dim=-1)
    assert float(ref[:, 1].abs().max()) > 0.1  # the input really moves the arm
    assert rel_diff(sim, ref) < RTOL
    # The module's vector field and friction curve are the model's.
    x = torch.randn(64, 2, dtype=torch.float64) * torch.tensor([2.0, 3.0], dtype=torch.float64)
    uu = torch.randn(64, dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(
            module.field(x, uu), model.vector_field(x, uu), rtol=1e-12, atol=0
        )
        v = torch.linspace(-4.0, 4.0, 81, dtype=torch.float64)
        torch.testing.assert_close(module.friction(v), model.friction_torque(v), rtol=1e-12, atol=0)
    assert module.parameters_by_name == model.physical_parameters()


def test_export_keeps_the_asymmetric_term(tmp_path: pathlib.Path) -> None:
    """The term the first exporter dropped: a·|q̇| must act on the exported simulation."""
    with_a = make_arm("tanh", asymmetric=True, offset=True)
    params = with_a.physical_parameters()
    params["asymmetric"] = 0.0
    without_a = make_arm("tanh", asymmetric=True, offset=True)
    without_a.set_theta(without_a.from_physical(torch.tensor(list(params.values()))))
    t, u = excitation(600, 1e-3, 0.2)
    x0 = torch.zeros(2, dtype=torch.float64)
    a = round_trip(export_model(with_a, dt=1e-3), tmp_path, "a.pt").simulate(t, u, x0)[0]
    b = round_trip(export_model(without_a, dt=1e-3), tmp_path, "b.pt").simulate(t, u, x0)[0]
    with torch.no_grad():
        ref = simulate(with_a, t, u, x0)[:, 0]
    assert float((a - ref).abs().max()) <= RTOL * float(ref.abs().max())
    assert float((a - b).abs().max()) > 1e-3 * float(ref.abs().max())  # the term matters here


def stiff_arm() -> ArmModel:
    """A sharp Coulomb corner: auto_substeps is 1 at 0.2 ms and rises with the sample time."""
    friction = make_friction("coulomb", 1, fc=0.05, eps=2e-3)
    return ArmModel(friction, inertia=0.03, viscous=0.01, c_m=2.0, offset=0.01, asymmetric=0.003)


@pytest.mark.parametrize("dt", [2e-4, 1e-3, 4e-3, 1.7e-2, 5e-2])
def test_export_simulates_at_any_sample_time(dt: float, tmp_path: pathlib.Path) -> None:
    """Exported for 1 ms data, called at another sample time: the sub-steps follow the dt passed
    in (`auto_substeps`' rule), so the result is torchfric.models.simulate's at that dt."""
    model = stiff_arm()
    module = round_trip(export_model(model, dt=1e-3), tmp_path)
    assert module.nominal_dt == 1e-3
    t, u = excitation(300, dt, 0.15)
    x0 = torch.tensor([0.0, 0.2], dtype=torch.float64)
    assert module.substeps_for(t) == auto_substeps(model, dt)
    with torch.no_grad():
        ref = simulate(model, t, u, x0)
    sim = torch.stack(module.simulate(t, u, x0), dim=-1)
    assert torch.isfinite(sim).all()
    assert rel_diff(sim, ref) < RTOL


def test_substep_rule_is_auto_substeps(tmp_path: pathlib.Path) -> None:
    model = stiff_arm()
    module = export_model(model, dt=1e-3)
    counts = set()
    for dt in torch.logspace(-5, 0, 60, dtype=torch.float64).tolist():
        t = torch.tensor([0.0, dt, 2 * dt], dtype=torch.float64)
        counts.add(module.substeps_for(t))
        assert module.substeps_for(t) == auto_substeps(model, dt), dt
    assert min(counts) == 1 and max(counts) == 64 and len(counts) > 10
    # Non-uniform times: the longest interval decides, as in simulate.
    t = torch.tensor([0.0, 1e-3, 2e-3, 2e-2], dtype=torch.float64)
    assert module.substeps_for(t) == auto_substeps(model, 18e-3)


def test_fixed_substeps_and_other_solvers(tmp_path: pathlib.Path) -> None:
    model = make_arm("stribeck", offset=True, gravity=True, asymmetric=True)
    t, u = excitation(400, 2e-3, 0.2)
    x0 = torch.tensor([0.3, 0.0], dtype=torch.float64)
    for method in SOLVERS:
        for substeps in ("auto", 3):
            module = round_trip(
                export_model(model, dt=2e-3, substeps=substeps, method=method), tmp_path
            )
            with torch.no_grad():
                ref = simulate(model, t, u, x0, method=method, substeps=substeps)
            assert rel_diff(torch.stack(module.simulate(t, u, x0), -1), ref) < RTOL, (
                method,
                substeps,
            )
    with pytest.raises(TorchfricError, match="substeps must be"):
        export_model(model, substeps=0)
    with pytest.raises(TorchfricError, match="unknown solver"):
        export_model(model, method="dopri5")


def test_batch_simulation(tmp_path: pathlib.Path) -> None:
    model = make_arm("polytopic", viscous=False, offset=True, asymmetric=True)
    module = round_trip(export_model(model, dt=1e-3), tmp_path)
    t, u1 = excitation(300, 1e-3, 0.2)
    u = torch.stack([u1, -0.5 * u1, 0.3 * u1.flip(0)], dim=1)
    x0 = torch.tensor([[0.0, 0.0], [0.1, 0.4], [-0.2, -1.0]], dtype=torch.float64)
    with torch.no_grad():
        ref = simulate(model, t, u, x0)
    out = module.simulate_batch(t, u, x0)
    assert out.shape == ref.shape == (300, 3, 2)
    assert rel_diff(out, ref) < RTOL


def test_bad_inputs_are_refused(tmp_path: pathlib.Path) -> None:
    module = round_trip(export_model(make_arm("tanh"), dt=1e-3), tmp_path)
    t = torch.arange(10, dtype=torch.float64) * 1e-3
    u = torch.zeros(10, dtype=torch.float64)
    x0 = torch.zeros(2, dtype=torch.float64)
    with pytest.raises(Exception, match="strictly increasing"):
        module.simulate(t.flip(0), u, x0)
    with pytest.raises(Exception, match="one input per sample"):
        module.simulate(t, u[:5], x0)
    with pytest.raises(Exception, match="end in 2 entries"):
        module.simulate(t, u, torch.zeros(3, dtype=torch.float64))


def test_exported_asymmetric_model_runs_without_torchfric(tmp_path: pathlib.Path) -> None:
    model = make_arm("tanh", offset=True, gravity=True, asymmetric=True)
    path = tmp_path / "arm.ts"
    save_exported(export_model(model, dt=1e-3), path)
    t, u = excitation(300, 5e-3, 0.2)  # not the export's 1 ms
    x0 = torch.tensor([0.05, 0.0], dtype=torch.float64)
    with torch.no_grad():
        ref = simulate(model, t, u, x0)
    torch.save({"t": t, "u": u, "x0": x0}, tmp_path / "inputs.pt")
    script = textwrap.dedent(
        f"""
        import sys
        sys.modules["torchfric"] = None  # any import of torchfric now fails
        import torch
        m = torch.jit.load({str(path)!r})
        d = torch.load({str(tmp_path / "inputs.pt")!r})
        q, qd = m.simulate(d["t"], d["u"], d["x0"])
        torch.save(torch.stack([q, qd], -1), {str(tmp_path / "out.pt")!r})
        """
    )
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120)
    out = torch.load(tmp_path / "out.pt")
    assert rel_diff(out, ref) < RTOL
