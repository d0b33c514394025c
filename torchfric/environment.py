"""The ``TORCHFRIC_*`` environment variables, read and checked in one place.

=========================  ==========================================================  =======
variable                   meaning                                                     default
=========================  ==========================================================  =======
TORCHFRIC_THREADS          torch's intra-op threads of a run (an integer >= 1)         1
TORCHFRIC_NATIVE           1: run the filter as generated C; 0: the torch paths        1
TORCHFRIC_NATIVE_THREADS   threads that share an ensemble's members (integer >= 1)     cores
TORCHFRIC_CACHE            folder of the compiled-code cache (created private, 0700)   ~/.cache/torchfric
TORCHFRIC_PAINTER          1: a run's figures drawn by a helper process; 0: in the run  1
=========================  ==========================================================  =======

A value that does not parse is a one-line `TorchfricError` naming the variable, the value (cut
to 200 characters) and what is allowed; an unknown ``TORCHFRIC_*`` name is reported with the
closest known one.
"""

from __future__ import annotations

import contextlib
import difflib
import os
import warnings
from collections.abc import Iterator, Mapping
from typing import Any

from .errors import TorchfricError, shorten

__all__ = ["KNOWN", "check_environment", "native_enabled", "painter_enabled", "torch_settings"]

KNOWN: tuple[str, ...] = (
    "TORCHFRIC_THREADS",
    "TORCHFRIC_NATIVE",
    "TORCHFRIC_NATIVE_THREADS",
    "TORCHFRIC_CACHE",
    "TORCHFRIC_PAINTER",
)


def _switch(name: str, text: str | None, on: str, off: str) -> bool:
    """A 0/1 setting: "1", empty or unset → True; "0" → False; else a one-line error that says
    what each means (`on`, `off`)."""
    if text is None or text in ("", "1"):
        return True
    if text == "0":
        return False
    raise TorchfricError(
        f"{name}={shorten(text)!r} is not a valid value: use {name}=1 ({on}, the default) or "
        f"{name}=0 ({off}), or unset it"
    )


def native_enabled(text: str | None) -> bool:
    """``TORCHFRIC_NATIVE``: "1", empty or unset → True; "0" → False; else a one-line error."""
    return _switch("TORCHFRIC_NATIVE", text, "generated C", "the Inductor/eager path")


def painter_enabled(text: str | None) -> bool:
    """``TORCHFRIC_PAINTER``: "1", empty or unset → True; "0" → False; else a one-line error."""
    return _switch("TORCHFRIC_PAINTER", text, "a run's figures drawn by a helper process",
                   "in the run's own process")  # fmt: skip


def _positive_int(name: str, text: str) -> int:
    try:
        value = int(text.strip())
    except ValueError:
        value = 0
    if not 1 <= value <= 4096:
        raise TorchfricError(
            f"{name}={shorten(text)!r} is not a thread count; give an integer from 1 to 4096, or "
            f"unset it"
        )
    return value


def check_environment(env: Mapping[str, str] | None = None) -> dict[str, Any]:
    """The checked settings (missing ones at their defaults); raises on a bad value."""
    env = os.environ if env is None else env
    out: dict[str, Any] = {
        "TORCHFRIC_THREADS": 1,
        "TORCHFRIC_NATIVE": True,
        "TORCHFRIC_NATIVE_THREADS": None,
        "TORCHFRIC_CACHE": None,
        "TORCHFRIC_PAINTER": True,
    }
    for name, text in env.items():
        if not name.startswith("TORCHFRIC_"):
            continue
        if name in ("TORCHFRIC_THREADS", "TORCHFRIC_NATIVE_THREADS"):
            out[name] = _positive_int(name, text)
        elif name == "TORCHFRIC_NATIVE":
            out[name] = native_enabled(text)
        elif name == "TORCHFRIC_PAINTER":
            out[name] = painter_enabled(text)
        elif name == "TORCHFRIC_CACHE":
            if not text.strip() or "\0" in text:
                raise TorchfricError(
                    f"TORCHFRIC_CACHE={shorten(text)!r} is not a folder path; give a folder you own, "
                    "or unset it for ~/.cache/torchfric"
                )
            if os.path.exists(text) and not os.path.isdir(text):
                raise TorchfricError(
                    f"TORCHFRIC_CACHE={shorten(text)!r} is a file, not a folder; give a folder you "
                    "own, or unset it"
                )
            out[name] = text
        else:
            close = difflib.get_close_matches(name, KNOWN, n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]}?)" if close else ""
            warnings.warn(
                f"{shorten(name)} is not a torchfric setting{hint}; known: {', '.join(KNOWN)}",
                stacklevel=2,
            )
    return out


@contextlib.contextmanager
def torch_settings() -> Iterator[None]:
    """torch as a run uses it, restored afterwards: float64 by default, and the thread count of
    ``TORCHFRIC_THREADS`` (default 1: the filter's tensors are tiny, a thread pool only adds
    overhead to them, and one thread makes a run's arithmetic the same on every machine; the
    pre-fit's least squares summed in another order on 2 threads, and on EMPS that rounding
    alone moved the LuGre EKF's test RMSE from 14.5 to 8.2 mm). `torchfric.app.run.train`
    runs inside it, so the CLI, `torchfric.fit` and a direct call compute the same."""
    import torch

    threads_wanted = check_environment()["TORCHFRIC_THREADS"]
    dtype, threads = torch.get_default_dtype(), torch.get_num_threads()
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(threads_wanted)
    try:
        yield
    finally:
        torch.set_default_dtype(dtype)
        torch.set_num_threads(threads)
