"""Checkpoints: round trip, weights_only loading, refusal of unsafe/corrupt files, atomicity."""

from __future__ import annotations

import os
import pathlib
import pickle

import numpy as np
import pytest
import torch

from torchfric.app.artifacts import checkpoint as ck
from torchfric.app.artifacts.checkpoint import (
    FORMAT,
    FORMAT_VERSION,
    build_checkpoint,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
    sha256_file,
)
from torchfric.app.config import Config
from torchfric.errors import TorchfricError
from torchfric.models.arm import ArmModel
from torchfric.models.friction import OddTanhFriction, PolytopicFriction


def tanh_arm() -> ArmModel:
    friction = OddTanhFriction(3, w1=[0.7, 2.5, 9.0], w2=[0.05, -0.02, 0.11])
    return ArmModel(friction, inertia=0.0292, viscous=0.013, c_m=16.0, offset=-0.03)


def polytopic_arm() -> ArmModel:
    friction = PolytopicFriction(3)
    return ArmModel(friction, inertia=0.05, viscous=None, c_m=16.0, offset=0.2, gravity=0.4)


def perturbed(model: ArmModel) -> ArmModel:
    """θ off the constructor's values, as after estimation (so that a load cannot just re-init)."""
    gen = torch.Generator().manual_seed(1)
    theta = model.get_theta()
    return model.set_theta(theta + 0.1 * torch.randn(theta.shape, generator=gen))


def payload(model: ArmModel, **changes: object) -> dict:
    p = build_checkpoint(
        model,
        config=Config(),
        estimator_state={
            "P_theta": torch.eye(model.num_parameters),
            "pass_index": 3,
            "history": [{"index": 1, "theta": [0.1, 0.2], "nis": 1.9}],
        },
        metrics={
            "inertia": float(model.inertia.detach()),
            "validation": {"rig:validation": {"fit_q": 97.1}},
        },
        data_fingerprints={"rig:identification": "ab" * 32},
        name="arm",
        complete=True,
    )
    p.update(changes)
    return p


@pytest.mark.parametrize("make", [tanh_arm, polytopic_arm])
def test_round_trip(tmp_path: pathlib.Path, make) -> None:
    model = perturbed(make())
    path = tmp_path / "checkpoints" / "arm.pt"  # parent folders are created
    save_checkpoint(path, payload(model))
    loaded = load_checkpoint(path)
    assert torch.equal(loaded.get_theta(), model.get_theta())  # exact, not approximately
    assert loaded.theta_names == model.theta_names
    assert loaded.physical_parameters() == model.physical_parameters()
    x = torch.randn(50, 2) * torch.tensor([1.0, 8.0])
    u = torch.randn(50)
    torch.testing.assert_close(loaded.vector_field(x, u), model.vector_field(x, u), rtol=0, atol=0)
    v = torch.linspace(-10, 10, 41)
    with torch.no_grad():
        torch.testing.assert_close(
            loaded.friction_torque(v), model.friction_torque(v), rtol=0, atol=0
        )


def test_file_is_self_describing_and_loads_with_weights_only(tmp_path: pathlib.Path) -> None:
    model = perturbed(tanh_arm())
    path = tmp_path / "arm.pt"
    save_checkpoint(path, payload(model))
    raw = torch.load(path, weights_only=True)  # plain torch, no torchfric involved
    assert raw["format"] == FORMAT and raw["format_version"] == FORMAT_VERSION
    assert isinstance(raw["torchfric_version"], str) and "T" in raw["created"]
    assert raw["name"] == "arm" and raw["complete"] is True
    assert raw["config"] == Config().to_dict()
    assert Config.from_dict(raw["config"]) == Config()
    assert raw["model"]["friction"]["kind"] == "tanh" and raw["model"]["friction"]["size"] == 3
    assert raw["theta_names"] == model.theta_names
    assert raw["parameters"] == model.physical_parameters()
    assert raw["parameters"]["inertia"] == pytest.approx(float(model.inertia.detach()), rel=1e-15)
    assert raw["estimator"]["method"] == "ekf"
    assert torch.equal(raw["estimator"]["state"]["P_theta"], torch.eye(model.num_parameters))
    assert raw["estimator"]["state"]["history"][0]["nis"] == 1.9
    assert raw["metrics"]["validation"]["rig:validation"]["fit_q"] == 97.1
    assert raw["data"] == {"rig:identification": "ab" * 32}
    assert read_checkpoint(path).keys() == raw.keys()


def test_sha256_file(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "d.csv"
    path.write_bytes(b"abc")
    assert sha256_file(path) == "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    with pytest.raises(TorchfricError, match="cannot fingerprint"):
        sha256_file(tmp_path / "missing.csv")


def test_numpy_scalars_become_plain_numbers(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "a.pt"
    metrics = {"fit": np.float64(97.5), "n": np.int64(3), "ok": np.bool_(True)}
    save_checkpoint(path, payload(tanh_arm(), metrics=metrics))
    stored = torch.load(path, weights_only=True)["metrics"]
    assert stored == {"fit": 97.5, "n": 3, "ok": True}
    assert [type(v) for v in stored.values()] == [float, int, bool]


# -- refusals --------------------------------------------------------------------------------


class Payload:
    """A class the loader must never instantiate (its unpickling would run code)."""

    def __reduce__(self):
        return (os.system, ("echo pwned > pwned.txt",))


class Plain:
    pass


@pytest.fixture
def good(tmp_path: pathlib.Path) -> pathlib.Path:
    path = tmp_path / "good.pt"
    save_checkpoint(path, payload(tanh_arm()))
    return path


def test_refuses_missing_file(tmp_path: pathlib.Path) -> None:
    with pytest.raises(TorchfricError, match=r"checkpoint '.*nope\.pt' not found"):
        load_checkpoint(tmp_path / "nope.pt")
    with pytest.raises(TorchfricError, match="is a directory"):
        read_checkpoint(tmp_path)


def test_refuses_truncated_file(good: pathlib.Path, tmp_path: pathlib.Path) -> None:
    data = good.read_bytes()
    half = tmp_path / "half.pt"
    half.write_bytes(data[: len(data) // 2])
    with pytest.raises(TorchfricError, match="is truncated or not a torchfric checkpoint"):
        load_checkpoint(half)
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    with pytest.raises(TorchfricError, match="is truncated or not a torchfric checkpoint"):
        load_checkpoint(empty)


def test_refuses_flipped_bytes(good: pathlib.Path, tmp_path: pathlib.Path) -> None:
    # torch.load alone would accept this file and return wrong numbers; the CRC check does not.
    data = bytearray(good.read_bytes())
    theta = torch.load(good, weights_only=True)["theta"].numpy().tobytes()
    i = bytes(data).find(theta)
    assert i > 0
    data[i + 3] ^= 0xFF
    bad = tmp_path / "flipped.pt"
    bad.write_bytes(bytes(data))
    with pytest.raises(TorchfricError, match="fails its CRC check"):
        load_checkpoint(bad)


def test_refuses_random_bytes(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "random.pt"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(TorchfricError, match="is truncated or not a torchfric checkpoint"):
        load_checkpoint(path)
    path.write_bytes(b"PK\x03\x04" + np.random.default_rng(1).bytes(4096))  # zip magic only
    with pytest.raises(TorchfricError, match="is truncated or not a torchfric checkpoint"):
        load_checkpoint(path)


@pytest.mark.parametrize("obj", [Payload(), Plain()])
def test_refuses_arbitrary_python_objects(
    tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch, obj: object
) -> None:
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "evil.pt"
    evil = payload(tanh_arm())
    evil["metrics"] = {"x": obj}
    torch.save(evil, path)  # bypasses save_checkpoint's own refusal
    with pytest.raises(TorchfricError, match="contains arbitrary Python objects.*refuses to unp"):
        load_checkpoint(path)
    assert not (tmp_path / "pwned.txt").exists()  # nothing was executed
    plain_pickle = tmp_path / "evil.pkl"
    plain_pickle.write_bytes(pickle.dumps(obj))
    with pytest.raises(TorchfricError, match="is truncated or not a torchfric checkpoint"):
        load_checkpoint(plain_pickle)
    assert not (tmp_path / "pwned.txt").exists()


def test_refuses_dict_without_format(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "state_dict.pt"
    torch.save(tanh_arm().state_dict(), path)
    with pytest.raises(TorchfricError, match="is not a torchfric checkpoint"):
        load_checkpoint(path)
    torch.save([1, 2], path)
    with pytest.raises(TorchfricError, match=r"is not a torchfric checkpoint \(list"):
        read_checkpoint(path)


def test_refuses_newer_format(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "future.pt"
    save_checkpoint(path, payload(tanh_arm(), format_version=FORMAT_VERSION + 1))
    with pytest.raises(TorchfricError, match="written by a newer torchfric.*upgrade torchfric"):
        load_checkpoint(path)
    save_checkpoint(path, payload(tanh_arm(), format_version="1"))
    with pytest.raises(TorchfricError, match="invalid format_version"):
        load_checkpoint(path)


def test_refuses_non_plain_payload_before_writing(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "x.pt"
    bad = payload(tanh_arm())
    bad["estimator"]["state"]["obj"] = Plain()
    with pytest.raises(
        TorchfricError, match=r"checkpoint\['estimator'\]\['state'\]\['obj'\] is a "
    ):
        save_checkpoint(path, bad)
    with pytest.raises(
        TorchfricError, match="checkpoint\\['metrics'\\]\\['a'\\] is a numpy.ndarray"
    ):
        save_checkpoint(path, payload(tanh_arm(), metrics={"a": np.zeros(3)}))
    with pytest.raises(TorchfricError, match="has a key"):
        save_checkpoint(path, payload(tanh_arm(), metrics={(1, 2): 3.0}))
    assert list(tmp_path.iterdir()) == []


# -- atomicity -------------------------------------------------------------------------------


def test_crash_during_rename_keeps_previous(
    good: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = good.read_bytes()

    def crash(*args: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ck.os, "replace", crash)
    with pytest.raises(TorchfricError, match="cannot write checkpoint.*previous file.*unchanged"):
        save_checkpoint(good, payload(perturbed(tanh_arm())))
    assert good.read_bytes() == before
    assert sorted(p.name for p in good.parent.iterdir()) == ["good.pt"]  # no temp file left
    monkeypatch.undo()
    assert torch.equal(load_checkpoint(good).get_theta(), tanh_arm().get_theta())


def test_crash_during_write_keeps_previous(
    good: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = good.read_bytes()
    real_save = torch.save

    def killed(obj: object, f) -> None:  # half the bytes reach the disk, then the process "dies"
        import io

        buf = io.BytesIO()
        real_save(obj, buf)
        f.write(buf.getvalue()[: len(buf.getvalue()) // 2])
        raise KeyboardInterrupt

    monkeypatch.setattr(ck.torch, "save", killed)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(good, payload(perturbed(tanh_arm())))
    monkeypatch.undo()
    assert good.read_bytes() == before
    assert sorted(p.name for p in good.parent.iterdir()) == ["good.pt"]
    load_checkpoint(good)


def test_save_overwrites_and_refuses_directory(good: pathlib.Path) -> None:
    model = perturbed(tanh_arm())
    save_checkpoint(good, payload(model))
    assert torch.equal(load_checkpoint(good).get_theta(), model.get_theta())
    with pytest.raises(TorchfricError, match="is a directory"):
        save_checkpoint(good.parent, payload(model))


def test_underflowed_positive_parameter_round_trips(tmp_path) -> None:
    """A log-stored parameter driven so low that exp() underflows to 0.0 still loads, exactly."""
    from torchfric import ArmModel, PolytopicFriction
    from torchfric.app.artifacts.checkpoint import (
        build_checkpoint,
        load_checkpoint,
        save_checkpoint,
    )

    arm = ArmModel(PolytopicFriction(3), viscous=0.01, c_m=16.0)
    theta = arm.get_theta()
    theta[arm.theta_names.index("viscous")] = -800.0  # exp(-800) == 0.0 in float64
    theta[arm.theta_names.index("sigma2")] = -760.0
    arm.set_theta(theta)
    assert float(arm.viscous) == 0.0
    payload = build_checkpoint(
        arm,
        config={},
        estimator_state={},
        metrics={},
        data_fingerprints={},
        name="x",
        complete=True,
    )
    save_checkpoint(tmp_path / "x.pt", payload)
    back = load_checkpoint(tmp_path / "x.pt")
    torch.testing.assert_close(back.get_theta(), theta, rtol=0, atol=0)
