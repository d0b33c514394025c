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
    "app": {"leaf", "models", "data", "accel", "estimators"},
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
