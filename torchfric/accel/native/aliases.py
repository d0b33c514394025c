"""Aliases of `torchfric.accel.native`'s compiled libraries: a cached library found without
generating its source.

Generating the source means tracing the step and scalarising its graph: about half a second
per step, and the trace imports torch's compiler stack (another 0.7 s), in every process, only
to compute the hash that names the library. An alias names it by what the caller says the code
depends on instead (`alias_key`: the step's structural description, the shapes and 0/1
structure of its inputs, torch's version, a digest of torchfric's own source, compiler and
CPU), recorded after the first build in ``alias_<key>.json`` beside the libraries, under the
cache's rules (`torchfric.accel.native.cache`: the user's own folder, a regular file of the
user's, written atomically; nothing is recorded or read in a refused folder). The record only
points at a library, which is verified by its SHA-256 before it is loaded, as always. The key
is the caller's promise that it names everything the code depends on
(`torchfric.accel.structure_key` includes the model's classes and the code of their methods as
loaded, so a user's own friction, or a method replaced at run time, gets code of its own).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import json
import os
import sys
import tempfile
from pathlib import Path

from . import cache as _cache
from .cache import _PACKAGE, _cached, _cpu, _discard, _folder, _open_checked

__all__ = ["alias_key", "find_alias", "store_alias"]

_ALIAS_FORMAT = 1
_DTYPES = {"float64", "int64", "bool"}


@functools.cache
def _code_digest() -> str:
    """SHA-256 of torchfric's own Python source (every module under the package folder): any
    change to the package's code gives every step a new alias."""
    h = hashlib.sha256()
    for path in sorted(Path(_PACKAGE).rglob("*.py")):
        h.update(str(path.relative_to(_PACKAGE)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def alias_key(description: str, cc: str) -> str:
    """The alias of the code described by `description` (the caller's structural key and the
    input shapes) when built by `cc` on this machine with this torch and this torchfric."""
    import torch

    parts = [str(_ALIAS_FORMAT), description, torch.__version__, _code_digest(), cc,
             sys.platform, _cpu()]  # fmt: skip
    return hashlib.sha256("\0".join(parts).encode()).hexdigest()[:24]


def _alias_path(folder: Path, alias: str) -> Path:
    return folder / f"alias_{alias}.json"


def _read_alias(path: Path) -> dict | None:
    """The alias record at `path` when it is there and well formed (else None); `_Refused`
    when it may not be trusted."""
    try:
        fd = _open_checked(path)
    except FileNotFoundError:
        return None
    with os.fdopen(fd, "rb") as f:
        raw = f.read(65536)
    try:
        rec = json.loads(raw)
        ok = (
            rec["format"] == _ALIAS_FORMAT
            and isinstance(rec["library"], str) and len(rec["library"]) == 24
            and all(c in "0123456789abcdef" for c in rec["library"])
            and rec["lanes"] in (1, 2, 4, 8)
            and len(rec["shapes"]) == len(rec["dtypes"])
            and all(isinstance(d, int) and 0 <= d < 1 << 20 for s in rec["shapes"] for d in s)
            and all(d in _DTYPES for d in rec["dtypes"])
        )  # fmt: skip
    except (ValueError, KeyError, TypeError):
        ok = False
    return rec if ok else None


def find_alias(alias: str) -> tuple[ctypes.CDLL, dict] | None:
    """The verified library an alias record points at, and the record; None when there is no
    usable record or library (a malformed record is removed). Never raises for the cache's
    state: a folder or file that may not be used counts as no record (the build that follows
    says why)."""
    try:
        folder = _folder()
        if folder == _cache._PRIVATE:
            return None
        rec_path = _alias_path(folder, alias)
        rec = _read_alias(rec_path)
        if rec is None:
            if rec_path.exists():
                _discard(rec_path)
            return None
        with _cache._LOCK:  # (the module's current state: tests reset it)
            handle = _cache._LOADED.get(rec["library"]) or _cached(folder, rec["library"])
            if handle is None:
                return None
            _cache._LOADED[rec["library"]] = handle
        return handle, rec
    except (OSError, _cache._Refused):
        return None


def store_alias(alias: str, library: str, shapes: list, dtypes: list, lanes: int) -> None:
    """Record that `alias` is served by the library `library` (best effort: a record that
    cannot be written only costs the next process a trace)."""
    rec = {"format": _ALIAS_FORMAT, "library": library, "lanes": lanes,
           "shapes": [list(s) for s in shapes], "dtypes": [str(d).split(".")[-1] for d in dtypes]}  # fmt: skip
    tmp = None
    try:
        folder = _folder()
        if folder == _cache._PRIVATE:
            return
        fd, tmp = tempfile.mkstemp(prefix=".alias-", dir=folder)
        with os.fdopen(fd, "w") as f:
            os.fchmod(f.fileno(), 0o600)
            json.dump(rec, f)
        os.replace(tmp, _alias_path(folder, alias))
        tmp = None
    except OSError:
        pass
    finally:
        if tmp is not None:  # a record half written (a full disk): not left behind
            _discard(Path(tmp))
