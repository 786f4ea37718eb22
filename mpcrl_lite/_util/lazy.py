"""Modules imported on first use: the heavy libraries stay out of the package's import.

``pd = lazy_module("pandas")`` gives an object that imports pandas the first time one of its
names is read (``pd.read_csv``, ``pd.Series`` in an ``isinstance`` check) and hands every name
on from then on (each name is looked up once and kept, so a name the module rebinds later
keeps its first value here: meant for functions, classes and constants). Until then
``pandas`` is not in ``sys.modules``: importing the package and
building an :class:`~mpcrl_lite.learning.experiment.Experiment` pay for a library only where
it is used (``tests/package/test_imports.py``).

``__getattr__ = lazy_names(__name__, {"Name": "package.module", ...})`` does the same for names
a module hands on from others (the package's face, names kept importable where they moved):
each is imported from its home at its first read and then kept in the module.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from types import ModuleType
from typing import Any

__all__ = ["LazyModule", "lazy_module", "lazy_names"]


class LazyModule:
    """Stands for the module ``name`` and imports it when a name of it is first read."""

    def __init__(self, name: str) -> None:
        self._name = name
        self._module: ModuleType | None = None

    def __getattr__(self, attribute: str) -> Any:
        if attribute.startswith("__"):
            raise AttributeError(attribute)
        module = self.__dict__["_module"]
        if module is None:
            module = self.__dict__["_module"] = importlib.import_module(self.__dict__["_name"])
        value = getattr(module, attribute)
        # kept: the next read of the name is a plain attribute read (hot loops read the
        # kernels' functions and constants through it)
        self.__dict__[attribute] = value
        return value

    def __repr__(self) -> str:
        state = "imported" if self.__dict__["_module"] is not None else "not imported yet"
        return f"<lazy module {self.__dict__['_name']!r} ({state})>"


def lazy_module(name: str) -> LazyModule:
    """The module ``name``, imported when first used (see the module docstring)."""
    return LazyModule(name)


def lazy_names(module: str, homes: Mapping[str, str]) -> Callable[[str], Any]:
    """A ``__getattr__`` for the module named ``module``: a name of ``homes`` is imported from
    its home (the full name of the module defining it) at its first read and set on
    ``module``, so that later reads skip this function; any other name raises
    AttributeError, as for a module without it."""

    def __getattr__(name: str) -> Any:
        home = homes.get(name)
        if home is None:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(home), name)
        setattr(sys.modules[module], name, value)
        return value

    return __getattr__
