"""Run directories that never lose a user's files, and outputs written atomically.

The rules (`claim_run_dir`):

- A run writes only inside its run directory. The default one is ``out_dir/NAME``, or the first
  free ``NAME-2``, ``NAME-3``, … — claimed with an atomic ``mkdir``, so two runs started at once
  get two folders and an earlier run is never touched.
- An explicit directory (``--out DIR``) is used when it does not exist or is empty. One that
  holds an earlier torchfric run (its `MARKER` file) is refused unless ``overwrite``; then the new
  run is written beside it in ``DIR.new`` and replaces it only once it has finished, so a failing
  or interrupted re-run leaves the earlier run as it was. A directory holding anything torchfric
  did not write (``--out .`` in a project folder, say) is refused, with or without ``overwrite``.
- One process at a time writes a run directory: `RunLock` creates `LOCK` exclusively and names
  the owner's pid; a second run stops with that pid. A lock left by a process that no longer
  exists is taken over.

Outputs go through `atomic_write_text` / `write_json`: a temporary file in the same folder,
fsync, rename; the temporary file is removed whatever happens (an error, Ctrl-C). JSON never
holds NaN or Infinity: such a value becomes ``null`` and its dotted path is listed under
``"null_reasons"``.
"""

from __future__ import annotations

import json
import os
import pathlib
import re
import shutil
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from ...errors import TorchfricError
from ...files import atomic_write_text

__all__ = [
    "LOCK",
    "MARKER",
    "RunDir",
    "RunLock",
    "claim_run_dir",
    "foreign_entries",
    "next_run_dir",
]

MARKER = ".torchfric-run"
"""A run directory's stamp: written first, it tells later runs that torchfric owns the folder."""
LOCK = ".torchfric.lock"
"""Held (created exclusively) while a process writes the run directory; holds the owner's pid."""

# What a run writes at the top of its directory; anything else is the user's.
_OURS = re.compile(
    r"(\.torchfric-run|\.torchfric\.lock|config\.toml|metrics\.json|ensemble\.json|report\.html"
    r"|[^/]+\.pt|passes|figures|events\.out\.tfevents\..*|\..*\.tmp)"
)


def foreign_entries(folder: pathlib.Path) -> list[str]:
    """Names in `folder` that a torchfric run does not write."""
    return sorted(p.name for p in folder.iterdir() if not _OURS.fullmatch(p.name))


def _is_run(folder: pathlib.Path) -> bool:
    return (folder / MARKER).is_file()


@dataclass
class RunDir:
    """Where a run writes (`path`) and, for ``overwrite``, the earlier run it replaces at the end.

    `finish` moves the finished `path` into `replaces`' place (the earlier run is removed only
    then); without `replaces` it does nothing.
    """

    path: pathlib.Path
    replaces: pathlib.Path | None = None

    @property
    def final(self) -> pathlib.Path:
        """The folder the run's files end up in."""
        return self.replaces or self.path

    def finish(self) -> pathlib.Path:
        if self.replaces is None:
            return self.path
        old = self.replaces.with_name(f"{self.replaces.name}.old-{os.getpid()}")
        os.rename(self.replaces, old)
        os.rename(self.path, self.replaces)
        shutil.rmtree(old, ignore_errors=True)
        return self.replaces


def _stamp(folder: pathlib.Path) -> None:
    atomic_write_text(
        folder / MARKER,
        json.dumps({"torchfric_run": 1, "created": time.strftime("%Y-%m-%dT%H:%M:%S")}) + "\n",
    )


def _mkdir_new(path: pathlib.Path) -> bool:
    """Create `path` (parents too); False when it exists already."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.mkdir()
    except FileExistsError:
        return False
    except OSError as exc:
        raise TorchfricError(
            f"cannot create the run directory {path}: {exc.strerror or exc}; choose another "
            "with --out DIR"
        ) from None
    return True


def _candidates(default: pathlib.Path) -> Iterator[pathlib.Path]:
    """The default run directories in the order they are tried: NAME, NAME-2, … NAME-9999."""
    for i in range(1, 10_000):
        yield default if i == 1 else default.with_name(f"{default.name}-{i}")


def _all_taken(default: pathlib.Path) -> TorchfricError:
    return TorchfricError(
        f"{default}-2 … {default}-9999 all exist; clean up {default.parent} or give --out"
    )


def next_run_dir(default: pathlib.Path) -> pathlib.Path:
    """The folder `claim_run_dir` would claim now for a new run without ``--out``: `default`
    (``out_dir/NAME``) or the first free ``NAME-2``, ``NAME-3``, …; creates nothing (for
    ``torchfric check``). A run started later claims the first one free at that moment."""
    for path in _candidates(default):
        if not (path.exists() or path.is_symlink()):
            return path
    raise _all_taken(default)


def claim_run_dir(
    default: pathlib.Path,
    *,
    explicit: pathlib.Path | None = None,
    overwrite: bool = False,
    resume: bool = False,
) -> RunDir:
    """The run directory for a new run (or the one to `resume`), claimed and stamped.

    `default` is ``out_dir/NAME`` (suffixed when taken); `explicit` is ``--out DIR``.
    """
    if resume:
        folder = explicit or default
        legacy = (folder / "config.toml").is_file() and (folder / "passes").is_dir()
        if not _is_run(folder) and legacy and not foreign_entries(folder):
            _stamp(folder)  # a run written before run directories were stamped
        if not _is_run(folder):
            raise TorchfricError(
                f"--resume {folder}: not a torchfric run directory (no {MARKER}); give the "
                "folder of the run to continue"
            )
        # An interrupted --overwrite run (DIR.new) still replaces DIR once it finishes.
        if folder.name.endswith(".new") and len(folder.name) > len(".new"):
            earlier = folder.with_name(folder.name[: -len(".new")])
            if _is_run(earlier):
                return RunDir(folder, replaces=earlier)
        return RunDir(folder)
    if explicit is None:
        if overwrite:
            explicit = default
        else:
            for path in _candidates(default):
                if _mkdir_new(path):
                    _stamp(path)
                    return RunDir(path)
            raise _all_taken(default)
    folder = explicit
    if folder.exists() and not folder.is_dir():
        raise TorchfricError(f"--out {folder} is a file, not a folder; give a directory name")
    if _mkdir_new(folder):
        _stamp(folder)
        return RunDir(folder)
    _check_not_in_use(folder)  # a run being written there now: name its owner (a stale lock goes)
    entries = sorted(p.name for p in folder.iterdir())
    if not entries:
        _stamp(folder)
        return RunDir(folder)
    foreign = foreign_entries(folder) if _is_run(folder) else entries
    if foreign:
        shown = ", ".join(foreign[:5]) + (
            f" and {len(foreign) - 5} more" if len(foreign) > 5 else ""
        )
        raise TorchfricError(
            f"--out {folder} holds files torchfric did not write ({shown}); a run never writes "
            "over them: give an empty or new directory"
        )
    if not overwrite:
        raise TorchfricError(
            f"{folder} holds an earlier run; keep it and choose another --out, continue it with "
            f"--resume {folder}, or replace it with --overwrite (the earlier run is removed only "
            "once the new one has finished)"
        )
    staging = folder.with_name(folder.name + ".new")
    if staging.exists():
        _check_not_in_use(staging)
        if not _is_run(staging) or foreign_entries(staging):
            raise TorchfricError(
                f"{staging} exists and is not a torchfric run; move it away to use --overwrite"
            )
        shutil.rmtree(staging)  # an earlier --overwrite that did not finish: ours to replace
    if not _mkdir_new(staging):
        raise TorchfricError(f"{staging} appeared while starting; is another run starting there?")
    _stamp(staging)
    return RunDir(staging, replaces=folder)


def _check_not_in_use(folder: pathlib.Path) -> None:
    """Raise when a live process holds `folder`'s lock."""
    lock = RunLock(folder)
    if lock.path.exists():
        lock.acquire()  # raises naming the owner when it is alive; takes over a stale lock
        lock.release()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class RunLock:
    """An exclusive lock on a run directory, held by creating `LOCK` (with the pid) atomically."""

    def __init__(self, folder: pathlib.Path) -> None:
        self.path = folder / LOCK
        self.held = False

    def acquire(self) -> RunLock:
        owner = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.time()}
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                other = self._owner()
                pid = other.get("pid")
                same_host = other.get("host") == owner["host"]
                if isinstance(pid, int) and (not same_host or _alive(pid)):
                    where = "" if same_host else f" on {other.get('host')}"
                    raise TorchfricError(
                        f"{self.path.parent} is in use by another torchfric run (pid {pid}"
                        f"{where}); wait for it to finish or choose another --out"
                    ) from None
                self.path.unlink(missing_ok=True)  # its owner is gone: a stale lock
                continue
            with os.fdopen(fd, "w") as f:
                json.dump(owner, f)
            self.held = True
            return self
        raise TorchfricError(f"cannot lock {self.path.parent}; another run keeps taking it")

    def _owner(self) -> dict[str, Any]:
        try:
            data = json.loads(self.path.read_text())
            return data if isinstance(data, dict) else {}
        except (OSError, ValueError):
            return {}

    def release(self) -> None:
        if self.held:
            self.path.unlink(missing_ok=True)
            self.held = False


@contextmanager
def locked(*folders: pathlib.Path) -> Iterator[list[RunLock]]:
    """Hold `RunLock`s on `folders` (in order) for the block."""
    locks: list[RunLock] = []
    try:
        for folder in folders:
            locks.append(RunLock(folder).acquire())
        yield locks
    finally:
        for lock in reversed(locks):
            lock.release()
