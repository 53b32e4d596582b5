"""The installed package's version, declared once in `pyproject.toml` and read from its metadata."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("mpsim")
except PackageNotFoundError:  # run from a source tree that was never installed
    __version__ = "0+unknown"
