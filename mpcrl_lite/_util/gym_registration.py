"""``gymnasium.make("mpcrl_lite/Batteries-v0")`` after ``import mpcrl_lite``, without importing
Gymnasium (or anything heavy) at that import.

Gymnasium 1.x reads no plugin entry points, so a package registers its environments itself.
:func:`install` (called by ``mpcrl_lite/__init__``) registers at once when Gymnasium is
already imported; otherwise it puts a small finder on ``sys.meta_path`` that waits for the
import of ``gymnasium``, lets it complete, registers, and removes itself. The registration
names the environment by its import path (``mpcrl_lite.sim.env:BatteryEnv``), so the
environment's module is loaded only by ``gymnasium.make``.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import sys
from typing import Any

__all__ = ["ENTRY_POINT", "ENV_ID", "VECTOR_ENTRY_POINT", "install", "register"]

#: The environment's id (namespace ``mpcrl_lite``, name ``Batteries``, version 0).
ENV_ID = "mpcrl_lite/Batteries-v0"
ENTRY_POINT = "mpcrl_lite.sim.env:BatteryEnv"
VECTOR_ENTRY_POINT = "mpcrl_lite.sim.env:make_day_vector_env"


def register(gymnasium: Any) -> None:
    """Register the environment with the imported ``gymnasium`` module (once)."""
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(ENV_ID, entry_point=ENTRY_POINT, vector_entry_point=VECTOR_ENTRY_POINT)


class _Loader(importlib.abc.Loader):
    """Gymnasium's own loader, followed by the registration."""

    def __init__(self, loader: importlib.abc.Loader) -> None:
        self.loader = loader

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> Any:
        return self.loader.create_module(spec)

    def exec_module(self, module: Any) -> None:
        self.loader.exec_module(module)
        register(module)


class _Finder(importlib.abc.MetaPathFinder):
    """Waits for ``import gymnasium``; finds it with the other finders and wraps its loader."""

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> Any:
        if name != "gymnasium":
            return None
        _remove()
        for finder in list(sys.meta_path):  # the finders that would have found it
            find = getattr(finder, "find_spec", None)
            spec = find(name, path, target) if find is not None else None
            if spec is not None:
                if spec.loader is not None:
                    spec.loader = _Loader(spec.loader)
                return spec
        return None


def _remove() -> None:
    sys.meta_path[:] = [f for f in sys.meta_path if not isinstance(f, _Finder)]


def install() -> None:
    """Register now if Gymnasium is imported, else when it is (see the module docstring)."""
    gymnasium = sys.modules.get("gymnasium")
    if gymnasium is not None and hasattr(gymnasium, "register"):
        register(gymnasium)
    elif not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.insert(0, _Finder())
