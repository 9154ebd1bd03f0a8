"""Lazy exports for a package ``__init__``: its contract is importable from the package, but a name's module
(and the heavy libraries it uses: OpenCV, Open3D, MuJoCo) loads only when the name is first used.

A package writes::

    _lazy = LazyExports(__name__, {".survey": ("run_survey", "SurveySettings"), ...})
    __getattr__ = _lazy.attribute
    __dir__ = _lazy.names
    TYPE_CHECKING = False
    if TYPE_CHECKING:
        from darp.acquisition.survey import SurveySettings, run_survey

and lists the same names in ``__all__``; the ``TYPE_CHECKING`` imports give type checkers the real types.
"""

from __future__ import annotations

import importlib
import sys

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing (this module loads with every package)
if TYPE_CHECKING:
    from collections.abc import Mapping
    from typing import Any


class LazyExports:
    """The names a package exports and the submodule (``.name``, relative to the package) each comes from."""

    def __init__(self, package: str, modules: Mapping[str, tuple[str, ...]]) -> None:
        self.package = package
        self.where = {name: module for module, names in modules.items() for name in names}

    def attribute(self, name: str) -> Any:
        """The package's ``__getattr__``: import the name's module, keep the value on the package, return it."""
        module = self.where.get(name)
        if module is None:
            raise AttributeError(f"module {self.package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module, self.package), name)
        setattr(sys.modules[self.package], name, value)
        return value

    def names(self) -> list[str]:
        """The package's ``__dir__``: what it holds now and every lazy export."""
        return sorted({*vars(sys.modules[self.package]), *self.where})
