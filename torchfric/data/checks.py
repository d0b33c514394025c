"""Data warnings: plain sentences about records that would almost certainly give a wrong model.

`data_warnings` flags an input that was clipped or saturated and a time column that looks like
milliseconds in a seconds column. It only reads the record; the app layer prints the warnings.
`position_step` is the records' resolution in position (an encoder's count).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..errors import TorchfricError
from .experiment import Experiment
from .velocity import DEFAULT_CUTOFF_HZ

__all__ = ["data_warnings", "position_step"]

# Saturation: u at its exact minimum or maximum in more than this fraction of the samples ...
_SATURATION_FRACTION = 0.01
# ... reached gradually: the median distance of the samples next to those runs from the limit is
# below this fraction of u's range (a clipped continuous signal: 0.002-0.005 for the rig's input
# clipped at ±60 % of its peak, 0.12 at ±80 %, where the rig's breakaway kicks jump onto the
# limit). A step / PRBS input jumps onto its levels from far away (the HSM150 torque steps: 1.0,
# the whole range) and is not flagged; neither is an input of fewer than
# `_SATURATION_MIN_LEVELS` distinct values (a few levels, by design).
_SATURATION_APPROACH = 0.25
_SATURATION_MIN_LEVELS = 20
# Time units: only sample times of at least this many seconds (<= 20 Hz) are suspected ...
_MS_MIN_STEP = 0.05
# ... when a measured qdot is this many times the finite difference of q (1000 for t in ms) ...
_MS_QDOT_RATIO = (300.0, 3000.0)
# ... or, without qdot, when the velocity filter's cut-off is above Nyquist and q is smooth on
# the scale of a sample: rms(Δ²q)/rms(Δq) ≈ ω·Δt (ω the motion's rms angular frequency) is below
# this. Measured: 0.003-0.063 on the 1 kHz records (rig 0.027-0.063, EMPS 0.005, HSM150 0.003),
# 0.28 on the 40 Hz unbalanced disc; a genuine ≤ 20 Hz servo record moving at ≥ 0.5 Hz exceeds it.
_MS_SMOOTHNESS = 0.15
# ... or that ratio, read as a frequency ω/2π = ratio/(2π·Δt), puts the motion below 0.02 Hz (a
# period over 50 s; servo test motions are faster). t in ms divides it by 1000: rig 0.0066 Hz,
# EMPS 0.0007, HSM150 0.0005, the disc (genuinely 40 Hz, ratio 0.28) 0.0018.
_MS_MOTION_HZ = 0.02


def _saturation_warnings(exp: Experiment) -> list[str]:
    u = exp.u.numpy()
    if u.size < 2 or not np.all(np.isfinite(u)):
        return []
    lo, hi = float(u.min()), float(u.max())
    span = hi - lo
    if not span > 0 or np.unique(u).size < _SATURATION_MIN_LEVELS:
        return []
    out = []
    for which, value in (("minimum", lo), ("maximum", hi)):
        at = u == value
        # a run at the limit that opens or closes the record is the input at rest before or
        # after the test (a logger started early), not a clip: the samples inside count
        inside = np.flatnonzero(~at)
        if not inside.size:
            continue
        at[: inside[0]] = at[inside[-1] + 1 :] = False
        count = int(at.sum())
        if count <= _SATURATION_FRACTION * u.size:
            continue
        edge = np.flatnonzero(at[1:] != at[:-1])  # at[k] != at[k+1]
        outside = np.where(at[edge], u[edge + 1], u[edge])  # the neighbour off the limit
        approach = float(np.median(np.abs(outside - value))) / span
        if approach > _SATURATION_APPROACH:
            continue  # jumps onto the level: a step input, not a clip
        out.append(
            f"{exp.name}: the input u sits at its exact {which} {value:.6g} in "
            f"{count / u.size:.1%} of the samples ({count} of {u.size}), as a clipped or "
            "saturated signal does; remove the saturated segments or raise the amplifier's "
            "limit, because identification assumes the applied input equals the recorded one"
        )
    return out


def _time_unit_warning(exp: Experiment, velocity: str, cutoff_hz: float | None) -> str | None:
    dt = exp.dt
    if not (math.isfinite(dt) and dt >= _MS_MIN_STEP):
        return None
    q = exp.q.numpy()
    if not np.all(np.isfinite(q)) or q.size < 3:
        return None
    evidence = None
    if exp.qdot is not None:
        qdot = exp.qdot.numpy()
        fd = np.gradient(q, dt)
        if not np.all(np.isfinite(qdot)) or not np.any(fd) or not np.any(qdot):
            return None
        ratio = math.sqrt(float(np.mean(qdot**2)) / float(np.mean(fd**2)))
        if float(np.corrcoef(qdot, fd)[0, 1]) > 0.5 and (
            _MS_QDOT_RATIO[0] <= ratio <= _MS_QDOT_RATIO[1]
        ):
            evidence = f"the measured qdot is {ratio:.0f} times the finite difference of q"
    elif velocity in DEFAULT_CUTOFF_HZ:
        cutoff = DEFAULT_CUTOFF_HZ[velocity] if cutoff_hz is None else cutoff_hz
        nyquist = 0.5 / dt
        d1 = np.diff(q)
        if cutoff >= nyquist and np.any(d1):
            smooth = math.sqrt(float(np.mean(np.diff(d1) ** 2)) / float(np.mean(d1**2)))
            motion_hz = smooth / (2.0 * math.pi * dt)
            if smooth < _MS_SMOOTHNESS or motion_hz < _MS_MOTION_HZ:
                evidence = (
                    f"the {velocity} velocity cut-off {cutoff:g} Hz is above the Nyquist "
                    f"frequency {nyquist:g} Hz, and q moves as if sampled much faster: rms "
                    f"second/first difference {smooth:.3g}, a motion at {motion_hz:.2g} Hz"
                )
    if evidence is None:
        return None
    return (
        f"{exp.name}: sample time {dt:g} s ({1 / dt:g} Hz) looks like milliseconds in a seconds "
        f"column ({evidence}); convert the t column to seconds (t/1000)"
    )


def data_warnings(
    exp: Experiment, *, velocity: str = "highpass", velocity_cutoff_hz: float | None = None
) -> list[str]:
    """Plain one-sentence warnings about data that would almost certainly give a wrong model.

    Pure: reads `exp` only. Empty list when nothing is suspicious. Checks:

    - saturation: u sits at its exact minimum or maximum in more than 1 % of the samples (not
      counting a run at that value that opens or closes the record: the input at rest before
      or after the test) and reaches that value gradually (the samples next to those runs
      lie, in the median, within 25 % of u's range of it; u has at least 20 distinct values). Step and PRBS inputs, which
      jump onto their few levels, are not flagged.
    - time units: a sample time of at least 0.05 s (≤ 20 Hz) that contradicts the data: a
      measured ``qdot`` 300-3000 times the finite difference of q (t in ms makes it 1000), or,
      without ``qdot``, a velocity cut-off (`velocity`, `velocity_cutoff_hz`, as in
      `Experiment.with_velocity`) at or above the Nyquist frequency ``1/(2·dt)`` together with
      a position that moves as if sampled much faster: ``r = rms(Δ²q)/rms(Δq) < 0.15`` (q smooth
      on the scale of one sample) or ``r/(2π·dt) < 0.02 Hz`` (a motion slower than any servo
      test's).

    Args:
        exp: the record as loaded (before velocity reconstruction, so a measured qdot is seen).
        velocity: "highpass", "zero_phase" or "measured" (the config's ``data.velocity``).
        velocity_cutoff_hz: the reconstruction's cut-off; None = the method's default.
    """
    if not isinstance(exp, Experiment):
        raise TorchfricError(f"data_warnings: expected an Experiment, got {type(exp).__name__}")
    out = _saturation_warnings(exp)
    unit = _time_unit_warning(exp, velocity, velocity_cutoff_hz)
    if unit is not None:
        out.append(unit)
    return out


def position_step(records: list[Experiment]) -> float:
    """The records' position step Δq: the 1st percentile of the nonzero |q[k+1] − q[k]| (one
    encoder count for a quantised record, a fraction of the noise for an analogue one); NaN
    when q never moves. A record that moves one count a sample too rarely for that (a fine
    encoder on a fast axis: a robot joint's 222 one-count steps of 30,000 put the percentile
    at two counts) gets its count: the `COUNT_RANK`-th smallest step, when the steps up to the
    percentile are whole multiples of it (`_whole_counts`) and the percentile is two or more."""
    steps = torch.cat([(e.q[1:] - e.q[:-1]).abs().to(torch.float64) for e in records])
    steps = steps[steps > 0][:1_000_000]
    if not steps.numel():
        return math.nan
    percentile = float(torch.quantile(steps, 0.01))
    count = float(torch.kthvalue(steps, min(COUNT_RANK, steps.numel())).values)
    if percentile >= 1.5 * count and _whole_counts(steps[steps <= percentile], count):
        return count
    return percentile


COUNT_RANK = 20
"""`position_step`'s count is the 20th smallest nonzero step: the smallest that recurs, not a
single odd one."""


def _whole_counts(steps: Tensor, count: float) -> bool:
    """Nine in ten of `steps` lie within a tenth of `count` of a whole multiple of it (a
    quantised record read from text: its counts round to the file's digits, not exactly; an
    analogue one's steps fall anywhere)."""
    r = steps / count
    return bool(((r - r.round()).abs() <= 0.1).to(torch.float64).mean() >= 0.9)
