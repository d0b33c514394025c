"""Figures drawn where the user does not wait for them: a helper process that renders the run's
figure specs (`torchfric.app.artifacts.drawing`) to PNG while the run goes on.

A run's figures cost about a quarter of a short run's wall time on 2 cores when the run draws
them itself (matplotlib's import and six to eight figures, about 1.3 s of the quick start). The
`Painter` starts a helper (`drawing.serve`: numpy and matplotlib only, no torch) at the run's
start; `Painter.submit` hands it a spec and returns at once, `Painter.png`
waits for that figure's PNG. The starting model's figures are drawn during the passes, the kept
model's while the run writes its checkpoint and metrics.

The figures are the same either way: where the helper cannot start, dies or fails on a figure,
that figure is drawn in this process (`drawing.render`, the helper's own function), and
``TORCHFRIC_PAINTER=0`` draws every figure here. The helper reads its parent's requests from
its stdin and ends when that closes (the run's end, or the parent's death); it writes only to
its stdout.

The frames are `drawing.serve`'s: the parent never unpickles what the helper sends.
"""

from __future__ import annotations

import atexit
import itertools
import os
import pickle
import queue
import subprocess
import sys
import threading
from collections.abc import Mapping
from typing import Any

from ...environment import painter_enabled
from . import drawing
from .drawing import ANSWER, HEAD, read_exact, render

__all__ = ["Painter", "painting", "shared_painter"]


def painting() -> bool:
    """Whether figures go to the helper process (``$TORCHFRIC_PAINTER``, default on)."""
    return painter_enabled(os.environ.get("TORCHFRIC_PAINTER"))


# The helper: Python in isolated mode (no current folder, no PYTHONPATH, no user site on its
# path) runs `drawing.serve` from the very file this process imported.
_HELPER = (
    "import importlib.util as u; s = u.spec_from_file_location('torchfric_drawing', {path!r}); "
    "m = u.module_from_spec(s); s.loader.exec_module(m); m.serve()"
)


class Painter:
    """Renders figure specs to PNG in a helper process, in the order submitted; falls back to
    this process for any figure the helper does not deliver (module docstring)."""

    def __init__(self) -> None:
        self._proc: subprocess.Popen[bytes] | None = None
        self._outbox: queue.Queue[bytes | None] = queue.Queue()
        self._specs: dict[int, tuple[str, Mapping[str, Any]]] = {}
        self._done: dict[int, bytes | None] = {}  # None: the helper failed on it
        self._arrived: dict[int, threading.Event] = {}
        self._ids = itertools.count()
        self._broken = not painting()
        self._pid = os.getpid()  # a forked child's copy has no threads: it starts its own
        self._reader: threading.Thread | None = None  # reads the helper's answers

    def start(self) -> None:
        """Start the helper (it imports matplotlib while the run goes on); no-op when started,
        switched off, or when it cannot start (every figure is then drawn here)."""
        if self._proc is not None or self._broken:
            return
        if not sys.executable:  # an embedded interpreter: no Python to start
            self._broken = True
            return
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-I", "-c", _HELPER.format(path=str(drawing.__file__))],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
            )  # fmt: skip
        except (OSError, ValueError):
            self._broken = True
            return
        threading.Thread(target=self._write, daemon=True, name="torchfric-painter-in").start()
        self._reader = threading.Thread(
            target=self._read, daemon=True, name="torchfric-painter-out"
        )
        self._reader.start()

    def _write(self) -> None:
        """Requests to the helper's stdin, on a thread: a full pipe never blocks the run."""
        assert self._proc is not None and self._proc.stdin is not None
        stdin = self._proc.stdin
        while (frame := self._outbox.get()) is not None:
            try:
                stdin.write(frame)
                stdin.flush()
            except (OSError, ValueError):  # the helper is gone: `png` draws what is missing
                break
        try:
            stdin.close()
        except (OSError, ValueError):
            pass

    def _read(self) -> None:
        """Answers from the helper's stdout as they come; at its end every figure still
        waited for is released (`png` draws it here)."""
        assert self._proc is not None and self._proc.stdout is not None
        stdout = self._proc.stdout
        while (head := read_exact(stdout, ANSWER.size)) is not None:
            fid, status, size = ANSWER.unpack(head)
            payload = read_exact(stdout, size)
            if payload is None:
                break
            self._done[fid] = payload if status == 0 else None
            if (event := self._arrived.get(fid)) is not None:
                event.set()
        self._broken = True
        for event in list(self._arrived.values()):
            event.set()
        stdout.close()  # the helper has ended

    def submit(self, kind: str, spec: Mapping[str, Any]) -> int:
        """Queue the figure `spec` of `kind`; its id for `png`. Returns at once."""
        self.start()
        fid = next(self._ids)
        self._specs[fid] = (kind, spec)
        self._arrived[fid] = event = threading.Event()
        if self._broken:
            event.set()
        else:
            payload = pickle.dumps((fid, kind, dict(spec)), protocol=pickle.HIGHEST_PROTOCOL)
            self._outbox.put(HEAD.pack(len(payload)) + payload)
        return fid

    def ready(self, fid: int) -> bool:
        """Whether `png` of figure `fid` returns without waiting for the helper."""
        return self._arrived[fid].is_set()

    def png(self, fid: int) -> bytes:
        """The PNG of figure `fid` (once: its data is then let go), waiting for the helper;
        drawn here when the helper cannot deliver it."""
        self._arrived[fid].wait()
        del self._arrived[fid]
        kind, spec = self._specs.pop(fid)
        png = self._done.pop(fid, None)
        return png if png is not None else render(kind, spec)

    def close(self) -> None:
        """Let the helper end (it finishes the figures asked for, then sees its input close);
        returns at once. A figure not yet collected is drawn here if asked for."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        self._outbox.put(None)
        assert self._reader is not None
        _ENDING.append((proc, self._reader))


_ENDING: list[tuple[subprocess.Popen[bytes], threading.Thread]] = []  # told to end
_SHARED: Painter | None = None


def shared_painter() -> Painter:
    """This process's painter, started at the first call and kept for the runs after it (a
    sweep's worker, a notebook, a test session start one helper, not one per run); a new
    one when the last has failed."""
    global _SHARED
    if _SHARED is None or (_SHARED._broken and painting()) or _SHARED._pid != os.getpid():
        if _SHARED is not None and _SHARED._pid == os.getpid():
            _SHARED.close()
        _SHARED = Painter()
        _SHARED.start()
    return _SHARED


@atexit.register
def _reap() -> None:
    """At exit: tell the helpers to end and wait for them (a helper ends within milliseconds
    of its input closing: it leaves without the interpreter's teardown)."""
    if _SHARED is not None and _SHARED._pid == os.getpid():
        _SHARED.close()
    for proc, reader in _ENDING:
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
        reader.join(timeout=1)
