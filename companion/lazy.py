"""A package's public names imported on first access (PEP 562), so that importing the package
loads none of the heavy dependencies its submodules need (torch, pybullet, scipy) until a name
from one of them is used.

Used by :mod:`companion.policy_net` (the torch modules) and :mod:`sitl_sim` (the ``[sim]``
extra); standard library only.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Iterable
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(
    package: str, modules: dict[str, str], public: Iterable[str]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of ``package``: a name of ``modules`` (public name
    -> submodule, relative to ``package``) is imported from that submodule on first access and
    kept in the package; any other name is an AttributeError.

    Usage, at the end of the package's ``__init__``:
    ``__getattr__, __dir__ = lazy_exports(__name__, _LAZY, __all__)``.
    """
    names = list(public)

    def __getattr__(name: str) -> Any:
        module = modules.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(names))

    return __getattr__, __dir__
