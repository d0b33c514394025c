"""The installed package's version (a leaf module: `torchfric --version` reads it without torch)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("torchfric")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+local"

__all__ = ["__version__"]
