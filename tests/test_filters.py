"""torchfric's own velocity filters (`torchfric.data.filters`) against an independent
implementation, scipy.signal, and against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.signal as ss

from torchfric.data.filters import butter_sos, first_order, sosfilt, sosfiltfilt

RNG = np.random.default_rng(7)
# (order, cut-off, sampling rate): the pre-fit's 50 Hz at 1 kHz and 8 Hz at 40 Hz, a cut-off
# near Nyquist, and a slow one (poles 6·10⁻⁴ from the unit circle)
CASES = [(o, fc, fs) for o in (1, 2, 3, 4, 5, 8) for fc, fs in
         ((50, 1000), (8, 40), (200, 1000), (10, 1000), (1, 10000))]  # fmt: skip


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / np.abs(b).max())


def _tol(fc: float, fs: float) -> float:
    """Rounding, relative; the slow filter's poles, 6·10⁻⁴ from the unit circle, make it
    ill-conditioned: scipy itself moves by 2·10⁻¹⁰ when its sections are reordered."""
    return 1e-12 if fc / fs >= 1e-3 else 1e-8


@pytest.mark.parametrize(("order", "fc", "fs"), CASES)
def test_butterworth_design_is_scipys(order: int, fc: float, fs: float) -> None:
    ours, theirs = butter_sos(order, fc, fs), ss.butter(order, fc, fs=fs, output="sos")
    assert ours.shape == theirs.shape
    w = np.linspace(0, np.pi, 257)
    _, h_ours = ss.sosfreqz(ours, w)
    _, h_theirs = ss.sosfreqz(theirs, w)
    np.testing.assert_allclose(np.abs(h_ours - h_theirs), 0.0, atol=_tol(fc, fs))
    # the Butterworth facts: unity at DC, −3 dB at the cut-off, zero at Nyquist
    _, (dc, corner, nyq) = ss.sosfreqz(ours, [0.0, 2 * np.pi * fc / fs, np.pi])
    assert abs(dc) == pytest.approx(1.0, abs=_tol(fc, fs))
    assert abs(corner) == pytest.approx(1 / math.sqrt(2), abs=1e-9)
    assert abs(nyq) < 1e-6


@pytest.mark.parametrize(("order", "fc", "fs"), CASES)
def test_zero_phase_filtering_is_scipys(order: int, fc: float, fs: float) -> None:
    sos = ss.butter(order, fc, fs=fs, output="sos")
    x = RNG.standard_normal((2, 3000)).cumsum(-1)
    padlen = min(x.shape[-1] - 1, math.ceil(3 * order * fs / fc))
    ours = sosfiltfilt(sos, x, padlen)
    theirs = ss.sosfiltfilt(sos, x, axis=-1, padtype="odd", padlen=padlen)
    assert _rel(ours, theirs) < _tol(fc, fs)
    assert _rel(sosfiltfilt(sos, x[1], padlen), ours[1]) < _tol(fc, fs)  # one signal alone


def test_sections_with_initial_states_are_scipys() -> None:
    sos = ss.butter(4, 30, fs=1000, output="sos")
    x = RNG.standard_normal((3, 1234))
    zi = RNG.standard_normal((len(sos), 3, 2))
    theirs, _ = ss.sosfilt(sos, x, axis=-1, zi=zi)
    assert _rel(sosfilt(sos, x, zi), theirs) < 1e-13
    assert _rel(sosfilt(sos, x[:, :5]), ss.sosfilt(sos, x[:, :5])) < 1e-14  # shorter than a block


def test_first_order_recursion_is_the_sample_by_sample_one() -> None:
    x = RNG.standard_normal(5003)
    for p in (0.228, -0.6, 0.999):
        y, want, prev = first_order(x, p, 2.5), [], 0.0
        for v in x:
            prev = p * prev + 2.5 * v
            want.append(prev)
        assert _rel(y, np.array(want)) < 1e-13
        assert _rel(y, ss.lfilter([2.5], [1.0, -p], x)) < 1e-13


def test_a_constant_passes_unchanged_and_a_ramp_stays_a_ramp() -> None:
    sos = butter_sos(4, 50, 1000)
    np.testing.assert_allclose(sosfiltfilt(sos, np.full(500, 3.0), 240), 3.0, rtol=1e-12)
    ramp = 0.01 * np.arange(2000.0)
    np.testing.assert_allclose(sosfiltfilt(sos, ramp, 240), ramp, atol=1e-10)
