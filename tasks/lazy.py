"""Package names loaded at first use (PEP 562), for package ``__init__`` files whose names come from torch-bound
modules: a torch-free submodule of the package can then be imported alone."""

from __future__ import annotations

import importlib
from collections.abc import Callable

__all__ = ["lazy_names"]


def lazy_names(package: dict, where: dict[str, str]) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of a package whose globals are ``package``: each name of
    ``where`` (name -> relative module) is imported from its module at first use and kept in the package."""

    def __getattr__(name: str):
        if name not in where:
            raise AttributeError(f"module {package['__name__']!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(where[name], package["__name__"]), name)
        package[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted({*package, *package["__all__"]})

    return __getattr__, __dir__
