"""The compiled-code cache of `torchfric.accel.native`: it only loads code nobody else could have
written, verifies every library against its recorded SHA-256 before loading it, repairs a bad
entry instead of crashing, and says when a run loses the native path.

Every test builds into its own cache under `tmp_path` (``TORCHFRIC_CACHE``), never the user's.
One library is compiled per module (`built`) and copied where a test needs a valid entry; the
in-process caches (`_LOADED`, the warnings already given, the private folder) are reset for
every test, so each one sees what a fresh process would.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import stat
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import pytest
import torch

from torchfric.accel import make_chunk, native
from torchfric.accel.native import NativeCacheWarning, NativeUnavailable, make_native_chunk
from torchfric.errors import TorchfricError

pytestmark = pytest.mark.skipif(native.compiler() is None, reason="no C compiler here")

ROOT = Path(__file__).resolve().parents[1]


def _fn(x, c):  # type: ignore[no-untyped-def]
    return (torch.tanh(x) + c,), ()


def _args():  # type: ignore[no-untyped-def]
    return (torch.ones(3),), (), torch.ones(4, dtype=torch.bool), (torch.tensor(0.25),)


def _eager() -> torch.Tensor:
    x = torch.ones(3)
    for _ in range(4):
        x = torch.tanh(x) + 0.25
    return x


def _run() -> torch.Tensor:
    """The step through the native path (a new chunk: traced and loaded or built again)."""
    (x,), _ = make_native_chunk(_fn)(*_args())
    return x


def _check(x: torch.Tensor) -> None:
    torch.testing.assert_close(x, _eager(), rtol=1e-15, atol=0)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _verifies(lib: Path) -> bool:
    """The entry is complete: a library whose SHA-256 is the one recorded beside it."""
    record = lib.with_name(lib.name + ".sha256")
    return record.exists() and record.read_text().split()[0] == _sha(lib)


def _native_warnings(record: list[warnings.WarningMessage]) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, NativeCacheWarning)]


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:  # type: ignore[no-untyped-def]
    """A folder holding one valid entry (library and record) for `_fn`, built once."""
    folder = tmp_path_factory.mktemp("built") / "cache"
    mp = pytest.MonkeyPatch()
    mp.setenv("TORCHFRIC_CACHE", str(folder))
    mp.setattr(native.cache, "_LOADED", {})
    try:
        _check(_run())
    finally:
        mp.undo()
    (lib,) = folder.glob("step_*.so")
    assert _verifies(lib)
    return folder


@pytest.fixture(scope="module")
def planted(tmp_path_factory) -> Path:  # type: ignore[no-untyped-def]
    """A library whose constructor (and entry point) writes the file named by
    ``$TORCHFRIC_TEST_MARKER``: code that must never run."""
    folder = tmp_path_factory.mktemp("planted")
    src = folder / "planted.c"
    src.write_text(
        textwrap.dedent(
            """\
            #include <stdio.h>
            #include <stdlib.h>
            #include <stdint.h>
            static void mark(void) {
              const char *p = getenv("TORCHFRIC_TEST_MARKER");
              FILE *f = p ? fopen(p, "w") : NULL;
              if (f) { fputs("planted code ran\\n", f); fclose(f); }
            }
            __attribute__((constructor)) static void planted(void) { mark(); }
            void torchfric_chunk(int64_t a, int64_t b, int64_t c, int64_t d, void **p) { mark(); }
            """
        )
    )
    out = folder / "planted.so"
    subprocess.run([native.compiler(), "-shared", "-fPIC", str(src), "-o", str(out)], check=True)
    return out


@pytest.fixture(autouse=True)
def cache(native_cache, tmp_path, monkeypatch) -> Path:  # type: ignore[no-untyped-def]
    """A cache of the test's own, and nothing loaded, warned about or made private yet."""
    monkeypatch.setenv("TORCHFRIC_TEST_MARKER", str(tmp_path / "planted-code-ran"))
    return native_cache


def _seed(built: Path, cache: Path) -> Path:
    """`cache` (mode 0700) with a copy of the valid entry; its library."""
    cache.mkdir(mode=0o700, parents=True)
    for f in built.iterdir():
        shutil.copy2(f, cache / f.name)
    (lib,) = cache.glob("step_*.so")
    return lib


def _plant(planted: Path, lib: Path, record: str) -> None:
    """The planted library under `lib`'s name, with no record, a wrong one or its own."""
    digest = lib.with_name(lib.name + ".sha256")
    shutil.copy2(planted, lib)
    if record == "none":
        digest.unlink(missing_ok=True)
    elif record == "own":  # a record that matches: only the permission rule can refuse it
        digest.write_text(f"{_sha(lib)}  {lib.name}\n")
    # "stale": the record of the real library stays


def _marker_absent(tmp_path: Path) -> None:
    assert not (tmp_path / "planted-code-ran").exists(), "the planted library's code ran"


# ---------------------------------------------------------------------------------------------
# Folders and files only the user could have written
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("umask", [0o000, 0o277], ids=["umask 000", "umask 277"])
def test_cache_folders_and_files_are_private_whatever_the_umask(  # type: ignore[no-untyped-def]
    umask, tmp_path, monkeypatch
) -> None:
    """Folders 0700 (the parents made too), libraries 0700, records 0600: neither wider (umask
    000) nor narrower (umask 277, which would leave folders the owner cannot write)."""
    cache = tmp_path / "a" / "b" / "cache"
    monkeypatch.setenv("TORCHFRIC_CACHE", str(cache))
    old = os.umask(umask)
    try:
        with warnings.catch_warnings(record=True) as record:
            warnings.simplefilter("always")
            _check(_run())
    finally:
        os.umask(old)
    assert not _native_warnings(record)
    for d in (tmp_path / "a", tmp_path / "a" / "b", cache):
        assert stat.S_IMODE(d.stat().st_mode) == 0o700, d
    (lib,) = cache.glob("step_*.so")
    assert stat.S_IMODE(lib.stat().st_mode) == 0o700
    assert stat.S_IMODE(lib.with_name(lib.name + ".sha256").stat().st_mode) == 0o600
    assert _verifies(lib)
    assert sorted(p.name for p in cache.iterdir()) == [lib.name, lib.name + ".sha256"]


_MODES = {"group": 0o770, "others": 0o707, "both": 0o777, "shared like /tmp": 0o1777}


@pytest.mark.parametrize("kind", list(_MODES))
def test_a_cache_folder_others_can_write_is_refused(kind, built, planted, tmp_path, cache) -> None:  # type: ignore[no-untyped-def]
    """Even an entry whose record matches is not loaded from a folder others could write: the
    step is built in a private folder instead, after a warning naming the path and the fix
    (for a shared folder such as /tmp: another folder, not closing that one)."""
    lib = _seed(built, cache)
    _plant(planted, lib, "own")
    mode = _MODES[kind]
    cache.chmod(mode)
    before = {p.name: _sha(p) for p in cache.iterdir()}
    fix = (
        "set TORCHFRIC_CACHE to a folder of your own"
        if mode & stat.S_ISVTX
        else f"chmod 700 {re.escape(str(cache))}"
    )
    with pytest.warns(
        NativeCacheWarning, match=f"{re.escape(str(cache))}: it is writable by .*fix: {fix}"
    ) as record:
        _check(_run())
        _check(_run())  # warned once per process
    assert len(_native_warnings(record)) == 1
    _marker_absent(tmp_path)
    assert {p.name: _sha(p) for p in cache.iterdir()} == before, "wrote into a refused folder"
    assert stat.S_IMODE(cache.stat().st_mode) == mode
    private = native.cache._PRIVATE
    assert private is not None and private != cache
    assert stat.S_IMODE(private.stat().st_mode) == 0o700
    assert _verifies(private / lib.name)


def _give_away(path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """`path` owned by another user: really where this runs as root, else as `os.fstat` and
    `os.stat` report it to the cache."""
    if os.geteuid() == 0:
        os.chown(path, 65534, -1, follow_symlinks=False)
        return
    ino = path.stat().st_ino

    def other(st: os.stat_result) -> os.stat_result:
        if st.st_ino != ino:
            return st
        fields = list(st)
        fields[4] = os.geteuid() + 1
        return os.stat_result(fields)

    real_fstat, real_stat = os.fstat, os.stat
    monkeypatch.setattr(native.cache.os, "fstat", lambda fd: other(real_fstat(fd)))
    monkeypatch.setattr(native.cache.os, "stat", lambda p, *a, **k: other(real_stat(p, *a, **k)))


def test_a_cache_folder_owned_by_another_user_is_refused(  # type: ignore[no-untyped-def]
    built, planted, tmp_path, cache, monkeypatch
) -> None:
    lib = _seed(built, cache)
    _plant(planted, lib, "own")
    _give_away(cache, monkeypatch)
    with pytest.warns(NativeCacheWarning, match=f"{re.escape(str(cache))}.*owned by uid"):
        _check(_run())
    _marker_absent(tmp_path)
    assert _verifies(native.cache._PRIVATE / lib.name)


@pytest.mark.parametrize("problem", ["owned by another user", "writable by others", "a link"])
def test_a_library_file_others_could_have_written_is_refused(  # type: ignore[no-untyped-def]
    problem, built, planted, tmp_path, cache, monkeypatch
) -> None:
    """The planted library's record matches: only the file's owner and mode refuse it."""
    lib = _seed(built, cache)
    _plant(planted, lib, "own")
    if problem == "owned by another user":
        _give_away(lib, monkeypatch)
        expected = "owned by uid"
    elif problem == "writable by others":
        lib.chmod(0o777)
        expected = "writable by"
    else:
        lib.unlink()
        lib.symlink_to(planted)
        expected = "cannot be opened"
    with pytest.warns(NativeCacheWarning, match=f"{re.escape(str(lib))}.*{expected}"):
        _check(_run())
    _marker_absent(tmp_path)
    assert _verifies(native.cache._PRIVATE / lib.name)


# ---------------------------------------------------------------------------------------------
# Verification before every load
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("record", ["none", "stale"])
def test_a_planted_library_without_a_matching_record_never_runs(  # type: ignore[no-untyped-def]
    record, built, planted, tmp_path, cache
) -> None:
    lib = _seed(built, cache)
    _plant(planted, lib, record)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _check(_run())
    assert not _native_warnings(caught)  # repaired in place: nothing to tell
    _marker_absent(tmp_path)
    assert _verifies(lib) and _sha(lib) == _sha(built / lib.name)


@pytest.mark.parametrize("record", ["stale", "matching"])
def test_a_garbage_library_is_removed_and_rebuilt(record, built, cache) -> None:  # type: ignore[no-untyped-def]
    """Garbage with the old record fails verification; garbage with a record of its own fails
    to load. Either way the entry is rebuilt and the run goes on."""
    lib = _seed(built, cache)
    lib.write_bytes(os.urandom(3000))
    if record == "matching":
        lib.with_name(lib.name + ".sha256").write_text(f"{_sha(lib)}  {lib.name}\n")
    _check(_run())
    assert _verifies(lib) and _sha(lib) == _sha(built / lib.name)


_CHILD = """
import torch
torch.set_default_dtype(torch.float64)
from torchfric.accel.native import make_native_chunk

def fn(x, c):
    return (torch.tanh(x) + c,), ()

(x,), _ = make_native_chunk(fn)(
    (torch.ones(3),), (), torch.ones(4, dtype=torch.bool), (torch.tensor(0.25),))
expect = torch.ones(3)
for _ in range(4):
    expect = torch.tanh(expect) + 0.25
torch.testing.assert_close(x, expect, rtol=1e-15, atol=0)
print("ok")
"""


def _child(cache: Path) -> subprocess.Popen:
    env = {**os.environ, "TORCHFRIC_CACHE": str(cache), "PYTHONPATH": str(ROOT)}
    env.pop("TORCHFRIC_NATIVE", None)
    return subprocess.Popen([sys.executable, "-c", _CHILD], env=env, cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip


def _finished(child: subprocess.Popen) -> None:
    out, err = child.communicate(timeout=120)
    assert child.returncode == 0, f"exit status {child.returncode} (-7: SIGBUS)\n{err[-2000:]}"
    assert out.strip() == "ok"


def test_a_truncated_library_is_rebuilt_without_a_crash(built, cache) -> None:
    """Mapped and run, a truncated library dies of SIGBUS (exit 135): the run is a separate
    process, so that such a regression fails this test instead of killing pytest."""
    lib = _seed(built, cache)
    size = lib.stat().st_size
    with open(lib, "r+b") as f:
        f.truncate(min(5000, size // 2))
    _finished(_child(cache))
    assert lib.stat().st_size == size and _verifies(lib)


def test_concurrent_builders_both_end_with_a_valid_library(cache) -> None:
    """Two processes build the same key at once: each loads its own build, the later
    `os.replace` wins, and the entry left verifies."""
    children = [_child(cache), _child(cache)]
    for child in children:
        _finished(child)
    (lib,) = cache.glob("step_*.so")
    assert _verifies(lib)
    assert not list(cache.glob("tmp*")), "a build folder was left behind"


# ---------------------------------------------------------------------------------------------
# The switch, bad settings and the fallback notice
# ---------------------------------------------------------------------------------------------
def test_native_off_takes_the_fallback(monkeypatch, cache) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setenv("TORCHFRIC_NATIVE", "0")
    chunk = make_chunk(_fn, native=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        (x,), _ = chunk(*_args())
    _check(x)
    assert chunk.path in ("inductor", "eager")
    assert chunk.why_not_native == ["TORCHFRIC_NATIVE=0"]
    assert not _native_warnings(caught)  # the user's choice: nothing to announce
    assert not cache.exists()
    monkeypatch.setenv("TORCHFRIC_NATIVE", "1")
    (x,), _ = chunk(*_args())
    _check(x)
    assert chunk.path == "native"


@pytest.mark.parametrize("value", ["yes", "2", "true", " 1", "x" * 5000 + "\nsecond line"])
def test_an_invalid_native_switch_is_a_one_line_error(value, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setenv("TORCHFRIC_NATIVE", value)
    with pytest.raises(TorchfricError) as info:
        make_native_chunk(_fn)
    message = str(info.value)
    assert "\n" not in message and len(message) < 400
    assert "TORCHFRIC_NATIVE=" in message and repr(value[:20])[:-1] in message
    assert "TORCHFRIC_NATIVE=1" in message and "TORCHFRIC_NATIVE=0" in message
    # set wrong after the step was made: the next call says so too
    monkeypatch.setenv("TORCHFRIC_NATIVE", "1")
    chunk = make_native_chunk(_fn)
    monkeypatch.setenv("TORCHFRIC_NATIVE", value)
    with pytest.raises(TorchfricError, match="TORCHFRIC_NATIVE="):
        chunk(*_args())


def test_no_compiler_falls_back_with_one_notice(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setattr(native, "compiler", lambda: None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(2):  # two steps, two calls each: one notice per process
            chunk = make_chunk(_fn, native=True)
            for _ in range(2):
                (x,), _ = chunk(*_args())
                _check(x)
            assert chunk.path in ("inductor", "eager")
    (notice,) = _native_warnings(caught)
    assert "no C compiler" in notice and "slower" in notice and "\n" not in notice


@pytest.mark.parametrize("setting", ["a file", "below a file"])
def test_an_unusable_cache_setting_warns_and_builds_privately(  # type: ignore[no-untyped-def]
    setting, tmp_path, monkeypatch
) -> None:
    """A ``TORCHFRIC_CACHE`` that names a file, or a folder that cannot be created, costs a
    warning and a private build, not the run."""
    target = tmp_path / "not-a-folder"
    target.write_text("a file")
    bad = target if setting == "a file" else target / "cache"
    monkeypatch.setenv("TORCHFRIC_CACHE", str(bad))
    with pytest.warns(
        NativeCacheWarning, match=f"{re.escape(str(bad))}.*cannot be used.*TORCHFRIC_CACHE"
    ):
        _check(_run())
    assert target.read_text() == "a file"
    assert list(native.cache._PRIVATE.glob("step_*.so"))


def test_a_full_disk_falls_back_with_the_reason(monkeypatch, cache) -> None:  # type: ignore[no-untyped-def]
    """No room in the cache: built privately; no room there either: the slower path, said once."""

    def full(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(native.cache, "_compile", full)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(2):
            with pytest.raises(NativeUnavailable, match="No space left"):
                _run()
    notices = _native_warnings(caught)
    assert len(notices) == 2, notices
    assert "cannot build in cache folder" in notices[0] and "No space left" in notices[0]
    assert "No space left" in notices[1] and "slower" in notices[1]
