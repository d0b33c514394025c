"""Velocity (and acceleration) reconstruction from a measured position.

- `highpass_derivative` (causal, the paper's choice): the first-order high-pass differentiator
  ``H(s) = s·ωc/(s + ωc)``, ``ωc = 2π·cutoff_hz``, discretised with the bilinear (Tustin) map.
- `zero_phase_derivative` / `zero_phase_acceleration` (off-line): a Butterworth low-pass run
  forwards and backwards, then central differences.
- `reconstruct_velocity` picks one by name (`VELOCITY_METHODS`, `DEFAULT_CUTOFF_HZ`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from torch import Tensor

from ..errors import TorchfricError
from .convert import ArrayLike, _as_tensor, _check_cutoff, _check_step, _signal
from .filters import butter_sos, first_order, sosfiltfilt

__all__ = [
    "highpass_derivative",
    "zero_phase_derivative",
    "zero_phase_acceleration",
    "reconstruct_velocity",
    "settling_samples",
    "quiet_cutoff_hz",
    "velocity_noise",
    "quieter_cutoff_hz",
    "NOISY_VELOCITY",
    "VELOCITY_METHODS",
    "DEFAULT_CUTOFF_HZ",
]


def highpass_derivative(q: ArrayLike, dt: float, cutoff_hz: float = 200.0) -> Tensor:
    """Causal velocity from position by the high-pass differentiator ``H(s) = s·ωc/(s + ωc)``.

    Discretisation: bilinear (Tustin) ``s ← (2/dt)(1 − z⁻¹)/(1 + z⁻¹)`` *without* pre-warping.
    Its low-frequency gain is exactly that of ``s`` (a ramp gives its exact slope) and its
    response is ``H(jΩ)`` at ``Ω = (2/dt)·tan(ω·dt/2)``, i.e. the continuous filter to
    ``O((ω·dt)²)`` in the band where velocities are used. Pre-warping at ωc would instead scale
    every low-frequency velocity by ``(ωc·dt/2)/tan(ωc·dt/2)`` (0.865 for 200 Hz at 1 kHz), a
    bias that goes straight into viscous friction. The price: the −3 dB corner sits at
    ``atan(ωc·dt/2)/(π·dt)`` (178.6 Hz for 200 Hz at 1 kHz). Backward Euler would add half a
    sample of lag. With ``K = 2/dt``, ``p = (K − ωc)/(K + ωc)``, ``g = K·ωc/(K + ωc)``::

        v[k] = p·v[k−1] + g·(q[k] − q[k−1])

    started as if the motion before the record had gone on at its first step's speed
    ``s = (q[1] − q[0])/dt``: ``v[−1] = s``, ``q[−1] = q[0] − s·dt``, the filter's steady state
    on that ramp, so ``v[0] = s``. A record that starts at rest (``q[1] = q[0]``) starts at
    ``v = 0`` exactly, as from a zero initial state, and a constant q gives exactly 0 from the
    first sample; one that starts in motion (a logger started mid-move, a record cut out of a
    longer one with ``data.start``) starts at its speed, not at 0. Before 2026-11-26 the filter
    started from rest, and its first samples read about 0 on such a record: with the paper's
    ``P0 = 0`` (the initial state known) the EKF then took that 0 as the truth and the
    estimates wandered off (on an EMPS-like axis cut at 60 s, moving at 0.085 m/s, inertia
    0.2 kg against 95).

    Args:
        q: `(..., N)` position; filtered along the last axis.
        dt: sample period in s.
        cutoff_hz: ωc/2π; must be below the Nyquist frequency 1/(2·dt).

    Returns:
        `(..., N)` float64 velocity.
    """
    dt = _check_step(dt, "highpass_derivative: dt")
    wc = 2.0 * math.pi * _check_cutoff(cutoff_hz, dt, "highpass_derivative")
    qa = _signal(q, "highpass_derivative: q", 2)
    k = 2.0 / dt
    p = (k - wc) / (k + wc)
    g = k * wc / (k + wc)
    # the first step's speed s; Δq[k] = q[k] − q[k−1] with q[−1] = q[0] − s·dt
    first = qa[..., 1:2] - qa[..., :1]
    dq = np.diff(qa, axis=-1, prepend=qa[..., :1] - first)
    # v[k] = p·v[k−1] + g·Δq[k] from v[−1] = s: the zero-state response plus s·p^(k+1)
    v = first_order(dq, p, g)
    if np.any(first != 0.0):
        n = min(qa.shape[-1], _decay_samples(p))
        v[..., :n] += (first / dt) * p ** np.arange(1, n + 1)
    return _as_tensor(v)


def _decay_samples(p: float) -> int:
    """Samples until ``|p|^k`` is below 1e-20 (past rounding of any velocity it is added to)."""
    return 1 if abs(p) < 1e-20 else math.ceil(math.log(1e-20) / math.log(abs(p)))


def _zero_phase_lowpass(
    q: ArrayLike, dt: float, cutoff_hz: float, order: int, what: str
) -> np.ndarray:
    """Butterworth low-pass of order `order` run forwards and backwards (|H|², zero phase)."""
    dt = _check_step(dt, f"{what}: dt")
    cutoff_hz = _check_cutoff(cutoff_hz, dt, what)
    if isinstance(order, bool) or not isinstance(order, int) or not 1 <= order <= 12:
        raise TorchfricError(f"{what}: order = {order!r}; expected an integer from 1 to 12")
    qa = _signal(q, f"{what}: q", 3)
    sos = butter_sos(order, cutoff_hz, 1.0 / dt)
    # pad by 3·order cut-off periods (the filter's transient has died out by then); odd
    # extension continues a ramp as a ramp, so the ends keep their velocity
    padlen = min(qa.shape[-1] - 1, math.ceil(3 * order / (cutoff_hz * dt)))
    return sosfiltfilt(sos, qa, padlen)


def zero_phase_derivative(
    q: ArrayLike, dt: float, cutoff_hz: float = 50.0, order: int = 4
) -> Tensor:
    """Off-line velocity: zero-phase Butterworth low-pass, then central differences.

    ``q_f = filtfilt(butter(order, cutoff_hz), q)`` (second-order sections, odd padding), then
    ``v[k] = (q_f[k+1] − q_f[k−1]) / (2·dt)`` (second-order one-sided at the ends, `np.gradient`).
    Non-causal: sample k uses the future, so use it for off-line pre-processing only. The odd
    pad flips the curvature at the ends: the first and last ≈ 3 cut-off periods
    (``3/(cutoff_hz·dt)`` samples, 60 at 50 Hz and 1 kHz) can be off by a few % of the velocity
    (drop them in fits, as the EMPS recipe drops 50); inside, the error is the sinc
    ``1 − (ω·dt)²/6`` of the central difference and the Butterworth roll-off ``|H_B(ω)|²``.

    Args:
        q: `(..., N)` position, N >= 3; processed along the last axis.
        dt: sample period in s.
        cutoff_hz: low-pass cut-off, below 1/(2·dt).
        order: Butterworth order (the forward-backward pass doubles it).

    Returns:
        `(..., N)` float64 velocity.
    """
    qf = _zero_phase_lowpass(q, dt, cutoff_hz, order, "zero_phase_derivative")
    v = np.gradient(qf, dt, axis=-1, edge_order=2)
    return _as_tensor(v)


def zero_phase_acceleration(
    q: ArrayLike, dt: float, cutoff_hz: float = 50.0, order: int = 4
) -> Tensor:
    """Off-line acceleration: central differences applied twice to the zero-phase filtered q.

    ``a = gradient(gradient(q_f, dt), dt)``, i.e. ``(q_f[k+2] − 2·q_f[k] + q_f[k−2]) / (2·dt)²``
    inside, the derivative of `zero_phase_derivative`'s output. `(..., N)` → `(..., N)`.
    The ends (≈ 3 cut-off periods) are unreliable, up to tens of % for a curved q: drop them.
    """
    qf = _zero_phase_lowpass(q, dt, cutoff_hz, order, "zero_phase_acceleration")
    v = np.gradient(qf, dt, axis=-1, edge_order=2)
    a = np.gradient(v, dt, axis=-1, edge_order=2)
    return _as_tensor(a)


VELOCITY_METHODS: dict[str, Callable[[ArrayLike, float, float], Tensor]] = {
    "highpass": highpass_derivative,
    "zero_phase": zero_phase_derivative,
}
DEFAULT_CUTOFF_HZ: dict[str, float] = {"highpass": 200.0, "zero_phase": 50.0}


def reconstruct_velocity(
    q: ArrayLike, dt: float, method: str = "highpass", cutoff_hz: float | None = None
) -> Tensor:
    """Velocity from position by `method` ("highpass" or "zero_phase"), `(..., N)` → `(..., N)`.

    `cutoff_hz=None` uses `DEFAULT_CUTOFF_HZ[method]` (200 Hz high-pass, 50 Hz zero-phase).
    """
    if method not in VELOCITY_METHODS:
        raise TorchfricError(
            f"unknown velocity method {method!r}; choose one of {sorted(VELOCITY_METHODS)}"
        )
    cutoff = DEFAULT_CUTOFF_HZ[method] if cutoff_hz is None else cutoff_hz
    return VELOCITY_METHODS[method](q, dt, cutoff)


def settling_samples(method: str, dt: float, cutoff_hz: float | None = None) -> int:
    """Samples after a start in motion before `method`'s velocity is the motion's: the
    high-pass differentiator starts at its first step's speed, off by the noise of one
    difference and what the speed changed within the step, and that error decays as ``p^k``
    (to 1e-3 here; a segment that gaps cut is started after them, a margin);
    the zero-phase filter's ends are off for ≈ 3 cut-off periods (``3/(cutoff_hz·dt)``);
    0 for any other method (a measured velocity)."""
    if method not in VELOCITY_METHODS:
        return 0
    cutoff = DEFAULT_CUTOFF_HZ[method] if cutoff_hz is None else cutoff_hz
    if method == "zero_phase":
        return math.ceil(3.0 / (cutoff * dt))
    k, wc = 2.0 / dt, 2.0 * math.pi * cutoff
    p = (k - wc) / (k + wc)
    return 1 if p <= 0 else math.ceil(math.log(1e-3) / math.log(p))


def quiet_cutoff_hz(
    records: Sequence[tuple[ArrayLike, float]],
    highest: float,
    share: float = 0.02,
    lowest: float = 0.0,
) -> float:
    """The highest zero-phase cut-off, from `highest` down by steps of 10^0.1 to `highest`/25
    and not below `lowest`, at which the position noise of the records ``(q, dt)`` puts at most
    `share` of the signal's variance into `zero_phase_acceleration`, pooled over the records as
    a regression stacks them; the lowest step when none does.

    Inverse-dynamics least squares with a noisy q̈ biases the inertia towards 0 by about that
    share (errors in the regressor): a coarse encoder on a slow axis (4096 counts, J 0.5 kg m²,
    peaks of 4 rad/s²) gave q̈ noise 2.6 times its signal at 50 Hz and a pre-fitted inertia of
    0.116 for 0.5. The noise is each record's own, white: ``σ² = var(Δ⁴q) / 70``
    (`_white_variance`: a count's quantisation while the axis moves, or an analogue sensor's
    noise), through the filter's gain on unit white noise (a fixed
    20,000-sample draw), against ``var(q̈_fc)`` minus that. Up to 200,000 samples of each
    record are read."""
    draws = _unit_draws()
    qs = []
    for q, dt in records:  # each record's first 200,000 samples and its white noise σ²
        qa = _signal(q, "quiet_cutoff_hz: q", 5)[..., :200_000]
        qs.append((qa, dt, _white_variance(qa)))
    found = highest
    for step in range(15):
        fc = highest * 10 ** (-0.1 * step)
        if step and fc < lowest:
            break
        noise = signal = 0.0
        for qa, dt, white in qs:
            edge = math.ceil(3.0 / (fc * dt)) + 1
            if qa.shape[-1] <= 2 * edge + 2:
                continue
            a = zero_phase_acceleration(qa, dt, fc).numpy()[edge:-edge]
            gain = float(np.var(zero_phase_acceleration(draws, dt, fc).numpy()[edge:-edge]))
            noise, signal = noise + white * gain * a.size, signal + float(np.var(a)) * a.size
        found = fc
        if noise <= share * max(signal - noise, 0.0):
            break
    return found


def velocity_noise(q: ArrayLike, dt: float, method: str, cutoff_hz: float | None = None) -> float:
    """The standard deviation of the noise that `reconstruct_velocity` carries from the record's
    white position noise, ``σ² = var(Δ⁴q) / 70`` (`_white_variance`), through `method`'s
    gain on unit white noise (a fixed 20,000-sample draw); up to 200,000 samples are read.
    On a 4096-count encoder at 1 kHz (the heavy axis of docs/results.md) it gives 0.41 rad/s
    at 200 Hz, where the reconstructed velocity is 0.42 rad/s off the truth."""
    qa = _signal(q, "velocity_noise: q", 5)[..., :200_000]
    return _noise_std(_white_variance(qa), dt, method, cutoff_hz)


def _noise_std(white: float, dt: float, method: str, cutoff_hz: float | None) -> float:
    """The velocity noise of white position noise of variance `white`: `method`'s variance gain
    on unit white noise (`_unit_draws`)."""
    unit = reconstruct_velocity(_unit_draws(), dt, method, cutoff_hz).numpy()
    return math.sqrt(white * float(np.var(unit[settling_samples(method, dt, cutoff_hz) :])))


# The velocity noise (`velocity_noise`), as a share of the data's 95th-percentile speed, above
# which a cut-off is worth lowering (`quieter_cutoff_hz`), and the share it is lowered to.
NOISY_VELOCITY = 0.02
QUIET_VELOCITY = 0.01


def quieter_cutoff_hz(
    q: ArrayLike, dt: float, method: str, cutoff_hz: float, v95: float
) -> tuple[float, float] | None:
    """``(share, cut-off)`` when `method`'s velocity at `cutoff_hz` carries noise
    (`velocity_noise`) above `NOISY_VELOCITY` of the speed `v95`: that share, and the highest
    cut-off, in steps of 10^0.1 down to `cutoff_hz`/25, whose noise is at most `QUIET_VELOCITY`
    of it (two significant digits). None for a quieter record, no speed or a method without a
    cut-off. A heavy axis with a 4096-count encoder (3.1 % at 200 Hz) did not converge in 100
    passes at 200 Hz and converged in 3 at 100, 50 or 20 Hz (docs/results.md); the built-in
    rig is at 0.7 %."""
    if method not in DEFAULT_CUTOFF_HZ or not v95 > 0:
        return None
    white = _white_variance(_signal(q, "quieter_cutoff_hz: q", 5)[..., :200_000])  # read once
    share = _noise_std(white, dt, method, cutoff_hz) / v95
    if not share > NOISY_VELOCITY:
        return None
    quieter = cutoff_hz
    while (
        quieter > cutoff_hz / 25 and _noise_std(white, dt, method, quieter) > QUIET_VELOCITY * v95
    ):
        quieter *= 10**-0.1
    return share, float(f"{quieter:.2g}")


def _white_variance(q: np.ndarray) -> float:
    """The variance σ² of white noise on the positions `q`: ``var(Δ⁴q) / 70`` (white noise's
    fourth difference has variance C(8, 4)·σ² = 70σ²; a motion's own is ``q⁽⁴⁾ dt⁴``, which
    falls as ``(ω dt)⁴``). The second difference (``var(Δ²q) / 6``, used until 2026-11-27) took
    the motion for noise where the sampling is slow: the unbalanced disc at 40 Hz read 5.7 % of
    its v95 as velocity noise, 0.6 % by the fourth; both read 3.1 % on a 4096-count encoder at
    1 kHz, where quantisation is the noise."""
    return float(np.var(np.diff(q, 4))) / 70.0


def _unit_draws() -> np.ndarray:
    """A fixed draw of unit white noise (20,000 samples) whose filtered variance is a filter's
    gain on white noise."""
    return np.random.default_rng(0).standard_normal(20_000)
