"""The package's layout holds its shape (docs/architecture.md): imports point one way, no
cycles, no giant modules or functions, no private names across subpackages, `__all__` everywhere.

These read the source with `ast`; nothing is imported, so a violation is named with its file and
line even when the import itself would work.
"""

from __future__ import annotations

import ast
import pathlib
from collections import defaultdict

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1] / "torchfric"
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 80

# which layers each layer may import (besides itself); "leaf" = the top-level helper modules
ALLOWED = {
    "leaf": {"leaf"},
    "models": {"leaf"},
    "data": {"leaf"},
    "accel": {"leaf", "models"},
    "estimators": {"leaf", "models", "data", "accel"},
    "export": {"leaf", "models", "accel"},
    "app": {"leaf", "models", "data", "accel", "estimators", "export"},
    "face": {"leaf", "models", "data", "estimators"},
    "main": {"app"},
}


def _modules() -> dict[str, pathlib.Path]:
    mods = {}
    for path in sorted(ROOT.rglob("*.py")):
        parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = path
    return mods


MODULES = _modules()


def _layer(module: str) -> str:
    parts = module.split(".")
    if module == "torchfric":
        return "face"
    if module == "torchfric.__main__":
        return "main"
    if len(parts) == 2 and not (ROOT / parts[1]).is_dir():
        return "leaf"
    return parts[1]


def _subpackage(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and (ROOT / parts[1]).is_dir() else module


def _imports(module: str) -> list[tuple[str, str, int]]:
    """(imported module, imported name, line) for every torchfric import in `module`."""
    path = MODULES[module]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("torchfric"):
                continue
            for alias in node.names:
                full = f"{target}.{alias.name}"
                found.append((full if full in MODULES else target, alias.name, node.lineno))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("torchfric"):
                    found.append((alias.name, "", node.lineno))
    return found


def test_the_package_has_its_subpackages():
    subpackages = {p.name for p in ROOT.iterdir() if (p / "__init__.py").exists()}
    assert {"models", "data", "estimators", "accel", "app"} <= subpackages


def test_imports_point_one_way():
    wrong = []
    for module in MODULES:
        layer = _layer(module)
        for target, _, line in _imports(module):
            to = _layer(target)
            if to != layer and to not in ALLOWED[layer]:
                wrong.append(f"{MODULES[module].name}:{line} {module} ({layer}) → {target} ({to})")
    assert not wrong, "\n".join(wrong)


def test_there_are_no_import_cycles():
    graph = defaultdict(set)
    for module in MODULES:
        for target, _, _ in _imports(module):
            if target in MODULES and target != module:
                graph[module].add(target)
    # a package importing its own submodules is not a cycle of design; leave the edge
    # submodule → package out (submodules never import their package's __init__ here anyway)
    state: dict[str, int] = {}
    cycles = []

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(" → ".join(trail[trail.index(nxt) :] + [nxt]))
            elif nxt not in state:
                visit(nxt, trail + [nxt])
        state[node] = 2

    for module in sorted(MODULES):
        if module not in state:
            visit(module, [module])
    assert not cycles, "\n".join(cycles)


def test_no_private_name_crosses_a_subpackage():
    wrong = []
    for module in MODULES:
        for target, name, line in _imports(module):
            if name.startswith("_") and not name.startswith("__"):
                if _subpackage(target) != _subpackage(module):
                    wrong.append(f"{module}:{line} imports {target}.{name}")
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_module_and_function_sizes(module: str):
    path = MODULES[module]
    text = path.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= MAX_MODULE_LINES, f"{path} has {len(text.splitlines())} lines"
    long = [
        f"{node.name} ({node.end_lineno - node.lineno + 1} lines, line {node.lineno})"
        for node in ast.walk(ast.parse(text))
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
    ]
    assert not long, f"{path}: {', '.join(long)}"


@pytest.mark.parametrize("module", sorted(m for m in MODULES if not m.endswith("__main__")))
def test_every_module_declares_its_public_names(module: str):
    tree = ast.parse(MODULES[module].read_text(encoding="utf-8"))
    names = {
        t.id
        for node in tree.body
        if isinstance(node, ast.Assign | ast.AnnAssign)
        for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
        if isinstance(t, ast.Name)
    }
    assert "__all__" in names, f"{MODULES[module]} has no __all__"


def test_the_public_face_lists_what_it_offers():
    import torchfric

    assert sorted(set(torchfric.__all__)) == sorted(torchfric.__all__)
    for name in torchfric.__all__:
        assert getattr(torchfric, name) is not None, name
    # the design's public API (DESIGN.md)
    for name in ("ArmModel", "OddTanhFriction", "PolytopicFriction", "simulate", "identify_ekf"):
        assert name in torchfric.__all__
    assert "load_checkpoint" in torchfric.__all__


def test_importing_torchfric_does_not_import_the_app_layer():
    import subprocess
    import sys

    script = (
        "import sys, torchfric; "
        "print(sorted(m for m in sys.modules if m.startswith('torchfric.app.')), "
        "'torch' in sys.modules); torchfric.identify_ekf; print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    # every public name loads on first use: torch only with the first of them
    assert out.stdout.split("\n")[:2] == ["[] False", "True"]


# ---------------------------------------------------------------------------- the app's rooms
# The application layer's rooms, lowest first: a room imports only the rooms before it (and
# itself); `cli` (the parser and its command table) sits on top. docs/architecture.md.
APP_ROOMS = ("config", "artifacts", "run", "sweep", "commands", "cli")
MAX_MODULES_PER_FOLDER = 12
# Folders that held more modules than the cap when it was set; they may not grow (a new
# module there goes into a subpackage of its own).
MODULE_CEILINGS = {"torchfric/data": 13, "torchfric/estimators": 19}
NEAR_CAP = int(0.9 * MAX_MODULE_LINES)
SIZE_REASON = "Why this size:"


def _room(module: str) -> str | None:
    parts = module.split(".")
    if len(parts) < 3 or parts[1] != "app":
        return None
    return parts[2]


def test_app_rooms_import_only_the_rooms_below_them():
    rooms = {p.name for p in (ROOT / "app").iterdir() if (p / "__init__.py").exists()}
    assert rooms | {"cli"} == set(APP_ROOMS), "a new room needs its place in APP_ROOMS"
    wrong = []
    for module in MODULES:
        room = _room(module)
        if room is None:
            continue
        for target, _, line in _imports(module):
            to = _room(target)
            if to is None or to == room:
                if target == "torchfric.app" and module != "torchfric.app":
                    wrong.append(f"{module}:{line} imports the app package itself")
                continue
            if APP_ROOMS.index(to) >= APP_ROOMS.index(room):
                wrong.append(f"{module}:{line} ({room}) imports {target} ({to}): rooms point down")
    assert not wrong, "\n".join(wrong)


def test_a_room_is_entered_by_its_face():
    """Another room imports a room's names from its package (its ``__init__``), never from
    the modules inside: the face is the room's only public surface."""
    wrong = []
    for module in MODULES:
        room = _room(module)
        for target, _, line in _imports(module):
            to = _room(target)
            if to is None or to == room or to == "cli":
                continue
            if target != f"torchfric.app.{to}" and (ROOT / "app" / to).is_dir():
                wrong.append(f"{module}:{line} imports {target}: import from torchfric.app.{to}")
    assert not wrong, "\n".join(wrong)


def test_every_face_name_resolves_and_loads_nothing_first():
    import importlib
    import subprocess
    import sys

    for room in APP_ROOMS[:-1]:
        face = importlib.import_module(f"torchfric.app.{room}")
        assert face.__all__ == sorted(face.__all__), room
        for name in face.__all__:
            assert getattr(face, name) is not None, f"torchfric.app.{room}.{name}"
    # importing the faces (and the CLI's parser) imports none of their modules, nor torch
    script = (
        "import sys, torchfric.app.cli, "
        + ", ".join(f"torchfric.app.{r}" for r in APP_ROOMS[:-1])
        + "; print(sorted(m for m in sys.modules if m.count('.') >= 3 and m.startswith("
        "'torchfric.app.')), 'torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[] False"


def test_folders_hold_at_most_twelve_modules():
    crowded = []
    for folder in sorted({p.parent for p in ROOT.rglob("*.py")}):
        name = folder.relative_to(ROOT.parent).as_posix()
        count = len(list(folder.glob("*.py")))
        if count > MODULE_CEILINGS.get(name, MAX_MODULES_PER_FOLDER):
            crowded.append(f"{name}: {count} modules")
    assert not crowded, "\n".join(crowded)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_a_module_near_the_line_cap_says_why(module: str):
    """A module within 10 % of the line cap states in its docstring why it is one module
    ("Why this size: ..."): the concept, not the cap, decides where code goes."""
    text = MODULES[module].read_text(encoding="utf-8")
    if len(text.splitlines()) > NEAR_CAP:
        doc = ast.get_docstring(ast.parse(text)) or ""
        assert SIZE_REASON in doc, f"{MODULES[module]} has {len(text.splitlines())} lines"


def test_the_architecture_page_names_every_module_and_no_missing_file():
    page = (ROOT.parent / "docs" / "architecture.md").read_text(encoding="utf-8")
    missing = []
    for module, path in MODULES.items():
        if path.name == "__init__.py" and module.count(".") < 2:
            continue
        if path.name not in page:
            missing.append(path.relative_to(ROOT).as_posix())
    assert not missing, "docs/architecture.md does not name: " + ", ".join(missing)
    import re

    # every path the page names exists (NAME.py-style placeholders aside)
    refs = re.findall(r"`((?:torchfric|app|models|data|estimators|accel)/[a-z_/]+\.py)`", page)
    for ref in set(refs):
        path = ROOT.parent / ref if ref.startswith("torchfric/") else ROOT / ref
        assert path.exists(), f"docs/architecture.md names {ref}, which does not exist"
