"""On-line tracking: the EKF run recursively from an identified θ, with change detection.

The paper identifies off-line and names recursive estimation as future work. `Tracker` runs
the augmented-state EKF (`torchfric.estimators.ekf`, the same step, compiled the same way) over
a record as it comes, chunk by chunk, from a checkpoint's θ and ``P_θθ``:

- **Random-walk parameters.** θ follows ``θ̇ = w_θ`` with intensity `q_theta` (estimation
  coordinates per second: a log-stored M with ``q_theta = 1e-6`` may drift by 0.1 % per
  second's square root), so the filter keeps following a slow change; optionally a forgetting
  factor λ divides ``P_θθ`` by λ per sample (applied at the end of each chunk as ``λ^n``).
- **Change detection** (`NisDetector`): the normalised innovations squared (NIS) of a filter
  that matches its machine have a stationary mean; a change of the machine raises it. The NIS
  is averaged over blocks (0.1 s) and calibrated on the record itself over its first 20 s
  (again after each change's hold-off): their mean μ, spread σ, ranks, and the upper tail of
  their logs as an exponential beyond the 90th percentile u (peaks over a threshold:
  ``P(m) = 0.1 · exp(−(ln m − ln u)/β)``, β the mean excess of the top 10 %, at least a
  log-normal tail's with the spread of ln m between its median and u: 0.473 σ_ln). Each later
  block scores ``y = min((m − μ)/σ, r)``, r its rarity as a normal score (``Φ⁻¹`` of its rank
  up to u, ``−Φ⁻¹(P(m))`` beyond), and a one-sided CUSUM ``g ← max(0, g + y − κ)``, κ = 2,
  raises an alarm above a threshold h chosen for a stated mean time between false alarms
  (Siegmund's approximation of the average run length,
  ``ARL₀ ≈ (e^{2κb} − 2κb − 1) / 2κ², b = h + 1.166``, for independent Gaussian block means;
  h = 1.98 for one false alarm an hour in 0.1 s blocks). Everything is in units of the
  record's own calibration, so no setting depends on the machine's scale (rad or m, N m or N,
  kg m² or kg).
- **Why κ = 2** (the CUSUM ignores scores below 2 and accumulates only the excess): the NIS of
  a static model on a dynamic machine varies with the regime (stick or slip, slow or fast,
  reversals), and on unchanged data that variation is itself a shift of 1–3 standard
  deviations held for seconds (measured on the EMPS-like linear axis of
  `torchfric.data.axis`: block means at 1–2.8 σ for 6 s of a fast trapezoid and reversal,
  which a κ = 1 CUSUM called a change). The changes it must find are larger where they show:
  one to a few blocks at 3–40 σ (a 40 % Coulomb change on the linear and rotary user axes, the
  rig's static friction removed).
- **Why the rarity too**: on a stick-slip machine single blocks are that large without any
  change. On a user's linear carriage (2.5 kg, a 1 µm encoder) the calibration's blocks had
  median 0.036, mean 0.38 and σ 0.88, and slip onsets reached 17 σ: scored by z alone, the
  CUSUM raised 13 false alarms in each of two unchanged 10-minute records. A block counts no
  more than its rarity among the record's own blocks says: slip onsets like those the
  calibration saw score 2–3, while the rig's maintenance change, one block 3× the
  calibration's largest, scores 5.8 (its z is 12) and is still found at once. Ranks or the
  tail alone (without the min) were tried: they score the axes' regime shifts higher than z
  does and raised 5–8 false alarms in 10 minutes there. `benchmarks/tracking.py` measures the
  delay and the false alarms on four machines (the rig, a rotary and an EMPS-like linear axis,
  the stick-slip carriage). Block means are not independent (lag-one correlation 0.2–0.6) nor
  Gaussian, so the design run length is a guide, not a guarantee.
- **After a change** ``P_θθ`` is re-opened (``+ reopen · I``) so that θ converges to the new
  machine quickly, and detection holds off while it does.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from statistics import NormalDist

import numpy as np
import torch
from torch import Tensor

from ..accel import iter_chunks
from ..errors import TorchfricError
from ..models.arm import ArmModel
from ..models.simulate import filter_substeps
from .ekf import MEASUREMENTS, EKFState, make_propagator, make_step, update
from .passes import belief, measurements
from .settings import EKFTuning

__all__ = [
    "TrackSettings",
    "NisDetector",
    "Tracker",
    "TrackRow",
    "cusum_threshold",
    "tracking_data",
]

_KAPPA = 2.0  # CUSUM reference value, in standard deviations of a block mean (docstring)
_NORMAL = NormalDist()
TAIL_FRACTION = 0.1
"""The share of the calibration's largest block means whose log is fitted as an exponential
tail (`NisDetector`)."""
_LOGNORMAL_EXCESS = 0.473  # E[Z − z | Z > z] for z the standard normal's 90th percentile


def cusum_threshold(arl0: float, kappa: float = _KAPPA) -> float:
    """The CUSUM threshold h whose in-control average run length is `arl0` blocks (Siegmund's
    approximation for a unit-variance Gaussian; monotone in h, solved by bisection)."""
    if not arl0 > 1:
        raise TorchfricError(f"the mean run to a false alarm must exceed one block, got {arl0}")

    def arl(h: float) -> float:
        b = 2.0 * kappa * (h + 1.166)
        return (math.exp(b) - b - 1.0) / (2.0 * kappa * kappa)

    lo, hi = 0.0, 1.0
    while arl(hi) < arl0:
        hi *= 2.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if arl(mid) < arl0 else (lo, mid)
    return hi


@dataclass(frozen=True)
class TrackSettings:
    """Tracking settings (the ``[track]`` config section; times in seconds).

    Attributes:
        q_theta: random-walk intensity of θ (estimation coordinates² per second).
        forgetting: λ in (0, 1]: ``P_θθ`` is divided by λ every sample (1 = off).
        block: length of the NIS blocks the detector averages.
        calibrate: how long the detector measures its baseline, at the start and after each
            change's hold-off.
        holdoff: after a change, how long detection pauses while θ re-converges.
        false_alarm_hours: the mean time between false alarms on unchanged data that the
            threshold is designed for.
        reopen: the variance added to ``P_θθ``'s diagonal after a change.
        detect: run the change detector at all.
    """

    q_theta: float = 1e-6
    forgetting: float = 1.0
    block: float = 0.1
    calibrate: float = 20.0
    holdoff: float = 10.0
    false_alarm_hours: float = 1.0
    reopen: float = 0.01
    detect: bool = True


@dataclass
class NisDetector:
    """One-sided CUSUM on NIS block means, each scored by the smaller of its standardised
    value and its rarity in the calibration (see the module docstring).

    Feed it per-sample NIS values with their times (`feed`); it returns the times of the changes
    it detects. `block` and the other periods are in samples; `threshold` is h."""

    block: int
    calibrate_blocks: int
    holdoff_blocks: int
    threshold: float
    _pending: list[float] = field(default_factory=list)
    _baseline: list[float] = field(default_factory=list)
    _sorted: list[float] | None = None  # the calibration's block means, sorted
    _mean: float = float("nan")
    _std: float = float("nan")
    _tail: tuple[float, float, float] = (math.inf, 1.0, 0.0)  # (ln u, β, share beyond u)
    _wait: int = 0
    g: float = 0.0

    @classmethod
    def from_settings(cls, s: TrackSettings, dt: float) -> NisDetector:
        block = max(1, round(s.block / dt))
        block_s = block * dt
        arl0 = s.false_alarm_hours * 3600.0 / block_s
        return cls(
            block=block,
            calibrate_blocks=max(10, round(s.calibrate / block_s)),
            holdoff_blocks=round(s.holdoff / block_s),
            threshold=cusum_threshold(arl0),
        )

    @property
    def calibrated(self) -> bool:
        return self._sorted is not None

    def score(self, mean: float) -> float:
        """A block mean's score: ``min((m − μ)/σ, rarity)``, the rarity being the normal score
        of its rank among the calibration blocks (ties count half) up to the tail's threshold
        u, beyond it ``−Φ⁻¹(share · exp(−(ln m − ln u)/β))`` (`_calibrate`)."""
        assert self._sorted is not None
        z = (mean - self._mean) / self._std
        log_u, beta, share = self._tail
        log_m = math.log(mean) if mean > 0.0 else -math.inf
        if log_m > log_u:
            tail = share * math.exp(-(log_m - log_u) / beta)
            return min(z, -_NORMAL.inv_cdf(max(tail, 1e-300)))
        lo = bisect.bisect_left(self._sorted, mean)
        hi = bisect.bisect_right(self._sorted, mean)
        return min(z, _NORMAL.inv_cdf((lo + 0.5 * (hi - lo) + 0.5) / (len(self._sorted) + 1)))

    def _calibrate(self) -> None:
        """μ, σ and the tail from the calibration blocks: the upper tail of ln m as an
        exponential (peaks over a threshold), u the value below the top `TAIL_FRACTION` (at
        least 5 blocks), β the mean excess of ln m over ln u among them, at least 0.473 σ_ln,
        σ_ln = (its 90th − 50th percentile)/1.2816 (and 1e-3)."""
        b = np.sort(np.asarray(self._baseline))
        self._sorted = b.tolist()
        self._mean, self._std = float(b.mean()), float(max(b.std(), 1e-12 * abs(b.mean())))
        n = len(b)
        k = min(n - 1, max(5, round(TAIL_FRACTION * n)))
        logs = np.log(np.maximum(b[n - k - 1 :], 1e-300))
        # β no lighter than the log-normal tail that the upper half's spread implies (its
        # σ_ln from the 50th to 90th percentile of ln m; mean excess over the 90th percentile
        # 0.473 σ_ln; the lower half is rest, where the NIS goes to 0, and says nothing of the
        # top): fitted to 20 blocks alone, a calibration whose top happened to bunch gave β
        # 0.061 against 0.077, and two later blocks 10 % above its largest then scored 3.4
        # each and raised an alarm on an unchanged axis
        bulk = np.log(b[b > 0.0])
        spread = (
            np.diff(np.quantile(bulk, [0.5, 0.9]))[0] / _NORMAL.inv_cdf(0.9)
            if bulk.size > 1
            else 0.0
        )
        beta = max(float(np.mean(logs[1:] - logs[0])), _LOGNORMAL_EXCESS * float(spread), 1e-3)
        self._tail = (float(logs[0]), beta, k / (n + 1))

    def feed(self, nis: np.ndarray, t: np.ndarray) -> list[float]:
        """Per-sample NIS and times; the times at which a change was detected (the end of the
        block that crossed the threshold)."""
        changes = []
        values = np.concatenate([np.asarray(self._pending), nis])
        times = np.concatenate([np.full(len(self._pending), np.nan), t])
        n = len(values) // self.block
        for j in range(n):
            mean = float(values[j * self.block : (j + 1) * self.block].mean())
            if self._block(mean):
                changes.append(float(times[(j + 1) * self.block - 1]))
        self._pending = values[n * self.block :].tolist()
        return changes

    def _block(self, mean: float) -> bool:
        """One block mean through hold-off, calibration and the CUSUM; True on an alarm."""
        if self._wait > 0:
            self._wait -= 1
            return False
        if not self.calibrated:
            self._baseline.append(mean)
            if len(self._baseline) >= self.calibrate_blocks:
                self._calibrate()
            return False
        self.g = max(0.0, self.g + self.score(mean) - _KAPPA)
        if self.g <= self.threshold:
            return False
        # a change: start over after the hold-off, with a new calibration
        self.g, self._wait = 0.0, self.holdoff_blocks
        self._baseline, self._sorted = [], None
        return True


@dataclass
class TrackRow:
    """The estimate after sample `k` (time `t`): θ `(k,)` and ``P_θθ`` `(k, k)`."""

    t: float
    theta: Tensor
    P_theta: Tensor


class Tracker:
    """The recursive EKF over a stream of samples (see the module docstring).

    Args:
        model: the identified model (its structure; θ and P_θθ are the start).
        theta, P_theta: the start, estimation coordinates.
        tuning: the filter's Q (states), R, measurement and sub-steps (from the run's config).
        settings: `TrackSettings`.
        dt: the sample time.
        every: samples per compiled chunk, and per row of the output.
        compile: run the step as generated C (as a run does); False: eager.
    """

    def __init__(
        self,
        model: ArmModel,
        theta: Tensor,
        P_theta: Tensor,
        tuning: EKFTuning,
        settings: TrackSettings,
        dt: float,
        *,
        every: int = 100,
        compile: bool = True,
    ) -> None:
        self.settings, self.tuning, self.every = settings, tuning, every
        k, s = model.num_parameters, model.state_size
        Q, P0_xx, self.H, self.R = tuning.matrices(k, s)
        Q[s:, s:] = Q[s:, s:] + settings.q_theta * torch.eye(k, dtype=torch.float64)
        self.Q, self.P0_xx, self.states = Q, P0_xx, s
        self.dt = torch.tensor(dt, dtype=torch.float64)
        self.bound = torch.tensor(tuning.theta_bound, dtype=torch.float64)
        steps = tuning.substeps  # "auto": as a run resolves it, at the tracked θ
        steps = filter_substeps(model, dt, theta=theta) if steps == "auto" else steps
        flow = make_propagator(model, steps)
        self.step = make_step(flow, compile=compile, chunk=every)
        self.theta0 = theta.clone()
        self.state: EKFState | None = None
        self._P_theta0 = P_theta.clone()
        self.detector = NisDetector.from_settings(settings, dt) if settings.detect else None
        self.changes: list[float] = []
        self.samples = 0

    def _start(self, y0: Tensor) -> None:
        """The belief at the first sample (`passes.belief`: [q0, q̇0 as measured, else 0; z = 0;
        θ]), then an update."""
        x0 = torch.zeros(2, dtype=torch.float64)
        for j, i in enumerate(MEASUREMENTS[self.tuning.measure]):
            x0[i] = y0[j]  # the measured entries of [q, q̇]
        x, P = belief(x0, self.theta0[None], self._P_theta0[None], self.P0_xx)
        self.state, _ = update(EKFState(x[0], P[0]), y0, self.H, self.R)

    def run(self, t: Tensor, u: Tensor, y: Tensor) -> Iterator[TrackRow]:
        """Filter the samples ``(t, u, y)`` that follow those already seen (u held over each
        interval from its sample to the next); yields a row every `every` samples."""
        if self.state is None:
            self._start(y[0])
            t, u, y = t[1:], u, y[1:]
            u_prev = u[:-1]
        else:
            u_prev = torch.cat([self._u_last, u[:-1]])
        self._u_last = u[-1:].clone()
        for i, m, xs, valid in iter_chunks((u_prev, y), self.every):
            yield self._chunk(t[i : i + m], xs, valid)

    def _chunk(self, t: Tensor, xs: tuple[Tensor, Tensor], valid: Tensor) -> TrackRow:
        """One chunk: `t` the times of its real samples, `xs` = (u, y) padded to `every` rows
        (`iter_chunks`), `valid` marking the real ones."""
        assert self.state is not None
        u, y = xs
        consts = (self.dt, self.Q, self.H, self.R, self.bound)
        chunk = getattr(self.step, "chunk", None)
        if chunk is not None:
            (x, P), (_, nis, _, ok) = chunk((self.state.x, self.state.P), xs, valid, consts)
        else:
            x, P, nis_list, ok_list = self.state.x, self.state.P, [], []
            for j in range(len(t)):
                x, P, _, nis_j, _, ok_j = self.step(x, P, u[j], y[j], *consts)
                nis_list.append(nis_j)
                ok_list.append(ok_j)
            nis, ok = torch.stack(nis_list), torch.stack(ok_list)
        if not bool(ok[: len(t)].all()):
            bad = int((~ok[: len(t)]).nonzero()[0, 0])
            raise TorchfricError(
                f"the tracking filter diverged at t = {float(t[bad]):.4f} s (the belief became "
                "non-finite, non-PSD or θ left its box); lower track.q_theta or track.reopen"
            )
        s = self.states
        if self.settings.forgetting < 1.0:
            P = P.clone()
            P[s:, s:] = P[s:, s:] / self.settings.forgetting ** len(t)
        self.samples += len(t)
        if self.detector is not None:
            found = self.detector.feed(nis[: len(t)].numpy(), t.numpy())
            if found:
                self.changes.extend(found)
                P = P.clone()
                k = P.shape[0] - s
                P[s:, s:] = P[s:, s:] + self.settings.reopen * torch.eye(k, dtype=P.dtype)
        self.state = EKFState(x, P)
        return TrackRow(float(t[-1]), x[s:].clone(), P[s:, s:].clone())


def tracking_data(exp, measure: str) -> tuple[Tensor, Tensor, Tensor]:  # type: ignore[no-untyped-def]
    """``(t, u, y)`` of an `Experiment` for the tracker (the filter's measured channels)."""
    return exp.t.to(torch.float64), exp.u.to(torch.float64), measurements(exp, measure)
