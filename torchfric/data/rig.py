"""The synthetic rig: torchfric's own "true system" (Hensen et al. §2, §5; DESIGN.md "Data").

A rotating arm without gravity, driven by a motor current ``u`` [A]::

    M v̇ = c_m u − F + τ_d(t),      q̇ = v,
    ż = v − σ0 |v| z / g(v),       g(v) = Fc + (Fs − Fc) exp(−(v/vs)²),
    F = σ0 z + σ1 ż + σ2 v                                   (LuGre friction)

so that, like the real arm, it shows pre-sliding (bristle deflection ``z``), hysteresis and a
Stribeck curve that the grey-box models ``M q̈ = c_m u − b q̇ − C(q̇)`` do not contain. The
steady-state friction curve is ``F_ss(v) = sign(v) g(v) + σ2 v``.

Parameter values (`RigParameters` defaults), each physically motivated:

- ``inertia = 0.0292 kg m²`` and ``c_m = 16 N m/A``: the values identified in the paper (§5).
- ``Fc = 0.15 N m``: Coulomb level of a small geared arm; sliding needs ``u > Fc/c_m ≈ 9.4 mA``.
- ``Fs = 0.25 N m``: static friction ≈ 1.7 Fc, a pronounced Stribeck peak as in the paper's Fig. 3.
- ``vs = 0.5 rad/s``: Stribeck velocity; the peak has decayed (< 2 %) by 1 rad/s.
- ``sigma0 = 1250 N m/rad``: the pre-sliding displacement ``Fs/σ0 = 2e-4 rad`` is one encoder
  count, so pre-sliding is (barely) visible in the measurement, as on a real encoder.
- ``sigma1 = 12 N m s/rad``: bristle damping ratio ``σ1 / (2 sqrt(σ0 M)) ≈ 0.99`` (well damped;
  the bristle resonance ``sqrt(σ0/M)/2π ≈ 33 Hz`` does not ring).
- ``sigma2 = 0.01 N m s/rad``: viscous friction; ``F_ss(10 rad/s) = 0.25 N m = Fs`` and the
  mechanical time constant is ``M/σ2 ≈ 2.9 s``.
- ``disturbance_std = 0.003 N m`` (2 % of Fc), low-pass 10 Hz: small and band-limited, well below
  the stick margins of the excitation, so stick phases stay stuck.
- ``quantum = 2e-4 rad``, ``dt = 1e-3 s``: the paper's encoder resolution and 1 kHz sampling.
- ``substeps = 10``: sub-step 0.1 ms; against a 10× finer reference the positions of a whole
  identification run agree to a fraction of an encoder count (see tests/test_rig.py).

Integration (`simulate_rig`): fixed sub-steps ``h = dt/substeps`` with the input held over each
sample (zero-order hold). Per sub-step, ``a = σ0 |v| / g(v)`` is frozen at the (extrapolated)
midpoint velocity; with the velocity linear over the sub-step the bristle equation
``ż = v − a z`` is solved *exactly* (exponential integrator, valid for any stiffness ``a h``), the
friction enters through the exact sub-step mean of ``z`` and the exact increment of ``z`` (the
``σ1 ż`` term), and the momentum balance is trapezoidal in ``σ2 v``. Everything is linear in
the new velocity, so one division solves the sub-step: no iteration, stable in stick (implicit
spring-damper) and in slip (bristle relaxation 10⁴–10⁵ 1/s handled exactly), second order in
``h``, and exactly ``F = F_ss(v)`` in steady sliding. Against a 10× finer reference the default
10 sub-steps are within 2e-5 rad (0.1 count) over a 30 s run; at 200 sub-steps the scheme agrees
with scipy's Radau (rtol 1e-10) to 1e-6. A plain Python-float loop runs at ≈ 0.8 µs per
sub-step: all five experiments (120 s at 1 kHz, 1.2 M sub-steps) take ≈ 1 s.

Experiments (`EXPERIMENTS`, `rig_experiment`, `generate`): identification (30 s, peak ≈ 10 rad/s),
validation (20 s, another signal, peak within the identification range), extrapolation (20 s,
peak ≈ 1.6× identification), and the same identification/validation inputs applied to the system
"after maintenance" (`RigParameters.changed`: no static friction, Fs = Fc).
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import pathlib
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import TorchfricError
from ..files import atomic_write_bytes, atomic_write_text

__all__ = [
    "RigParameters",
    "excitation",
    "simulate_rig",
    "EXPERIMENTS",
    "EXCITATIONS",
    "rig_experiment",
    "generate",
]

EXPERIMENTS: tuple[str, ...] = (
    "identification",
    "validation",
    "extrapolation",
    "changed_identification",
    "changed_validation",
)
EXCITATIONS: tuple[str, ...] = ("identification", "validation", "extrapolation")

# Per experiment: (excitation kind, duration [s], system "nominal" | "changed").
_EXPERIMENT_SPEC: dict[str, tuple[str, float, str]] = {
    "identification": ("identification", 30.0, "nominal"),
    "validation": ("validation", 20.0, "nominal"),
    "extrapolation": ("extrapolation", 20.0, "nominal"),
    "changed_identification": ("identification", 30.0, "changed"),
    "changed_validation": ("validation", 20.0, "changed"),
}
# Design peak velocity [rad/s] of each excitation kind (the feed-forward velocity profile).
_PEAK_VELOCITY: dict[str, float] = {
    "identification": 10.0,
    "validation": 8.5,
    "extrapolation": 16.0,
}
# Stream codes that make the random streams of different purposes independent for one seed.
_KIND_CODE: dict[str, int] = {"identification": 1, "validation": 2, "extrapolation": 3}
_DISTURBANCE_CODE: dict[str, int] = {name: 10 + i for i, name in enumerate(EXPERIMENTS)}


@dataclass(frozen=True)
class RigParameters:
    """Physical parameters of the synthetic rig (SI units; see the module docstring for why)."""

    inertia: float = 0.0292
    c_m: float = 16.0
    Fc: float = 0.15
    Fs: float = 0.25
    vs: float = 0.5
    sigma0: float = 1250.0
    sigma1: float = 12.0
    sigma2: float = 0.01
    quantum: float = 2e-4
    dt: float = 1e-3
    substeps: int = 10
    disturbance_std: float = 0.003

    def __post_init__(self) -> None:
        for name in ("inertia", "c_m", "Fc", "Fs", "vs", "sigma0", "quantum", "dt"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise TorchfricError(
                    f"RigParameters.{name} must be a finite number > 0, got {value!r}"
                )
        for name in ("sigma1", "sigma2", "disturbance_std"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise TorchfricError(
                    f"RigParameters.{name} must be a finite number >= 0, got {value!r}"
                )
        if self.Fs < self.Fc:
            raise TorchfricError(
                f"RigParameters.Fs ({self.Fs}) must be >= Fc ({self.Fc}): Fs is the static peak"
            )
        if (
            isinstance(self.substeps, bool)
            or not isinstance(self.substeps, int)
            or self.substeps < 1
        ):
            raise TorchfricError(
                f"RigParameters.substeps must be an integer >= 1, got {self.substeps!r}"
            )

    def stribeck(self, v: Any) -> Any:
        """``g(v) = Fc + (Fs − Fc) exp(−(v/vs)²)`` for a NumPy array or a torch tensor."""
        if _is_tensor(v):
            import torch

            return self.Fc + (self.Fs - self.Fc) * torch.exp(-((v / self.vs) ** 2))
        v = np.asarray(v, dtype=np.float64)
        return self.Fc + (self.Fs - self.Fc) * np.exp(-((v / self.vs) ** 2))

    def steady_state_friction(self, v: Any) -> Any:
        """``F_ss(v) = sign(v) g(v) + σ2 v`` [N m]; same type (array or tensor) as ``v``."""
        if _is_tensor(v):
            import torch

            return torch.sign(v) * self.stribeck(v) + self.sigma2 * v
        v = np.asarray(v, dtype=np.float64)
        return np.sign(v) * self.stribeck(v) + self.sigma2 * v

    def changed(self) -> RigParameters:
        """The system "after maintenance" (paper §5): no static friction (Fs = Fc), else equal."""
        return dataclasses.replace(self, Fs=self.Fc)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _check_seed(seed: Any) -> int:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise TorchfricError(f"rig seed must be an integer >= 0, got {seed!r}")
    return int(seed)


def _is_tensor(v: Any) -> bool:
    return type(v).__module__.startswith("torch") and hasattr(v, "detach")


# --------------------------------------------------------------------------------------------
# Excitation
# --------------------------------------------------------------------------------------------


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

    # Plan segments: ("stick", t0, t1, level) and ("move", t0, t1, coefficients, scale).
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


# --------------------------------------------------------------------------------------------
# Simulation
# --------------------------------------------------------------------------------------------


def _disturbance(n: int, dt: float, std: float, seed: Sequence[int]) -> np.ndarray:
    """Band-limited Gaussian torque τ_d [N m] with sample standard deviation ``std``.

    White noise through a 2nd-order Butterworth low-pass (10 Hz, bilinear transform; equal to
    ``scipy.signal.butter`` + ``sosfilt`` without importing scipy.signal), 1000 samples of
    burn-in, mean removed, scaled to ``std``.
    """
    if std == 0.0 or n < 2:
        return np.zeros(n)
    rng = np.random.default_rng(list(seed))
    burn = 1000
    white = rng.standard_normal(n + burn).tolist()
    k = math.tan(math.pi * min(10.0, 0.4 / dt) * dt)
    norm = 1.0 / (1.0 + math.sqrt(2.0) * k + k * k)
    b0 = k * k * norm
    a1 = 2.0 * (k * k - 1.0) * norm
    a2 = (1.0 - math.sqrt(2.0) * k + k * k) * norm
    x1 = x2 = y1 = y2 = 0.0
    out = []
    for x in white:
        y = b0 * (x + 2.0 * x1 + x2) - a1 * y1 - a2 * y2
        out.append(y)
        x2, x1, y2, y1 = x1, x, y1, y
    d = np.asarray(out[burn:])
    d -= d.mean()
    return d * (std / d.std())


def _integrate(
    cmu: list[float],
    dist: list[float],
    p: RigParameters,
    q: float,
    v: float,
    z: float,
) -> tuple[list[float], list[float], list[float]]:
    """The sub-stepped LuGre integrator (see the module docstring); states at the sample times.

    One sub-step ``h`` from ``(q, v, z)`` with the torque ``f = c_m u + τ_d`` held:

    - ``a = σ0 |v_m| / g(v_m)`` frozen at the midpoint velocity ``v_m``, extrapolated from the
      previous sub-step's increment (second order, no extra solve);
    - with ``v(t)`` linear from ``v`` to the unknown ``v1`` and ``x = a h``, the bristle equation
      ``ż = v − a z`` is solved exactly: ``z1 = e^{−x} z + v h (φ − ψ) + v1 h ψ`` and its mean
      ``z̄ = z φ + v h (ψ − χ) + v1 h χ`` with ``φ = (1 − e^{−x})/x``, ``ψ = (1 − φ)/x``,
      ``χ = (1/2 − ψ)/x`` (Taylor series for small ``x``);
    - momentum over the sub-step: ``M (v1 − v) = h f − h σ0 z̄ − σ1 (z1 − z) − h σ2 (v + v1)/2``,
      linear in ``v1`` with a denominator ``> M``: one division, no iteration, no instability;
    - ``q1 = q + h (v + v1)/2`` (exact for the linear velocity).
    """
    expm1 = math.expm1
    exp = math.exp
    ns = p.substeps
    h = p.dt / ns
    M = p.inertia
    Fc = p.Fc
    dF = p.Fs - p.Fc
    ivs = 1.0 / p.vs
    s0 = p.sigma0
    s1 = p.sigma1
    hs0 = h * s0
    hhs0 = h * hs0
    s1h = s1 * h
    hh = 0.5 * h
    hs2h = 0.5 * h * p.sigma2
    m_num = M - hs2h
    den0 = M + hs2h
    dv = 0.0  # previous sub-step's velocity increment
    qs = [q]
    vs = [v]
    zs = [z]
    for k in range(len(cmu) - 1):
        hf = h * (cmu[k] + dist[k])
        for _ in range(ns):
            vm = v + 0.5 * dv
            w = vm * ivs
            x = hs0 * (vm if vm >= 0.0 else -vm) / (Fc + dF * exp(-w * w))  # x = a h
            if x < 1e-2:
                ph = 1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0 - x / 120.0)))
                E = 1.0 - x * ph
                ps = 0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0 - x * (1.0 / 120.0 - x / 720.0)))
                ch = 1.0 / 6.0 - x * (
                    1.0 / 24.0 - x * (1.0 / 120.0 - x * (1.0 / 720.0 - x / 5040.0))
                )
            else:
                em1 = expm1(-x)
                E = 1.0 + em1
                ph = -em1 / x
                ps = (1.0 - ph) / x
                ch = (0.5 - ps) / x
            vh = v * h
            z_mean0 = z * ph + vh * (ps - ch)  # z̄ without its v1 term
            dz0 = z * (E - 1.0) + vh * (ph - ps)  # z1 − z without its v1 term
            v1 = (m_num * v + hf - hs0 * z_mean0 - s1 * dz0) / (den0 + hhs0 * ch + s1h * ps)
            z += dz0 + v1 * h * ps
            q += hh * (v + v1)
            dv = v1 - v
            v = v1
        qs.append(q)
        vs.append(v)
        zs.append(z)
    return qs, vs, zs


def simulate_rig(
    params: RigParameters,
    u: np.ndarray,
    *,
    seed: int | Sequence[int],
    x0: Sequence[float] = (0.0, 0.0, 0.0),
) -> dict[str, np.ndarray]:
    """Simulate the rig under the sampled input ``u`` [A] (zero-order hold, period ``params.dt``).

    ``seed`` selects the disturbance realisation; ``x0 = (q, q̇, z)`` is the initial state.
    Returns arrays of length ``len(u)`` at ``t = k dt``: ``t``, ``u``, ``q_true``, ``qdot_true``,
    ``z``, ``friction`` (the LuGre torque F), ``disturbance`` (τ_d) and ``q`` (the measurement:
    ``q_true`` rounded to the nearest encoder count).
    """
    if not isinstance(params, RigParameters):
        raise TorchfricError(f"simulate_rig needs RigParameters, got {type(params).__name__}")
    u = np.asarray(u, dtype=np.float64)
    if u.ndim != 1 or u.size < 1:
        raise TorchfricError(
            f"simulate_rig needs a 1-D input u with >= 1 samples, got shape {u.shape}"
        )
    if not np.all(np.isfinite(u)):
        raise TorchfricError("simulate_rig input u contains NaN or inf; give finite currents")
    x0 = tuple(float(x) for x in x0)
    if len(x0) != 3 or not all(math.isfinite(x) for x in x0):
        raise TorchfricError(f"simulate_rig x0 must be 3 finite numbers (q, qdot, z), got {x0!r}")
    seed_list = [_check_seed(s) for s in ((seed,) if np.ndim(seed) == 0 else seed)]
    n = u.size
    dist = _disturbance(n, params.dt, params.disturbance_std, seed_list)
    qs, vs, zs = _integrate((params.c_m * u).tolist(), dist.tolist(), params, *x0)
    q_true = np.asarray(qs)
    v = np.asarray(vs)
    z = np.asarray(zs)
    g = params.stribeck(v)
    zdot = v - params.sigma0 * np.abs(v) * z / g
    friction = params.sigma0 * z + params.sigma1 * zdot + params.sigma2 * v
    q = np.round(q_true / params.quantum) * params.quantum + 0.0  # + 0.0: no "-0" in files
    return {
        "t": np.arange(n) * params.dt,
        "u": u.copy(),
        "q_true": q_true,
        "qdot_true": v,
        "z": z,
        "friction": friction,
        "disturbance": dist,
        "q": q,
    }


# --------------------------------------------------------------------------------------------
# Named experiments and data files
# --------------------------------------------------------------------------------------------

_CACHE: dict[tuple[str, int], dict[str, np.ndarray]] = {}


def _check_name(name: str) -> tuple[str, float, str]:
    if name not in _EXPERIMENT_SPEC:
        raise TorchfricError(
            f"unknown rig experiment {name!r}; choose one of {', '.join(EXPERIMENTS)}"
        )
    return _EXPERIMENT_SPEC[name]


def _run_experiment(name: str, seed: int) -> dict[str, np.ndarray]:
    kind, duration, system = _check_name(name)
    nominal = RigParameters()
    params = nominal.changed() if system == "changed" else nominal
    u = excitation(kind, duration=duration, dt=nominal.dt, seed=seed, params=nominal)
    return simulate_rig(params, u, seed=(int(seed), _DISTURBANCE_CODE[name]))


def rig_experiment(name: str, *, seed: int = 0) -> dict[str, np.ndarray]:
    """One named experiment of `EXPERIMENTS` (see `simulate_rig` for the keys); deterministic.

    Results are memoised per ``(name, seed)``; the returned arrays are copies.
    """
    _check_name(name)
    key = (name, _check_seed(seed))
    if key not in _CACHE:
        _CACHE[key] = _run_experiment(name, int(seed))
    return {k: v.copy() for k, v in _CACHE[key].items()}


def _friction_table(params: RigParameters, v: np.ndarray) -> list[list[float]]:
    return [[float(a), float(b)] for a, b in zip(v, params.steady_state_friction(v), strict=True)]


def _write_npz(path: pathlib.Path, arrays: dict[str, np.ndarray]) -> None:
    """An uncompressed ``.npz`` with fixed time stamps, so equal arrays give identical bytes."""
    whole = io.BytesIO()
    with zipfile.ZipFile(whole, "w", compression=zipfile.ZIP_STORED) as zf:
        for key in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arrays[key]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())
    atomic_write_bytes(path, whole.getvalue())


def generate(
    outdir: str | pathlib.Path, *, seed: int = 0, force: bool = False
) -> dict[str, pathlib.Path]:
    """Write every experiment as ``<outdir>/<name>.csv`` (``t,u,q``), plus ground truth.

    ``truth.json`` holds the nominal and changed `RigParameters`, per experiment its system,
    duration, seed and peak |q̇|, and the steady-state friction curve ``F_ss`` of both systems
    on a velocity grid; ``truth_states.npz`` holds ``<name>/<state>`` arrays (q_true,
    qdot_true, friction, z, disturbance). Creates ``outdir``; same seed → identical bytes.
    Returns ``{file stem: path}`` for every file written. Existing files are replaced only with
    `force` (otherwise nothing is written); each file is written atomically.
    """
    seed = _check_seed(seed)
    out = pathlib.Path(outdir)
    targets = [out / f"{n}.csv" for n in EXPERIMENTS] + [out / "truth.json", out / "truth_states.npz"]
    existing = [p.name for p in targets if p.exists() or p.is_symlink()]
    if existing and not force:
        raise TorchfricError(
            f"{out} already holds {', '.join(existing[:4])}"
            + (f" and {len(existing) - 4} more" if len(existing) > 4 else "")
            + "; choose another folder, or pass --force to replace the rig's files there"
        )
    if out.exists() and not out.is_dir():
        raise TorchfricError(f"{out} is a file, not a folder; give a folder for the rig's data")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TorchfricError(
            f"cannot create output directory {str(out)!r}: {exc.strerror}"
        ) from exc
    nominal = RigParameters()
    changed = nominal.changed()
    paths: dict[str, pathlib.Path] = {}
    states: dict[str, np.ndarray] = {}
    per_experiment: dict[str, dict[str, Any]] = {}
    for name in EXPERIMENTS:
        data = rig_experiment(name, seed=seed)
        kind, duration, system = _EXPERIMENT_SPEC[name]
        path = out / f"{name}.csv"
        table = np.column_stack([data["t"], data["u"], data["q"]])
        rows = ("%.17g,%.17g,%.17g\n" * len(table)) % tuple(table.ravel().tolist())
        atomic_write_text(path, "t,u,q\n" + rows)
        paths[name] = path
        for key in ("q_true", "qdot_true", "friction", "z", "disturbance"):
            states[f"{name}/{key}"] = data[key]
        per_experiment[name] = {
            "system": system,
            "excitation": kind,
            "duration": duration,
            "samples": int(data["t"].size),
            "seed": int(seed),
            "disturbance_seed": [int(seed), _DISTURBANCE_CODE[name]],
            "design_peak_qdot": _PEAK_VELOCITY[kind],
            "peak_abs_qdot": float(np.max(np.abs(data["qdot_true"]))),
        }
    grid = np.round(np.linspace(-20.0, 20.0, 801), 10)
    truth = {
        "description": "torchfric synthetic rig: LuGre friction, Stribeck curve (torchfric.rig)",
        "seed": int(seed),
        "parameters": {"nominal": nominal.to_dict(), "changed": changed.to_dict()},
        "experiments": per_experiment,
        "steady_state_friction": {
            "columns": ["v", "F_ss"],
            "nominal": _friction_table(nominal, grid),
            "changed": _friction_table(changed, grid),
        },
    }
    path = out / "truth.json"
    atomic_write_text(path, json.dumps(truth, indent=1, sort_keys=True) + "\n")
    paths["truth"] = path
    path = out / "truth_states.npz"
    _write_npz(path, states)
    paths["truth_states"] = path
    return paths
