"""LuGre dynamic friction (`model.dynamic = "lugre"`, torchfric.models.lugre): the model against
the synthetic rig's own LuGre simulator, the positivity and oddness of its sliding curve for any
parameters, the exactness of its step in steady sliding, the EKF's transition Jacobian, the
compiled engine and its gradient, the export, checkpoints and the config keys."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import torchfric.accel  # noqa: F401  (registers the "compiled" engine)
from torchfric.data.rig import RigParameters, excitation, simulate_rig
from torchfric.errors import TorchfricError
from torchfric.estimators.ekf import make_propagator
from torchfric.models import ArmModel, make_friction, simulate
from torchfric.models.lugre import bristle_solve, sliding_curve, sliding_level
from torchfric.models.torchscript import export_model

F64 = torch.float64


def true_model(p: RigParameters) -> ArmModel:
    """The rig's own system as a torchfric model: LuGre around its Stribeck curve (the
    Stribeck module's tanh(v/ε) with ε = 1e-8 is 1 from the stick velocity 1e-6 on, so g is
    the rig's g to rounding)."""
    fr = make_friction("stribeck", 1, fc=p.Fc, fs=p.Fs, vs=p.vs, eps=1e-8)
    return ArmModel(fr, inertia=p.inertia, viscous=p.sigma2, c_m=p.c_m, dynamic="lugre",
                    sigma0=p.sigma0, sigma1=p.sigma1, stick_velocity=1e-6)  # fmt: skip


def random_tanh(seed: int, size: int = 4) -> ArmModel:
    g = torch.Generator().manual_seed(seed)
    w1 = torch.randn(size, generator=g, dtype=F64) * 5
    w2 = torch.randn(size, generator=g, dtype=F64) * 0.3
    fr = make_friction("tanh", size, w1=w1, w2=w2)
    return ArmModel(fr, inertia=0.03, viscous=0.01, c_m=2.0, dynamic="lugre",
                    sigma0=float(10 ** (2 + 3 * torch.rand(1, generator=g))), sigma1=3.0,
                    stick_velocity=float(10 ** (-3 + 2 * torch.rand(1, generator=g))))  # fmt: skip


@pytest.fixture(scope="module")
def rig_run():
    """A 4 s record of the rig without disturbance, integrated with 100 sub-steps per sample
    (10x the rig's own: a reference close to the exact solution)."""
    p = dataclasses.replace(RigParameters(), disturbance_std=0.0)
    u = excitation("validation", duration=4.0, seed=3)
    return p, u, simulate_rig(dataclasses.replace(p, substeps=100), u, seed=0)


def _simulated(p: RigParameters, u: np.ndarray, substeps: int | str):
    t = torch.arange(u.size, dtype=F64) * p.dt
    with torch.no_grad():
        return simulate(true_model(p), t, torch.tensor(u), torch.zeros(2, dtype=F64),
                        substeps=substeps, engine="compiled")  # fmt: skip


def test_true_curve_reproduces_the_rig_simulator(rig_run):
    p, u, ref = rig_run
    q, v = torch.tensor(ref["q_true"]), torch.tensor(ref["qdot_true"])
    # the rig was stuck and slid in this record: pre-sliding and sliding are both tested
    assert (np.abs(ref["qdot_true"]) < 1e-6).mean() > 0.05
    assert np.abs(ref["qdot_true"]).max() > 3.0
    # two different second-order schemes converge to the same solution: at the same fine step
    # they agree to 3e-7 rad over the whole record (1/600 of an encoder count)
    fine = _simulated(p, u, 100)
    assert float((fine[:, 0] - q).abs().max()) < 1e-6
    assert float((fine[:, 1] - v).abs().max()) < 1e-4
    # at the rig's own sub-step (0.1 ms) within 0.2 counts of the reference (measured 2.8e-5)
    assert float((_simulated(p, u, 10)[:, 0] - q).abs().max()) < 0.2 * p.quantum


def test_auto_substeps_stay_close_to_the_rig(rig_run):
    p, u, ref = rig_run
    x = _simulated(p, u, "auto")  # 2 sub-steps per ms on the rig
    q = ref["q_true"]
    fit = 100 * (1 - np.linalg.norm(x[:, 0].numpy() - q) / np.linalg.norm(q - q.mean()))
    assert fit > 99.9


@pytest.mark.parametrize("seed", range(6))
def test_sliding_curve_positive_and_odd_for_random_parameters(seed):
    model = random_tanh(seed)
    fric, arm = model.split(model.get_theta())
    vs = arm["lugre_vstick"]
    v = torch.cat([torch.zeros(1, dtype=F64), torch.logspace(-9, 3, 400, dtype=F64)])
    g = sliding_level(model.friction, v, fric, vs)
    assert bool((g > 0).all()) and bool(torch.isfinite(g).all())
    assert torch.equal(g, sliding_level(model.friction, -v, fric, vs))  # even
    s = sliding_curve(model.friction, v, fric, vs)
    assert torch.equal(s, -sliding_curve(model.friction, -v, fric, vs))  # odd
    assert float(s[0]) == 0.0
    # the steady state is |C(v)| for v >= v_s (C where C has v's sign, its mirror where a random
    # C has not; ε = 1e-9 shifts it by ε²/2|C| < 1e-14 where |C| > 1e-4), held at |C(v_s)| below
    c = model.friction.evaluate(v, fric)
    above = (v >= vs) & (c.abs() > 1e-4)
    assert int(above.sum()) > 50
    torch.testing.assert_close(s[above], c[above].abs(), rtol=1e-12, atol=0.0)
    below = (v > 0) & (v < vs)
    c_vs = model.friction.evaluate(vs.reshape(1), fric).abs()
    torch.testing.assert_close(s[below], c_vs.expand(int(below.sum())), rtol=1e-12, atol=1e-15)
    # the bristles stop relaxing at rest, σ0 |v| / g(v) -> 0 linearly (the condition for
    # sticking): below v_s the rate over |v| is the constant σ0 / g(0)
    rate = arm["lugre_sigma0"] * v / g
    assert float(rate[0]) == 0.0
    slope = (arm["lugre_sigma0"] / g[0]).expand(int(below.sum()))
    torch.testing.assert_close(rate[below] / v[below], slope, rtol=1e-12, atol=0.0)


def test_the_model_sticks_below_breakaway():
    """Under a slow torque below its static friction (0.9 Fs, 0.5 Hz) the LuGre model follows
    the rig's pre-sliding loop (2.3 bristle ranges Fs/σ0 at most, back to 0.03 of one after a
    period) to 1e-7 rad: it sticks. Read at |q̇| alone, g(0) = 0 would let it creep 11 mrad."""
    p = dataclasses.replace(RigParameters(), disturbance_std=0.0)
    t = torch.arange(2000, dtype=F64) * 1e-3
    u = 0.9 * p.Fs / p.c_m * torch.sin(2 * math.pi * 0.5 * t)
    with torch.no_grad():
        x = simulate(true_model(p), t, u, torch.zeros(2, dtype=F64), engine="compiled")
    rig = torch.tensor(simulate_rig(p, u.numpy(), seed=0)["q_true"])
    assert float((x[:, 0] - rig).abs().max()) < 2e-7
    assert float(x[:, 0].abs().max()) < 3 * p.Fs / p.sigma0
    assert abs(float(x[-1, 0])) < 0.1 * p.Fs / p.sigma0


def test_steady_sliding_is_a_fixed_point_of_the_step():
    model = random_tanh(1, size=3)
    theta = model.get_theta()
    fric, arm = model.split(theta)
    for v in (0.3, 2.0, -7.0):
        vt = torch.tensor(v, dtype=F64)
        z = sliding_curve(model.friction, vt, fric, arm["lugre_vstick"]) / arm["lugre_sigma0"]
        total = float(model.friction_torque(vt, theta))
        u = torch.tensor(total / float(arm["c_m"]), dtype=F64)  # balances the steady friction
        x = torch.stack([torch.tensor(0.0, dtype=F64), vt, z])
        for h in (1e-4, 1e-3, 1e-2):
            x1 = model.substep(x, u, h, fric, arm)
            assert abs(float(x1[1]) - v) < 1e-12 * max(1.0, abs(v))
            assert abs(float(x1[2] - z)) < 1e-12 * abs(float(z))
            assert math.isclose(float(x1[0]), v * h, rel_tol=1e-12)


def test_bristle_solve_is_exact_for_the_frozen_rate():
    """With M huge (v constant) and σ1 = b = 0, ż = v − a z has z(h) = z e^{−ah} + v(1 − e^{−ah})/a,
    on both sides of the series threshold (a h = 1e-2) and far beyond it (a h = 1e3). Below the
    threshold the truncated series errs by about x⁵/720 (2e-13 at x = 1e-2), hence 1e-12."""
    one = torch.tensor(1.0, dtype=F64)
    for ah in (1e-6, 9.99e-3, 1.001e-2, 0.7, 30.0, 1e3):
        h = torch.tensor(1e-3, dtype=F64)
        a = torch.tensor(ah / 1e-3, dtype=F64)
        x = torch.tensor([0.0, 0.4, -2e-4], dtype=F64)
        v1, z1 = bristle_solve(x, 0 * one, a, h, 1e-30 * one, 0 * one, 1e30 * one)
        x_ = float(a * h)
        exact = -2e-4 * math.exp(-x_) + 0.4e-3 * (-math.expm1(-x_)) / x_
        assert math.isclose(float(z1), exact, rel_tol=1e-12, abs_tol=0.0)
        assert float(v1) == 0.4


def test_ekf_transition_jacobian_matches_finite_differences():
    model = random_tanh(2, size=3)
    flow = make_propagator(model, 2)
    n = 3 + model.num_parameters
    z = torch.cat([torch.tensor([0.1, 0.8, 1e-4], dtype=F64), model.get_theta()])
    u, dt = torch.tensor(0.05, dtype=F64), torch.tensor(1e-3, dtype=F64)
    x1, Phi = flow(z, u, dt)
    assert Phi.shape == (3, n)
    for j in range(n):
        e = torch.zeros(n, dtype=F64)
        step = 1e-6 * max(1.0, abs(float(z[j])))
        e[j] = step
        fd = (flow(z + e, u, dt)[0] - flow(z - e, u, dt)[0]) / (2 * step)
        torch.testing.assert_close(Phi[:, j], fd, rtol=1e-5, atol=1e-9)


def test_compiled_engine_and_its_gradient_match_the_reference_loop():
    model = random_tanh(3, size=3)
    t = torch.arange(400, dtype=F64) * 1e-3
    u = 0.2 * torch.sin(torch.arange(400, dtype=F64) * 0.02)
    x0 = torch.tensor([0.0, 0.5], dtype=F64)
    theta_a = model.get_theta().requires_grad_(True)
    theta_b = model.get_theta().requires_grad_(True)
    xa = simulate(model, t, u, x0, theta=theta_a, substeps=2, engine="odeint")
    xb = simulate(model, t, u, x0, theta=theta_b, substeps=2, engine="compiled")
    torch.testing.assert_close(xa, xb, rtol=1e-10, atol=1e-12)
    (ga,) = torch.autograd.grad((xa[:, 0] ** 2).sum(), theta_a)
    (gb,) = torch.autograd.grad((xb[:, 0] ** 2).sum(), theta_b)
    torch.testing.assert_close(ga, gb, rtol=1e-8, atol=1e-12)


def test_export_simulates_as_simulate(tmp_path):
    model = random_tanh(4, size=3)
    t = torch.arange(600, dtype=F64) * 1e-3
    u = 0.3 * torch.sign(torch.sin(torch.arange(600, dtype=F64) * 0.01))
    x0 = torch.tensor([0.2, 0.0], dtype=F64)
    module = export_model(model, dt=1e-3)
    q, qd = module.simulate(t, u, x0)
    with torch.no_grad():
        ref = simulate(model, t, u, x0)
        v = torch.linspace(-8, 8, 33, dtype=F64)
        curve = model.friction_torque(v)
    torch.testing.assert_close(q, ref[:, 0], rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(qd, ref[:, 1], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(module.friction(v), curve, rtol=1e-14, atol=1e-15)


def test_spec_round_trip_and_static_twin():
    model = random_tanh(5, size=2)
    again = ArmModel.from_spec(model.spec())
    assert again.dynamic == "lugre" and again.theta_names == model.theta_names
    torch.testing.assert_close(again.get_theta(), model.get_theta(), rtol=1e-15, atol=0)
    static = model.static_twin()
    assert static.state_size == 2 and "dynamic" not in static.spec()
    assert static.theta_names == model.theta_names[:-3]
    back = model.with_static(static)
    torch.testing.assert_close(back.get_theta(), model.get_theta(), rtol=0, atol=0)


def test_bad_dynamic_values_are_refused():
    with pytest.raises(TorchfricError, match="dynamic = 'dahl' is not known"):
        ArmModel(make_friction("tanh", 2), dynamic="dahl")
    with pytest.raises(TorchfricError, match="sigma0 must be > 0"):
        ArmModel(make_friction("tanh", 2), dynamic="lugre", sigma0=0.0)


def test_filter_health_reads_theta_after_the_bristle_state():
    """The EKF's box check and its message see θ after [q, q̇, z]: a large z is not a parameter,
    and a parameter out of the box is named by its own index."""
    from torchfric.estimators.ekf import EKFState, Innovation, _check, healthy

    model = random_tanh(6, size=2)
    flow = make_propagator(model, 1)
    assert flow.states == 3
    n = 3 + model.num_parameters
    P = torch.eye(n, dtype=F64)
    inn = Innovation(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64),
                     torch.tensor(1.0, dtype=F64), torch.tensor(0.0, dtype=F64))  # fmt: skip
    bound = torch.tensor(1e6, dtype=F64)
    x = torch.cat([torch.tensor([0.0, 0.0, 2e6], dtype=F64), model.get_theta()])
    assert (
        bool(healthy(EKFState(x, P), inn, bound, 3)) and _check(EKFState(x, P), inn, 1e6, 3) is None
    )
    x[3 + 1] = 3e6  # θ[1]
    assert not bool(healthy(EKFState(x, P), inn, bound, 3))
    assert _check(EKFState(x, P), inn, 1e6, 3).startswith("parameter 1 left the box")
