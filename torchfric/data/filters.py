"""The linear filters of velocity reconstruction, in numpy: a Butterworth design in
second-order sections, a filter of such sections (with initial states) and its zero-phase
forward-backward run, the same operations as scipy.signal's ``butter(..., output="sos")``,
``sosfilt`` and ``sosfiltfilt(padtype="odd")``, which they match to rounding (tested).

Why not scipy.signal: importing it costs half a second (it imports scipy.stats), a fifth of a
whole quick-start run; these few functions are all that velocity reconstruction needs.

How the recursion runs fast in numpy: a section is the linear state-space system
``s[k+1] = A s[k] + b x[k]``, ``y[k] = c s[k] + d x[k]`` (transposed direct form II, state
of 2), so over a block of L samples ``y = H x + O s₀`` and ``s_L = A^L s₀ + G x`` with the
block's impulse-response matrix H (Toeplitz, h₀ = d, h_m = c A^{m−1} b), O (rows c A^i) and G
(columns A^{L−1−j} b). Every block's forced response is one matrix product; only the 2-vector
state is carried from block to block in a Python loop (N/L steps). It is the same linear map as
the sample-by-sample recursion, summed in another order: results agree to rounding for the
stable filters designed here.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["butter_sos", "sosfilt", "sosfiltfilt", "first_order"]

_BLOCK = 64


def butter_sos(order: int, cutoff_hz: float, fs: float) -> np.ndarray:
    """Digital Butterworth low-pass of `order` with its −3 dB point at `cutoff_hz` (sampling
    rate `fs`), as ``(ceil(order/2), 6)`` second-order sections ``[b0 b1 b2 1 a1 a2]``.

    The analog prototype's poles ``−exp(iπm/2N)``, ``m = −N+1, −N+3, …, N−1``, scaled to the
    pre-warped cut-off ``4 tan(π·cutoff/fs)`` and mapped by the bilinear transform (all zeros
    at z = −1); conjugate poles share a section, the real pole of an odd order has one of its
    own, the sections run from the pole farthest from the unit circle to the closest, and the
    gain (unity at DC) goes to the first."""
    m = np.arange(-order + 1, order, 2)
    warped = 4.0 * math.tan(math.pi * (2.0 * cutoff_hz / fs) / 2.0)
    poles = warped * -np.exp(1j * np.pi * m / (2 * order))
    z_poles = (4.0 + poles) / (4.0 - poles)
    gain = float(np.real(warped**order / np.prod(4.0 - poles)))
    upper = [p for p in z_poles if p.imag > 1e-14 * abs(p)]  # one of each conjugate pair
    real = [p for p in z_poles if abs(p.imag) <= 1e-14 * abs(p)]
    sections = []
    for p in sorted(upper, key=lambda p: -(1.0 - abs(p))):  # farthest from the circle first
        sections.append([1.0, 2.0, 1.0, 1.0, -2.0 * p.real, abs(p) ** 2])
    for p in real:  # an odd order's real pole: a first-order section (zero at −1)
        sections.insert(0, [1.0, 1.0, 0.0, 1.0, -p.real, 0.0])
    sos = np.array(sections, dtype=np.float64)
    sos[0, :3] *= gain
    return sos


def _section_blocks(section: np.ndarray, length: int) -> tuple[np.ndarray, ...]:
    """(A, H, O, G, A^L) of one section over blocks of `length` (see the module docstring)."""
    b0, b1, b2, _, a1, a2 = section
    A = np.array([[-a1, 1.0], [-a2, 0.0]])
    b = np.array([b1 - a1 * b0, b2 - a2 * b0])
    powers = [np.eye(2)]
    for _ in range(length):
        powers.append(A @ powers[-1])
    c = np.array([1.0, 0.0])
    h = np.array([b0] + [c @ powers[m - 1] @ b for m in range(1, length)])
    idx = np.arange(length)
    diff = idx[:, None] - idx[None, :]
    H = np.where(diff >= 0, h[np.clip(diff, 0, None)], 0.0)
    O = np.stack([c @ powers[i] for i in range(length)])
    G = np.stack([powers[length - 1 - j] @ b for j in range(length)], axis=1)
    return A, H, O, G, powers[length]


def _section(section: np.ndarray, x: np.ndarray, state: np.ndarray) -> np.ndarray:
    """One section along the last axis of `x` `(..., N)` from the states `state` `(..., 2)`."""
    n = x.shape[-1]
    length = min(_BLOCK, n)
    blocks = -(-n // length)
    _, H, O, G, AL = _section_blocks(section, length)
    xp = np.zeros((*x.shape[:-1], blocks * length))
    xp[..., :n] = x
    xb = xp.reshape(*x.shape[:-1], blocks, length)
    y = xb @ H.T  # forced responses (..., blocks, L)
    forced_end = xb @ G.T  # (..., blocks, 2)
    s = np.array(state, dtype=np.float64)
    starts = np.empty((*x.shape[:-1], blocks, 2))
    for i in range(blocks):
        starts[..., i, :] = s
        s = s @ AL.T + forced_end[..., i, :]
    y += starts @ O.T
    return y.reshape(*x.shape[:-1], blocks * length)[..., :n]


def sosfilt(sos: np.ndarray, x: np.ndarray, zi: np.ndarray | None = None) -> np.ndarray:
    """`x` `(..., N)` through the sections `sos` in turn, along the last axis; `zi`
    `(n_sections, ..., 2)` their initial states (default zero), as scipy.signal.sosfilt."""
    y = np.asarray(x, dtype=np.float64)
    for i, section in enumerate(sos):
        state = np.zeros((*y.shape[:-1], 2)) if zi is None else zi[i]
        y = _section(section, y, state)
    return y


def _steady_states(sos: np.ndarray) -> np.ndarray:
    """The sections' states `(n_sections, 2)` after a unit step has settled (scipy's
    ``sosfilt_zi``): each section's state for a constant input times the DC gain before it."""
    out = np.empty((len(sos), 2))
    scale = 1.0
    for i, (b0, b1, b2, _, a1, a2) in enumerate(sos):
        # (I − Aᵀ) s = b − a·b0 for the companion form of lfilter's transposed direct form II
        lhs = np.array([[1.0 + a1, -1.0], [a2, 1.0]])
        out[i] = scale * np.linalg.solve(lhs, np.array([b1 - a1 * b0, b2 - a2 * b0]))
        scale *= (b0 + b1 + b2) / (1.0 + a1 + a2)
    return out


def sosfiltfilt(sos: np.ndarray, x: np.ndarray, padlen: int) -> np.ndarray:
    """Zero-phase filtering of `x` `(..., N)` along its last axis: odd extension by `padlen`
    samples at each end (``2·x₀ − x[padlen:0:−1]``, a ramp continues as a ramp), the sections
    forwards from the steady state of the first sample, then backwards from that of the last,
    the extension cut off again; as ``scipy.signal.sosfiltfilt(sos, x, padtype="odd")``."""
    x = np.asarray(x, dtype=np.float64)
    if padlen > 0:
        head = 2.0 * x[..., :1] - x[..., padlen:0:-1]
        tail = 2.0 * x[..., -1:] - x[..., -2 : -padlen - 2 : -1]
        ext = np.concatenate([head, x, tail], axis=-1)
    else:
        ext = x
    zi = _steady_states(sos)
    zi_of = lambda v: zi[:, *(None,) * v.ndim, :] * v[..., None]  # noqa: E731
    y = sosfilt(sos, ext, zi_of(ext[..., 0]))
    y = sosfilt(sos, y[..., ::-1], zi_of(y[..., -1]))[..., ::-1]
    return y[..., padlen : y.shape[-1] - padlen] if padlen > 0 else y


def first_order(x: np.ndarray, p: float, g: float) -> np.ndarray:
    """``y[k] = p·y[k−1] + g·x[k]`` from ``y[−1] = 0`` along the last axis (|p| < 1): the
    one-pole section ``[g 0 0 1 −p 0]``."""
    return _section(np.array([g, 0.0, 0.0, 1.0, -p, 0.0]), np.asarray(x, dtype=np.float64),
                    np.zeros((*np.shape(x)[:-1], 2)))  # fmt: skip
