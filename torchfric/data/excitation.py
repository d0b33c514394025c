"""Input currents for the synthetic rig's experiments (`excitation`).

Each excitation kind ("identification", "validation", "extrapolation") is a random sequence of
stick and move segments with its own design peak velocity; see `excitation` for the design.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import TorchfricError
from .rig_model import RigParameters, _check_seed

__all__ = ["EXCITATIONS", "excitation"]

EXCITATIONS: tuple[str, ...] = ("identification", "validation", "extrapolation")

# Design peak velocity [rad/s] of each excitation kind (the feed-forward velocity profile).
_PEAK_VELOCITY: dict[str, float] = {
    "identification": 10.0,
    "validation": 8.5,
    "extrapolation": 16.0,
}
# Stream codes that make the random streams of different purposes independent for one seed.
_KIND_CODE: dict[str, int] = {"identification": 1, "validation": 2, "extrapolation": 3}


def excitation(
    kind: str,
    *,
    duration: float,
    dt: float = 1e-3,
    seed: int = 0,
    peak_velocity: float | None = None,
    params: RigParameters | None = None,
    max_acceleration: float = 50.0,
) -> np.ndarray:
    """Input current ``u`` [A] (``(round(duration/dt),)``, zero-order hold) for one experiment.

    Design: a random sequence of *stick* and *move* segments. A stick segment (0.15–0.8 s) holds
    the current at zero or at a random level below ``0.7 Fc / c_m``, i.e. below the static
    friction of both the nominal and the changed system, so the arm rests there (pre-sliding
    only). A move segment (0.6–2.5 s) follows a smooth velocity profile ``v_d(t) = A w(t/T)``,
    ``w(s) = Σ_k c_k sin(kπs)`` with 1–5 random harmonics (so most segments reverse direction
    while sliding) that starts and ends at rest; the current is the inverse-dynamics feed-forward
    ``u = (M v̇_d + F_ss(v_d) + 0.3 Fs sign(v_d) exp(−(v_d/vs)²)) / c_m`` of the nominal rig
    (the last term is a breakaway margin, so that motion starts decisively rather than at exactly
    the static-friction level), sampled at the middle of each sample.
    The stick phases reset the open-loop drift, so the measured peak velocity stays close to the
    design. Amplitudes ``A``: 30 % low-velocity (0.2–1.5 rad/s, the Stribeck region), the rest
    uniform up to ``peak_velocity``; one of the first three move segments (when the duration
    holds it) is scaled to exactly ``peak_velocity`` (default 10 rad/s identification, 8.5
    validation, 16 extrapolation). Accelerations are capped at ``max_acceleration`` [rad/s²] by
    stretching a segment (50 rad/s², ≈ 6× the friction deceleration Fs/M). The signal ends at
    rest with zero current. Deterministic for ``(kind, seed)``; other kinds give other signals.
    """
    if kind not in _KIND_CODE:
        raise TorchfricError(
            f"unknown excitation kind {kind!r}; choose one of {', '.join(EXCITATIONS)}"
        )
    for name, value in (("duration", duration), ("dt", dt), ("max_acceleration", max_acceleration)):
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise TorchfricError(f"excitation {name} must be a finite number > 0, got {value!r}")
    p = params if params is not None else RigParameters()
    vmax = _PEAK_VELOCITY[kind] if peak_velocity is None else float(peak_velocity)
    if not (math.isfinite(vmax) and vmax > 0):
        raise TorchfricError(f"excitation peak_velocity must be a finite number > 0, got {vmax!r}")
    n = int(round(duration / dt))
    if n < 2:
        raise TorchfricError(
            f"excitation needs at least 2 samples, got duration={duration}, dt={dt}"
        )
    rng = np.random.default_rng([_check_seed(seed), _KIND_CODE[kind]])
    segments = _plan_segments(rng, p, vmax, duration, dt, max_acceleration)
    return _feed_forward(segments, p, n, dt)


def _plan_segments(
    rng: np.random.Generator,
    p: RigParameters,
    vmax: float,
    duration: float,
    dt: float,
    max_acceleration: float,
) -> list[tuple[Any, ...]]:
    """The random segment plan of `excitation`, drawn from `rng` in a fixed order.

    Segments are ``("stick", t0, t1, level)`` and ``("move", t0, t1, coefficients, scale)``,
    alternating from a 0.5 s rest and ending with a stick at zero current up to `duration`.
    """
    peak_index = int(rng.integers(0, 3))  # this move segment is scaled to exactly vmax
    s_fine = np.linspace(0.0, 1.0, 2001)
    segments: list[tuple[Any, ...]] = []
    t = 0.0
    while True:
        if not segments:
            t_stick, level = 0.5, 0.0  # start at rest, no current
        else:
            t_stick = float(rng.uniform(0.15, 0.8))
            level = 0.0 if rng.random() < 0.3 else float(rng.uniform(-0.7, 0.7)) * p.Fc / p.c_m
        segments.append(("stick", t, t + t_stick, level))
        t += t_stick
        n_harm = int(rng.choice([1, 2, 3, 4, 5], p=[0.1, 0.25, 0.3, 0.2, 0.15]))
        coef = rng.standard_normal(n_harm) / np.sqrt(np.arange(1, n_harm + 1))
        if rng.random() < 0.3:
            amp = float(rng.uniform(0.2, 1.5))
        else:
            amp = float(rng.uniform(min(1.5, vmax), vmax))
        length = float(rng.uniform(0.6, 2.5))
        n_moves = sum(seg[0] == "move" for seg in segments)
        if n_moves == peak_index:
            amp = vmax
        w, dw = _harmonics(s_fine, coef)
        scale = amp / np.max(np.abs(w))
        length = max(length, scale * np.max(np.abs(dw)) / max_acceleration)
        if t + length + 0.3 > duration:
            break
        segments.append(("move", t, t + length, coef, scale))
        t += length
    segments.append(("stick", t, max(t, duration) + dt, 0.0))
    return segments


def _feed_forward(
    segments: list[tuple[Any, ...]], p: RigParameters, n: int, dt: float
) -> np.ndarray:
    """The `n` samples of current that realise the segment plan on the nominal rig `p`."""
    tm = (np.arange(n) + 0.5) * dt  # mid-sample times (zero-order hold)
    u = np.zeros(n)
    for seg in segments:
        mask = (tm >= seg[1]) & (tm < seg[2])
        if seg[0] == "stick":
            u[mask] = seg[3]
            continue
        _, t0, t1, coef, scale = seg
        w, dw = _harmonics((tm[mask] - t0) / (t1 - t0), coef)
        v_d = scale * w
        a_d = scale * dw / (t1 - t0)
        # Breakaway margin: 30 % of Fs on top of the feed-forward near zero velocity, fading out
        # over the Stribeck velocity. Without it a slow start asks for exactly Fs, and whether
        # the arm breaks away becomes a coin toss for the rig and for every model of it.
        kick = 0.3 * p.Fs * np.sign(v_d) * np.exp(-((v_d / p.vs) ** 2))
        u[mask] = (p.inertia * a_d + p.steady_state_friction(v_d) + kick) / p.c_m
    return u


def _harmonics(s: np.ndarray, coef: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``w(s) = Σ_k c_k sin(kπs)`` and ``dw/ds``, summed term by term (no BLAS: bitwise stable)."""
    w = np.zeros_like(s)
    dw = np.zeros_like(s)
    for j, c in enumerate(coef.tolist(), start=1):
        w += c * np.sin(j * np.pi * s)
        dw += c * j * np.pi * np.cos(j * np.pi * s)
    return w, dw
