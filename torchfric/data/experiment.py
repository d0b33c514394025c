"""The `Experiment` record and its checks.

An `Experiment` is one uniformly sampled record of the input ``u`` (e.g. motor current) and the
encoder position ``q``, with an optional velocity ``qdot``. Every signal is a float64 tensor of
shape `(N,)`. `make_experiment` and `load_experiment` (in `torchfric.data.readers`) check the
record (`validate_experiment`); the plain constructor only converts and checks shapes.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
from torch import Tensor

from ..errors import TorchfricError
from .convert import ArrayLike, _as_numpy, _as_tensor
from .units import COLUMN_NAMES
from .velocity import reconstruct_velocity

__all__ = [
    "Experiment",
    "validate_experiment",
    "make_experiment",
]


# --------------------------------------------------------------------------- validation
def _check_shapes(cols: Mapping[str, np.ndarray], labels: Mapping[str, str], where: str) -> int:
    """Every column 1-D and of one length; returns that length."""
    for key, arr in cols.items():
        if arr.ndim != 1:
            raise TorchfricError(
                f"{where}: {labels[key]} has shape {tuple(arr.shape)}; expected a 1-D signal (N,) "
                "(flatten (N, 1) arrays first)"
            )
    lengths = {key: arr.shape[0] for key, arr in cols.items()}
    if len(set(lengths.values())) > 1:
        desc = ", ".join(f"{labels[k]}: {n}" for k, n in lengths.items())
        raise TorchfricError(
            f"{where}: columns have different lengths ({desc}); give all signals the same samples"
        )
    return next(iter(lengths.values()))


def _validate(
    cols: Mapping[str, np.ndarray],
    *,
    where: str,
    labels: Mapping[str, str],
    rtol: float,
    min_samples: int,
    offset: int = 0,
) -> None:
    """All checks of `validate_experiment`; indices in messages are shifted by `offset`."""
    if not (isinstance(rtol, (int, float)) and math.isfinite(rtol) and rtol > 0):
        raise TorchfricError(f"rtol = {rtol!r}; expected a positive relative tolerance")
    if isinstance(min_samples, bool) or not isinstance(min_samples, int) or min_samples < 2:
        raise TorchfricError(f"min_samples = {min_samples!r}; expected an integer >= 2")
    n = _check_shapes(cols, labels, where)
    if n < min_samples:
        raise TorchfricError(
            f"{where}: only {n} samples; at least {min_samples} are needed (use a longer record)"
        )
    for key, arr in cols.items():
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            k, value = int(bad[0]), float(arr[bad[0]])
            raise TorchfricError(
                f"{where}: {labels[key]} has a non-finite value {value!r} at index {k + offset} "
                f"({bad.size} in all); remove or fill these samples"
            )
    t = cols["t"]
    steps = np.diff(t)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise TorchfricError(
            f"{where}: time is not strictly increasing at index {k + offset} "
            f"(t = {float(t[k - 1])!r} then {float(t[k])!r}); sort the samples and drop duplicates"
        )
    median = float(np.median(steps))
    deviation = np.abs(steps - median)
    bad = np.flatnonzero(deviation > rtol * median)
    if bad.size:
        k = int(bad[0])
        raise TorchfricError(
            f"{where}: sampling is not uniform at index {k + 1 + offset} (step {steps[k]:.9g} s "
            f"vs median {median:.9g} s, relative tolerance {rtol:g}); resample the record, or "
            "split it at the gap into separate files (data.train takes a list); in Python, "
            "load_experiment's rtol widens the tolerance"
        )


def validate_experiment(
    t: ArrayLike,
    u: ArrayLike,
    q: ArrayLike,
    qdot: ArrayLike | None = None,
    *,
    name: str,
    rtol: float = 1e-3,
    min_samples: int = 10,
) -> None:
    """Check one record; raise `TorchfricError` naming the column and first bad index.

    Checks: every signal 1-D with the same length `N >= min_samples`; all values finite;
    ``t`` strictly increasing; uniform sampling, ``max_k |Δt_k − median(Δt)| <= rtol·median(Δt)``.
    The default ``rtol = 1e-3`` accepts time-stamp jitter (EMPS: ±4e-8 s at 1 ms, i.e. 4e-5)
    and rejects a single missing sample (a step of 2·Δt).
    """
    cols = {"t": t, "u": u, "q": q} | ({} if qdot is None else {"qdot": qdot})
    arrays = {key: _as_numpy(val, f"{name}: column {key}") for key, val in cols.items()}
    labels = {key: f"column {key}" for key in arrays}
    _validate(arrays, where=name, labels=labels, rtol=rtol, min_samples=min_samples)


# --------------------------------------------------------------------------- the record
@dataclass(frozen=True, eq=False, repr=False)
class Experiment:
    """One uniformly sampled record.

    Attributes:
        t: `(N,)` time in s, strictly increasing, uniform step.
        u: `(N,)` input (e.g. motor current or voltage).
        q: `(N,)` position (rad or m).
        qdot: `(N,)` measured or reconstructed velocity, or None.
        name: label used in messages and reports.

    The constructor converts every signal to a float64 CPU tensor (a copy) and checks shapes
    only; use `make_experiment` or `load_experiment` for the full checks of
    `validate_experiment`.
    """

    t: Tensor
    u: Tensor
    q: Tensor
    qdot: Tensor | None = None
    name: str = "experiment"

    def __post_init__(self) -> None:
        cols = {key: getattr(self, key) for key in COLUMN_NAMES if getattr(self, key) is not None}
        arrays = {key: _as_numpy(val, f"{self.name}: column {key}") for key, val in cols.items()}
        n = _check_shapes(arrays, {key: f"column {key}" for key in arrays}, self.name)
        if n < 2:
            raise TorchfricError(f"{self.name}: {n} samples; an experiment needs at least 2")
        for key, arr in arrays.items():
            object.__setattr__(self, key, _as_tensor(arr))

    @property
    def n(self) -> int:
        """Number of samples N."""
        return int(self.t.shape[0])

    @property
    def dt(self) -> float:
        """Mean sample step ``(t[N-1] − t[0]) / (N − 1)`` in s."""
        return float((self.t[-1] - self.t[0]) / (self.n - 1))

    @property
    def duration(self) -> float:
        """``t[N-1] − t[0]`` in s."""
        return float(self.t[-1] - self.t[0])

    def __repr__(self) -> str:
        has_qdot = "yes" if self.qdot is not None else "no"
        return f"Experiment(name={self.name!r}, n={self.n}, dt={self.dt:.6g}, qdot={has_qdot})"

    def with_velocity(
        self, method: str = "highpass", *, cutoff_hz: float | None = None
    ) -> Experiment:
        """A copy with ``qdot`` reconstructed from ``q`` (an existing ``qdot`` is replaced).

        `method` is "highpass" (causal) or "zero_phase" (off-line); `cutoff_hz=None` takes the
        method's default (`DEFAULT_CUTOFF_HZ`: 200 Hz and 50 Hz).
        """
        qdot = reconstruct_velocity(self.q, self.dt, method, cutoff_hz)
        return replace(self, qdot=qdot)

    def slice(self, start: int, stop: int | None = None) -> Experiment:
        """Samples ``start ≤ k < stop`` (``stop=None``: to the end); ``t`` is kept as is."""
        stop = self.n if stop is None else stop
        ok = all(isinstance(i, int) and not isinstance(i, bool) for i in (start, stop))
        if not ok or not (0 <= start and start + 2 <= stop <= self.n):
            raise TorchfricError(
                f"{self.name}: slice({start!r}, {stop!r}) is invalid for {self.n} samples; "
                f"expected integers 0 <= start, start + 2 <= stop <= {self.n} (data.start, "
                "data.stop in a run config)"
            )
        qdot = None if self.qdot is None else self.qdot[start:stop]
        return replace(
            self, t=self.t[start:stop], u=self.u[start:stop], q=self.q[start:stop], qdot=qdot
        )

    def delay_input(self, samples: int) -> Experiment:
        """A copy in which the input acts `samples` steps late: ``u_new[k] = u[k − samples]``.

        A transport delay of whole samples (e.g. one controller cycle between the logged command
        and the actuator). The first `samples` samples have no known input and are dropped, so
        the result has ``N − samples`` samples; ``t`` is kept as is. ``samples = 0`` is a copy.
        """
        ok = isinstance(samples, int) and not isinstance(samples, bool)
        if not ok or not 0 <= samples <= self.n - 2:
            raise TorchfricError(
                f"{self.name}: delay_input({samples!r}) is invalid for {self.n} samples; expected "
                f"an integer 0 <= samples <= {self.n - 2} (data.input_delay in a run config)"
            )
        if samples == 0:
            return replace(self)
        qdot = None if self.qdot is None else self.qdot[samples:]
        return replace(self, t=self.t[samples:], u=self.u[:-samples], q=self.q[samples:], qdot=qdot)

    def to_numpy(self) -> dict[str, np.ndarray]:
        """``{"t", "u", "q"[, "qdot"]}`` as float64 `(N,)` arrays (copies)."""
        return {
            key: getattr(self, key).numpy().copy()
            for key in COLUMN_NAMES
            if getattr(self, key) is not None
        }

    def fingerprint(self) -> str:
        """SHA-256 hex digest of the little-endian float64 bytes of t, u, q (and qdot if set)."""
        digest = hashlib.sha256()
        for arr in self.to_numpy().values():
            digest.update(arr.astype("<f8").tobytes())
        return digest.hexdigest()


def make_experiment(
    t: ArrayLike,
    u: ArrayLike,
    q: ArrayLike,
    qdot: ArrayLike | None = None,
    *,
    name: str = "experiment",
    rtol: float = 1e-3,
) -> Experiment:
    """Validate (`validate_experiment`) and build an `Experiment` of float64 tensors."""
    validate_experiment(t, u, q, qdot, name=name, rtol=rtol)
    return Experiment(t=t, u=u, q=q, qdot=qdot, name=name)  # type: ignore[arg-type]
