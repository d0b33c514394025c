"""The generated config reference (docs/config.md) against the schema it documents, and the
error messages' hints against the keys that exist."""

from __future__ import annotations

import ast
import dataclasses
import functools
import math
import pathlib
import re
import subprocess
import sys
from typing import Any

import pytest

import torchfric
from torchfric.app.config import (
    ENSEMBLE_KEYS,
    ESTIMATOR_KEYS,
    ESTIMATORS,
    INIT_KEYWORDS,
    MAX_EPOCHS,
    MAX_PASSES,
    VELOCITY_SOURCES,
    Config,
    reference,
)
from torchfric.app.config.estimator import SELECT_RULES
from torchfric.app.config.toml_io import toml_value
from torchfric.data.rig import EXPERIMENTS
from torchfric.data.units import COLUMN_NAMES, POSITION_UNITS, TIME_UNITS
from torchfric.errors import TorchfricError
from torchfric.estimators.ekf import MEASUREMENTS
from torchfric.estimators.settings import TUNING_UNITS
from torchfric.models.friction import FRICTIONS
from torchfric.models.lugre import DYNAMICS
from torchfric.models.simulate import SOLVERS

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "config.md"


@pytest.fixture(scope="module")
def text() -> str:
    return reference.config_reference()


@pytest.fixture(scope="module")
def entries(text: str) -> dict[str, dict[str, str]]:
    """The page read back: key → {"type", "default", "allowed", "sets", "meaning"}."""
    out: dict[str, dict[str, str]] = {}
    current: dict[str, str] | None = None
    for line in text.splitlines():
        heading = re.fullmatch(r"### `([^`]+)`", line)
        if heading:
            assert heading[1] not in out, f"{heading[1]} documented twice"
            current = out[heading[1]] = {"meaning": ""}
        elif line.startswith("## "):
            current = None
        elif current is not None:
            field = re.fullmatch(r"- (Type|Default|Allowed|Sets): (.*)", line)
            if field:
                current[field[1].lower()] = field[2]
            elif line.strip():
                current["meaning"] += line.strip()
    return out


def _flat(config: Config) -> dict[str, Any]:
    """A config's own tables (`to_dict`) as dotted key → value."""
    out: dict[str, Any] = {}
    for name, value in config.to_dict().items():
        if isinstance(value, dict):
            out |= {f"{name}.{key}": v for key, v in value.items()}
        else:
            out[name] = value
    return out


@functools.cache
def _accepted_keys() -> frozenset[str]:
    """Every key of a config, from a default config's own tables, `ESTIMATOR_KEYS` and the
    column names (not from the generator's enumeration)."""
    keys = set(_flat(Config()))
    keys |= {f"estimator.{key}" for key in ESTIMATOR_KEYS}
    keys |= {f"data.columns.{c}" for c in COLUMN_NAMES}
    return frozenset(keys)


def _first_value(default: str) -> str | None:
    """The TOML value a documented default starts with (None for "unset")."""
    if default.startswith("unset"):
        return None
    match = re.match(r"`([^`]*)`", default)
    assert match, default
    return match[1]


def _choices(allowed: str) -> set[str]:
    return set(re.findall(r'`"([^"`]+)"`', allowed))


# -- every key, documented -------------------------------------------------------------------


def test_every_accepted_key_has_an_entry_with_type_default_and_meaning(entries: dict) -> None:
    assert set(entries) == _accepted_keys()
    for key, entry in entries.items():
        assert entry.get("type"), key
        assert entry.get("default"), key
        assert entry.get("allowed"), key
        assert len(entry["meaning"]) > 10, key


def test_every_documented_key_loads_and_its_default_changes_nothing(entries: dict) -> None:
    """`--set KEY=<documented default>` is accepted by the loader and leaves a default config
    as it was: the documented key exists and the documented value is the default."""
    base = _flat(Config())
    for key, entry in entries.items():
        value = _first_value(entry["default"])
        if value is None:
            continue
        config = Config.loads("", [f"{key}={value}"])
        if key.startswith("data.columns."):
            assert config.data.columns == {key.rpartition(".")[2]: value.strip('"')}
            continue
        assert _flat(config) == base, key


def test_keys_outside_the_reference_are_refused() -> None:
    for key in ("data.rtol", "estimator.members", "model.c", "simulation.solver", "rtol"):
        with pytest.raises(TorchfricError, match="unknown key"):
            Config.loads("", [f"{key}=1"])


def test_a_default_config_values_are_the_documented_defaults(entries: dict) -> None:
    for key, value in _flat(Config()).items():
        documented = _first_value(entries[key]["default"])
        assert documented == (None if value is None else toml_value(value)), key
    for column in COLUMN_NAMES:  # an unmapped column is read under its own name
        assert _first_value(entries[f"data.columns.{column}"]["default"]) == f'"{column}"'


def test_defaults_that_depend_on_the_data_say_so_and_hold(entries: dict) -> None:
    own = Config.from_dict(
        {"data": {"train": ["data.csv"]}, "model": {"c_m": 2.5}}, check_files=False
    )
    assert entries["data.validation"]["default"] == (
        f"`{toml_value(list(Config().data.validation))}` with rig data, "
        f"`{toml_value(list(own.data.validation))}` with your own data"
    )
    assert entries["model.c_m"]["default"].endswith("required with your own data")
    with pytest.raises(TorchfricError, match=r"^model\.c_m is required"):
        Config.from_dict({"data": {"train": ["data.csv"]}}, check_files=False)
    marked = {k for k, e in entries.items() if "your own data" in e["default"]}
    assert marked == {"data.validation", "model.c_m"}


# -- allowed values against the code ---------------------------------------------------------


def test_choice_lists_are_the_codes(entries: dict) -> None:
    expected = {
        "model.friction": set(FRICTIONS),
        "simulation.method": set(SOLVERS),
        "data.velocity": set(VELOCITY_SOURCES),
        "data.position_unit": set(POSITION_UNITS),
        "data.time_unit": set(TIME_UNITS),
        "estimator.method": set(ESTIMATORS),
        "estimator.measure": set(MEASUREMENTS),
        "model.init": set(INIT_KEYWORDS),
        "model.dynamic": {*DYNAMICS, "auto"},
        "estimator.units": set(TUNING_UNITS),
        "estimator.select": set(SELECT_RULES),
    }
    for key, choices in expected.items():
        assert _choices(entries[key]["allowed"]) == choices, key
    for key in ("data.train", "data.validation", "data.test"):
        rigs = set(re.findall(r"`rig:(\w+)`", entries[key]["allowed"]))
        assert rigs == set(EXPERIMENTS), key
    # no other string key lists choices (a column name is free, `"A:k"` is its form)
    strings = {k for k, e in entries.items() if e["type"] == "string"}
    listed = {k for k in strings if _choices(entries[k]["allowed"])}
    assert listed - {f"data.columns.{c}" for c in COLUMN_NAMES} == set(expected)


def test_listed_choices_load_and_others_are_refused(entries: dict) -> None:
    for key in ("model.friction", "simulation.method", "data.velocity", "data.position_unit"):
        for choice in _choices(entries[key]["allowed"]):
            counts = ["data.counts_per_rev=4096"] if choice == "counts" else []  # its resolution
            Config.loads("", [f"{key}={choice}", *counts])
        with pytest.raises(TorchfricError, match="not allowed; choose one of"):
            Config.loads("", [f"{key}=nonesuch"])
    for choice in _choices(entries["estimator.measure"]["allowed"]):
        r = [1e-3] * len(MEASUREMENTS[choice])
        Config.loads("", [f"estimator.measure={choice}", f"estimator.r={r}"])


def _below(x: float) -> float:
    return math.nextafter(x, -math.inf)


def test_documented_bounds_are_the_checked_ones(entries: dict) -> None:
    """Each "> x" / ">= x" of a number or integer key: x itself and the value just below."""
    context = {"model.viscous": ["model.log_positive=false"]}
    checked = 0
    for key, entry in entries.items():
        bound = re.match(r"(>=?) (-?[\d.]+)(?:[;,]|$)", entry["allowed"])
        if entry["type"] not in ("float", "integer", 'integer or "auto"') or not bound:
            continue
        integer = entry["type"] != "float"
        x = int(bound[2]) if integer else float(bound[2])
        below = x - 1 if integer else _below(x)
        extra = context.get(key, [])
        if bound[1] == ">=":
            Config.loads("", [*extra, f"{key}={x}"])
        else:
            with pytest.raises(TorchfricError, match=re.escape(key)):
                Config.loads("", [*extra, f"{key}={x}"])
        with pytest.raises(TorchfricError, match=re.escape(key)):
            Config.loads("", [*extra, f"{key}={below}"])
        checked += 1
    assert checked >= 25  # the pattern finds the bounds (29 when written)


def test_documented_array_lengths_and_element_bounds_hold(entries: dict) -> None:
    for key, entry in entries.items():
        length = re.search(r"exactly (\d+) numbers", entry["allowed"])
        if length:
            n = int(length[1])
            Config.loads("", [f"{key}={[0.0] * n}"])
            with pytest.raises(TorchfricError, match=re.escape(key)):
                Config.loads("", [f"{key}={[0.0] * (n + 1)}"])
        if "each >= 0" in entry["allowed"]:
            n = int(length[1]) if length else 1
            with pytest.raises(TorchfricError, match=re.escape(key)):
                Config.loads("", [f"{key}={[-1e-9] * n}"])


OE = "estimator.method=output_error"
RULES: dict[str, tuple[list[str], list[str]]] = {
    # key: (overrides that the rule accepts, overrides that it refuses)
    "data.validation": (
        ["data.validation=[]"],
        ["data.train=a.csv", "data.validation=rig:validation"],
    ),
    "data.test": (
        ["data.test=rig:extrapolation"],
        ["data.train=a.csv", "data.test=rig:validation"],
    ),
    "data.stop": (["data.start=5", "data.stop=6"], ["data.start=5", "data.stop=5"]),
    "model.size": (
        ["model.friction=polytopic", "model.size=5"],
        ["model.friction=polytopic", "model.size=4"],
    ),
    "model.sizes": (["model.size=auto", "model.sizes=[1, 2]"], ["model.sizes=[1, 2]"]),
    "model.viscous": (["model.friction=polytopic", "model.viscous=0"], ["model.viscous=0"]),
    "estimator.passes": (
        [f"estimator.passes={MAX_PASSES}"],
        [f"estimator.passes={MAX_PASSES + 1}"],
    ),
    "estimator.r": (
        ["estimator.measure=position", "estimator.r=[0.5]"],
        ["estimator.r=[0.001, 0.0]"],
    ),
    "estimator.epochs": (
        [f"estimator.epochs={MAX_EPOCHS}", OE, "estimator.lbfgs_steps=0"],
        [OE, "estimator.epochs=0", "estimator.lbfgs_steps=0"],
    ),
    "estimator.lr_final": ([OE, "estimator.lr_final=0.01"], [OE, "estimator.lr_final=0.011"]),
    "estimator.window": ([OE, "estimator.window=2"], [OE, "estimator.window=1"]),
    "estimator.schedule": ([OE, "estimator.schedule=[0, 2]"], [OE, "estimator.schedule=[0, 1]"]),
    "estimator.learn_states": (
        [OE, "estimator.learn_states=true", "estimator.window=2"],
        [OE, "estimator.learn_states=true", "estimator.schedule=[50]"],
    ),
    "estimator.ensemble_q_scales": (
        ["estimator.ensemble_q_scales=[1e-9]"],
        ["estimator.ensemble_q_scales=[]"],
    ),
    "estimator.ensemble_r_scales": (
        ["estimator.ensemble_r_scales=[2.0]"],
        ["estimator.ensemble_r_scales=[0.0]"],
    ),
}


def test_rules_beyond_the_bounds_hold(
    entries: dict, tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each rule the reference states besides `Check`'s bounds: one config it accepts and one
    it refuses; and every stated rule is tested here."""
    monkeypatch.chdir(tmp_path)
    assert set(RULES) == set(reference._RULES)
    for key, (ok, bad) in RULES.items():
        assert reference._RULES[key] in entries[key]["allowed"]
        Config.loads("", ok, check_files=False)
        with pytest.raises(TorchfricError, match=re.escape(key)):
            Config.loads("", bad, check_files=False)
    # the caps beside the lower bounds, and epochs = 0 with an L-BFGS polish
    for key, cap in (("estimator.passes", MAX_PASSES), ("estimator.epochs", MAX_EPOCHS)):
        assert f"at most {cap}" in entries[key]["allowed"]
        with pytest.raises(TorchfricError, match=re.escape(key)):
            Config.loads("", [f"{key}={cap + 1}"])
    Config.loads("", [OE, "estimator.epochs=0", "estimator.lbfgs_steps=5"])
    # the ensemble keys: only their defaults with output error (and ensemble = 0)
    for key in ENSEMBLE_KEYS:
        assert reference._ENSEMBLE_RULE in entries[f"estimator.{key}"]["allowed"]
        default = toml_value(_flat(Config())[f"estimator.{key}"])
        Config.loads("", [OE, f"estimator.{key}={default}"])
        other = "0" if key == "ensemble" else "[2.0]" if "scales" in key else "2.0"
        if key == "ensemble":
            Config.loads("", [OE, "estimator.ensemble=0"])
            other = "2"
        with pytest.raises(TorchfricError, match='needs estimator.method = "ekf"'):
            Config.loads("", [OE, f"estimator.{key}={other}"])


def test_estimator_keys_name_the_settings_they_set(entries: dict) -> None:
    for key, routes in ESTIMATOR_KEYS.items():
        sets = entries[f"estimator.{key}"].get("sets", "")
        for holder, field in routes:
            if holder:
                owner = type(getattr(Config().estimator, holder)).__name__
                assert f"`{owner}.{field}`" in sets, key


# -- meanings come from the docstrings ----------------------------------------------------------


def test_attribute_docs_reads_entries_shared_names_and_continuations() -> None:
    @dataclasses.dataclass
    class Example:
        """Title.

        Attributes:
            alpha: first line
                and its continuation.
            beta, gamma: shared text.
            sub.key: a dotted entry.

        After the section.
        """

        alpha: int = 0

    assert reference.attribute_docs(Example) == {
        "alpha": "first line and its continuation.",
        "beta": "shared text.",
        "gamma": "shared text.",
        "sub.key": "a dotted entry.",
    }


def test_meanings_are_the_docstrings(entries: dict) -> None:
    from torchfric.app.config.sections import DataConfig, ModelConfig
    from torchfric.estimators.settings import EKFTuning, EnsembleSpec

    docs = reference.attribute_docs
    for key, doc in [
        ("data.velocity", docs(DataConfig)["velocity"]),
        ("data.columns.q", docs(DataConfig)["columns.q"]),
        ("model.init", docs(ModelConfig)["init"]),
        ("estimator.rollback", docs(EKFTuning)["rollback"]),
        ("estimator.ensemble_spread", docs(EnsembleSpec)["spread"]),
    ]:
        meaning = entries[key]["meaning"]
        assert meaning[1:] == doc[1:] and meaning[0].lower() == doc[0].lower(), key


# -- the committed page and the command --------------------------------------------------------


def test_committed_page_is_the_generated_one(text: str) -> None:
    assert DOC.read_text(encoding="utf-8") == text, (
        f"docs/config.md is stale: regenerate it with `{reference.COMMAND}`"
    )
    assert reference.COMMAND in text.splitlines()[2]


def test_check_command_passes_on_the_page_and_fails_on_a_stale_one(tmp_path: pathlib.Path) -> None:
    command = [sys.executable, "-m", "torchfric.app.config.reference"]
    ok = subprocess.run([*command, "--check", str(DOC)], capture_output=True, text=True, cwd=ROOT)
    assert (ok.returncode, ok.stdout, ok.stderr) == (0, "", "")
    stale = tmp_path / "config.md"
    stale.write_text(
        DOC.read_text(encoding="utf-8").replace("### `seed`", "### `seeds`"), encoding="utf-8"
    )
    bad = subprocess.run(
        [*command, "--check", str(stale)], capture_output=True, text=True, cwd=ROOT
    )
    assert bad.returncode == 1 and bad.stdout == ""
    assert bad.stderr.count("\n") == 1 and "regenerate it with" in bad.stderr
    printed = subprocess.run(command, capture_output=True, cwd=ROOT)
    assert printed.returncode == 0 and printed.stdout.decode("utf-8") == DOC.read_text(
        encoding="utf-8"
    )


# -- messages name real keys -------------------------------------------------------------------

SECTIONS = ("data", "model", "estimator", "simulation", "log")
_DOTTED = re.compile(r"(?<![\w./-])(" + "|".join(SECTIONS) + r")\.([A-Za-z_]\w*)(?:\.(\w+))?")
_SET = re.compile(r"--set\s+([\w.]+)=")
_FILE_SUFFIXES = {"csv", "npz", "mat", "json", "toml", "pt", "txt", "png", "html", "py", "md"}


def _docstring_nodes(tree: ast.AST) -> set[int]:
    """ids of the string constants that are docstrings (module, class, function, attribute)."""
    out = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list):
            for stmt in body:
                if isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant):
                    out.add(id(stmt.value))
    return out


def _message_strings() -> list[tuple[str, int, str]]:
    """(file, line, text) of every string literal of the package that is not a docstring (the
    constant parts of f-strings included)."""
    out = []
    for path in sorted(pathlib.Path(torchfric.__file__).parent.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        docs = _docstring_nodes(tree)
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Constant)
                and isinstance(node.value, str)
                and id(node) not in docs
            ):
                out.append((str(path.relative_to(ROOT)), node.lineno, node.value))
    return out


def _known(key: str) -> bool:
    """Whether dotted `key` (section.key, or data.columns.X) is a config key."""
    return key in _accepted_keys()


def test_messages_name_only_real_keys() -> None:
    found, wrong = 0, []
    for path, line, text in _message_strings():
        for m in _DOTTED.finditer(text):
            section, name, sub = m.groups()
            if name in _FILE_SUFFIXES or name.isupper():  # "data.csv", a placeholder "data.KEY"
                continue
            key = f"{section}.{name}" + (f".{sub}" if sub and name == "columns" else "")
            found += 1
            if not _known(key):
                wrong.append(f"{path}:{line}: {key} in {text!r}")
        for m in _SET.finditer(text):
            key = m[1]
            if key.isupper():  # --set KEY=VALUE
                continue
            found += 1
            if not _known(key):
                wrong.append(f"{path}:{line}: --set {key} in {text!r}")
    assert not wrong, "\n".join(wrong)
    assert found > 40  # the scan sees the messages (a broken pattern would find nothing)


def test_the_key_scan_catches_a_wrong_key() -> None:
    hits = [
        m.group(0)
        for m in _DOTTED.finditer("raise data.rtol, or see torchfric.data.rig and config.toml")
    ]
    assert hits == ["data.rtol"] and not _known("data.rtol")
    assert _SET.findall("use --set model.size=5") == ["model.size"]


def test_data_and_estimator_errors_name_the_key_that_fixes_them(tmp_path: pathlib.Path) -> None:
    import numpy as np

    from torchfric.data import load_experiment, make_experiment
    from torchfric.estimators.settings import EKFTuning

    no_t = tmp_path / "no_t.csv"
    no_t.write_text("u,q\n" + "0,0\n" * 20, encoding="utf-8")
    with pytest.raises(TorchfricError, match=r"data\.time_step in a run config"):
        load_experiment(no_t)
    t = np.arange(20) * 1e-3
    t[10:] += 5e-3  # a gap
    gap = tmp_path / "gap.csv"
    gap.write_text("t,u,q\n" + "".join(f"{x!r},0,0\n" for x in t.tolist()), encoding="utf-8")
    with pytest.raises(
        TorchfricError,
        match=r"gap\.csv: .*t skips samples after line 11 \(5 samples\)",
    ):
        load_experiment(gap)
    with pytest.raises(
        TorchfricError, match=r'map it in data\.columns, e\.g\. data\.columns\.q = "<name>"'
    ):
        load_experiment(no_t, columns={"q": "qm"}, time_step=1e-3)
    exp = make_experiment(np.arange(50) * 1e-2, np.zeros(50), np.sin(np.arange(50) * 0.1))
    with pytest.raises(
        TorchfricError, match=r"below 50 Hz \(data\.velocity_cutoff_hz in a run config\)"
    ):
        exp.with_velocity("highpass")  # 200 Hz by default, above this record's Nyquist
    with pytest.raises(TorchfricError, match=r"^estimator\.lr_final = 1\.0 is invalid"):
        Config.loads("", [OE, "estimator.lr_final=1.0"])
    with pytest.raises(TorchfricError, match=r"estimator\.p0_theta in a run config"):
        EKFTuning(p0_theta=(1.0, 1.0)).check(3)
