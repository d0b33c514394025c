"""The one exception users meet: a `ValueError` whose message names the problem and the fix."""

from __future__ import annotations

__all__ = [
    "SHOW_LIMIT",
    "DivergenceError",
    "MissingColumn",
    "RunInterrupted",
    "TorchfricError",
    "shorten",
]

SHOW_LIMIT = 200
"""At most this many characters of a bad value (or a library's message) are echoed in an error."""


def shorten(text: str, limit: int = SHOW_LIMIT) -> str:
    """`text`, cut to `limit` characters with the number of characters it had."""
    if len(text) <= limit:
        return text
    return f"{text[: limit - 40]}… ({len(text)} characters)"


class TorchfricError(ValueError):
    """Bad input, bad configuration or a failed estimation, explained in one line.

    Subclasses `ValueError` so that callers that only know the standard library can still catch
    it. The CLI prints `error: <message>` and exits with status 2 instead of a traceback.
    """


class DivergenceError(TorchfricError):
    """The estimator diverged (NaN/inf, a non-PSD covariance, or θ left its box).

    Carries the last good result so that nothing already estimated is lost.
    """

    def __init__(self, message: str, *, last_good: object = None) -> None:
        super().__init__(message)
        self.last_good = last_good


class MissingColumn(TorchfricError):
    """A record lacks one of our columns (t, u, q, qdot): `role` names which, so that a caller
    can say how its own user maps it (``data.columns`` in a config, ``--column`` on the command
    line)."""

    def __init__(self, message: str, *, role: str) -> None:
        super().__init__(message)
        self.role = role


class RunInterrupted(TorchfricError):
    """A run stopped by Ctrl-C: where its last completed pass is, to continue with ``--resume``.

    Attributes:
        run_dir: the run directory to pass to ``--resume`` (None when nothing was saved yet).
        last: a description of the last completed pass or epoch ("pass 3"), or None.
    """

    def __init__(self, message: str, *, run_dir: object = None, last: str | None = None) -> None:
        super().__init__(message)
        self.run_dir = run_dir
        self.last = last
