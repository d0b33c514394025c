"""The synthetic rig (torchfric.data.rig): integrator accuracy, LuGre physics, experiments, files."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from scipy.optimize import brentq

from torchfric.data import rig
from torchfric.errors import TorchfricError

NOMINAL = rig.RigParameters()
QUIET = dataclasses.replace(NOMINAL, disturbance_std=0.0)  # deterministic physics checks


def reversals(v: np.ndarray, threshold: float = 0.05) -> int:
    """Sign changes of the velocity, with hysteresis ±threshold [rad/s] against chatter."""
    state, count = 0, 0
    for x in v:
        if x > threshold:
            count += state == -1
            state = 1
        elif x < -threshold:
            count += state == 1
            state = -1
    return count


def stick_phases(v: np.ndarray, threshold: float = 1e-3, min_samples: int = 100) -> int:
    """Runs of at least `min_samples` samples (100 ms) with |v| < threshold: the arm at rest."""
    still = np.r_[0, (np.abs(v) < threshold).astype(int), 0]
    edges = np.diff(still)
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return int(np.sum(ends - starts >= min_samples))


# --- parameters ------------------------------------------------------------------------------


def test_parameters_are_physical_and_changed_system_drops_static_friction() -> None:
    p = NOMINAL
    assert p.Fs / p.sigma0 == pytest.approx(p.quantum)  # pre-sliding range = one encoder count
    zeta = p.sigma1 / (2.0 * math.sqrt(p.sigma0 * p.inertia))
    assert 0.7 <= zeta <= 1.2  # well-damped bristles
    assert 0.01 <= p.disturbance_std / p.Fc <= 0.05  # "a few % of Fc"
    c = p.changed()
    assert c.Fs == c.Fc == p.Fc
    assert dataclasses.replace(c, Fs=p.Fs) == p  # everything else equal
    assert rig.RigParameters(**p.to_dict()) == p
    with pytest.raises(TorchfricError, match="Fs"):
        rig.RigParameters(Fs=0.1)  # below Fc
    with pytest.raises(TorchfricError, match="substeps"):
        rig.RigParameters(substeps=0)
    with pytest.raises(TorchfricError, match="sigma0"):
        rig.RigParameters(sigma0=-1.0)


def test_steady_state_friction_numpy_and_torch_agree() -> None:
    v = np.array([-20.0, -1.0, -0.1, 0.0, 0.1, 0.5, 10.0])
    f_np = NOMINAL.steady_state_friction(v)
    f_t = NOMINAL.steady_state_friction(torch.tensor(v))
    assert isinstance(f_np, np.ndarray) and isinstance(f_t, torch.Tensor)
    np.testing.assert_allclose(f_t.numpy(), f_np, rtol=1e-14)
    assert f_np[3] == 0.0
    np.testing.assert_allclose(NOMINAL.steady_state_friction(-v), -f_np)  # odd
    assert NOMINAL.steady_state_friction(np.array([1e-9]))[0] == pytest.approx(NOMINAL.Fs)
    assert NOMINAL.steady_state_friction(np.array([10.0]))[0] == pytest.approx(0.25, abs=1e-12)


def test_changed_system_has_no_stribeck_peak() -> None:
    v = np.linspace(1e-6, 20.0, 4001)
    nominal = NOMINAL.steady_state_friction(v)
    changed = NOMINAL.changed().steady_state_friction(v)
    assert np.all(np.diff(changed) > 0)  # monotone: Coulomb + viscous only
    assert changed[0] == pytest.approx(NOMINAL.Fc)
    assert np.any(np.diff(nominal) < 0)  # the nominal curve dips after the static peak
    assert nominal[0] - nominal.min() > 0.08  # Stribeck dip: 0.25 → 0.16 N m near 1 rad/s


# --- integrator -------------------------------------------------------------------------------


def test_integrator_matches_10x_finer_reference_with_second_order_convergence() -> None:
    # 5 s of the identification input: a stick phase, breakaway, a 10 rad/s swing and reversals.
    u = rig.rig_experiment("identification")["u"][:5000]
    runs = {
        ns: rig.simulate_rig(dataclasses.replace(NOMINAL, substeps=ns), u, seed=3)
        for ns in (5, 10, 100)
    }
    ref = runs[100]
    assert np.abs(ref["qdot_true"]).max() > 9.0
    err = {
        ns: (
            np.abs(runs[ns]["q_true"] - ref["q_true"]).max(),
            np.abs(runs[ns]["qdot_true"] - ref["qdot_true"]).max(),
        )
        for ns in (5, 10)
    }
    # Default 10 sub-steps: measured 4e-6 rad (0.02 encoder count) and 1.9e-5 rad/s.
    assert err[10][0] < 2e-5
    assert err[10][1] < 1e-4
    # Second order: halving the sub-step divides the error by ≈ 4 (measured 4.5 and 4.1).
    assert err[5][0] / err[10][0] > 3.0
    assert err[5][1] / err[10][1] > 3.0


def test_state_outputs_are_consistent() -> None:
    u = rig.excitation("validation", duration=2.0, seed=4)
    r = rig.simulate_rig(NOMINAL, u, seed=1, x0=(0.3, 0.0, 0.0))
    n = u.size
    assert set(r) >= {"t", "u", "q_true", "qdot_true", "z", "friction", "q"}
    assert all(a.shape == (n,) for a in r.values())
    np.testing.assert_array_equal(r["t"], np.arange(n) * 1e-3)
    assert r["q_true"][0] == 0.3
    # q is the integral of q̇ (trapezoid over samples, up to the sub-step curvature).
    q_int = 0.3 + np.r_[0.0, np.cumsum(0.5 * (r["qdot_true"][1:] + r["qdot_true"][:-1]) * 1e-3)]
    assert np.abs(q_int - r["q_true"]).max() < 1e-4
    # The friction follows the LuGre output equation.
    g = NOMINAL.Fc + (NOMINAL.Fs - NOMINAL.Fc) * np.exp(-((r["qdot_true"] / NOMINAL.vs) ** 2))
    zdot = r["qdot_true"] - NOMINAL.sigma0 * np.abs(r["qdot_true"]) * r["z"] / g
    f = NOMINAL.sigma0 * r["z"] + NOMINAL.sigma1 * zdot + NOMINAL.sigma2 * r["qdot_true"]
    np.testing.assert_allclose(r["friction"], f, atol=1e-12)
    assert np.std(r["disturbance"]) == pytest.approx(NOMINAL.disturbance_std, rel=1e-9)
    # Band-limited (10 Hz at 1 kHz): neighbouring samples almost equal.
    d = r["disturbance"]
    assert np.corrcoef(d[1:], d[:-1])[0, 1] > 0.99


# --- LuGre physics ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("params", "torque"),
    [(QUIET, 0.30), (QUIET, -0.27), (QUIET.changed(), 0.20)],
    ids=["nominal+", "nominal-", "changed"],
)
def test_constant_input_settles_at_steady_state_friction_velocity(params, torque) -> None:
    v_star = math.copysign(
        brentq(lambda v: float(params.steady_state_friction(np.array(v))) - abs(torque), 2.0, 1e3),
        torque,
    )
    # Start in sliding at 0.9 v*: beyond the Stribeck region the linearised velocity error decays
    # as exp(-σ2 t / M) (dF_ss/dv = σ2, M/σ2 = 2.9 s), i.e. 0.1 |v*| e^{-15/2.92} ≈ 0.6e-3 |v*|
    # after 15 s; the tolerance is twice that bound (the integrator's steady state is exact).
    v0 = 0.9 * v_star
    x0 = (0.0, v0, float(np.sign(v0) * params.stribeck(np.array(v0)) / params.sigma0))
    duration = 15.0
    r = rig.simulate_rig(params, np.full(15000, torque / params.c_m), seed=0, x0=x0)
    bound = 0.1 * abs(v_star) * math.exp(-params.sigma2 * duration / params.inertia)
    assert abs(r["qdot_true"][-1] - v_star) < 2.0 * bound
    assert abs(r["qdot_true"][-1] - v_star) > 0.2 * bound  # still approaching, from below
    assert abs(r["friction"][-1] - torque) < 2.0 * params.sigma2 * bound + 1e-9


def test_constant_input_from_rest_above_static_friction_breaks_away() -> None:
    r = rig.simulate_rig(QUIET, np.full(3000, 0.3 / QUIET.c_m), seed=0)
    assert r["qdot_true"][-1] > 2.0


@pytest.mark.parametrize("fraction", [0.5, 0.8])
def test_input_below_static_friction_sticks_with_presliding_only(fraction) -> None:
    torque = fraction * QUIET.Fs
    r = rig.simulate_rig(QUIET, np.full(2000, torque / QUIET.c_m), seed=0)
    pre = QUIET.Fs / QUIET.sigma0
    assert abs(r["qdot_true"][-1]) < 1e-9  # at rest
    assert np.all(np.abs(r["q_true"]) < 3.0 * pre)  # pre-sliding displacement only
    assert r["q_true"][-1] > 0.3 * pre  # ... which is there (the bristles deflect)
    assert r["friction"][-1] == pytest.approx(torque, rel=1e-9)  # friction balances the input
    # The changed system (no static friction) slides under the same input when it exceeds Fc.
    if torque > QUIET.Fc:
        c = rig.simulate_rig(QUIET.changed(), np.full(2000, torque / QUIET.c_m), seed=0)
        assert c["qdot_true"][-1] > 0.5


def test_presliding_hysteresis_is_rate_independent() -> None:
    """Friction vs displacement under a slow oscillating force below Fs encloses a loop."""
    areas = []
    for freq in (0.25, 0.5):
        n = int(round(2.0 / freq / QUIET.dt)) + 1
        t = np.arange(n) * QUIET.dt
        u = 0.5 * QUIET.Fs / QUIET.c_m * np.sin(2.0 * np.pi * freq * t)
        r = rig.simulate_rig(QUIET, u, seed=0)
        f, q = r["friction"][n // 2 :], r["q_true"][n // 2 :]  # the second period
        area = float(np.trapezoid(f, q))  # ∮ F dq = energy dissipated in one cycle
        box = float(np.ptp(f) * np.ptp(q))
        assert np.ptp(q) < 2.0 * QUIET.Fs / QUIET.sigma0  # pre-sliding, no gross sliding
        assert area / box > 0.1  # a loop, not a single-valued curve F(q) (measured 0.19)
        areas.append(area)
    # Viscous-like (rate-dependent) loss would double with the frequency; LuGre's is ≈ equal.
    assert areas[1] / areas[0] == pytest.approx(1.0, abs=0.2)


def test_quantisation_rounds_to_nearest_count() -> None:
    r = rig.rig_experiment("identification")
    quantum = NOMINAL.quantum
    assert np.all(np.abs(r["q"] - r["q_true"]) <= quantum / 2 + 1e-12)
    counts = r["q"] / quantum
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-6)
    assert np.unique(np.round(counts)).size > 100


# --- experiments ------------------------------------------------------------------------------


def test_experiments_meet_their_velocity_specs() -> None:
    runs = {name: rig.rig_experiment(name, seed=0) for name in rig.EXPERIMENTS}
    peak = {name: float(np.abs(r["qdot_true"]).max()) for name, r in runs.items()}
    assert peak["identification"] == pytest.approx(10.0, rel=0.15)
    assert 0.5 * peak["identification"] < peak["validation"] <= peak["identification"]
    assert peak["extrapolation"] / peak["identification"] == pytest.approx(1.6, rel=0.15)
    assert peak["changed_validation"] <= peak["changed_identification"]
    for name, duration in (("identification", 30.0), ("validation", 20.0)):
        assert runs[name]["t"].size == int(duration * 1000)
        # The changed system gets the same input as the nominal one.
        np.testing.assert_array_equal(runs[name]["u"], runs[f"changed_{name}"]["u"])
    assert runs["extrapolation"]["t"].size == 20000
    assert not np.array_equal(runs["identification"]["u"][:20000], runs["validation"]["u"])
    # Many reversals and stick phases (seed 0 measures 25/16, 11/11, 15/10, 25/15, 11/10).
    minimum = {"identification": (15, 10), "changed_identification": (15, 10)}
    for name, r in runs.items():
        n_rev, n_stick = minimum.get(name, (8, 6))
        assert reversals(r["qdot_true"]) >= n_rev, name
        assert stick_phases(r["qdot_true"]) >= n_stick, name
    # Both velocity directions and the low-velocity (Stribeck) region are covered.
    v = runs["identification"]["qdot_true"]
    assert v.max() > 5.0 and v.min() < -5.0
    assert np.mean((np.abs(v) > 0.05) & (np.abs(v) < 1.0)) > 0.05


def test_experiments_are_memoised_copies_and_deterministic() -> None:
    a = rig.rig_experiment("validation", seed=0)
    a["q"][:] = 0.0  # callers cannot corrupt the memo
    b = rig.rig_experiment("validation", seed=0)
    fresh = rig._run_experiment("validation", 0)  # recomputed from scratch
    for key in fresh:
        np.testing.assert_array_equal(b[key], fresh[key])
    u0 = rig.excitation("validation", duration=20.0, seed=0)
    np.testing.assert_array_equal(u0, b["u"])
    assert not np.array_equal(u0, rig.excitation("validation", duration=20.0, seed=1))


def test_unknown_names_and_bad_inputs_raise_torchfric_error() -> None:
    with pytest.raises(TorchfricError, match="identification, validation, extrapolation"):
        rig.rig_experiment("nonsense")
    with pytest.raises(TorchfricError, match="unknown excitation kind"):
        rig.excitation("changed_identification", duration=1.0, dt=1e-3, seed=0)
    with pytest.raises(TorchfricError, match="duration"):
        rig.excitation("identification", duration=-1.0, dt=1e-3, seed=0)
    with pytest.raises(TorchfricError, match="NaN"):
        rig.simulate_rig(NOMINAL, np.array([0.0, np.nan]), seed=0)
    with pytest.raises(TorchfricError, match="x0"):
        rig.simulate_rig(NOMINAL, np.zeros(3), seed=0, x0=(0.0, 0.0))
    with pytest.raises(TorchfricError, match="seed"):
        rig.rig_experiment("identification", seed=-1)


# --- files ------------------------------------------------------------------------------------


def test_generate_into_a_file_path_is_a_clear_error(tmp_path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(TorchfricError, match="output directory"):
        rig.generate(blocker / "sub", seed=0)


def test_generate_writes_all_files_deterministically(tmp_path) -> None:
    paths = rig.generate(tmp_path / "a", seed=0)
    expected = {*rig.EXPERIMENTS, "truth", "truth_states"}
    assert set(paths) == expected
    assert all(p.is_file() and p.parent == tmp_path / "a" for p in paths.values())

    for name in rig.EXPERIMENTS:
        text = paths[name].read_text()
        assert text.startswith("t,u,q\n")
        table = np.loadtxt(paths[name], delimiter=",", skiprows=1)
        r = rig.rig_experiment(name, seed=0)
        for i, key in enumerate(("t", "u", "q")):
            np.testing.assert_array_equal(table[:, i], r[key])  # %.17g round-trips exactly

    truth = json.loads(paths["truth"].read_text())
    assert truth["parameters"]["nominal"] == NOMINAL.to_dict()
    assert truth["parameters"]["changed"]["Fs"] == NOMINAL.Fc
    for name in rig.EXPERIMENTS:
        info = truth["experiments"][name]
        r = rig.rig_experiment(name, seed=0)
        assert info["peak_abs_qdot"] == float(np.abs(r["qdot_true"]).max())
        assert info["seed"] == 0 and info["duration"] in (20.0, 30.0)
    for system, params in (("nominal", NOMINAL), ("changed", NOMINAL.changed())):
        curve = np.array(truth["steady_state_friction"][system])
        np.testing.assert_allclose(curve[:, 1], params.steady_state_friction(curve[:, 0]))
        assert curve[:, 0].min() <= -16.0 and curve[:, 0].max() >= 16.0

    with np.load(paths["truth_states"]) as npz:
        for name in rig.EXPERIMENTS:
            r = rig.rig_experiment(name, seed=0)
            for key in ("q_true", "qdot_true", "friction", "z", "disturbance"):
                np.testing.assert_array_equal(npz[f"{name}/{key}"], r[key])

    again = rig.generate(tmp_path / "b", seed=0)
    for key, path in paths.items():
        assert path.read_bytes() == again[key].read_bytes(), key

    other = rig.generate(tmp_path / "c", seed=1)
    for key, path in paths.items():
        assert path.read_bytes() != other[key].read_bytes(), key


def test_the_compiled_lugre_loop_gives_the_python_loops_numbers_to_the_bit(monkeypatch):
    """`torchfric.accel.native.lugre` (what the CLI runs) against the reference Python loop,
    every state of whole records, the changed system and another seed included."""
    from torchfric.accel import native
    from torchfric.accel.native.lugre import lugre_integrator
    from torchfric.data.rig import _run_experiment

    if native.compiler() is None:
        pytest.skip("no C compiler here")
    compiled = lugre_integrator()
    assert compiled is not None
    for name, seed in (("identification", 0), ("changed_validation", 5)):
        ref, fast = _run_experiment(name, seed), _run_experiment(name, seed, compiled)
        for key in ref:
            assert np.array_equal(ref[key], fast[key]), (name, key)
    monkeypatch.setenv("TORCHFRIC_NATIVE", "0")
    assert lugre_integrator() is None  # the switch turns it off: the Python loop runs
