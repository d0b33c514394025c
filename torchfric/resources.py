"""Up-front memory checks: a run that cannot fit is refused before it starts, with figures.

The estimate is deliberately rough (within a small factor): it is there to turn "the machine
swaps for an hour, then the kernel kills the run" into one line naming the setting, the memory
it needs and the memory available.
"""

from __future__ import annotations

import os

from .errors import TorchfricError

__all__ = ["available_memory", "ekf_bytes", "prefit_bytes", "require_memory", "format_bytes"]

# Buffers of n×n float64 one filter member keeps alive in a step: P, Φ and the RK4 stages of
# Ṗ, the Jacobian, the Joseph update's temporaries (counted on the eager step; the compiled
# paths need fewer).
_EKF_SQUARES = 16
# Per-sample rows the pre-fit keeps for each start: the Jacobian row, its scaled copy and the
# normal equations' temporaries.
_PREFIT_ROWS = 4
_PREFIT_STARTS = 3


def format_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1024 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PB"  # pragma: no cover


def available_memory() -> int | None:
    """Bytes the system can give a new allocation now (MemAvailable), or None if unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


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
