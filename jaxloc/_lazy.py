"""Packages whose public names are imported on first use (PEP 562), so that importing a package
costs only what is used: ``jaxloc --help`` imports no JAX, a LiDAR command no camera code; and
public names kept for one more release under an old spelling, with a ``DeprecationWarning``.

A package lists each public name once, as a redundant-alias import (``from module import name as
name``, the re-export convention of type checkers): at module level when the package imports it
eagerly, under ``if TYPE_CHECKING:`` when it imports it on first use. :func:`public_names` reads
these imports from the package's source for its ``__all__``, :func:`lazy_exports` the lazy ones for
where each name comes from, and the docs build's griffe extension for the API reference.
"""

from __future__ import annotations

import ast
import importlib
import importlib.abc
import importlib.util
import sys
import warnings
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

#: The release that drops the deprecated names.
REMOVED_IN = "0.4"


def type_checking_imports(path: str | Path) -> dict[str, str]:
    """Public name -> ``"module:attribute"`` of every ``from module import attribute [as name]``
    under the ``if TYPE_CHECKING:`` blocks of the module at ``path`` (``"module.name:"`` for a
    submodule imported by name: ``from package import submodule``)."""
    exports = {}
    for node in ast.parse(Path(path).read_text()).body:
        if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING":
            for statement in node.body:
                for alias in statement.names:
                    exports[alias.asname or alias.name] = f"{statement.module}:{alias.name}"
    return exports


def public_names(path: str | Path) -> list[str]:
    """The public names of the package at ``path``, in source order: its redundant-alias imports
    (``from module import name as name``) at module level and under ``if TYPE_CHECKING:``, the one
    place each is listed (the package's ``__all__`` is this list)."""
    statements = []
    for node in ast.parse(Path(path).read_text()).body:
        if isinstance(node, ast.ImportFrom):
            statements.append(node)
        elif isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING":
            statements += [s for s in node.body if isinstance(s, ast.ImportFrom)]
    return [a.name for s in statements for a in s.names if a.asname == a.name]


def _resolve(source: str) -> object:
    """The object ``"module:attribute"`` names: a submodule of that name, else the attribute."""
    module_name, _, attribute = source.partition(":")
    module = importlib.import_module(module_name)
    if attribute in vars(module):
        return vars(module)[attribute]
    submodule = f"{module_name}.{attribute}"
    if hasattr(module, "__path__") and importlib.util.find_spec(submodule) is not None:
        return importlib.import_module(submodule)
    return getattr(module, attribute)


def lazy_exports(
    package: str,
    path: str,
    deprecated: Mapping[str, Iterable[str]] | None = None,
    instead: Mapping[str, str] | None = None,
) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` of a package with lazily imported public names.

    Args:
        package: the package's name (``__name__``).
        path: the package's source (``__file__``): its ``if TYPE_CHECKING:`` imports name the
            public names and where each comes from (:func:`type_checking_imports`).
        deprecated, instead: the package's deprecated names, as for :func:`deprecated_names`.

    Each public name is imported on its first lookup and stored in the package, so later
    lookups cost nothing. An unknown name raises AttributeError, as for any module.
    """
    exports = type_checking_imports(path)
    deprecated_getattr = deprecated_names(package, deprecated or {}, instead or {})

    def __getattr__(name: str) -> object:
        if name not in exports:
            return deprecated_getattr(name)
        value = _resolve(exports[name])
        importlib.import_module(package).__dict__[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted({*importlib.import_module(package).__dict__, *exports})

    __getattr__.deprecated = deprecated_getattr.deprecated
    return __getattr__, __dir__


def deprecated_names(
    package: str, deprecated: Mapping[str, Iterable[str]], instead: Mapping[str, str]
) -> Callable[[str], object]:
    """``__getattr__`` of a package for its deprecated names: each lookup warns
    (``DeprecationWarning``: removed in release :data:`REMOVED_IN`) and returns the object, never
    stored, so that every use is told.

    Args:
        package: the package's name (``__name__``).
        deprecated: module -> the old public names it defines (``"attribute"``, or
            ``"old_name=attribute"`` for a name renamed there).
        instead: old name -> what to use instead (by default the object's new place, or "it is
            internal now" for a private module).
    """
    sources = {}
    for module, names in deprecated.items():
        for entry in names:
            old, _, attribute = entry.partition("=")
            sources[old] = f"{module}:{attribute or old}"

    def __getattr__(name: str) -> object:
        if name not in sources:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        source = sources[name].replace(":", ".")
        hint = "it is internal now" if "._" in source else f"use {source}"
        hint = f"use {instead[name]}" if name in instead else hint
        warnings.warn(
            f"{package}.{name} is deprecated and will be removed in jaxloc {REMOVED_IN}; {hint}",
            DeprecationWarning,
            stacklevel=2,
        )
        return _resolve(sources[name])

    __getattr__.deprecated = sources  # for the tests that check every old name
    return __getattr__


def renamed_names(module: str, renamed: Mapping[str, str]) -> Callable[[str], object]:
    """``__getattr__`` of a module whose public names ``renamed`` (old -> new) were renamed in
    it: each old name resolves to the new one, with a warning (as :func:`deprecated_names`)."""
    return deprecated_names(
        module,
        {module: [f"{old}={new}" for old, new in renamed.items()]},
        {old: f"{module}.{new}" for old, new in renamed.items()},
    )


class _ModuleAliases(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports ``old`` module names as the modules they became (``import package.old``), with a
    ``DeprecationWarning``."""

    def __init__(self, aliases: Mapping[str, str]):
        self.aliases = dict(aliases)

    def find_spec(self, fullname, path=None, target=None):
        if fullname not in self.aliases:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        new = self.aliases[spec.name]
        warnings.warn(
            f"{spec.name} is deprecated and will be removed in jaxloc {REMOVED_IN}; it is "
            f"internal now (its public names are in {new.rpartition('.')[0]})",
            DeprecationWarning,
            stacklevel=2,
        )
        return importlib.import_module(new)

    def exec_module(self, module) -> None:
        """Nothing to run: the module is the one it became, already imported."""


def renamed_modules(package: str, renamed: Mapping[str, str]) -> None:
    """Let ``import package.old`` (for each ``old -> new`` of ``renamed``) import
    ``package.new``, with a ``DeprecationWarning``, until release :data:`REMOVED_IN`."""
    sys.meta_path.append(
        _ModuleAliases({f"{package}.{old}": f"{package}.{new}" for old, new in renamed.items()})
    )
