"""The compiled-code cache of `torchfric.accel.native`: where libraries are kept, when they may
be loaded, and the compiler driver that builds them (with the compiler the package's
`compiler` names).

Loading a shared library runs its code (its constructors run at ``dlopen``), so the cache is
treated as executable code and trusted only when nobody else could have written it:

* **Where.** ``$TORCHFRIC_CACHE`` when set and not empty (``~`` expanded, made absolute), else
  ``$XDG_CACHE_HOME/torchfric/native``, else ``~/.cache/torchfric/native`` (`cache_dir`).
  Folders this module creates, the missing parents included, are made mode 0700 whatever the
  umask; libraries are stored 0700 and digests 0600.
* **Permission rule.** Code is loaded from the cache folder only when that folder (the one a
  symbolic link leads to, if it is one) is owned by the current user and not writable by group
  or others, and only from files that are regular files (not links) meeting the same rule
  (the folders above the cache folder are not examined). Otherwise nothing is loaded from or
  written to it: a `NativeCacheWarning` names the path and the fix (``chmod 700 PATH``; for a
  shared folder such as /tmp, a folder of one's own), and the libraries are built in a private
  temporary folder (`tempfile.mkdtemp`, mode 0700, removed at exit). A ``TORCHFRIC_CACHE``
  that cannot be used at all (it names a file, or a folder that cannot be created or written)
  is handled the same way: a warning and the private folder, never an error (it costs a
  compilation per process, not the run).
* **Verification.** Each library ``step_<key>.so`` is compiled in a fresh temporary folder
  beside it and moved into place with `os.replace` (atomic: readers see all of it or nothing);
  its SHA-256 is then stored the same way in ``step_<key>.so.sha256`` (``sha256sum -c``
  format). Before every load the file is hashed through the descriptor that was checked and
  compared with that record; a missing or different record (a truncated, garbled or planted
  file), or a file that then fails to load, is deleted and rebuilt, and the run goes on. No
  file is handed to ``dlopen`` before it passed (a truncated library that is mapped and run
  dies of SIGBUS; one that is planted runs its constructor). Two processes that build the
  same key each load their own fresh build; the later `os.replace` wins, and as the compiler's
  output depends only on source, flags and compiler, the two records agree (should they not,
  the next load sees a mismatch and rebuilds).

Notices go through `_warn_once` (one `NativeCacheWarning` line per process and reason, see the
package docstring); a reason of the environment that loses the native path is `_fallback`.
"""

from __future__ import annotations

import atexit
import ctypes
import functools
import hashlib
import os
import shutil
import stat
import subprocess
import sys
import tempfile
import threading
import warnings
from pathlib import Path

from ...errors import shorten
from .scalar import NativeUnavailable

__all__ = ["NativeCacheWarning", "cache_dir"]

# The torchfric package folder: warnings are attributed to the first caller outside it.
_PACKAGE = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))) + os.sep


class NativeCacheWarning(UserWarning):
    """The generated-code cache was refused or could not be used, or the native path was lost
    and the run takes a much slower path: one line with the reason (and the fix), issued once
    per process and reason. Filter it like any warning
    (``warnings.filterwarnings("ignore", category=NativeCacheWarning)``)."""


def cache_dir() -> Path:
    """Where compiled libraries are kept: ``$TORCHFRIC_CACHE`` or ``~/.cache/torchfric/native``
    (``$XDG_CACHE_HOME/torchfric/native`` when that is set). The configured place; whether it is
    used is decided at build time (see the module docstring: a folder others could write is
    refused for a private temporary one)."""
    env = os.environ.get("TORCHFRIC_CACHE")
    if env:
        return Path(os.path.abspath(os.path.expanduser(env)))
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "torchfric" / "native"


_WARNED: set[tuple[str, str]] = set()
_WARN_LOCK = threading.Lock()


def _warn_once(kind: str, subject: str, message: str) -> None:
    """`message` as one line of `NativeCacheWarning`, once per process for (kind, subject)."""
    with _WARN_LOCK:
        if (kind, subject) in _WARNED:
            return
        _WARNED.add((kind, subject))
    # attributed to the first caller outside torchfric (what Python shows as the warning's place)
    frame, level = sys._getframe(0), 1
    while frame.f_back is not None and frame.f_code.co_filename.startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    warnings.warn(
        f"torchfric.native: {' '.join(message.split())}", NativeCacheWarning, stacklevel=level
    )


def _fallback(kind: str, reason: str) -> NativeUnavailable:
    """The `NativeUnavailable` for a reason of the environment, announced (once per process and
    kind): the run goes on on the much slower Inductor/eager path."""
    _warn_once(
        "fallback", kind,
        f"{reason.strip().splitlines()[0] if reason.strip() else kind}; the filter takes the "
        "much slower Inductor/eager path instead (TORCHFRIC_NATIVE=0 chooses that path "
        "without this notice)",
    )  # fmt: skip
    return NativeUnavailable(reason)


# -march=native: 1.6x faster than the generic target on the step (tanh(3)); no fast-math and no
# contraction into FMAs, so the arithmetic stays the traced graph's, operation by operation.
# A compiler that rejects a flag of the first set (-march=native on some ARM toolchains) gets
# the second.
_FLAGS = ["-O2", "-march=native", "-fno-fast-math", "-ffp-contract=off", "-fPIC", "-shared"]
_PORTABLE_FLAGS = ["-O2", "-fno-fast-math", "-ffp-contract=off", "-fPIC", "-shared"]
_LOADED: dict[str, ctypes.CDLL] = {}
_LOCK = threading.Lock()
_PRIVATE: Path | None = None  # the private build folder, once a cache folder was refused


@functools.cache
def _cpu() -> str:
    """The processor's identity (-march=native code must not move to another CPU model)."""
    import platform

    try:
        info = Path("/proc/cpuinfo").read_text()
        return next(
            (ln for ln in info.splitlines() if ln.startswith(("flags", "Features"))), info[:500]
        )
    except OSError:
        return platform.processor() + platform.machine()


def _uid() -> int | None:
    """The user the cache must belong to (None where there are no POSIX owners)."""
    return os.geteuid() if hasattr(os, "geteuid") else None


def _untrusted(st: os.stat_result) -> str | None:
    """Why a file or folder with status `st` is not to be trusted (owned by someone else, or
    writable by group or others), or None."""
    uid = _uid()
    if uid is not None and st.st_uid != uid:
        return f"owned by uid {st.st_uid}, not by you (uid {uid})"
    if st.st_mode & 0o022:
        who = "group and others" if st.st_mode & 0o022 == 0o022 else (
            "group" if st.st_mode & 0o020 else "others")  # fmt: skip
        return f"writable by {who} (mode {stat.S_IMODE(st.st_mode):o})"
    return None


class _Refused(Exception):
    """A cache file that may not be loaded (see `_untrusted`)."""


def _make_dirs(folder: Path) -> None:
    """`folder` and its missing parents, each created mode 0700 whatever the umask."""
    missing = []
    p = folder
    while not os.path.isdir(p) and p.parent != p:
        missing.append(p)
        p = p.parent
    for d in reversed(missing):
        try:
            os.mkdir(d, 0o700)
        except FileExistsError:
            if not os.path.isdir(d):
                raise
            continue  # made meanwhile by another process: checked like any existing folder
        os.chmod(d, 0o700)  # mkdir's mode is masked by the umask: 0700 exactly


def _private_dir() -> Path:
    """This process's private build folder (`tempfile.mkdtemp`: mode 0700, removed at exit)."""
    global _PRIVATE
    if _PRIVATE is None or not _PRIVATE.is_dir():
        folder = Path(tempfile.mkdtemp(prefix="torchfric-native-"))
        os.chmod(folder, 0o700)
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        _PRIVATE = folder
    return _PRIVATE


def _folder() -> Path:
    """The folder to load from and build in: the cache folder when it is (or could be made)
    the user's own and closed to others; else, after a warning, `_private_dir`."""
    folder = cache_dir()
    try:
        _make_dirs(folder)
        st = os.stat(folder)
    except OSError as exc:
        why = "it is not a folder" if os.path.lexists(folder) else exc.strerror or str(exc)
        _warn_once(
            "unusable", str(folder),
            f"cache folder {shorten(str(folder))!r} cannot be used ({why}): set TORCHFRIC_CACHE "
            "to a folder of your own; building in a private temporary folder for this process",
        )  # fmt: skip
        return _private_dir()
    why = _untrusted(st)
    if why:
        shared = st.st_mode & stat.S_ISVTX or (_uid() is not None and st.st_uid != _uid())
        fix = (
            "set TORCHFRIC_CACHE to a folder of your own, e.g. ~/.cache/torchfric/native"
            if shared  # /tmp and the like: not to be closed
            else f"chmod 700 {folder}"
        )
        _warn_once(
            "refused", str(folder),
            f"not loading compiled code from cache folder {folder}: it is {why} (fix: {fix}); "
            "building in a private temporary folder for this process",
        )  # fmt: skip
        return _private_dir()
    return folder


def _paths(folder: Path, key: str) -> tuple[Path, Path]:
    """The library of `key` in `folder` and its digest record."""
    return folder / f"step_{key}.so", folder / f"step_{key}.so.sha256"


def _open_checked(path: Path) -> int:
    """A read descriptor of `path`, opened without following a link and checked: a regular
    file of the user's, not writable by others. FileNotFoundError when there is none;
    `_Refused` when it may not be used."""
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags | getattr(os, "O_NONBLOCK", 0))  # no hanging on a FIFO
    except FileNotFoundError:
        raise
    except OSError as exc:  # ELOOP: a symbolic link
        raise _Refused(f"{path} cannot be opened as a file ({exc.strerror or exc})") from exc
    st = os.fstat(fd)
    why = None if stat.S_ISREG(st.st_mode) else "not a regular file"
    why = why or _untrusted(st)
    if why:
        os.close(fd)
        raise _Refused(f"{path} is {why}")
    return fd


def _digest(fd: int) -> str:
    """SHA-256 of the file open on `fd` (which this closes)."""
    with os.fdopen(fd, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _recorded(path: Path) -> str | None:
    """The digest recorded in `path` (``sha256sum`` format), or None when there is none
    readable. `_Refused` when the record may not be trusted."""
    try:
        fd = _open_checked(path)
    except FileNotFoundError:
        return None
    with os.fdopen(fd, "rb") as f:
        words = f.read(4096).split()
    try:
        return words[0].decode("ascii") if words else None
    except UnicodeDecodeError:
        return None


def _discard(*paths: Path) -> None:
    """Remove cache entries that failed verification (best effort: a rebuild replaces them)."""
    for p in paths:
        try:
            os.unlink(p)
        except OSError:
            pass


def _open(path: Path) -> ctypes.CDLL:
    """Load a verified library and type its entry point."""
    handle = ctypes.CDLL(str(path))
    handle.torchfric_chunk.argtypes = [*[ctypes.c_int64] * 4, ctypes.POINTER(ctypes.c_void_p)]
    handle.torchfric_chunk.restype = None
    return handle


def _cached(folder: Path, key: str) -> ctypes.CDLL | None:
    """The library of `key` in `folder` when it is there and its SHA-256 is the recorded one;
    None when it is not there, or after removing an entry that failed verification (no
    record, another digest: truncated, garbled or planted) or then failed to load. `_Refused`
    when a file of the entry may not be used at all."""
    lib, record = _paths(folder, key)
    try:
        actual = _digest(_open_checked(lib))
    except FileNotFoundError:
        return None
    if _recorded(record) != actual:
        _discard(lib, record)
        return None
    try:
        return _open(lib)  # only now, verified: nothing unverified is ever mapped
    except (OSError, AttributeError):
        _discard(lib, record)
        return None


def _compile(cc: str, flags: list[str], source: str, folder: Path, key: str) -> ctypes.CDLL | str:
    """Build `source` in a fresh temporary folder inside `folder`, load the result and publish
    it as ``step_<key>.so`` with its digest record (each moved into place atomically, the
    library first); the loaded library, or the compiler's complaint. OSError when `folder`
    cannot be written; a failure to publish only costs the next process a compilation."""
    lib, record = _paths(folder, key)
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        os.chmod(tmp, 0o700)  # mkdtemp's 0700, less what the umask takes: 0700 exactly
        Path(tmp, "step.c").write_text(source)
        # relative names, in the build folder: the output does not depend on where it was made
        run = subprocess.run([cc, *flags, "step.c", "-o", lib.name, "-lm"], cwd=tmp,
                             capture_output=True, text=True)  # fmt: skip
        if run.returncode != 0:
            return run.stderr.strip()[:300] or f"{cc} exited with {run.returncode}"
        out = Path(tmp, lib.name)
        os.chmod(out, 0o700)  # the compiler's mode is masked by the umask only
        digest = _digest(os.open(out, os.O_RDONLY))
        try:
            # the fresh build, in a folder only this user can write: loaded under its own
            # unique name, so it serves this process whatever happens to the cache meanwhile
            handle = _open(out)
        except (OSError, AttributeError) as exc:
            return f"the library built does not load: {exc}"
        try:
            os.replace(out, lib)
            side = Path(tmp, record.name)
            fd = os.open(side, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            os.fchmod(fd, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(f"{digest}  {lib.name}\n")
                f.flush()
                os.fsync(f.fileno())
            os.replace(side, record)
        except OSError as exc:
            _warn_once(
                "store", str(folder),
                f"cannot store compiled code in {folder} ({exc.strerror or exc}); later "
                "processes compile it again",
            )  # fmt: skip
    return handle


def _load_or_build(cc: str, flags: list[str], source: str, key: str) -> ctypes.CDLL | str:
    """The library of `key`: verified from the cache, else built there (or, when the cache
    folder is refused or cannot be written, in the private folder); or the compiler's complaint.
    `NativeUnavailable` when not even the private folder can be written (a full disk)."""
    try:
        folder = _folder()
        if folder != _PRIVATE:
            try:
                handle = _cached(folder, key)
                if handle is not None:
                    return handle
                return _compile(cc, flags, source, folder, key)
            except _Refused as exc:
                _warn_once(
                    "refused", str(folder),
                    f"not loading compiled code from {exc} (fix: delete it, and keep {folder} "
                    "mode 0700); building in a private temporary folder for this process",
                )  # fmt: skip
            except OSError as exc:
                _warn_once(
                    "unwritable", str(folder),
                    f"cannot build in cache folder {folder} ({exc.strerror or exc}); building "
                    "in a private temporary folder for this process",
                )  # fmt: skip
        private = _private_dir()
        handle = _cached(private, key)
        return handle if handle is not None else _compile(cc, flags, source, private, key)
    except (OSError, _Refused) as exc:
        raise _fallback("io", f"cannot build the generated code: {exc}") from exc


def _build(source: str, cc: str) -> tuple[ctypes.CDLL, str]:
    """Compile `source` with the C compiler `cc` once (cached on disk by the hash of source,
    flags, compiler and CPU, verified before every load: see the module docstring) and load it:
    with `_FLAGS`, or `_PORTABLE_FLAGS` where the compiler rejects those. Returns the library
    and its key (what `_store_alias` records)."""
    errors: list[str] = []
    for flags in (_FLAGS, _PORTABLE_FLAGS):
        ident = " ".join([*flags, cc, sys.platform, _cpu()])
        key = hashlib.sha256((source + ident).encode()).hexdigest()[:24]
        with _LOCK:
            if key not in _LOADED:
                handle = _load_or_build(cc, flags, source, key)
                if isinstance(handle, str):
                    errors.append(handle)
                    continue
                _LOADED[key] = handle
            return _LOADED[key], key
    raise _fallback("build-failed", f"C compiler failed: {errors[-1]}")
