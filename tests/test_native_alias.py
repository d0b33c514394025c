"""Aliases of the native code: a later process finds a step's library by the step's structural
key, without tracing the step, and only when everything its code depends on is the same.

Each test has a cache of its own (``TORCHFRIC_CACHE`` under `tmp_path`) and starts with nothing
loaded, as a fresh process would.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from torchfric import ArmModel, OddTanhFriction
from torchfric.accel import native, structure_key
from torchfric.accel.native import make_native_chunk

pytestmark = pytest.mark.skipif(native.compiler() is None, reason="no C compiler here")


def _fn(x, c):  # type: ignore[no-untyped-def]
    return (torch.tanh(x) + c,), ()


def _other(x, c):  # type: ignore[no-untyped-def]
    return (torch.sin(x) + c,), ()


def _args(n: int = 3, c: float = 0.25):  # type: ignore[no-untyped-def]
    return (torch.ones(n, dtype=torch.float64),), (), torch.ones(4, dtype=torch.bool), (
        torch.tensor(c, dtype=torch.float64),
    )


def _eager(fn, n: int = 3, c: float = 0.25) -> torch.Tensor:  # type: ignore[no-untyped-def]
    x = torch.ones(n, dtype=torch.float64)
    for _ in range(4):
        (x,), _ = fn(x, torch.tensor(c, dtype=torch.float64))
    return x


@pytest.fixture(autouse=True)
def cache(native_cache) -> Path:  # type: ignore[no-untyped-def]
    return native_cache


@pytest.fixture
def traces(monkeypatch) -> list[str]:  # type: ignore[no-untyped-def]
    """The names of the functions traced from now on (each a generated source)."""
    seen: list[str] = []
    real = native._source

    def counting(fn, *args, **kwargs):  # type: ignore[no-untyped-def]
        seen.append(fn.__name__)
        return real(fn, *args, **kwargs)

    monkeypatch.setattr(native, "_source", counting)
    return seen


def _fresh_process(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setattr(native.cache, "_LOADED", {})


def test_a_later_process_loads_the_library_without_tracing(cache, traces, monkeypatch):
    (x,), _ = make_native_chunk(_fn, key="tanh step")(*_args())
    assert traces == ["_fn"]
    (record,) = cache.glob("alias_*.json")
    rec = json.loads(record.read_text())
    assert (cache / f"step_{rec['library']}.so").is_file()
    assert record.stat().st_mode & 0o077 == 0  # the user's alone, like the libraries
    _fresh_process(monkeypatch)
    (y,), _ = make_native_chunk(_fn, key="tanh step")(*_args())
    assert traces == ["_fn"]  # not traced again
    assert torch.equal(x, y)
    torch.testing.assert_close(y, _eager(_fn), rtol=1e-15, atol=0)


def test_without_a_key_the_step_is_traced_in_every_process(traces, monkeypatch):
    make_native_chunk(_fn)(*_args())
    _fresh_process(monkeypatch)
    make_native_chunk(_fn)(*_args())
    assert traces == ["_fn", "_fn"]


def test_another_key_shape_or_constant_structure_gets_code_of_its_own(traces, monkeypatch):
    make_native_chunk(_fn, key="one")(*_args())
    _fresh_process(monkeypatch)
    # another function under another key: its own code, not the first one's
    (x,), _ = make_native_chunk(_other, key="two")(*_args())
    torch.testing.assert_close(x, _eager(_other), rtol=1e-15, atol=0)
    # the same key with another input shape, or a constant that is now exactly 1 (compiled
    # in as a constant): traced again
    (x,), _ = make_native_chunk(_fn, key="one")(*_args(n=5))
    torch.testing.assert_close(x, _eager(_fn, n=5), rtol=1e-15, atol=0)
    (x,), _ = make_native_chunk(_fn, key="one")(*_args(c=1.0))
    torch.testing.assert_close(x, _eager(_fn, c=1.0), rtol=1e-15, atol=0)
    assert len(traces) == 4


def test_a_garbled_record_is_replaced(cache, traces, monkeypatch):
    make_native_chunk(_fn, key="tanh step")(*_args())
    (record,) = cache.glob("alias_*.json")
    good = record.read_text()
    for junk in ("not json", '{"format": 1}', good.replace('"lanes": 1', '"lanes": 3')):
        record.write_text(junk)
        _fresh_process(monkeypatch)
        (x,), _ = make_native_chunk(_fn, key="tanh step")(*_args())
        torch.testing.assert_close(x, _eager(_fn), rtol=1e-15, atol=0)
        assert json.loads(record.read_text()) == json.loads(good)  # rebuilt and recorded again
    assert len(traces) == 4


def test_a_record_whose_library_fails_verification_costs_a_rebuild(cache, traces, monkeypatch):
    make_native_chunk(_fn, key="tanh step")(*_args())
    (lib,) = cache.glob("step_*.so")
    # not what its digest record says; a new file (writing into the one this process has
    # mapped would change the code it runs)
    garbled = lib.with_suffix(".tmp")
    garbled.write_bytes(lib.read_bytes()[:-64] + b"\0" * 64)
    garbled.chmod(0o700)
    os.replace(garbled, lib)
    _fresh_process(monkeypatch)
    (x,), _ = make_native_chunk(_fn, key="tanh step")(*_args())
    torch.testing.assert_close(x, _eager(_fn), rtol=1e-15, atol=0)
    assert len(traces) == 2


def test_no_record_is_read_from_a_folder_others_can_write(cache, traces, monkeypatch):
    make_native_chunk(_fn, key="tanh step")(*_args())
    cache.chmod(0o777)
    try:
        _fresh_process(monkeypatch)
        with pytest.warns(native.NativeCacheWarning, match="writable by group and others"):
            (x,), _ = make_native_chunk(_fn, key="tanh step")(*_args())
    finally:
        cache.chmod(0o700)
    torch.testing.assert_close(x, _eager(_fn), rtol=1e-15, atol=0)
    assert len(traces) == 2


def _tanh(size: int = 3, c_m: float = 16.0) -> ArmModel:
    return ArmModel(OddTanhFriction(size), inertia=0.03, viscous=0.01, c_m=c_m)


def test_structure_key_names_the_code_not_the_values(monkeypatch):
    base = structure_key(_tanh())
    other = _tanh()
    other.set_theta(other.get_theta() * 1.5)
    assert structure_key(other) == base  # θ is an input of the code
    assert structure_key(_tanh(4)) != base
    assert structure_key(_tanh(c_m=17.0)) != base  # a fixed c_m is compiled in
    # a method replaced at run time is other code
    monkeypatch.setattr(OddTanhFriction, "forward", lambda self, v: 2 * v)
    assert structure_key(_tanh()) != base


def test_structure_key_follows_a_users_own_friction_source(tmp_path):
    """A friction class defined outside torchfric: its file is part of the key."""
    module = tmp_path / "my_friction.py"
    script = textwrap.dedent(
        """
        import sys
        sys.path.insert(0, sys.argv[1])
        from my_friction import Mine
        from torchfric import ArmModel
        from torchfric.accel import structure_key
        print(structure_key(ArmModel(Mine(3), inertia=0.03, viscous=0.01, c_m=16.0)))
        """
    )
    keys = []
    for scale in ("1.0", "2.0"):
        module.write_text(
            "from torchfric import OddTanhFriction\n\n"
            "class Mine(OddTanhFriction):\n"
            f"    SCALE = {scale}  # (a module-level change the methods do not show)\n"
        )
        run = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True,
                             text=True, check=True)  # fmt: skip
        keys.append(run.stdout)
    assert keys[0] != keys[1]


def test_a_warm_process_runs_the_filter_without_tracing(tmp_path):
    """End to end, two fresh processes: the second finds the filter step's library by its alias
    and never loads torch's tracing and compiler stack."""
    script = textwrap.dedent(
        """
        import sys, torch
        from torchfric import ArmModel, OddTanhFriction, make_experiment
        from torchfric.data.rig import rig_experiment
        from torchfric.estimators import EKFTuning, identify_ekf
        d = rig_experiment("identification")
        exp = make_experiment(d["t"][:2000], d["u"][:2000], d["q"][:2000]).with_velocity("highpass")
        model = ArmModel(OddTanhFriction(3), inertia=0.03, viscous=0.01, c_m=16.0)
        res = identify_ekf(model, [exp], EKFTuning(passes=1, compile=True))
        print(repr(float(res.model.inertia)), "torch._inductor" in sys.modules)
        """
    )
    env = {**os.environ, "TORCHFRIC_CACHE": str(tmp_path / "cache")}
    env.pop("TORCHFRIC_NATIVE", None)
    out = [
        subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                       check=True, env=env).stdout.split()  # fmt: skip
        for _ in range(2)
    ]
    assert out[0][1] == "True"  # the first process traced (and built)
    assert out[1] == [out[0][0], "False"]  # the same result, nothing traced


def test_a_record_that_cannot_be_written_leaves_nothing_behind(cache, traces, monkeypatch):
    from torchfric.accel.native import aliases

    def full_disk(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(aliases.json, "dump", full_disk)
    (x,), _ = make_native_chunk(_fn, key="tanh step")(*_args())  # the run goes on
    torch.testing.assert_close(x, _eager(_fn), rtol=1e-15, atol=0)
    assert not list(cache.glob(".alias-*")) and not list(cache.glob("alias_*"))


def test_structure_key_names_the_arms_terms() -> None:
    """Two models with the same curve and θ of the same length but other white-box terms
    (offset + gravity against offset + asymmetric) have different keys, and the compiled rk4
    engine simulates each with its own code: the key once dropped the arm's term names, and a
    library built for one served the other (found by the FMU export's tests: 3 % off in q)."""
    import numpy as np
    import torch

    import torchfric
    from torchfric.accel import structure_key
    from torchfric.models import ArmModel
    from torchfric.models.friction import make_friction

    def arm(**terms: float) -> ArmModel:
        fric = make_friction("tanh", 2, velocity_scale=2.0, torque_scale=0.05)
        return ArmModel(fric, inertia=0.02, viscous=0.01, c_m=1.0, offset=0.004, **terms)

    a, b = arm(gravity=0.3), arm(asymmetric=0.02)
    assert a.num_parameters == b.num_parameters
    assert structure_key(a) != structure_key(b)
    t = torch.arange(300, dtype=torch.float64) * 1e-3
    u = torch.tensor(0.2 * np.sin(2 * np.pi * 2.0 * t.numpy()))
    x0 = torch.tensor([0.3, -0.5], dtype=torch.float64)
    with torch.no_grad():
        for model in (a, b):
            ref = torchfric.simulate(model, t, u, x0)
            got = torchfric.simulate(model, t, u, x0, engine="compiled")
            assert torch.allclose(got, ref, rtol=0, atol=1e-12)
