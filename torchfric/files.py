"""Files written whole or not at all: atomic writes (temp file, fsync, rename) and strict JSON.

A leaf module: every part of torchfric that writes a file (the rig's generator, checkpoints, the
export, run directories) goes through it, so no reader ever sees a half-written file.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import secrets
from typing import Any

from .errors import TorchfricError

__all__ = ["atomic_write_bytes", "atomic_write_text", "json_safe", "write_json"]


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, *, what: str = "") -> None:
    """Write `data` to `path` via a temporary file and a rename; never a half-written file.

    The temporary file sits beside the target and is removed whatever happens (an error,
    Ctrl-C); the previous file, if any, stays as it was until the rename.
    """
    target = pathlib.Path(path)
    tmp = target.with_name(f".{target.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
        _fsync_dir(target.parent)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError):
            raise TorchfricError(
                f"cannot write {what + ' ' if what else ''}{target}: {exc.strerror or exc}; the "
                "previous file (if any) is unchanged"
            ) from None
        raise


def _fsync_dir(folder: pathlib.Path) -> None:
    """Make a rename in `folder` durable (POSIX; directories cannot be fsync'ed on Windows)."""
    if os.name != "posix":
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """`atomic_write_bytes` of `text` in UTF-8."""
    atomic_write_bytes(path, text.encode("utf-8"))


def json_safe(value: Any, path: str = "") -> tuple[Any, dict[str, str]]:
    """`value` with every NaN/±Infinity replaced by None, and the dotted paths replaced."""
    reasons: dict[str, str] = {}

    def walk(v: Any, where: str) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            reasons[where or "."] = f"not a finite number ({v}): the computation diverged"
            return None
        if isinstance(v, dict):
            return {k: walk(x, f"{where}.{k}" if where else str(k)) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [walk(x, f"{where}[{i}]") for i, x in enumerate(v)]
        return v

    return walk(value, path), reasons


def write_json(path: str | os.PathLike[str], obj: dict[str, Any]) -> None:
    """`obj` as strict JSON (no NaN), atomically; replaced values listed in ``null_reasons``."""
    clean, reasons = json_safe(obj)
    if reasons:
        clean["null_reasons"] = {**clean.get("null_reasons", {}), **reasons}
    atomic_write_text(path, json.dumps(clean, indent=2, allow_nan=False) + "\n")


# -- run directories ---------------------------------------------------------------------------
