"""Names that load on first use (PEP 562): a package's public face without its imports.

``__getattr__, __dir__ = lazy_names(__name__, globals(), {"Config": "config", ...})`` in a
package's ``__init__`` makes ``from package import Config`` import the submodule ``config`` only
then. The CLI's ``--help`` and ``import torchfric`` stay light (no torch) this way, however
many names a face offers.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_names"]


def lazy_names(
    package: str, namespace: dict[str, Any], table: Mapping[str, str]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of `package` whose names `table` maps to the
    submodule (relative to `package`) that defines them; each is cached in `namespace` once
    loaded."""

    def __getattr__(name: str) -> Any:
        if name in table:
            value = getattr(importlib.import_module(f".{table[name]}", package), name)
            namespace[name] = value
            return value
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(table))

    return __getattr__, __dir__
