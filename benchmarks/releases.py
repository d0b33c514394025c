"""What the side-by-side benchmarks share: an earlier commit's files to import beside this tree
(`checkout`), and the best of repeated timed calls (`best`). Imports nothing of torchfric, so a
benchmark's child process can import another release's."""

from __future__ import annotations

import subprocess
import tarfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def checkout(ref: str, folder: Path) -> Path:
    """The files of commit `ref` (``git archive``) under `folder`; its torchfric importable from
    the returned folder (put it first on ``PYTHONPATH``)."""
    archive = folder / "release.tar"
    with archive.open("wb") as out:
        subprocess.run(["git", "-C", str(ROOT), "archive", ref], stdout=out, check=True)
    tree = folder / ref
    with tarfile.open(archive) as tar:
        tar.extractall(tree, filter="data")
    return tree


def best(fn: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    """The fastest of `repeat` calls of `fn` after one warm-up call (seconds), and the last
    call's result."""
    result = fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return min(times), result
