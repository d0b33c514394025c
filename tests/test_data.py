"""Tests of torchfric.data: velocity reconstruction against exact derivatives and the filters'
own frequency responses, loaders against files written here, and every bad-input message."""

from __future__ import annotations

import math
import pathlib
import tempfile

import numpy as np
import pytest
import scipy.io
import scipy.signal
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from torchfric.data import (
    DEFAULT_CUTOFF_HZ,
    Experiment,
    highpass_derivative,
    load_experiment,
    make_experiment,
    reconstruct_velocity,
    save_csv,
    validate_experiment,
    zero_phase_acceleration,
    zero_phase_derivative,
)
from torchfric.data.filters import first_order
from torchfric.errors import TorchfricError

DT = 1e-3  # 1 kHz, as in the paper and the EMPS / HSM150 records
QUANTUM = 2e-4  # encoder quantum of the synthetic rig, rad


def _time(n: int, dt: float = DT) -> np.ndarray:
    return np.arange(n) * dt


def _tustin_coefficients(dt: float, cutoff_hz: float) -> tuple[float, float]:
    """(p, g) of v[k] = p·v[k−1] + g·(q[k] − q[k−1]).

    H(s) = s·ωc/(s + ωc) with s ← (2/dt)(1 − z⁻¹)/(1 + z⁻¹).
    """
    wc = 2 * math.pi * cutoff_hz
    k = 2 / dt
    return (k - wc) / (k + wc), k * wc / (k + wc)


def _h_continuous(omega: np.ndarray, cutoff_hz: float) -> np.ndarray:
    """H(jω) = jω·ωc/(jω + ωc)."""
    wc = 2 * math.pi * cutoff_hz
    return 1j * omega * wc / (1j * omega + wc)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x**2)))


# ------------------------------------------------------------------- high-pass differentiator
def test_highpass_is_the_stated_difference_equation() -> None:
    q = np.cumsum(np.random.randn(60)) * 1e-3
    p, g = _tustin_coefficients(DT, 200.0)
    expected = np.zeros_like(q)
    s = (q[1] - q[0]) / DT  # the docstring's equation, literally, from v[−1] = s
    before, q_before = s, q[0] - s * DT
    for k in range(q.size):
        expected[k] = p * before + g * (q[k] - q_before)
        before, q_before = expected[k], q[k]
    torch.testing.assert_close(
        highpass_derivative(torch.from_numpy(q), DT), torch.from_numpy(expected)
    )


def test_highpass_matches_scipy_bilinear_transform() -> None:
    # an independent discretisation of H(s) = s·ωc/(s+ωc), run over 400 samples of the ramp
    # that continues the record's first step backwards (started at rest there, settled by
    # q[0]): the motion the differentiator assumes before the record
    wc = 2 * math.pi * 150.0
    b, a = scipy.signal.bilinear([wc, 0.0], [1.0, wc], fs=1 / DT)
    q = 0.4 + np.cumsum(np.random.randn(500)) * 1e-3
    lead = q[0] + (q[1] - q[0]) * np.arange(-400, 0)
    x = np.concatenate([lead, q])
    expected, _ = scipy.signal.lfilter(b, a, x, zi=scipy.signal.lfilter_zi(b, a) * x[0])
    torch.testing.assert_close(
        highpass_derivative(torch.from_numpy(q), DT, 150.0), torch.from_numpy(expected[400:])
    )


def test_highpass_starts_at_the_motions_speed() -> None:
    # a record that starts in motion reads its speed from the first sample (a ramp: exactly),
    # where a start from rest read about 0 for 5 samples; one that starts at rest is
    # bit-identical to the zero-state filter
    t = _time(200)
    ramp = highpass_derivative(torch.from_numpy(0.3 - 0.085 * t), DT).numpy()
    np.testing.assert_allclose(ramp, -0.085, rtol=1e-12)
    q = np.concatenate([np.full(5, 0.2), 0.2 + 0.5 * t[:195] ** 2])
    p, g = _tustin_coefficients(DT, 200.0)
    rest = first_order(np.diff(q, prepend=q[:1]), p, g)  # the filter from a zero state
    assert np.array_equal(highpass_derivative(torch.from_numpy(q), DT).numpy(), rest)
    # a sine entered at its fastest: within the filter's lag of the true derivative at once
    v = highpass_derivative(torch.from_numpy(0.3 * np.sin(2 * np.pi * 2.0 * t)), DT).numpy()
    true = 0.3 * 2 * np.pi * 2.0 * np.cos(2 * np.pi * 2.0 * t)
    assert np.abs(v - true).max() < 0.01 * true.max()


def test_highpass_sine_amplitude_and_phase() -> None:
    amp, f = 0.3, 7.0
    omega = 2 * math.pi * f
    t = _time(2000)
    v = highpass_derivative(torch.from_numpy(amp * np.sin(omega * t)), DT).numpy()
    # Tustin: H_d(e^{jω·dt}) = H(jΩ) exactly, Ω = (2/dt)·tan(ω·dt/2)
    h = _h_continuous(np.array(2 / DT * math.tan(omega * DT / 2)), 200.0)
    predicted = amp * abs(h) * np.sin(omega * t + np.angle(h))
    # the start-up transient decays as p^k, p = 0.228: below 1e-19 of the amplitude after 30 samples
    np.testing.assert_allclose(v[30:], predicted[30:], rtol=0, atol=1e-10 * amp * omega)
    # against the true derivative A·ω·cos(ωt): the only error is the filter's |H(jΩ) − jω|·A
    # (mostly the lag 1/ωc ≈ 0.9 ms, about 4 % of A·ω at 7 Hz); 1 % margin on that bound
    bound = amp * abs(h - 1j * omega)
    err = np.abs(v[30:] - amp * omega * np.cos(omega * t[30:]))
    assert 0.5 * bound < err.max() <= 1.01 * bound
    assert bound < 0.05 * amp * omega


def test_highpass_ramp_and_constant() -> None:
    t = _time(200)
    slope = 0.7
    v = highpass_derivative(torch.from_numpy(0.1 + slope * t), DT).numpy()
    # unit low-frequency gain, and the ramp continued before the record: the slope from the
    # first sample on (a filter started from rest read slope·(1 − p^k))
    np.testing.assert_allclose(v, slope, rtol=1e-10)
    # steady-state start: a signal at rest gives exactly 0 from the first sample
    rest = highpass_derivative(torch.full((100,), 1234.5678), DT)
    assert torch.equal(rest, torch.zeros(100))


# two incommensurate tones: a pure 2 Hz sine repeats every 500 samples, so its rounding error
# is periodic (a line spectrum); the second tone makes the error ≈ white and uniform
TONES = ((1.0, 2.0), (0.3, 5.42))  # (amplitude rad, frequency Hz): ~60 quanta per sample


def _two_tones(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q and its exact derivative."""
    q = sum(a * np.sin(2 * math.pi * f * t) for a, f in TONES)
    qdot = sum(a * 2 * math.pi * f * np.cos(2 * math.pi * f * t) for a, f in TONES)
    return q, qdot


def test_highpass_quantisation_noise_bound() -> None:
    t = _time(5000)
    q, qdot = _two_tones(t)
    q_enc = np.round(q / QUANTUM) * QUANTUM
    v_enc = highpass_derivative(torch.from_numpy(q_enc), DT).numpy()[30:]
    v_exact = highpass_derivative(torch.from_numpy(q), DT).numpy()[30:]
    # Rounding error: white, variance quantum²/12. Noise gain of g(1−z⁻¹)/(1−p·z⁻¹):
    # Σh² = g²·2/(1+p), g ≈ (1−p)/dt. So σ_v = (quantum/dt)/√12 · g·dt·√(2/(1+p))
    # = 0.057 rad/s for 2e-4 rad at 1 kHz and 200 Hz (g·dt = 0.77, √(2/(1+p)) = 1.28).
    p, g = _tustin_coefficients(DT, 200.0)
    sigma_v = QUANTUM / math.sqrt(12) * g * math.sqrt(2 / (1 + p))
    # 10 %: the white-uniform model holds to ~3 % here (5000 samples, RMS known to ~1 %)
    assert 0.9 * sigma_v < _rms(v_enc - v_exact) < 1.1 * sigma_v
    # total RMS error against the true derivative: noise ⊕ each tone's lag A·|H(jΩ) − jω|/√2
    bias_sq = 0.0
    for a, f in TONES:
        omega = 2 * math.pi * f
        h = _h_continuous(np.array(2 / DT * math.tan(omega * DT / 2)), 200.0)
        bias_sq += (a * abs(h - 1j * omega)) ** 2 / 2
    assert _rms(v_enc - qdot[30:]) < 1.1 * math.sqrt(sigma_v**2 + bias_sq)


@settings(max_examples=25, deadline=None)
@given(offset=st.floats(-1e3, 1e3), scale=st.floats(-10, 10))
def test_highpass_ignores_offsets_and_is_linear(offset: float, scale: float) -> None:
    q = torch.from_numpy(np.cumsum(np.random.default_rng(1).standard_normal(300)) * 1e-2)
    v = highpass_derivative(q, DT)
    # rounding of q + offset is ≤ 1e3·2⁻⁵² ≈ 2e-13 rad per sample, times g ≈ 772/s
    torch.testing.assert_close(
        highpass_derivative(scale * q + offset, DT), scale * v, rtol=1e-9, atol=1e-8
    )


def test_highpass_batched_along_last_axis() -> None:
    q = torch.randn(3, 100).cumsum(-1)
    v = highpass_derivative(q, DT)
    for i in range(3):
        torch.testing.assert_close(v[i], highpass_derivative(q[i], DT), rtol=0, atol=0)


# --------------------------------------------------------------------------- zero-phase option
def _butter_gain(f: float, cutoff_hz: float, order: int) -> float:
    """|H_B|² of the forward-backward Butterworth at f (from its own digital response)."""
    sos = scipy.signal.butter(order, cutoff_hz, fs=1 / DT, output="sos")
    _, h = scipy.signal.sosfreqz(sos, worN=[f], fs=1 / DT)
    return float(abs(h[0]) ** 2)


def test_zero_phase_derivative_and_acceleration_on_sine() -> None:
    amp, f = 0.3, 5.3  # 15.9 periods: the ends are not at a zero of the curvature
    omega = 2 * math.pi * f
    t = _time(3000)
    q = torch.from_numpy(amp * np.sin(omega * t))
    v = zero_phase_derivative(q, DT).numpy()
    a = zero_phase_acceleration(q, DT).numpy()
    # interior prediction: |H_B(ω)|² (zero phase) times the central difference's sin(ω·dt)/(ω·dt)
    gain = _butter_gain(f, 50.0, 4)
    sinc = math.sin(omega * DT) / (omega * DT)
    # the odd pad flips the curvature at the ends; that transient decays with the filter's own
    # poles: 2.5e-5 of A·ω at 60 samples (3 cut-off periods), < 1e-9 at 150 samples
    inner = slice(150, -150)
    np.testing.assert_allclose(
        v[inner], (amp * omega * gain * sinc * np.cos(omega * t))[inner], atol=1e-8 * amp * omega
    )
    np.testing.assert_allclose(
        a[inner],
        (-amp * omega**2 * gain * sinc**2 * np.sin(omega * t))[inner],
        atol=1e-7 * amp * omega**2,
    )
    # the plain truth beyond 3 cut-off periods: within 5e-4 of A·ω (sinc loses
    # (ω·dt)²/6 = 1.8e-4, |H_B|² 1e-8, the end transient 2.5e-5)
    np.testing.assert_allclose(
        v[60:-60], (amp * omega * np.cos(omega * t))[60:-60], atol=5e-4 * amp * omega
    )
    # at the ends: the pad's curvature jump 2·q'' acting over the filter's time scale 1/(2π·fc)
    # gives an error of order 2·A·ω²/(2π·fc) = 2·A·ω·f/fc; we allow half of it, A·ω·f/fc =
    # 10.6 % (4.1 % measured). A zero or constant pad would be off by ~A·ω.
    np.testing.assert_allclose(v, amp * omega * np.cos(omega * t), atol=f / 50.0 * amp * omega)


def test_zero_phase_ramp_and_constant() -> None:
    t = _time(500)
    # odd padding continues a ramp as a ramp and the low-pass has unit DC gain: exact everywhere
    v = zero_phase_derivative(torch.from_numpy(-0.2 + 1.3 * t), DT)
    torch.testing.assert_close(v, torch.full((500,), 1.3), rtol=0, atol=1e-9)
    a = zero_phase_acceleration(torch.from_numpy(-0.2 + 1.3 * t), DT)
    torch.testing.assert_close(a, torch.zeros(500), rtol=0, atol=1e-6)
    # a parabola c·t²: a zero-phase filter with unit DC gain only adds the constant c·Σh_k·k²,
    # and central differences are exact for quadratics, so inside (clear of the pads) v = 2ct
    # and a = 2c up to rounding (q ≤ 1, /dt² = 1e6: ~1e-9)
    c = 2.5
    inner = slice(150, -150)
    v2 = zero_phase_derivative(torch.from_numpy(c * t**2), DT)[inner]
    a2 = zero_phase_acceleration(torch.from_numpy(c * t**2), DT)[inner]
    torch.testing.assert_close(v2, torch.from_numpy(2 * c * t[inner]), rtol=0, atol=1e-9)
    torch.testing.assert_close(a2, torch.full_like(a2, 2 * c), rtol=0, atol=1e-6)
    # constant 1234.5: rounding ≈ 1234.5·2⁻⁵² ≈ 3e-13 per sample, / dt
    rest = zero_phase_derivative(torch.full((500,), 1234.5), DT)
    torch.testing.assert_close(rest, torch.zeros(500), rtol=0, atol=1e-8)


def test_zero_phase_quantisation_noise_bound() -> None:
    t = _time(8000)
    q, _ = _two_tones(t)
    q_enc = np.round(q / QUANTUM) * QUANTUM
    inner = slice(300, -300)
    noise = (
        zero_phase_derivative(torch.from_numpy(q_enc), DT)
        - zero_phase_derivative(torch.from_numpy(q), DT)
    ).numpy()[inner]
    # white noise σ² = quantum²/12 through |H_B(θ)|² (forward-backward) and the central
    # difference j·sin(θ)/dt: σ_v² = σ²/π ∫₀^π |H_B|⁴ sin²θ/dt² dθ (≈ 0.003 rad/s here)
    sos = scipy.signal.butter(4, 50.0, fs=1 / DT, output="sos")
    theta, h = scipy.signal.sosfreqz(sos, worN=8192)
    integrand = np.abs(h) ** 4 * np.sin(theta) ** 2 / DT**2
    sigma_v = QUANTUM / math.sqrt(12) * math.sqrt(np.trapezoid(integrand, theta) / math.pi)
    # 10 %: the white-uniform rounding model (holds to ~3 % here); after the 50 Hz low-pass only
    # ~7400/10 independent samples remain, so the RMS itself is known to ~3 %
    assert 0.9 * sigma_v < _rms(noise) < 1.1 * sigma_v
    # a twentieth of the causal 200 Hz differentiator's noise (0.057 rad/s)
    p, g = _tustin_coefficients(DT, 200.0)
    assert sigma_v < 0.1 * QUANTUM / math.sqrt(12) * g * math.sqrt(2 / (1 + p))


def test_reconstruct_velocity_dispatch_and_defaults() -> None:
    q = torch.from_numpy(np.sin(2 * math.pi * 3 * _time(400)))
    assert DEFAULT_CUTOFF_HZ == {"highpass": 200.0, "zero_phase": 50.0}
    assert torch.equal(reconstruct_velocity(q, DT), highpass_derivative(q, DT, 200.0))
    assert torch.equal(
        reconstruct_velocity(q, DT, "zero_phase"), zero_phase_derivative(q, DT, 50.0)
    )
    assert torch.equal(
        reconstruct_velocity(q, DT, "highpass", 80.0), highpass_derivative(q, DT, 80.0)
    )


# --------------------------------------------------------------------------- the record
def _experiment(n: int = 50, qdot: bool = False) -> Experiment:
    t = _time(n)
    return make_experiment(
        t,
        np.cos(t),
        np.sin(3 * t),
        3 * np.cos(3 * t) if qdot else None,
        name="demo",
    )


def test_experiment_properties_slice_and_velocity() -> None:
    e = _experiment(50)
    assert e.t.dtype == torch.float64 and e.u.dtype == torch.float64
    assert e.n == 50 and e.dt == pytest.approx(DT, rel=1e-12)
    assert e.duration == pytest.approx(49 * DT, rel=1e-12)
    assert e.qdot is None
    s = e.slice(10, 30)
    assert s.n == 20 and s.t[0].item() == e.t[10].item() and s.name == "demo"
    assert torch.equal(s.q, e.q[10:30])
    assert e.slice(45).n == 5
    w = e.with_velocity()
    assert torch.equal(w.qdot, highpass_derivative(e.q, e.dt))
    z = w.with_velocity("zero_phase")  # replaces qdot, 50 Hz default
    assert torch.equal(z.qdot, zero_phase_derivative(e.q, e.dt, 50.0))
    assert e.qdot is None  # the original is untouched (frozen)
    with pytest.raises(AttributeError):
        e.name = "other"  # type: ignore[misc]
    arrays = w.to_numpy()
    assert sorted(arrays) == ["q", "qdot", "t", "u"] and arrays["q"].dtype == np.float64


def test_columns_live_in_torch_aligned_memory(tmp_path: pathlib.Path) -> None:
    """Every column and reconstructed signal is a 64-byte aligned torch buffer, whatever the
    source's alignment: the compiled EKF step rounds misaligned inputs differently, so a
    numpy-owned buffer (16-byte aligned, at an address that changes per process) made the same
    run give θ differing by 3e-6 between processes (CI's kill-and-resume test caught it)."""
    n = 64
    raw = np.zeros(4 * n + 1)[1:].reshape(4, n)  # rows start 8 bytes past an allocation
    raw[0] = np.arange(n) * DT
    raw[1] = np.sin(np.arange(n) * 0.1)
    raw[2] = np.cos(np.arange(n) * 0.05)
    raw[3] = 0.5
    e = Experiment(t=raw[0], u=raw[1], q=raw[2], qdot=raw[3], name="odd")
    path = tmp_path / "odd.csv"
    save_csv(path, e)
    derived = [
        *(e.t, e.u, e.q, e.qdot),
        *(e.slice(3, 40).u, e.with_velocity().qdot, e.with_velocity("zero_phase").qdot),
        zero_phase_derivative(raw[2], DT),
        zero_phase_acceleration(raw[2], DT),
        load_experiment(path).u,
    ]
    assert [x.data_ptr() % 64 for x in derived] == [0] * len(derived)


def test_fingerprint_sees_every_bit() -> None:
    e = _experiment(40, qdot=True)
    same = Experiment(t=e.t.clone(), u=e.u.clone(), q=e.q.clone(), qdot=e.qdot.clone(), name="x")
    assert e.fingerprint() == same.fingerprint()
    assert len(e.fingerprint()) == 64
    q = e.q.numpy().copy()
    q[17] = np.nextafter(q[17], np.inf)  # one ulp
    assert Experiment(t=e.t, u=e.u, q=torch.from_numpy(q), qdot=e.qdot).fingerprint() != (
        e.fingerprint()
    )
    assert Experiment(t=e.t, u=e.u, q=e.q).fingerprint() != e.fingerprint()


# --------------------------------------------------------------------------- files
def test_csv_round_trip_is_bit_exact(tmp_path: pathlib.Path) -> None:
    n = 200
    e = make_experiment(
        _time(n) + 0.1234567,
        torch.randn(n) * 1e3,
        torch.randn(n).cumsum(0) * 1e-7,
        torch.randn(n) / 3,
        name="rt",
    )
    path = tmp_path / "rt.csv"
    save_csv(path, e)
    assert path.read_text().splitlines()[0] == "t,u,q,qdot"
    back = load_experiment(path)
    assert back.name == "rt" and back.fingerprint() == e.fingerprint()
    for key in ("t", "u", "q", "qdot"):
        assert torch.equal(getattr(back, key), getattr(e, key))
    save_csv(path, e, include_qdot=False)
    assert path.read_text().splitlines()[0] == "t,u,q"
    assert load_experiment(path).qdot is None


@settings(max_examples=20, deadline=None)
@given(
    values=arrays(
        np.float64, (2, 12), elements=st.floats(allow_nan=False, allow_infinity=False, width=64)
    )
)
def test_csv_round_trip_any_finite_float(values: np.ndarray) -> None:
    e = make_experiment(_time(12), values[0], values[1])
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "x.csv"
        save_csv(path, e)
        assert load_experiment(path).fingerprint() == e.fingerprint()


def test_csv_round_trip_keeps_negative_zero(tmp_path: pathlib.Path) -> None:
    # Hypothesis found it: a column of "-0" reads as integers and came back as +0.
    e = make_experiment(_time(12), -np.zeros(12), np.where(np.arange(12) % 2, -0.0, 1.5))
    path = tmp_path / "zeros.csv"
    save_csv(path, e)
    back = load_experiment(path)
    assert bool(torch.signbit(back.u).all()) and back.fingerprint() == e.fingerprint()


def test_csv_with_comments_extra_columns_and_mapping(tmp_path: pathlib.Path) -> None:
    t = _time(20)
    body = "\n".join(f"{ti!r}, {2 * ti!r}, 9.0, {ti**2!r}" for ti in t.tolist())
    path = tmp_path / "log.csv"
    path.write_text(f"# rig log\n# units: s, A, -, rad\ntime, current, temp, pos\n{body}\n# end\n")
    e = load_experiment(path, columns={"t": "time", "u": "current", "q": "pos"}, name="log")
    assert e.name == "log" and e.qdot is None
    np.testing.assert_array_equal(e.t.numpy(), t)
    np.testing.assert_array_equal(e.u.numpy(), 2 * t)
    np.testing.assert_array_equal(e.q.numpy(), t**2)


def test_npz_with_column_vectors_and_time_step(tmp_path: pathlib.Path) -> None:
    n = 100
    u, th = np.random.randn(n, 1), np.random.randn(1, n)
    path = tmp_path / "disc.npz"
    np.savez(path, u=u, th=th, note=np.array([1.0, 2.0]))
    e = load_experiment(path, columns={"q": "th"}, time_step=0.025)
    np.testing.assert_array_equal(e.u.numpy(), u[:, 0])
    np.testing.assert_array_equal(e.q.numpy(), th[0])
    np.testing.assert_array_equal(e.t.numpy(), np.arange(n) * 0.025)
    assert e.dt == pytest.approx(0.025)
    # start/stop select file samples; t keeps the file's time
    part = load_experiment(path, columns={"q": "th"}, time_step=0.025, start=30, stop=80)
    assert part.n == 50 and part.t[0].item() == 30 * 0.025
    np.testing.assert_array_equal(part.q.numpy(), th[0, 30:80])
    tail = load_experiment(path, columns={"q": "th"}, time_step=0.025, start=60)
    assert tail.n == 40


def test_mat_with_matrix_columns(tmp_path: pathlib.Path) -> None:
    n = 300
    t = _time(n)
    data = np.column_stack([t, np.zeros(n), np.sin(t), np.cos(t), np.full(n, 0.05)])
    path = tmp_path / "hsm.mat"
    scipy.io.savemat(path, {"data": data, "Tvz": 1e-3, "vir": np.random.randn(n)})
    cols = {"t": "data:0", "q": "data:2", "qdot": "data:3", "u": "data:4"}
    e = load_experiment(path, columns=cols)
    np.testing.assert_array_equal(e.t.numpy(), t)
    np.testing.assert_array_equal(e.q.numpy(), np.sin(t))
    np.testing.assert_array_equal(e.qdot.numpy(), np.cos(t))
    # a 1-D vector is stored by savemat as (1, N) and flattened back
    e2 = load_experiment(path, columns={"t": "data:0", "q": "data:2", "u": "vir"})
    assert e2.u.shape == (n,) and e2.qdot is None
    # a time column that agrees with time_step is accepted, one that does not is refused
    assert load_experiment(path, columns=cols, time_step=1e-3).n == n
    with pytest.raises(TorchfricError, match=r"time column has step 0.001 s but time_step = 0.002"):
        load_experiment(path, columns=cols, time_step=2e-3)


# --------------------------------------------------------------------------- bad input
def _write_npz(tmp_path: pathlib.Path, n: int = 50, **extra: np.ndarray) -> pathlib.Path:
    path = tmp_path / "x.npz"
    np.savez(path, t=_time(n), u=np.zeros(n), q=np.zeros(n), **extra)
    return path


def test_file_errors(tmp_path: pathlib.Path) -> None:
    with pytest.raises(TorchfricError, match=r"nope\.csv: file not found.*check the path"):
        load_experiment(tmp_path / "nope.csv")
    with pytest.raises(TorchfricError, match=r"unsupported file type '\.xlsx'.*\.csv"):
        load_experiment(tmp_path / "x.xlsx")
    path = _write_npz(tmp_path, pos=np.zeros(50))
    with pytest.raises(
        TorchfricError, match=r"no column 'qm' \(for q\); the file has: t, u, q, pos;"
    ):
        load_experiment(path, columns={"q": "qm"})
    with pytest.raises(
        TorchfricError, match=r"unknown key\(s\) \['pos', 'y'\] in columns.*t, u, q"
    ):
        load_experiment(path, columns={"y": "q", "pos": "pos"})
    with pytest.raises(TorchfricError, match=r"columns\['q'\] = 3; expected a column name"):
        load_experiment(path, columns={"q": 3})  # type: ignore[dict-item]
    with pytest.raises(TorchfricError, match=r"is a directory; give the path of a \.csv file"):
        (tmp_path / "folder.csv").mkdir()
        load_experiment(tmp_path / "folder.csv")
    # damaged files: a truncated .mat makes loadmat fail deep inside (IndexError), a truncated
    # .npz is no zip archive; both must come back as one-line TorchfricErrors
    good = tmp_path / "good.mat"
    scipy.io.savemat(good, {"t": _time(50), "u": np.zeros(50), "q": np.zeros(50)})
    for suffix, source in ((".mat", good), (".npz", path)):
        cut = tmp_path / f"cut{suffix}"
        cut.write_bytes(source.read_bytes()[:100])
        with pytest.raises(TorchfricError, match=rf"cut\{suffix}: cannot read as"):
            load_experiment(cut)
    for suffix in (".npz", ".mat", ".csv"):
        bad = tmp_path / f"garbage{suffix}"
        bad.write_bytes(b"\x00\x01not a real file\xff\xfe" * 5)
        with pytest.raises(TorchfricError, match=r"garbage\.(npz|mat|csv): cannot read"):
            load_experiment(bad)


def test_column_selection_errors(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "m.mat"
    scipy.io.savemat(path, {"data": np.zeros((30, 4)), "t": _time(30)})
    with pytest.raises(TorchfricError, match=r"'data' \(for q\) has shape \(30, 4\).*'data:k'"):
        load_experiment(path, columns={"q": "data", "u": "data:1"})
    with pytest.raises(TorchfricError, match=r"'data:4' \(for u\) selects column 4 .* \(30, 4\)"):
        load_experiment(path, columns={"q": "data:0", "u": "data:4"})
    with pytest.raises(TorchfricError, match=r"no column 'data:x'"):
        load_experiment(path, columns={"q": "data:0", "u": "data:x"})


def test_no_time_column_needs_time_step(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "no_t.npz"
    np.savez(path, u=np.zeros(40), th=np.zeros(40))
    with pytest.raises(
        TorchfricError, match=r"no time column 't'.*add a t column or give time_step"
    ):
        load_experiment(path, columns={"q": "th"})
    with pytest.raises(TorchfricError, match=r"time_step = -0.1; expected a positive"):
        load_experiment(path, columns={"q": "th"}, time_step=-0.1)


def test_a_sample_counter_keeps_the_samples_a_logger_dropped_as_a_gap(
    tmp_path: pathlib.Path,
) -> None:
    # A logger's file without a time column: a sample counter ("Index"), tabs, CRLF, a comment
    # line; 250 samples dropped after row 600. With time_step, t comes from the counter, so the
    # record is two segments whose times are the counter's; arange(N)·dt would join rows 599
    # and 850 as one step and q would jump there.
    from torchfric.data import load_segments
    from torchfric.data.lab import counter_time

    dt, n = 1e-3, 1200
    index = np.r_[np.arange(600), np.arange(850, 850 + n - 600)]
    q = np.sin(index * dt * 3.0)
    rows = "".join(
        f"{i}\t{0.1 * math.cos(i * dt)}\t{v:.9f}\r\n" for i, v in zip(index, q, strict=True)
    )
    path = tmp_path / "logger.txt"
    path.write_text("# logger, axis 1\r\nIndex\tCmd [V]\tPos [rad]\r\n" + rows)
    exps, notes = load_segments(path, columns={"u": "Cmd [V]", "q": "Pos [rad]"}, time_step=dt)
    assert [e.n for e in exps] == [600, 600] and "250 samples" in notes[0]
    np.testing.assert_allclose(exps[1].t.numpy(), index[600:] * dt, rtol=0, atol=1e-12)
    np.testing.assert_allclose(exps[1].q.numpy(), q[600:], rtol=0, atol=1e-9)
    t, label = counter_time({"Index": index.astype(float)}, dt)
    assert label == "t = (Index − 0)·0.001" and t[600] == pytest.approx(0.85)
    # not a counter: another name, a step back, steps of 2, a fraction
    assert counter_time({"Position": index.astype(float)}, dt) is None
    assert counter_time({"Sample": np.array([0.0, 1, 2, 1, 2])}, dt) is None
    assert counter_time({"Nr.": np.arange(0.0, 20, 2)}, dt) is None
    assert counter_time({"idx": np.array([0.0, 1, 2.5, 3])}, dt) is None
    assert counter_time({"Sample [-]": np.arange(5.0) + 7}, dt)[1] == "t = (Sample [-] − 7)·0.001"


def test_csv_errors(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "h.csv"
    path.write_text("0,1,2\n0.001,1,2\n")
    with pytest.raises(TorchfricError, match=r"holds numbers, not column names.*header"):
        load_experiment(path)
    path.write_text("t,u,q\n0,1\n")
    with pytest.raises(
        TorchfricError, match=r"cannot parse the data .*expected 3 comma-separated numbers per row"
    ):
        load_experiment(path)
    path.write_text("t,u,q\n0,1,abc\n")
    with pytest.raises(TorchfricError, match=r"line 2: 'abc' in column 'q' is not a number"):
        load_experiment(path)
    path.write_text("# only a comment\nt,u,q\n")
    with pytest.raises(TorchfricError, match=r"no data rows below the header"):
        load_experiment(path)


def test_nan_and_inf_name_column_and_index(tmp_path: pathlib.Path) -> None:
    t = _time(30)
    q = np.zeros(30)
    q[7] = np.nan
    with pytest.raises(
        TorchfricError, match=r"demo: column q has a non-finite value nan at index 7"
    ):
        validate_experiment(t, np.zeros(30), q, name="demo")
    u = np.zeros(30)
    u[3], u[9] = np.inf, -np.inf
    with pytest.raises(
        TorchfricError, match=r"column u has a non-finite value inf at index 3 \(2 in"
    ):
        make_experiment(t, u, np.zeros(30))
    qd = torch.zeros(30)
    qd[29] = float("nan")
    with pytest.raises(TorchfricError, match=r"column qdot has a non-finite value nan at index 29"):
        make_experiment(t, np.zeros(30), np.zeros(30), qd)
    # from a file: the file's column name and the file's row index (start is added back)
    n = 60
    pos = np.zeros(n)
    pos[42] = np.nan
    path = tmp_path / "nan.npz"
    np.savez(path, t=_time(n), u=np.zeros(n), pos=pos)
    # a file's missing value is named by its row (its line in a CSV); load_segments cuts there
    with pytest.raises(TorchfricError, match=r"column q \('pos'\) empty or NaN at index 42"):
        load_experiment(path, columns={"q": "pos"}, start=20)
    assert load_experiment(path, columns={"q": "pos"}, stop=40).n == 40


def test_time_axis_errors() -> None:
    t = _time(100)
    z = np.zeros(100)
    t_back = t.copy()
    t_back[5] = t_back[4]
    with pytest.raises(TorchfricError, match=r"not strictly increasing at index 5"):
        validate_experiment(t_back, z, z, name="x")
    gap = np.concatenate([t[:50], t[51:]])  # one sample missing
    with pytest.raises(TorchfricError, match=r"not uniform at index 50 \(step 0.002.*median 0.001"):
        validate_experiment(gap, z[:99], z[:99], name="x")
    # EMPS-like stamp jitter (±4e-8 s at 1 ms, 4e-5 relative) passes the default rtol
    jitter = t + np.random.uniform(-4e-8, 4e-8, size=100)
    validate_experiment(jitter, z, z, name="x")
    with pytest.raises(TorchfricError, match=r"not uniform"):
        validate_experiment(jitter, z, z, name="x", rtol=1e-5)


def test_shape_and_length_errors() -> None:
    z = np.zeros(20)
    with pytest.raises(TorchfricError, match=r"x: only 5 samples; at least 10"):
        validate_experiment(_time(5), z[:5], z[:5], name="x")
    with pytest.raises(TorchfricError, match=r"different lengths \(column t: 20, column u: 19"):
        make_experiment(_time(20), z[:19], z)
    with pytest.raises(TorchfricError, match=r"column q has shape \(20, 2\); expected a 1-D"):
        make_experiment(_time(20), z, np.zeros((20, 2)))
    with pytest.raises(TorchfricError, match=r"column u has dtype <U1; expected real numbers"):
        make_experiment(_time(20), ["a"] * 20, z)
    e = _experiment(20)
    with pytest.raises(TorchfricError, match=r"slice\(15, 16\) is invalid for 20 samples"):
        e.slice(15, 16)
    with pytest.raises(TorchfricError, match=r"start=30, stop=None is not a sample range"):
        with tempfile.TemporaryDirectory() as tmp:
            path = _write_npz(pathlib.Path(tmp), n=20)
            load_experiment(path, start=30)


def test_velocity_errors() -> None:
    q = torch.zeros(100)
    with pytest.raises(
        TorchfricError, match=r"unknown velocity method 'spline'.*'highpass', 'zero_phase'"
    ):
        reconstruct_velocity(q, DT, "spline")
    with pytest.raises(
        TorchfricError, match=r"cutoff_hz = 600.0 Hz is not in \(0, Nyquist = 500 Hz\)"
    ):
        highpass_derivative(q, DT, 600.0)
    with pytest.raises(
        TorchfricError, match=r"zero_phase_derivative: cutoff_hz = 500.0 Hz.*below 500"
    ):
        zero_phase_derivative(q, DT, 500.0)
    with pytest.raises(TorchfricError, match=r"Nyquist = 500 Hz"):
        _experiment(100).with_velocity(cutoff_hz=800.0)
    with pytest.raises(TorchfricError, match=r"dt = 0.0; expected a positive"):
        highpass_derivative(q, 0.0)
    with pytest.raises(TorchfricError, match=r"order = 0; expected an integer"):
        zero_phase_acceleration(q, DT, 50.0, 0)
    bad = torch.zeros(100)
    bad[12] = float("inf")
    with pytest.raises(TorchfricError, match=r"non-finite value at sample 12"):
        highpass_derivative(bad, DT)


# --------------------------------------------------------------------------- real records
def test_emps(shared_data: pathlib.Path) -> None:
    e = load_experiment(shared_data / "emps" / "DATA_EMPS.mat", columns={"u": "vir", "q": "qm"})
    assert e.n == 24841 and e.dt == pytest.approx(1e-3, rel=1e-6)
    # the file's stamps jitter by ±4e-8 s; position 0 … 0.2464 m (min −2.2e-5 m)
    assert e.q.min().item() == pytest.approx(0.0, abs=1e-4)
    assert e.q.max().item() == pytest.approx(0.2464, abs=1e-4)
    assert e.name == "DATA_EMPS" and e.qdot is None


def test_unbalanced_disk(shared_data: pathlib.Path) -> None:
    path = shared_data / "unbalanced_disk" / "training-val-test-data.npz"
    e = load_experiment(path, columns={"q": "th"}, time_step=0.025)
    assert e.n == 35000 and e.dt == pytest.approx(0.025)
    assert -1.91 < e.q.min().item() < -1.89 and 2.17 < e.q.max().item() < 2.19


def test_hsm150(shared_data: pathlib.Path) -> None:
    path = shared_data / "hsm150_two_motor" / "idf_pos_0.06_1.mat"
    cols = {"t": "data:0", "q": "data:2", "qdot": "data:3", "u": "data:4"}
    e = load_experiment(path, columns=cols)
    assert e.n == 20000 and e.dt == pytest.approx(1e-3, rel=1e-9)
    assert set(np.unique(e.u.numpy()).round(6)) == {0.05, 0.06}
    # SOURCE.md: col 3 is exactly the backward difference of col 2 over 1 ms
    torch.testing.assert_close(e.qdot[1:], torch.diff(e.q) / 1e-3, rtol=1e-9, atol=1e-9)
    # at ~140-215 rad/s the 200 Hz differentiator agrees with it within the quantum/dt noise
    v = e.with_velocity().qdot
    assert (v[100:] - e.qdot[100:]).abs().mean().item() < 0.628


def test_position_step_is_one_count_even_where_one_count_steps_are_rare() -> None:
    """A fine encoder on a fast axis moves one count a sample in fewer than 1 % of its moving
    samples (a robot joint's log: 222 of 30,000); the step is still that count, not the 1st
    percentile's two. Read from text (counts rounded to the file's digits) as well. An
    analogue record, whose steps fall anywhere, keeps the 1st percentile."""
    from torchfric.data import position_step

    quantum, n = 2 * math.pi / 262144, 30000
    t = np.arange(n) * 2e-3
    # mostly fast (6–40 counts a sample), with two slow creeps of one count every few samples
    speed = np.where((t % 20) < 0.12, 0.01, 1.0 + 0.5 * np.sin(t))
    counts = np.floor(np.cumsum(speed) * 2e-3 / quantum)
    for digits in (None, 6):
        q = counts * quantum if digits is None else np.round(np.degrees(counts * quantum), digits)
        q = q if digits is None else np.radians(q)
        e = make_experiment(t, np.zeros(n), q)
        steps = np.abs(np.diff(q))
        steps = steps[steps > 0]
        assert np.quantile(steps, 0.01) > 1.5 * quantum  # the percentile alone is off
        assert position_step([e]) == pytest.approx(quantum, rel=2e-3)
    noisy = make_experiment(t, np.zeros(n), np.sin(t) + 1e-4 * np.random.default_rng(1).standard_normal(n))
    steps = np.abs(np.diff(noisy.q.numpy()))
    assert position_step([noisy]) == pytest.approx(np.quantile(steps[steps > 0], 0.01), rel=1e-12)
