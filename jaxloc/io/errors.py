"""The errors of :mod:`jaxloc.io`: every reader raises ``FileNotFoundError`` for a missing file and
a ``ValueError`` naming the file (and line) for a malformed one; map files raise the subclass
:class:`MapFormatError`."""

from __future__ import annotations


class MapFormatError(ValueError):
    """A map file that is not a valid jaxloc map (corrupt, truncated, foreign, wrong version)."""
