"""Packages whose public names are imported on first use (PEP 562), so that importing a package
costs only what is used: ``jaxloc --help`` imports no JAX, a LiDAR command no camera code."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping


def lazy_exports(
    package: str, exports: Mapping[str, str]
) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` of a package with lazily imported public names.

    Args:
        package: the package's name (``__name__``).
        exports: public name -> where it comes from: ``"module"`` (a submodule of the package
            that defines the name) or ``"module:attribute"`` (a name defined under another
            name), or ``""`` for a submodule of that name.

    Each name is imported on its first lookup and stored in the package, so later lookups cost
    nothing. An unknown name raises AttributeError, as for any module.
    """

    def __getattr__(name: str) -> object:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        source, _, attribute = exports[name].partition(":")
        if not source:
            value = importlib.import_module(f"{package}.{name}")
        else:
            module = importlib.import_module(f"{package}.{source}")
            value = getattr(module, attribute or name)
        importlib.import_module(package).__dict__[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted({*importlib.import_module(package).__dict__, *exports})

    return __getattr__, __dir__
