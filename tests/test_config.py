"""Run configuration: defaults, TOML loading, path rules, --set overrides, errors, round trip."""

from __future__ import annotations

import dataclasses
import os
import pathlib

import pytest

from torchfric.app.config import (
    Config,
    DataConfig,
    EstimatorConfig,
    ModelConfig,
    SimulationConfig,
    to_toml,
)
from torchfric.errors import TorchfricError
from torchfric.estimators.identify import EKFTuning
from torchfric.models.friction import FRICTIONS


def write(folder: pathlib.Path, text: str, name: str = "run.toml") -> pathlib.Path:
    path = folder / name
    folder.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def touch(path: pathlib.Path) -> pathlib.Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("t,u,q\n", encoding="utf-8")
    return path


# -- defaults and the keys DESIGN.md names ---------------------------------------------------


def test_defaults() -> None:
    c = Config()
    assert (c.name, c.seed, c.out_dir) == ("run", 0, "runs")
    assert c.data == DataConfig(
        train=("rig:identification",),
        validation=("rig:validation",),
        test=(),
        columns={},
        time_step=None,
        velocity="highpass",
        velocity_cutoff_hz=None,
        position_unit="rad",
        start=0,
        stop=None,
    )
    m = c.model
    assert (m.friction, m.size, m.c_m, m.inertia, m.viscous) == ("tanh", 3, 16.0, 0.03, 0.01)
    assert (m.offset, m.gravity, m.velocity_scale, m.torque_scale) == (None,) * 4
    assert (m.estimate_c_m, m.log_positive, m.init) == (False, True, "prefit")
    assert m.saturation == 3.0  # tanh weights bounded below by 3 / v95 (issue 31)
    e = c.estimator
    # up to 30 passes, stopping after one that raises the log-likelihood by < 0.5 nat per
    # parameter (issue 31)
    assert (e.method, e.passes, e.tolerance) == ("ekf", 30, 0.5)
    assert (e.units, e.p0_relative, e.rollback) == ("relative", False, True)
    assert (e.p0_state, e.p0_theta, e.q_state, e.q_theta) == ((0.0, 0.0), 1.0, (0.0, 1e-3), 0.0)
    assert (e.r, e.measure, e.substeps, e.theta_bound) == ((1e-3, 1e-2), "both", 1, 1e6)
    assert (e.epochs, e.lr, e.window, e.batch) == (200, 0.01, 200, 64)  # = OETuning defaults
    assert (e.ensemble, e.ensemble_q_scales, e.ensemble_r_scales) == (1, (0.1, 1, 10), (0.1, 1, 10))
    assert c.simulation == SimulationConfig(method="rk4", substeps="auto")
    assert Config.loads("") == c


def test_design_keys_exist() -> None:
    d = Config().to_dict()
    for dotted in [
        "name",
        "seed",
        "data.train",
        "data.validation",
        "model.friction",
        "model.size",
        "model.c_m",
        "model.inertia",
        "model.viscous",
        "model.init",
        "estimator.method",
        "estimator.passes",
        "estimator.tolerance",
    ]:
        table = d
        *sections, key = dotted.split(".")
        for s in sections:
            table = table[s]
        assert key in table, dotted


def test_every_friction_in_the_registry_is_accepted() -> None:
    for kind in FRICTIONS:
        assert Config.loads(f'[model]\nfriction = "{kind}"').model.friction == kind


def test_ekf_tuning_matches() -> None:
    e = Config.loads(
        '[estimator]\npasses = 4\ntolerance = 0\nr = [0.002]\nmeasure = "position"\n'
        "p0_theta = [1, 2]\nq_theta = 1e-9\nsubsteps = 2\ntheta_bound = 50"
    ).estimator
    assert e.ekf_tuning() == EKFTuning(
        p0_state=(0.0, 0.0),
        p0_theta=(1.0, 2.0),
        q_state=(0.0, 1e-3),
        q_theta=1e-9,
        r=(0.002,),
        measure="position",
        passes=4,
        tolerance=0.0,
        substeps=2,
        theta_bound=50.0,
        compile=True,
    )
    # Both carry the paper's defaults, and the same compiled fast path: a config's section is
    # the estimator's own settings object, so the API's defaults are the CLI's.
    assert EstimatorConfig().ekf_tuning() == EKFTuning()
    assert EKFTuning().compile is True


# -- loading and paths -----------------------------------------------------------------------


def test_load_file_resolves_data_paths_against_its_folder(
    tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = tmp_path / "configs"
    a = touch(folder / "data" / "a.csv")
    b = touch(tmp_path / "b.csv")
    ckpt = touch(folder / "first.pt")
    cfg = write(
        folder,
        'name = "exp1"\nseed = 7\n[data]\ntrain = "data/a.csv"\nvalidation = ["../b.csv"]\n'
        '[model]\nfriction = "polytopic"\nc_m = 2.5\nsize = 5\noffset = -3\ninit = "first.pt"\n',
    )
    monkeypatch.chdir(tmp_path.parent)  # the working directory must not matter
    c = Config.load(cfg)
    assert c.name == "exp1" and c.seed == 7
    assert c.data.train == (str(a),)
    assert c.data.validation == (str(b),)
    assert c.data.test == ()
    assert c.model.init == str(ckpt)
    assert c.model.offset == -3.0 and isinstance(c.model.offset, float)
    assert all(os.path.isabs(p) for p in c.data.train + c.data.validation[:1])


def test_set_paths_are_relative_to_the_working_directory(
    tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = tmp_path / "configs"
    work = tmp_path / "work"
    a = touch(work / "x.csv")
    b = touch(work / "sub" / "y.csv")
    ckpt = touch(work / "warm.pt")
    cfg = write(folder, '[data]\ntrain = "nowhere.csv"\n')
    monkeypatch.chdir(work)
    c = Config.load(
        cfg,
        [
            "data.train=x.csv",
            'data.validation=["sub/y.csv"]',
            "model.init=warm.pt",
            "model.c_m=16",
        ],
    )
    assert c.data.train == (str(a),)
    assert c.data.validation == (str(b),)
    assert c.model.init == str(ckpt)


def test_set_values_are_parsed(tmp_path: pathlib.Path) -> None:
    cfg = write(tmp_path, "")
    c = Config.load(
        cfg,
        [
            "estimator.passes=20",
            "estimator.tolerance=1e-6",
            "estimator.r=[0.001]",
            "estimator.measure=position",
            "model.friction=polytopic",
            "model.log_positive=false",
            "model.c_m=2",  # int accepted for a float
            "name=2024",  # a string field keeps the text
            'out_dir="my runs"',
            "data.columns.q=qm",
            'data.columns={u = "vir"}',
            "simulation.substeps=8",
        ],
    )
    assert c.estimator.passes == 20 and isinstance(c.estimator.passes, int)
    assert c.estimator.tolerance == 1e-6
    assert c.estimator.r == (0.001,)
    assert c.model.friction == "polytopic"
    assert c.model.log_positive is False
    assert c.model.c_m == 2.0 and isinstance(c.model.c_m, float)
    assert c.name == "2024" and c.out_dir == "my runs"
    assert c.data.columns == {"u": "vir"}  # the later --set replaces the whole table
    assert c.simulation.substeps == 8
    assert Config.loads("", ["data.columns.q=qm"]).data.columns == {"q": "qm"}


def test_with_overrides() -> None:
    c = Config().with_overrides(["estimator.passes=3"])
    assert c.estimator.passes == 3 and c.model == Config().model


def test_to_toml_round_trip(tmp_path: pathlib.Path) -> None:
    touch(tmp_path / "a.csv")
    c = Config.loads(
        'name = "rt"\nseed = 3\n[data]\ntrain = ["a.csv", "rig:identification"]\n'
        'columns = { u = "vir", q = "weird \\"name\\"" }\ntime_step = 0.001\nstop = 500\n'
        'velocity = "zero_phase"\nvelocity_cutoff_hz = 40\n[model]\nfriction = "stribeck"\nc_m = 3\n'
        "offset = 0.25\ngravity = 0.5\nestimate_c_m = true\nvelocity_scale = 3.0\n"
        "[estimator]\np0_theta = [1.0, 0.5]\nq_theta = 1e-12\ntheta_bound = 1e300\n"
        '[simulation]\nmethod = "euler"\nsubsteps = 16\n',
        base_dir=tmp_path,
    )
    text = c.to_toml()
    assert "None" not in text and "time_step = 0.001" in text
    path = tmp_path / "resolved.toml"
    path.write_text(text, encoding="utf-8")
    assert Config.load(path) == c
    assert Config.loads(Config().to_toml()) == Config()
    assert Config.from_dict(c.to_dict()) == c


def test_toml_writer_escapes() -> None:
    import tomllib

    d = {"a": 'q"\\\n\t\x01\x7fé', "b": [1, 2.5, True], "t": {"x y": {"z": 1}, "n": None}}
    assert tomllib.loads(to_toml(d)) == {"a": d["a"], "b": d["b"], "t": {"x y": {"z": 1}}}


def test_sections_validate_on_construction() -> None:
    with pytest.raises(TorchfricError, match=r"model\.inertia = -1\.0 is out of range"):
        ModelConfig(inertia=-1.0)
    with pytest.raises(TorchfricError, match="Config.model must be a ModelConfig"):
        Config(model={"size": 3})  # type: ignore[arg-type]
    assert dataclasses.replace(Config(), seed=5).seed == 5


# -- errors --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "overrides", "match"),
    [
        (
            "[estimator]\npases = 3",
            [],
            r'unknown key "estimator\.pases" \(did you mean "estimator\.passes"\?\); allowed '
            r"keys in \[estimator\]: method, passes",
        ),
        ("[optimizer]\nlr = 1", [], r"unknown section \[optimizer\]; allowed sections: \[data\]"),
        ('nme = "x"', [], r'unknown key "nme" \(did you mean "name"\?\)'),
        ("", ["estimator.pases=3"], r'unknown key "estimator\.pases" \(did you mean'),
        ("", ["optimizer.lr=1"], r"unknown section \[optimizer\]"),
        ("", ["data=3"], r"\[data\] is a section; set one of its keys"),
        ("data = 3", [], r"data = 3 must be a table"),
        ('[model]\nsize = "3"', [], r'model\.size = "3" is a string, expected "auto" or an int'),
        ("[model]\nsize = 3.0", [], r'model\.size = 3\.0 is a float, expected "auto" or an int'),
        ("[estimator]\npasses = true", [], r"estimator\.passes = true is a boolean, expected an"),
        ("", ["estimator.passes=true"], r"estimator\.passes = true is a boolean"),
        ("[model]\ninertia = true", [], r"model\.inertia = true is a boolean, expected a number"),
        ('[model]\nlog_positive = "yes"', [], r"model\.log_positive = \"yes\" is a string"),
        ("[data]\ntrain = 5", [], r"data\.train = 5 is an integer, expected a path string"),
        (
            "[estimator]\npasses = 0",
            [],
            r"estimator\.passes = 0 is out of range; allowed: an "
            r"integer >= 1 \(the default is 30\)",
        ),
        ("[estimator]\ntolerance = -1", [], r"estimator\.tolerance = -1\.0 is out of range"),
        (
            '[estimator]\nunits = "si"',
            [],
            r'estimator\.units = "si" is not allowed; choose one of "relative", "absolute"',
        ),
        ("[model]\nsaturation = -1", [], r"model\.saturation = -1\.0 is out of range; allowed: a"),
        ("[model]\nsize = 0", [], r"model\.size = 0 is out of range"),
        (
            '[model]\ndynamic = "dahl"',
            [],
            r'model\.dynamic = "dahl" is not allowed; choose one of "none", "lugre"',
        ),
        (
            "[model]\ndynamic = true",
            [],
            r'model\.dynamic = true is a boolean, expected one of "none", "lugre"',
        ),
        ("", ["model.dynamic=lugre", "model.sigma0=0"], r"model\.sigma0 = 0\.0 is out of range"),
        ("", ["model.sigma1=-1"], r"model\.sigma1 = -1\.0 is out of range"),
        ("", ["model.stick_velocity=0"], r"model\.stick_velocity = 0\.0 is out of range"),
        ("[model]\nc_m = 0", [], r"model\.c_m = 0\.0 is out of range; allowed: a number > 0"),
        ("[model]\ninertia = -0.1", [], r"model\.inertia = -0\.1 is out of range"),
        ("[model]\nviscous = -0.1", [], r"model\.viscous = -0\.1 is out of range"),
        ("[model]\nviscous = 0", [], r"model\.viscous = 0\.0 cannot be estimated with model\."),
        ("[model]\ninertia = inf", [], r"model\.inertia = inf is out of range; allowed: a finite"),
        ("[estimator]\nq_state = [0, -1]", [], r"estimator\.q_state = \[0, -1\] is out of range"),
        ("[estimator]\np0_theta = -1", [], r"estimator\.p0_theta = -1\.0 is out of range"),
        ("[estimator]\np0_state = [0]", [], r"allowed: exactly 2 numbers"),
        ("[estimator]\nr = [0.0, 0.01]", [], r"estimator\.r = \[0\.0, 0\.01\] is out of range"),
        (
            '[estimator]\nmeasure = "position"',
            [],
            r"estimator\.r = \[0\.001, 0\.01\] has 2 value\(s\) but estimator\.measure = "
            r'"position" measures 1 channel\(s\); give 1, e\.g\. estimator\.r = \[0\.001\]',
        ),
        ("", ["estimator.r=[0.01]"], r'measure = "both" measures 2 channel\(s\); give 2'),
        (
            '[model]\nfriction = "tahn"',
            [],
            r'model\.friction = "tahn" is not allowed; choose one of "tanh", "polytopic", '
            r'"coulomb", "stribeck" \(did you mean "tanh"\?\)',
        ),
        (
            "",
            ["estimator.method=kalman"],
            r'estimator\.method = "kalman" is not allowed; choose '
            r'one of "ekf", "output_error"',
        ),
        ('[data]\nvelocity = "diff"', [], r'data\.velocity = "diff" is not allowed'),
        ('[data]\nposition_unit = "inch"', [], r'data\.position_unit = "inch" is not allowed'),
        ('[simulation]\nmethod = "dopri5"', [], r'simulation\.method = "dopri5" is not allowed'),
        ('[simulation]\nsubsteps = "x"', [], r'expected "auto" or an integer >= 1'),
        (
            '[log]\nfigure_every = "often"',
            [],
            r'log\.figure_every = "often" is a string, expected "auto" or an integer >= 0',
        ),
        (
            "[log]\nfigure_every = -1",
            [],
            r"log\.figure_every = -1 is out of range; allowed: an integer >= 0",
        ),
        (
            "",
            ["log.figure_evry=2"],
            r'unknown key "log\.figure_evry" \(did you mean "log\.figure_every"\?\)',
        ),
        (
            '[model]\nfriction = "polytopic"\nsize = 4',
            [],
            r'model\.size = 4 is not allowed for model\.friction = "polytopic": it needs an odd '
            r"number of local models \(1, 3, 5, \.\.\.\); use 3 or 5",
        ),
        ("", ["model.friction=polytopic", "model.size=2"], r"model\.size = 2 is not allowed"),
        ("", ["estimator.passes"], r"--set 'estimator\.passes': expected KEY=VALUE with a dotted"),
        (
            '[data]\ntrain = "rig:identificaton"',
            [],
            r'data\.train\[0\] = "rig:identificaton" is not a rig experiment \(did you mean '
            r'"rig:identification"\?\); choose one of rig:identification, rig:validation',
        ),
        ("[data]\ntrain = []", [], r"data\.train = \[\] is out of range; allowed: at least one"),
        ('[data]\ncolumns = { x = "y" }', [], r'unknown key "data\.columns\.x"'),
        ("", ["data.columns.z=3"], r'unknown key "data\.columns\.z"'),
        ("[data]\nstart = 5\nstop = 5", [], r"data\.stop = 5 is out of range; allowed: an integer"),
        ('name = "../x"', [], r'name = "\.\./x" is not a usable run name'),
        ("seed = -1", [], r"seed = -1 is out of range"),
        ("[model\n", [], r"<config>: invalid TOML"),
    ],
)
def test_errors(text: str, overrides: list[str], match: str) -> None:
    with pytest.raises(TorchfricError, match=match) as info:
        Config.loads(text, overrides)
    assert "\n" not in str(info.value)


def test_missing_files_are_errors(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    cfg = write(tmp_path, '[model]\ninit = "missing.pt"\n')
    with pytest.raises(TorchfricError, match=r'model\.init = ".*missing\.pt": no such checkpoint'):
        Config.load(cfg)
    with pytest.raises(TorchfricError, match=r"model\.init = .*gone\.pt.*no such checkpoint"):
        Config.loads("", ["model.init=gone.pt"])
    with pytest.raises(TorchfricError, match=r'data\.validation\[1\] = ".*b\.csv": no such file'):
        Config.loads('[data]\nvalidation = ["rig:validation", "b.csv"]')
    with pytest.raises(TorchfricError, match=r"config file .*nope\.toml' not found"):
        Config.load(tmp_path / "nope.toml")
    # check_files=False (e.g. reading the config stored in a checkpoint on another machine)
    c = Config.loads('[data]\ntrain = "b.csv"\n[model]\nc_m = 1', check_files=False)
    assert c.data.train == (str(tmp_path / "b.csv"),)


@pytest.mark.parametrize(
    "path",
    sorted(
        (pathlib.Path(__file__).resolve().parents[1] / "experiments" / "configs").glob("*.toml")
    ),
    ids=lambda p: p.stem,
)
def test_every_shipped_config_loads(path: pathlib.Path) -> None:
    """The configs in experiments/configs validate (the real-data ones name their files, which
    are only checked when loaded). The paper's reference EKF configs run its single filter (the
    LuGre one goes beyond the paper and keeps the default ensemble)."""
    cfg = Config.load(path)
    if path.stem.endswith("_ekf") and cfg.model.dynamic == "none":
        assert cfg.estimator.ensemble == 0, "reference EKF configs pin the paper's single filter"
    if path.stem.endswith("_defaults"):  # issue 9: "defaults need no tuning"
        assert cfg.estimator == EstimatorConfig()


def test_saturation_auto_is_six_for_a_static_model_and_three_for_lugre() -> None:
    """``model.saturation = "auto"`` (what init writes): each tanh neuron's input weight floor
    is 6 / v95 for a static model and 3 / v95 for LuGre; numbers stay as given; anything else
    is refused in one line."""
    import torch

    from torchfric.app.run.inputs import config_model, saturation_floor
    from torchfric.data import make_experiment

    t = torch.arange(200, dtype=torch.float64) * 1e-3
    exp = make_experiment(t, torch.zeros(200), 0.5 * t**2, t.clone())  # q̇ = t: v95 = 0.189
    v95 = float(torch.quantile(exp.qdot.abs(), 0.95))
    for dynamic, floor in (("none", 6.0), ("lugre", 3.0)):
        cfg = Config(model=ModelConfig(saturation="auto", dynamic=dynamic))
        model = config_model(cfg, [exp])
        assert model.friction.min_slope * v95 == pytest.approx(floor, rel=1e-12)
    assert saturation_floor("auto", "auto") == 3.0 and saturation_floor(4, "none") == 4.0
    assert Config(model=ModelConfig(saturation=4)).model.saturation == 4.0
    for bad, says in (("six", '"auto" or a number >= 0'), (-1.0, "a number >= 0")):
        with pytest.raises(TorchfricError, match=f"model.saturation = .*{says}") as err:
            Config(model=ModelConfig(saturation=bad))
        assert "\n" not in str(err.value)
