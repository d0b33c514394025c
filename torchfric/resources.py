"""Up-front memory checks: a run that cannot fit is refused before it starts, with figures.

The estimate is deliberately rough (within a small factor): it is there to turn "the machine
swaps for an hour, then the kernel kills the run" into one line naming the setting, the memory
it needs and the memory available.
"""

from __future__ import annotations

import os

from .errors import TorchfricError

__all__ = [
    "available_memory",
    "ekf_bytes",
    "prefit_bytes",
    "require_memory",
    "format_bytes",
    "run_peak_bytes",
    "run_seconds",
    "fewest_passes",
    "nominal_rate",
]

# Buffers of n×n float64 one filter member keeps alive in a step: P, Φ and the RK4 stages of
# Ṗ, the Jacobian, the Joseph update's temporaries (counted on the eager step; the compiled
# paths need fewer).
_EKF_SQUARES = 16
# Per-sample rows the pre-fit keeps for each start: the Jacobian row, its scaled copy and the
# normal equations' temporaries.
_PREFIT_ROWS = 4
_PREFIT_STARTS = 3


# `run_peak_bytes` and `run_seconds`: measured on the 20-minute axis record at 1 kHz (1.2 M
# samples, tanh(3): k = 8, the 9-filter ensemble; benchmarks/long_record.py, docs/results.md).
# The process before any record: Python, torch, the generated C, TensorBoard's writer.
_PROCESS = 410 << 20
# Bytes a sample each record costs for the whole run: t, u, q, q̇ and the filter's y (N, 2).
_RECORD = 48
# Bytes a sample of the largest stage over the longest record, per unit: the pre-fit per start
# and parameter (its Jacobian rows), the ensemble's selection per member (its open-loop
# simulation and the FIT's differences), and the covariance stage (the fixed-θ innovations
# and their variances, the record's sensitivities `(N, k)` per parameter, and the per-sample
# outputs of a batch of 8 filters: the polish's trial steps, e, S and e²/S, 24 bytes each).
_PREFIT_ROW = 16.0
_SELECTION_MEMBER = 58.0
_COVARIANCE_FIXED, _COVARIANCE_PARAMETER = 246.0, 20.0
# Filter-step equivalents a sample of the stages after the passes, per the ensemble's
# member-step rate: the noise model (63 fixed-θ filters in one batch), the sandwich and the
# polish (2k + 1 fixed-θ filters per Newton step, 8 to a batch, and its batched trial steps, as
# measured) and the selection's simulations.
_AFTER_PASSES = 150.0


def run_peak_bytes(*, samples: int, longest: int, n_theta: int, members: int) -> int:
    """The peak resident memory of a `train` run, roughly (within ~15 % on the axis records of
    2 and 20 minutes): the process, every record (`samples` in all) and the largest stage over
    the `longest` record: the pre-fit (3 starts), the selection of `members` filters by
    simulation, or the covariance stage with `n_theta` parameters. The passes themselves hold
    nothing per sample."""
    stage = max(
        _PREFIT_STARTS * n_theta * _PREFIT_ROW,
        members * _SELECTION_MEMBER,
        _COVARIANCE_FIXED + n_theta * _COVARIANCE_PARAMETER,
    )
    return int(_PROCESS + _RECORD * samples + stage * longest)


def nominal_rate(members: int) -> float:
    """Member-steps a second of the default model's filters where none were timed: one filter
    300 k samples/s, an ensemble 150 k a member (generated C, 2 busy cores; `torchfric check`
    times this machine's instead)."""
    return 3e5 if members == 1 else 1.5e5 * members


def fewest_passes(passes: int) -> int:
    """The fewest passes a run of at most `passes` can stop after: two (the likelihood rule
    compares a pass with the one before, and a rolled-back pass is the second at the
    earliest), one when only one is allowed."""
    return min(2, passes)


def run_seconds(*, samples: int, passes: int, members: int, rate: float) -> tuple[float, float]:
    """The seconds of an EKF run's filtering after its pre-fit: ``(after the fewest passes
    (`fewest_passes`), after all `passes`)`` at `rate` member-steps a second (the ensemble's,
    measured): the passes of `members` filters over `samples`, and the stages after them
    (`_AFTER_PASSES`)."""
    after = _AFTER_PASSES * samples / rate
    per_pass = members * samples / rate
    return after + fewest_passes(passes) * per_pass, after + passes * per_pass


def format_bytes(n: float) -> str:
    """``20.0 GiB``, ``512.0 MiB``, ``300 B``."""
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale:
            value = n / scale
            return f"{value:.1f} {unit}" if value < 100 else f"{value:.0f} {unit}"
    return f"{int(n)} B"


def _read_int(path: str) -> int | None:
    try:
        with open(path, encoding="ascii") as f:
            return int(f.read().strip())
    except (OSError, ValueError):  # absent, unreadable, or "max" (no limit)
        return None


def available_memory() -> int | None:
    """Bytes a new allocation can get: MemAvailable (else free pages), capped by a cgroup limit.

    None when the platform tells neither (then no memory check is made).
    """
    avail: int | None = None
    try:
        with open("/proc/meminfo", "rb") as f:
            for line in f:
                if line.startswith(b"MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (AttributeError, ValueError, OSError):
            return None
    for limit_file, usage_file in (
        ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),  # cgroup v2
        (
            "/sys/fs/cgroup/memory/memory.limit_in_bytes",
            "/sys/fs/cgroup/memory/memory.usage_in_bytes",
        ),
    ):
        limit, usage = _read_int(limit_file), _read_int(usage_file)
        if limit is not None and usage is not None and limit < 1 << 60:
            avail = min(avail, max(limit - usage, 0))
    return avail


def ekf_bytes(n_theta: int, members: int) -> int:
    """Memory of `members` augmented-state filters with `n_theta` parameters (state 2 + n_theta)."""
    n = 2 + n_theta
    return members * _EKF_SQUARES * n * n * 8


def prefit_bytes(n_theta: int, samples: int) -> int:
    """Memory of the least-squares pre-fit over `samples` rows of `n_theta` unknowns."""
    return _PREFIT_STARTS * _PREFIT_ROWS * samples * n_theta * 8


def require_memory(needed: int, what: str, fix: str, *, available: int | None = None) -> None:
    """Raise when `needed` bytes exceed what is available; `what` names the setting(s)."""
    available = available_memory() if available is None else available
    if available is not None and needed > available:
        raise TorchfricError(
            f"{what} needs about {format_bytes(needed)} of memory and {format_bytes(available)} "
            f"is available; {fix}"
        )
