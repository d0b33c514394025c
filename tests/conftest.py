from __future__ import annotations

import os
import pathlib

import numpy as np
import pytest
import torch

torch.set_default_dtype(torch.float64)
torch.set_num_threads(1)  # tiny tensors: threads only add overhead (see torchfric.app.cli.main)

SHARED_DATA = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)
    np.random.seed(0)


@pytest.fixture
def shared_data() -> pathlib.Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data sets not found at {SHARED_DATA} (they live beside the project)")
    return SHARED_DATA


@pytest.fixture
def native_cache(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> pathlib.Path:
    """A compiled-code cache of the test's own (``TORCHFRIC_CACHE``), the native path on, and
    nothing loaded, warned about or made private yet: what a fresh process sees."""
    from torchfric.accel import native

    monkeypatch.setenv("TORCHFRIC_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("TORCHFRIC_NATIVE", raising=False)
    monkeypatch.setattr(native.cache, "_LOADED", {})
    monkeypatch.setattr(native.cache, "_WARNED", set())
    monkeypatch.setattr(native.cache, "_PRIVATE", None)
    return tmp_path / "cache"


@pytest.fixture(scope="session")
def worker_cache_dir(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    """One compiled-code cache folder for the whole session, shared by the xdist workers (each
    model's C is built once, whichever worker needs it first; the cache is safe for concurrent
    builders, tests/test_native_cache.py): `worker_cache` sets it for a test; subprocesses take
    it by path."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the session's folder, above each worker's own
    folder = root / "native_cache"
    folder.mkdir(mode=0o700, exist_ok=True)
    return folder


@pytest.fixture
def worker_cache(worker_cache_dir: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> pathlib.Path:
    """A compiled-code cache (``TORCHFRIC_CACHE``) for the test worker's whole session, the
    native path on: each model's C is traced and built once per worker, not once per test
    (about 3 s a library). Tests of the cache itself take `native_cache`."""
    monkeypatch.setenv("TORCHFRIC_CACHE", str(worker_cache_dir))
    monkeypatch.delenv("TORCHFRIC_NATIVE", raising=False)
    return worker_cache_dir
