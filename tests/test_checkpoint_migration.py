"""Every checkpoint is complete and loadable: older formats and older stored configs are
migrated (`torchfric.app.artifacts.checkpoint.checkpoint_config`, `_FORMAT_MIGRATIONS`) or refused with one
line, and every shipped checkpoint in ``checkpoints/`` loads, builds its config, simulates,
scores and exports (the export simulating as `torchfric.models.simulate` does)."""

from __future__ import annotations

import dataclasses
import math
import pathlib
import warnings

import pytest
import torch

from torchfric.app.artifacts import checkpoint as ck
from torchfric.app.artifacts.checkpoint import (
    FORMAT_VERSION,
    build_checkpoint,
    checkpoint_config,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from torchfric.app.config import Config
from torchfric.data.experiment import Experiment, make_experiment
from torchfric.errors import TorchfricError
from torchfric.estimators.metrics import score_simulation
from torchfric.models.arm import ArmModel
from torchfric.models.friction import OddTanhFriction
from torchfric.models.simulate import simulate
from torchfric.models.torchscript import export_model, save_exported

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHIPPED = sorted((ROOT / "checkpoints").glob("*.pt"))
SHARED_DATA = ROOT.parent / "shared" / "data"
SAMPLES = 2000
RTOL = 1e-6


def small_arm() -> ArmModel:
    friction = OddTanhFriction(3, w1=[0.7, 2.5, 9.0], w2=[0.05, -0.02, 0.11])
    return ArmModel(friction, inertia=0.03, viscous=0.013, c_m=16.0, asymmetric=0.002)


def payload(config: object, **changes: object) -> dict:
    p = build_checkpoint(
        small_arm(),
        config=config,
        estimator_state={},
        metrics={"dt": 1e-3},
        data_fingerprints={},
        name="old",
        complete=True,
    )
    p.update(changes)
    return p


# --------------------------------------------------------------------------- stored configs
def old_output_error_config() -> dict:
    """What earlier versions stored for an output-error run: their ensemble defaults
    (0 starts, Q and R scales [1.0]) that the current schema accepts only for the EKF."""
    cfg = Config.from_dict({"estimator": {"method": "output_error"}}).to_dict()
    cfg["estimator"].update(
        ensemble=0, ensemble_spread=3.0, ensemble_q_scales=[1.0], ensemble_r_scales=[1.0]
    )
    return cfg


def test_output_error_config_with_old_ensemble_keys_migrates() -> None:
    raw = payload(old_output_error_config())
    cfg = checkpoint_config(raw)
    assert cfg.estimator.method == "output_error"
    assert cfg.estimator.ensemble_q_scales == Config().estimator.ensemble_q_scales
    assert raw["config"]["estimator"]["ensemble_q_scales"] == [1.0]  # the input is not changed


def test_ekf_ensemble_keys_are_kept() -> None:
    stored = Config().to_dict()
    stored["estimator"].update(ensemble=8, ensemble_q_scales=[1.0], ensemble_r_scales=[1.0, 10.0])
    cfg = checkpoint_config(payload(stored))
    assert cfg.estimator.ensemble == 8
    assert cfg.estimator.ensemble_q_scales == (1.0,)
    assert cfg.estimator.ensemble_r_scales == (1.0, 10.0)


def test_keys_the_schema_no_longer_has_are_dropped() -> None:
    stored = Config().to_dict()
    stored["estimator"]["retired_option"] = 3
    stored["retired_top_level"] = "x"
    stored["retired_section"] = {"a": 1}
    stored["simulation"]["substeps"] = 2
    cfg = checkpoint_config(payload(stored))
    assert cfg.simulation.substeps == 2 and cfg == dataclasses.replace(
        Config(), simulation=dataclasses.replace(Config().simulation, substeps=2)
    )


def test_no_config_gives_defaults() -> None:
    raw = payload(Config())
    raw["config"] = {}
    assert checkpoint_config(raw) == Config()
    del raw["config"]
    assert checkpoint_config(raw) == Config()


def test_data_paths_are_not_checked() -> None:
    stored = Config().to_dict()
    stored["data"]["train"] = ["/nonexistent/machine/data.csv"]
    stored["data"]["validation"] = []
    cfg = checkpoint_config(payload(stored))
    assert cfg.data.train == ("/nonexistent/machine/data.csv",)


def test_invalid_stored_config_is_one_line() -> None:
    stored = Config().to_dict()
    stored["estimator"]["passes"] = -4
    with pytest.raises(TorchfricError) as err:
        checkpoint_config(payload(stored))
    msg = str(err.value)
    assert "\n" not in msg and "'old'" in msg and "estimator.passes" in msg


def test_migrated_config_of_a_saved_checkpoint(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "old.pt"
    save_checkpoint(path, payload(old_output_error_config()))
    assert checkpoint_config(read_checkpoint(path)).estimator.method == "output_error"


# --------------------------------------------------------------------------- format versions
def test_older_format_without_migration_is_one_line(
    tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "v1.pt"
    save_checkpoint(path, payload(Config()))
    monkeypatch.setattr(ck, "FORMAT_VERSION", FORMAT_VERSION + 1)
    monkeypatch.setattr(ck, "_FORMAT_MIGRATIONS", {})
    with pytest.raises(TorchfricError) as err:
        load_checkpoint(path)
    msg = str(err.value)
    assert "\n" not in msg
    assert f"checkpoint format {FORMAT_VERSION} " in msg  # the version found
    assert f"reads format {FORMAT_VERSION + 1}" in msg  # the version supported
    assert "re-create it with torchfric train" in msg  # the fix


def test_older_format_is_migrated(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "v1.pt"
    model = small_arm()
    save_checkpoint(path, payload(Config()))
    calls = []

    def upgrade(ckpt: dict) -> dict:
        calls.append(ckpt["format_version"])
        return {**ckpt, "new_field": "added"}

    monkeypatch.setattr(ck, "FORMAT_VERSION", FORMAT_VERSION + 1)
    monkeypatch.setattr(ck, "_FORMAT_MIGRATIONS", {FORMAT_VERSION: upgrade})
    raw = read_checkpoint(path)
    assert calls == [FORMAT_VERSION]
    assert raw["format_version"] == FORMAT_VERSION + 1 and raw["new_field"] == "added"
    assert torch.equal(load_checkpoint(path).get_theta(), model.get_theta())


# --------------------------------------------------------------------------- shipped files
def _real_path(stored: str) -> pathlib.Path | None:
    """A stored data path, or the same file under ../shared/data (stored configs may hold
    another machine's absolute paths); None when neither exists."""
    p = pathlib.Path(stored)
    if p.is_file():
        return p
    here = SHARED_DATA / p.parent.name / p.name
    return here if here.is_file() else None


def _experiment(cfg: Config, raw: dict, model: ArmModel) -> Experiment:
    """The first SAMPLES samples of the checkpoint's own validation (else training) data; for a
    real-data file that is not here, a synthetic input at the data's sample time."""
    from torchfric.app.run import load_data

    paths = list(cfg.data.validation) + list(cfg.data.train)
    for p in paths:
        local = p if p.startswith("rig:") else _real_path(p)
        if local is None:
            continue
        data = dataclasses.replace(
            cfg.data,
            train=(str(local),),
            validation=(),
            test=(),
            start=0,
            stop=SAMPLES + cfg.data.input_delay,
        )
        train, _, _, _ = load_data(dataclasses.replace(cfg, data=data))
        return train[0]
    # Synthetic: sines and steps at the data's dt, scaled to the model's own friction level.
    dt = float(raw["metrics"].get("dt", 1e-3))
    t = torch.arange(SAMPLES, dtype=torch.float64) * dt
    span = SAMPLES * dt
    level = float(model.friction_torque(torch.tensor([-1.0, 1.0])).abs().max().detach())
    u = (2.0 * level / float(model.c_m.detach())) * (
        torch.sin(2 * math.pi * 2 * t / span)
        + 0.5 * torch.sign(torch.sin(2 * math.pi * 5 * t / span))
    )
    with torch.no_grad():
        states = simulate(model, t, u, torch.zeros(2, dtype=torch.float64))
    return make_experiment(t, u, states[:, 0], states[:, 1], name="synthetic")


def test_shipped_checkpoints_exist() -> None:
    assert len(SHIPPED) >= 18


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_checkpoint_loads_simulates_scores_and_exports(
    path: pathlib.Path, tmp_path: pathlib.Path
) -> None:
    model = load_checkpoint(path)
    raw = read_checkpoint(path)
    assert raw.get("complete") is True
    cfg = checkpoint_config(raw)
    exp = _experiment(cfg, raw, model)
    method, substeps = cfg.simulation.method, cfg.simulation.substeps
    score = score_simulation(model, exp, method=method, substeps=substeps)
    assert math.isfinite(score.fit_q) and math.isfinite(score.rms_q)
    assert torch.isfinite(score.states).all()

    dt = float(raw["metrics"].get("dt", exp.dt))
    module = export_model(model, dt=dt, substeps=substeps, method=method)
    save_exported(module, tmp_path / "model.ts")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        loaded = torch.jit.load(str(tmp_path / "model.ts"))
    x0 = torch.stack([exp.q[0], exp.qdot[0]])
    q, qd = loaded.simulate(exp.t, exp.u, x0)
    ref = score.states
    for i, out in enumerate((q, qd)):
        scale = float(ref[:, i].abs().max())
        assert float((out - ref[:, i]).abs().max()) <= RTOL * scale, (path.name, i)


def test_format_1_polytopic_keeps_its_gaussian_construction(tmp_path: pathlib.Path) -> None:
    """A polytopic checkpoint of format 1 was trained with the paper's Gaussian validity
    functions: it loads with them (its curve beyond the centres unchanged), not with the affine
    continuation that format 2 models use by default."""
    from torchfric.models.friction import PolytopicFriction

    fr = PolytopicFriction(3, a=[0.01, 0.02], b=[0.2], c=[2.0], sigma=[4.0, 0.5])
    model = ArmModel(fr, inertia=0.03, viscous=None, c_m=16.0)
    p = build_checkpoint(model, config=Config(), estimator_state={}, metrics={"dt": 1e-3},
                         data_fingerprints={}, name="old", complete=True)  # fmt: skip
    assert p["model"]["friction"]["kwargs"]["extrapolation"] == "affine"
    p["format_version"] = 1
    del p["model"]["friction"]["kwargs"]["extrapolation"]
    path = tmp_path / "v1.pt"
    save_checkpoint(path, p)
    old = load_checkpoint(path)
    assert old.friction.init_kwargs()["extrapolation"] == "gaussian"
    v = torch.linspace(-30.0, 30.0, 61, dtype=torch.float64)
    gauss = PolytopicFriction(3, a=[0.01, 0.02], b=[0.2], c=[2.0], sigma=[4.0, 0.5],
                              extrapolation="gaussian")  # fmt: skip
    with torch.no_grad():
        torch.testing.assert_close(old.friction(v), gauss(v), rtol=1e-14, atol=1e-15)
        assert not torch.allclose(model.friction(v), gauss(v))  # the constructions differ
