"""Griffe extension of the docs build: a jaxloc package's ``__all__`` is derived at run time from
its redundant-alias imports (``from module import name as name``,
:func:`jaxloc._lazy.public_names`),
which griffe cannot evaluate from the source; this extension reads the same imports, so the API
reference renders exactly the names the package exports.
"""

from __future__ import annotations

from typing import Any

import griffe

from jaxloc._lazy import public_names


class PublicNames(griffe.Extension):
    """Set each jaxloc package's exports to its public names once its members are visited."""

    def on_module_members(self, *, mod: griffe.Module, **kwargs: Any) -> None:
        if mod.package.name != "jaxloc" or not mod.is_init_module:
            return
        names = public_names(mod.filepath)
        if names:
            version = ["__version__"] if "__version__" in mod.members else []
            mod.exports = [*version, *names]
