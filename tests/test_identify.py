"""Parameter recovery by the iterative EKF (`identify_ekf`) on seeded synthetic data.

The data come from the project's own model class: an `ArmModel` with known θ (tanh(3) with
viscous friction, and polytopic(3)) simulated by `torchfric.models.simulate` under the first 3 s of the
rig's identification excitation (seed 2: one move segment up to ≈ 10 rad/s with a slow reversal,
so 0.2–1 rad/s, 1–3 rad/s and > 3 rad/s each hold ≈ 800 samples), positions quantised to the
rig's encoder (2e-4 rad), velocity reconstructed by the paper's high-pass differentiator. The
filter starts from a perturbed θ (inertia +20 %, friction parameters ±30 %) and runs 3 passes
with the paper's tuning. (The rig's own LuGre data and the 1 % / FIT targets are the benchmark's
job: 30 s × 10 passes do not fit a test budget.)

What is checked, with the measured values (3000 samples, 3 passes):

=========  ==============  ========================================  ====================
model      inertia error   friction RMS error, |v| ≥ 0.2 rad/s       start → identified
=========  ==============  ========================================  ====================
tanh(3)    0.41 %          1.14 % of peak (max 3.0 %)                3.3 % → 1.1 %
polytopic  0.03 %          1.10 % of peak (max 8.7 %, Stribeck dip)  15.4 % → 1.1 %
=========  ==============  ========================================  ====================

Below 0.2 rad/s = one encoder count per sample the reconstructed velocity is quantisation noise,
so friction there is not identifiable from these data and is not checked. The tolerances
(inertia 1.5 %, friction RMS 2.5 % of peak) leave about twice the measured error: over thousands
of samples the filter's ill-conditioned P (cond ≈ 1e12) makes results platform-dependent at the
percent level.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchfric.data.experiment import Experiment, make_experiment
from torchfric.data.rig import RigParameters, excitation
from torchfric.estimators.identify import EKFTuning, identify_ekf
from torchfric.models.arm import ArmModel
from torchfric.models.friction import OddTanhFriction, PolytopicFriction
from torchfric.models.simulate import simulate

pytestmark = pytest.mark.slow

N_SAMPLES = 3000
V_MIN = 0.2  # rad/s: quantum / dt, below it q̇ is quantisation noise


def _true_model(kind: str) -> ArmModel:
    if kind == "tanh":
        # Slopes from almost viscous to a sharp Coulomb-like neuron; peak friction ≈ 0.29 N m.
        friction = OddTanhFriction(3, w1=[0.5, 5.0, 50.0], w2=[0.04, 0.05, 0.1])
        return ArmModel(friction, inertia=0.0292, viscous=0.01, c_m=16.0)
    # Centre model: steep near zero; mirrored pair at ±2 rad/s with offset 0.17 N m and a
    # viscous slope; a Stribeck-like dip near 0.5 rad/s; 0.25 N m at 10 rad/s. No separate b.
    friction = PolytopicFriction(3, a=[1.0, 0.01], b=[0.17], c=[2.0], sigma=[0.05, 4.0])
    return ArmModel(friction, inertia=0.0292, viscous=None, c_m=16.0)


def _perturbed(model: ArmModel) -> ArmModel:
    """Inertia +20 %; every friction parameter (and b) scaled by 0.7 / 1.3 alternately."""
    start = ArmModel.from_spec(model.spec())
    theta = start.get_theta()
    mask = start.log_mask()
    for i, name in enumerate(start.theta_names):
        factor = 1.2 if name == "inertia" else (1.3 if i % 2 else 0.7)
        theta[i] = theta[i] + math.log(factor) if bool(mask[i]) else theta[i] * factor
    return start.set_theta(theta)


def _data(model: ArmModel) -> Experiment:
    rig = RigParameters()
    u = torch.as_tensor(excitation("identification", duration=30.0, seed=2)[:N_SAMPLES])
    t = torch.arange(N_SAMPLES) * rig.dt
    with torch.no_grad():
        x = simulate(model, t, u, torch.zeros(2))
    q = torch.round(x[:, 0] / rig.quantum) * rig.quantum
    return make_experiment(t, u, q, name="synthetic").with_velocity()


def _friction_error(true: ArmModel, other: ArmModel, exp: Experiment) -> tuple[float, float]:
    """RMS and max |F̂ − F| over the excited samples with |q̇| ≥ V_MIN, relative to the peak."""
    v = exp.qdot[exp.qdot.abs() >= V_MIN]
    with torch.no_grad():
        f_true = true.friction_torque(v)
        err = (other.friction_torque(v) - f_true) / f_true.abs().max()
    return float(err.pow(2).mean().sqrt()), float(err.abs().max())


@pytest.mark.parametrize("kind", ["tanh", "polytopic"])
def test_ekf_recovers_inertia_and_friction_curve(kind: str) -> None:
    true = _true_model(kind)
    exp = _data(true)
    assert float(exp.qdot.abs().max()) > 9.0  # the excitation reaches the design peak
    start = _perturbed(true)
    true_inertia = float(true.inertia.detach())
    rms0, _ = _friction_error(true, start, exp)

    result = identify_ekf(start, exp, EKFTuning(passes=3, tolerance=0.0))

    assert result.passes == 3
    inertia_error = float(result.model.inertia.detach()) / true_inertia - 1.0
    # measured: +0.41 % (tanh), +0.03 % (polytopic); the start is +20 %.
    assert abs(inertia_error) < 0.015, inertia_error
    rms, worst = _friction_error(true, result.model, exp)
    # measured: RMS 1.14 % / 1.10 %, max 3.0 % / 8.7 % of peak; the start is 3.3 % / 15.4 %.
    assert rms < 0.025, (rms, worst)
    assert rms < 0.5 * rms0, (rms, rms0)
    assert worst < (0.06 if kind == "tanh" else 0.15), worst
    # The per-pass diagnostics tell the same story: the innovations shrink from pass 1 to 3.
    first, last = result.history[0], result.history[-1]
    assert last.innovation_rms[0] < first.innovation_rms[0]
    assert last.loglik > first.loglik
    assert last.trace_P_theta < first.trace_P_theta
