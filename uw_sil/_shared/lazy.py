"""Lazy re-exports for a package ``__init__``: names load their module on first use (``import uw_sil`` stays light)."""
from __future__ import annotations

from importlib import import_module

__all__ = ["lazy_getattr"]


def lazy_getattr(package: str, exports: dict):
    """A module-level ``__getattr__`` for ``package`` that imports ``exports[name]`` (a submodule, relative
    to the package) the first time ``name`` is asked for."""

    def __getattr__(name):
        if name in exports:
            return getattr(import_module(f".{exports[name]}", package), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
