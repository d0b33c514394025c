"""Conversion and argument checks shared by the data modules.

Every signal handed to torchfric becomes a float64 numpy array (`_as_numpy`, for checks and
filters) and then a float64 CPU tensor in torch's own memory (`_as_tensor`). The checks raise
`TorchfricError` with the offending value and what to give instead.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from ..errors import TorchfricError, shorten

__all__ = ["ArrayLike"]

ArrayLike = Tensor | np.ndarray | Sequence[float]
"""What the data functions accept as a signal: a tensor, a numpy array or a sequence of floats."""


def _one_line(exc: BaseException) -> str:
    """The exception text on one line, at most `SHOW_LIMIT` characters (for wrapping errors)."""
    return shorten(" ".join(str(exc).split()) or type(exc).__name__)


def _as_numpy(x: ArrayLike, what: str) -> np.ndarray:
    """Convert a tensor / array / sequence of real numbers to a float64 numpy array."""
    if isinstance(x, Tensor):
        if x.is_complex():
            raise TorchfricError(f"{what} is a complex tensor; expected real numbers")
        return x.detach().to(device="cpu", dtype=torch.float64).numpy()
    try:
        arr = np.asarray(x)
    except (TypeError, ValueError) as exc:
        raise TorchfricError(f"{what} cannot be read as an array ({_one_line(exc)})") from None
    if arr.dtype.kind not in "biuf":
        raise TorchfricError(
            f"{what} has dtype {arr.dtype}; expected real numbers (a float tensor or array)"
        )
    return arr.astype(np.float64, copy=False)  # no copy of float64 data: callers only read it


def _as_tensor(arr: ArrayLike) -> Tensor:
    """A float64 CPU tensor that owns a copy of `arr`, in torch's own (64-byte aligned) memory.

    Not `torch.from_numpy`: numpy's buffers are only 16-byte aligned, at an address that
    changes from process to process, and the compiled EKF step rounds differently for
    differently aligned inputs. The filter amplifies one-ulp differences (a stick/slip event
    on one sample or the next), so the same run in two processes gave θ differing by 3e-6.
    """
    return torch.tensor(np.asarray(arr, dtype=np.float64), dtype=torch.float64)


def _check_step(dt: float, what: str) -> float:
    """`dt` as a float if it is a positive finite sample period; else a `TorchfricError`."""
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
        raise TorchfricError(f"{what} = {dt!r}; expected a positive finite sample period in s")
    return float(dt)


def _check_cutoff(cutoff_hz: float, dt: float, what: str) -> float:
    """`cutoff_hz` as a float if it lies strictly between 0 and the Nyquist frequency of `dt`."""
    nyquist = 0.5 / dt
    if isinstance(cutoff_hz, bool) or not isinstance(cutoff_hz, (int, float)):
        raise TorchfricError(f"{what}: cutoff_hz = {cutoff_hz!r}; expected a number in Hz")
    if not (0.0 < cutoff_hz < nyquist):
        raise TorchfricError(
            f"{what}: cutoff_hz = {cutoff_hz!r} Hz is not in (0, Nyquist = {nyquist:g} Hz) for "
            f"dt = {dt:g} s; choose a cut-off below {nyquist:g} Hz (data.velocity_cutoff_hz in "
            "a run config)"
        )
    return float(cutoff_hz)


def _signal(q: ArrayLike, what: str, min_len: int) -> np.ndarray:
    """`q` as a float64 array `(..., N)`, finite, with N >= min_len."""
    arr = _as_numpy(q, what)
    if arr.ndim == 0 or arr.shape[-1] < min_len:
        raise TorchfricError(
            f"{what} has shape {tuple(arr.shape)}; expected (..., N) with N >= {min_len} samples"
        )
    bad = np.flatnonzero(~np.isfinite(arr.reshape(-1)))
    if bad.size:
        k = int(bad[0]) % arr.shape[-1]
        raise TorchfricError(
            f"{what} has a non-finite value at sample {k}; remove or fill NaN/inf first"
        )
    return arr
