"""Griffe extension of the docs build: Sphinx cross-reference roles in jaxloc's docstrings
(``:func:`~jaxloc.sg2loc.localize``` and the like) become mkdocs-autorefs links.

A role's target is looked up as written when it starts with ``jaxloc.``, else relative to the
documented object's class, module and packages, as Sphinx does. A target found in jaxloc becomes
a link (a broken one then fails ``mkdocs build --strict``); anything else (``jax.*``, ``numpy.*``)
becomes inline code.
"""

from __future__ import annotations

import functools
import re
from typing import Any

import griffe

ROLE = re.compile(
    r":(?:py:)?(?:func|class|meth|mod|data|attr|obj|exc)`(~?)([A-Za-z_][\w.]*)(\(\))?`"
)


def _lookup(root: griffe.Module, path: str) -> griffe.Object | griffe.Alias | None:
    if path == root.path:
        return root
    if not path.startswith(root.path + "."):
        return None
    try:
        return root[path[len(root.path) + 1 :]]
    except (KeyError, ValueError, griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None


class SphinxRoles(griffe.Extension):
    """Rewrite the roles of every docstring of the package once it is loaded."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        if pkg.path != "jaxloc":
            return
        for obj in _walk(pkg):
            if obj.docstring is not None:
                obj.docstring.value = ROLE.sub(
                    functools.partial(_replace, pkg, obj), obj.docstring.value
                )


def _walk(obj: griffe.Object):
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from _walk(member)


def _replace(root: griffe.Module, obj: griffe.Object, match: re.Match) -> str:
    tilde, target, call = match.group(1), match.group(2), match.group(3) or ""
    text = (target.rsplit(".", 1)[-1] if tilde else target) + call
    candidates = [target] if target.startswith("jaxloc.") else []
    scope = obj if (obj.is_class or obj.is_module) else obj.parent
    while scope is not None:  # the class, its module, the enclosing packages
        candidates.append(f"{scope.path}.{target}")
        scope = scope.parent
    for path in candidates:
        found = _lookup(root, path)
        if found is not None:
            return f"[`{text}`][{found.path}]"  # an alias keeps its public path
    return f"`{text}`"
