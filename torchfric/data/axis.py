"""An independent simulated machine to test torchfric's claims on (`AxisParameters`, `axis_record`).

Why it exists: the built-in rig (`torchfric.data.rig`) is the machine torchfric was developed
on. A claim such as "the ±2σ band covers the truth 95 % of the time" must also hold on a
machine torchfric has never seen, of another scale and with another friction law. This module
is such a machine, written without torchfric's models or vector field: one axis

    M q̈ = c_m u − b q̇ − F(q̇) − offset + τ_d        (τ_d: white torque noise, held per sample)

- ``friction="stribeck"`` (static): ``F(v) = g(v) tanh(v/ε)``, ``g(v) = Fc + (Fs − Fc)
  exp(−(v/vs)²)``, ``ε = smoothing·vs`` (default 1e-3·vs). ε is far below every velocity the
  excitation aims at, so F is sign(v)·g(v) to within 1e-3 of Fs above 4ε; in rest phases the axis
  creeps at ``ε atanh(τ/Fs)`` (≈ 1e-3 rad/s on the default axis: stick, to a few counts).
  Integrated with classic RK4, sub-steps ``h = dt/n`` with ``n ≥ substeps`` raised until
  ``h Fs/(ε M) ≤ 0.5`` (the stiff slope of tanh near zero stays far inside RK4's stability).
- ``friction="lugre"`` (dynamic): bristle state z, ``ż = v − σ0 |v| z / g(v)``, ``F = σ0 z +
  σ1 ż`` (+ b v), integrated by the project's own true-system integrator
  (`torchfric.data.rig_model.python_integrator`, exact exponential sub-steps), never by the
  identified model.

The input is zero-order held over each sample ``dt``; the measured position is the true one
rounded to the encoder ``quantum`` plus optional white noise ``noise_std``.

Excitation (`axis_record`): a reference velocity made of random segments — random-phase
multisines (0.2–2 Hz), slow triangles through zero (|v| ≤ 4 vs: the Stribeck region, slow
reversals), trapezoids to 60–100 % of ``max_speed`` and back (so b is identifiable) and rests
(stiction) — each signed so that the reference position returns towards 0. The input is what a
lab's position loop would apply, computed inside the simulation from the *measured* position:
``u = u_ff + kp (q_ref − q_m) + kd (v_ref − v̂)``, a feed-forward ``u_ff = 0.9 (M a_ref + b v_ref +
Fc tanh(v_ref/(0.1 vs)))/c_m`` from 10 %-low guesses, PD gains for a 2 Hz loop (ζ = 0.7) and v̂
the measured position's difference through a 50 Hz first-order low-pass; the amplifier clips u at
±2 ``max_input``. The record holds the applied u, so replaying it open loop (`simulate_axis`, same
seed) gives the same trajectory. (A LuGre axis's recorded trajectory is the response to that u in
one run of the rig's integrator, whose sub-step extrapolation a per-sample restart would lose; the
loop itself sees a per-sample integration of it, within a count of that.)
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Literal

import numpy as np

from ..errors import TorchfricError
from .rig_model import RigParameters, integrator_constants, python_integrator

__all__ = ["LINEAR_AXIS", "LUGRE_AXIS", "STRIBECK_AXIS", "AxisParameters", "axis_record",
           "excitation_reference", "simulate_axis", "true_friction", "write_csv"]  # fmt: skip

Seed = int | Sequence[int]
_KIND_CODE = {"identification": 11, "validation": 12}


@dataclass(frozen=True)
class AxisParameters:
    """One axis (SI units; rotary: rad, N m, A; linear: m, N, V). Defaults: a small motor's
    axis with Stribeck friction — |u| ≤ 1 A, |c_m u| ≤ 0.8 N m, speeds up to 40 rad/s, Stribeck
    velocity 1.5 rad/s (≈ 0.5 × a tenth of the typical 30 rad/s), a 20000-count encoder."""

    inertia: float = 0.012  # M [kg m²]
    c_m: float = 0.8  # torque per unit of u [N m/A]
    viscous: float = 0.004  # b [N m s/rad]
    coulomb: float = 0.05  # Fc [N m]
    static: float = 0.08  # Fs [N m]
    stribeck_velocity: float = 1.5  # vs [rad/s]
    offset: float = 0.0  # constant torque subtracted [N m]
    quantum: float = 2 * math.pi / 20000  # encoder resolution [rad]
    dt: float = 1e-3  # sample time [s]
    disturbance_std: float = 0.0  # τ_d [N m], held per sample (std of the filtered noise)
    disturbance_bandwidth: float = 0.0  # τ_d's first-order low-pass [Hz]; 0: white
    noise_std: float = 0.0  # additive position noise [rad]
    friction: Literal["stribeck", "lugre"] = "stribeck"
    sigma0: float = 0.0  # LuGre bristle stiffness [N m/rad]
    sigma1: float = 0.0  # LuGre bristle damping [N m s/rad]
    smoothing: float = 1e-3  # ε / vs of the Stribeck law's tanh
    substeps: int = 10  # minimum integration sub-steps per sample
    max_speed: float = 40.0  # excitation's peak reference speed [rad/s]
    max_input: float = 1.0  # input the excitation may use [A]

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "friction":
                if value not in ("stribeck", "lugre"):
                    raise TorchfricError(f"AxisParameters.friction = {value!r}; expected "
                                         "'stribeck' or 'lugre'")  # fmt: skip
            elif f.name == "substeps":
                if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                    raise TorchfricError(f"AxisParameters.substeps = {value!r}; expected int >= 1")
            elif not (isinstance(value, int | float) and math.isfinite(value)):
                raise TorchfricError(f"AxisParameters.{f.name} = {value!r}; expected a number")
            elif f.name != "offset" and value < 0:
                raise TorchfricError(f"AxisParameters.{f.name} = {value!r}; expected >= 0")
        for name in ("inertia", "c_m", "coulomb", "stribeck_velocity", "quantum", "dt",
                     "smoothing", "max_speed", "max_input"):  # fmt: skip
            if getattr(self, name) <= 0:
                raise TorchfricError(f"AxisParameters.{name} must be > 0")
        if self.static < self.coulomb:
            raise TorchfricError("AxisParameters.static must be >= coulomb (the Stribeck peak)")
        if self.friction == "lugre" and (self.sigma0 <= 0 or self.sigma1 <= 0):
            raise TorchfricError("a LuGre axis needs sigma0 > 0 and sigma1 > 0")
        if self.max_acceleration <= 0:
            raise TorchfricError("max_input cannot overcome static + viscous friction at max_speed")

    @property
    def max_acceleration(self) -> float:
        """Reference acceleration limit: 80 % of what ``max_input`` leaves at ``max_speed``."""
        spare = self.c_m * self.max_input - self.static - self.viscous * self.max_speed
        return 0.8 * spare / self.inertia


STRIBECK_AXIS = AxisParameters()
"""The user-style Stribeck axis (the defaults)."""
LINEAR_AXIS = AxisParameters(inertia=95.0, c_m=35.0, viscous=200.0, coulomb=20.0, static=30.0,
                             stribeck_velocity=0.01, quantum=1e-6, max_speed=0.2,
                             max_input=3.0)  # fmt: skip
"""An EMPS-like linear axis: 95 kg, 35 N/V, 200 N s/m, Fc 20 N, Fs 30 N, 1 µm encoder, ≤ 0.2 m/s
(no offset; EMPS's −3.2 N would need ``offset=-3.2`` and a model with an offset term)."""
LUGRE_AXIS = AxisParameters(inertia=0.004, c_m=0.5, viscous=0.002, coulomb=0.02, static=0.035,
                            stribeck_velocity=1.0, friction="lugre", sigma0=300.0, sigma1=2.0,
                            substeps=40)  # fmt: skip
"""A LuGre axis unlike the rig (M 0.0292, c_m 16, Fc 0.15): 7× lighter, 30× smaller torque
scale; pre-sliding Fs/σ0 = 1.2e-4 rad (0.4 count), bristle damping ratio σ1/(2√(σ0 M)) ≈ 0.9;
40 sub-steps per sample keep q within 0.1 count of a 200-sub-step reference over 30 s."""


def _g(p: AxisParameters, v: np.ndarray | float) -> np.ndarray | float:
    """``g(v) = Fc + (Fs − Fc) exp(−(v/vs)²)``."""
    return p.coulomb + (p.static - p.coulomb) * np.exp(
        -((np.asarray(v) / p.stribeck_velocity) ** 2)
    )


def true_friction(p: AxisParameters, v: np.ndarray, *, include_offset: bool = False) -> np.ndarray:
    """True steady-state friction ``b v + F(v)`` at velocities v (``F = g tanh(v/ε)`` for
    "stribeck", ``sign(v) g(v)`` for "lugre"), plus ``offset`` if `include_offset`."""
    v = np.asarray(v, dtype=np.float64)
    eps = p.smoothing * p.stribeck_velocity
    shape = np.tanh(v / eps) if p.friction == "stribeck" else np.sign(v)
    return p.viscous * v + _g(p, v) * shape + (p.offset if include_offset else 0.0)


def _rig_constants(p: AxisParameters) -> tuple[float, ...]:
    """The rig integrator's constants for this LuGre axis (``sigma2`` is the viscous b)."""
    rig = RigParameters(inertia=p.inertia, c_m=p.c_m, Fc=p.coulomb, Fs=p.static,
                        vs=p.stribeck_velocity, sigma0=p.sigma0, sigma1=p.sigma1, sigma2=p.viscous,
                        quantum=p.quantum, dt=p.dt, substeps=p.substeps, disturbance_std=0.0)  # fmt: skip
    return integrator_constants(rig)


def _stepper(p: AxisParameters) -> Callable[[tuple[float, ...], float], tuple[float, ...]]:
    """One sample's step ``state → state`` under the held torque τ (c_m u + τ_d − offset)."""
    if p.friction == "lugre":
        consts, zero = _rig_constants(p), np.zeros(2)

        def lugre(x: tuple[float, ...], tau: float) -> tuple[float, ...]:
            q, v, z = python_integrator(np.array([tau, 0.0]), zero, consts, p.substeps, *x)
            return float(q[1]), float(v[1]), float(z[1])

        return lugre
    M, b, Fc, dF = p.inertia, p.viscous, p.coulomb, p.static - p.coulomb
    ivs, ieps = 1.0 / p.stribeck_velocity, 1.0 / (p.smoothing * p.stribeck_velocity)
    n = max(p.substeps, math.ceil(p.dt * p.static * ieps / M / 0.5))
    h, exp, tanh = p.dt / n, math.exp, math.tanh

    def acc(v: float, tau: float) -> float:
        w = v * ivs
        return (tau - b * v - (Fc + dF * exp(-w * w)) * tanh(v * ieps)) / M

    def stribeck(x: tuple[float, ...], tau: float) -> tuple[float, ...]:
        q, v = x
        for _ in range(n):  # classic RK4 on (q, v); q̇ = v
            k1 = acc(v, tau)
            v2 = v + 0.5 * h * k1
            k2 = acc(v2, tau)
            v3 = v + 0.5 * h * k2
            k3 = acc(v3, tau)
            v4 = v + h * k3
            k4 = acc(v4, tau)
            q += h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v += h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return q, v

    return stribeck


def _run(p: AxisParameters, u: np.ndarray | None, ref: tuple[np.ndarray, np.ndarray] | None,
         n: int, seed: Seed, change: tuple[int, AxisParameters] | None = None
         ) -> tuple[np.ndarray, ...]:  # fmt: skip
    """Simulate n samples open loop (u) or in the position loop (ref = (v_ref, a_ref)).
    Returns the applied u, measured q, true q, true q̇. A LuGre axis's trajectory is the response
    to the applied u in one run of the rig's integrator (restarting it every sample, as the loop
    must, drops its sub-step extrapolation: tens of counts off over 30 s instead of < 0.1).
    `change` = (k, after): from sample k on the machine is `after` (Stribeck only; the state
    carries over, the position loop keeps `p`'s feed-forward)."""
    seeds = [int(s) for s in ((seed,) if np.ndim(seed) == 0 else seed)]
    if any(s < 0 for s in seeds):
        raise TorchfricError(f"seed must be integers >= 0, got {seed!r}")
    rng = np.random.default_rng(seeds)
    dist = rng.standard_normal(n)
    if p.disturbance_bandwidth > 0:  # first-order low-pass, rescaled to unit variance
        a = math.exp(-2 * math.pi * p.disturbance_bandwidth * p.dt)
        for k in range(1, n):
            dist[k] = a * dist[k - 1] + math.sqrt(1 - a * a) * dist[k]
    dist = dist * p.disturbance_std
    noise = rng.standard_normal(n) * p.noise_std
    step, after = _stepper(p), (_stepper(change[1]) if change is not None else None)
    x: tuple[float, ...] = (0.0, 0.0, 0.0) if p.friction == "lugre" else (0.0, 0.0)
    ua, qm, qt, vt = (np.zeros(n) for _ in range(4))
    if ref is not None:
        v_ref, a_ref = ref
        q_ref = np.concatenate(([0.0], np.cumsum(0.5 * (v_ref[1:] + v_ref[:-1])) * p.dt))
        ff = p.inertia * a_ref + p.viscous * v_ref
        u_ff = 0.9 * (ff + p.coulomb * np.tanh(v_ref / (0.1 * p.stribeck_velocity))) / p.c_m
        w = 2 * math.pi * 2.0  # 2 Hz position loop, ζ = 0.7
        kp, kd = w * w * p.inertia / p.c_m, 1.4 * w * p.inertia / p.c_m
        alpha, v_hat = math.exp(-2 * math.pi * 50.0 * p.dt), 0.0
        u_lim = 2.0 * p.max_input  # the amplifier's limit
    for k in range(n if ref is not None or p.friction == "stribeck" else 0):
        qt[k], vt[k] = x[0], x[1]
        qm[k] = round(x[0] / p.quantum) * p.quantum + noise[k] + 0.0
        if ref is None:
            ua[k] = u[k]  # type: ignore[index]
        else:
            if k:
                v_hat = alpha * v_hat + (1 - alpha) * (qm[k] - qm[k - 1]) / p.dt
            uk = u_ff[k] + kp * (q_ref[k] - qm[k]) + kd * (v_ref[k] - v_hat)
            ua[k] = min(max(uk, -u_lim), u_lim)
        if change is not None and k == change[0]:
            step = after  # type: ignore[assignment]
        if k + 1 < n:
            x = step(x, p.c_m * ua[k] + dist[k] - p.offset)
    if p.friction == "lugre":
        ua = ua if ref is not None else np.asarray(u, dtype=np.float64)
        tau = p.c_m * ua + dist - p.offset
        qt, vt, _ = python_integrator(tau, np.zeros(n), _rig_constants(p), p.substeps, 0, 0, 0)
        qm = np.round(qt / p.quantum) * p.quantum + noise + 0.0
    return ua, qm, qt, vt


def simulate_axis(p: AxisParameters, u: np.ndarray, *, seed: Seed
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Open-loop response to the sampled input u (zero-order hold) from rest at q = 0.
    `seed` (int or ints) draws τ_d and the position noise. Returns ``(q_measured, q_true,
    qdot_true)``, each ``(len(u),)``."""
    u = np.asarray(u, dtype=np.float64)
    if u.ndim != 1 or u.size < 2 or not np.all(np.isfinite(u)):
        raise TorchfricError(f"simulate_axis needs a finite 1-D u of >= 2 samples, got {u.shape}")
    _, qm, qt, vt = _run(p, u, None, u.size, seed)
    return qm, qt, vt


def excitation_reference(p: AxisParameters, *, seed: int, duration: float = 30.0,
                         kind: str = "identification") -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Reference velocity and acceleration ``(v_ref, a_ref)`` at ``t = k dt`` (module docstring):
    a rest, a trapezoid to ``max_speed``, then random segments (multisine 40 %, slow triangle
    25 %, trapezoid 25 %, rest 10 %), accelerations ≤ ``max_acceleration``, each segment signed
    to bring the reference position back towards 0. Deterministic for ``(seed, kind)``."""
    if kind not in _KIND_CODE:
        raise TorchfricError(f"kind = {kind!r}; expected 'identification' or 'validation'")
    if not (math.isfinite(duration) and duration >= 20 * p.dt):
        raise TorchfricError(f"duration = {duration!r} s is too short")
    rng = np.random.default_rng([int(seed), _KIND_CODE[kind]])
    dt, vs, vmax, amax = p.dt, p.stribeck_velocity, p.max_speed, p.max_acceleration
    n = int(round(duration / dt))

    def trapezoid(a: float) -> np.ndarray:  # 0 → a (hold 0.2–0.6 s) → 0
        tr = a / (amax * rng.uniform(0.7, 1.0))
        knots = np.cumsum([0.0, tr, rng.uniform(0.2, 0.6), tr])
        return np.interp(np.arange(0.0, knots[-1], dt), knots, [0.0, a, a, 0.0])

    def multisine() -> np.ndarray:  # random phases, 3-6 tones up to f_top, sin² ends
        a = rng.uniform(0.05, 1.0) * vmax
        f_top = float(np.clip(1.5 * amax / (2 * np.pi * a), 0.3, 3.0))
        t = np.arange(0.0, rng.uniform(3.0, 6.0), dt)
        freqs = rng.uniform(0.1, f_top, size=rng.integers(3, 7))
        v = np.sin(2 * np.pi * freqs[:, None] * t + rng.uniform(0, 2 * np.pi, freqs.size)[:, None])
        v = v.sum(0) * np.sin(np.pi * np.minimum(1.0, np.minimum(t, t[-1] - t) / 0.5) / 2) ** 2
        v /= np.abs(v).max()
        return v * min(a, amax * dt / np.abs(np.diff(v)).max())

    def triangle() -> np.ndarray:  # 0 → a → −a → 0 slowly, a ≤ 4 vs: the Stribeck region
        a = rng.uniform(1.0, 4.0) * vs
        slope = max(rng.uniform(0.5, 2.0) * vs, a / 2.0)  # at most 8 s
        t = np.arange(0.0, 4 * a / slope, dt)
        return np.interp(t, [0, a / slope, 3 * a / slope, 4 * a / slope], [0, a, -a, 0])

    segs = [np.zeros(int(0.3 / dt)), trapezoid(vmax)]
    pos, total = float(segs[1].sum() * dt), sum(s.size for s in segs)
    while total < n:
        pick = rng.choice(4, p=[0.4, 0.25, 0.25, 0.1])
        if pick == 0:
            s = multisine()
        elif pick == 1:
            s = triangle()
        elif pick == 2:
            s = trapezoid(rng.uniform(0.5, 1.0) * vmax)
        else:
            s = np.zeros(int(rng.uniform(0.2, 0.6) / dt))
        disp = float(s.sum() * dt)
        s = -s if abs(pos - disp) < abs(pos + disp) else s  # head back towards q = 0
        pos, total = pos + float(s.sum() * dt), total + s.size
        segs.append(s)
    v_ref = np.concatenate(segs)[:n]
    return v_ref, np.gradient(v_ref, dt)


def axis_record(p: AxisParameters, *, seed: int, duration: float = 30.0,
                kind: str = "identification", change: tuple[float, AxisParameters] | None = None
                ) -> dict[str, np.ndarray]:  # fmt: skip
    """One record of the axis in its position loop (module docstring): ``t, u`` (applied), ``q``
    (measured), ``q_true, qdot_true``. Excitation and noise are drawn from ``(seed, kind)``;
    ``simulate_axis(p, rec["u"], seed=[seed, code])`` replays it open loop exactly.

    ``change = (t_c, after)``: the machine becomes `after` (a Stribeck axis with the same ``dt``,
    e.g. ``dataclasses.replace(p, coulomb=1.4 * p.coulomb)``) from the first sample at or after
    ``t_c`` on, its state carried across (the machine is not stopped; the position loop, tuned
    to `p`, does not know). The record then holds ``change``, that sample's time (a 0-d array);
    the open-loop replay does not cover it."""
    ref = excitation_reference(p, seed=seed, duration=duration, kind=kind)
    n = ref[0].size
    at = None
    if change is not None:
        t_c, later = change
        if p.friction != "stribeck" or later.friction != "stribeck" or later.dt != p.dt:
            raise TorchfricError("axis_record's change needs two Stribeck axes with the same dt")
        if not 0 < t_c < (n - 1) * p.dt:
            raise TorchfricError(f"change at t = {t_c!r} s is outside the record (0, {n * p.dt} s)")
        at = (math.ceil(t_c / p.dt - 1e-9), later)
    u, qm, qt, vt = _run(p, None, ref, n, [int(seed), _KIND_CODE[kind]], at)
    out = {"t": np.arange(n) * p.dt, "u": u, "q": qm, "q_true": qt, "qdot_true": vt}
    if at is not None:
        out["change"] = np.asarray(at[0] * p.dt)
    return out


def write_csv(path: str | os.PathLike[str], record: dict[str, np.ndarray], *,
              position_unit: Literal["rad", "deg", "mm", "counts"] = "rad",
              counts_per_rev: float | None = None, quantum: float | None = None,
              delimiter: str = ",", unit_header: bool = False) -> None:  # fmt: skip
    """Write ``t,u,q`` (header line, then one row per sample). q is scaled from rad (or m) to
    `position_unit`: "deg" × 180/π, "mm" × 1000, "counts" × counts_per_rev/2π (or ÷ `quantum`
    when counts_per_rev is None), rounded to whole counts. `unit_header` writes ``q [deg]`` etc.
    so that a reader converts back; without it only the numbers change (unit-invariance checks).
    """
    q = np.asarray(record["q"], dtype=np.float64)
    if position_unit == "deg":
        q = np.degrees(q)
    elif position_unit == "mm":
        q = q * 1000.0
    elif position_unit == "counts":
        if counts_per_rev is None and quantum is None:
            raise TorchfricError("position_unit='counts' needs counts_per_rev or quantum")
        q = np.round(q / quantum if counts_per_rev is None else q * counts_per_rev / (2 * math.pi))
    elif position_unit != "rad":
        raise TorchfricError(f"position_unit = {position_unit!r}; expected rad, deg, mm or counts")
    qname = f"q [{position_unit}]" if unit_header else "q"
    with open(path, "w", newline="") as fh:
        out = csv.writer(fh, delimiter=delimiter, lineterminator="\n")
        out.writerow(["t", "u", qname])
        fmt_q = "{:.0f}" if position_unit == "counts" else "{:.12g}"
        for t, u, qq in zip(record["t"], record["u"], q + 0.0, strict=True):
            out.writerow([f"{t:.6f}", f"{u:.10g}", fmt_q.format(qq)])
