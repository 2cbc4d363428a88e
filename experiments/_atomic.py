"""Atomic text writes for the experiment scripts (the library's own helper)."""

from jaxloc.io._atomic import write_text_atomic

__all__ = ["write_text_atomic"]
